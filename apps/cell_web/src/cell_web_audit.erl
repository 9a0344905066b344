%% @doc The audit trail of the operator panel: every command, every answer to an
%% error, every change of settings, recipes and users, every login — who, what, when,
%% from which address, and how it ended.
%%
%% One file a day, `Logs/audit YYYY-MM-DD.jsonl' (local date, like the task log), one
%% JSON object a line, only ever appended to; a day's file that reaches
%% `audit_file_max_bytes' (10 MB) goes on in `audit YYYY-MM-DD (2).jsonl' and so on,
%% and files older than `audit_keep_days' (365) are deleted when a day begins (both
%% settings of the `cell_web' application). A target is cut to 256 bytes, a detail to
%% 1024.
%%
%% Refused requests of callers who are not logged in ({@link refused/1}) are not each
%% written: the first of an address in a minute is, the rest are counted and written
%% as one line when the minute ends (see {@link cell_web_audit_rules}), so anonymous
%% clients cannot flood the trail or the disk. Each line is flushed to the disk
%% (datasync) before the request that caused it is answered, so a power cut loses no
%% answered request; a line cut short by a power cut is skipped when read back. A text
%% file needs no database to read it on the cell's PC and rotates like the task log;
%% `Databases/' is left to the statistics.
%%
%% Writes go through this process, in order; reads ({@link query/1}) read the files
%% from the caller.
-module(cell_web_audit).
-behaviour(gen_server).

-export([start_link/0, record/1, refused/1, flush/0, query/1, file_name/1, decode_line/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2, terminate/2]).

-export_type([entry/0]).

-type entry() :: #{time := integer(), who := binary(), role := binary(),
                   address := binary(), action := binary(), target := binary(),
                   outcome := binary(), detail => binary()}.

-define(REFUSED_INTERVAL_S, 60).
-define(REFUSED_ADDRESSES, 100).
-define(TARGET_MAX, 256).
-define(DETAIL_MAX, 1024).

-record(state, {date :: calendar:date() | undefined,
                part = 1 :: pos_integer(),
                bytes = 0 :: non_neg_integer(),
                fd :: file:io_device() | undefined,
                refusals = cell_web_audit_rules:new(?REFUSED_ADDRESSES)
                    :: cell_web_audit_rules:refusals(),
                timer :: reference() | undefined}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Appends an entry (`time' is set here); returns once it is on the disk.
-spec record(#{atom() => binary()}) -> ok | {error, term()}.
record(Entry) ->
    gen_server:call(?MODULE, {record, Entry#{time => os:system_time(millisecond)}}, 30000).

%% @doc A refused request of a caller who is not logged in: written if it is the
%% first of its address in the current minute, else counted (see the module doc).
-spec refused(#{atom() => binary()}) -> ok | {error, term()}.
refused(Entry) ->
    gen_server:call(?MODULE, {refused, Entry#{time => os:system_time(millisecond)}}, 30000).

%% @doc Writes the refusals counted so far now, without waiting for the minute to end;
%% the next refusal begins a new minute.
-spec flush() -> ok | {error, term()}.
flush() ->
    gen_server:call(?MODULE, flush, 30000).

%% @doc Entries back from the files, oldest first: `from' (inclusive) and `to'
%% (exclusive) in ms, default the last 24 hours; `who' and `action' filter; `offset'
%% and `limit' (default 200) page.
-spec query(#{from => integer(), to => integer(), who => binary(), action => binary(),
              offset => non_neg_integer(), limit => pos_integer()}) -> [entry()].
query(Q) ->
    Now = os:system_time(millisecond),
    From = maps:get(from, Q, Now - 86400000),
    To = maps:get(to, Q, Now + 1),
    Dir = cell_config:dir(logs),
    Entries = lists:append([read_day(Dir, D) || D <- dates(From, To)]),
    Keep = fun(#{time := T} = E) ->
                   T >= From andalso T < To andalso
                       matches(who, E, Q) andalso matches(action, E, Q)
           end,
    Selected = [E || E <- Entries, Keep(E)],
    Offset = maps:get(offset, Q, 0),
    case Offset >= length(Selected) of
        true -> [];
        false -> lists:sublist(lists:nthtail(Offset, Selected), maps:get(limit, Q, 200))
    end.

matches(Key, E, Q) ->
    case maps:find(Key, Q) of
        {ok, V} -> maps:get(Key, E, undefined) =:= V;
        error -> true
    end.

%% @doc `audit 2026-11-21.jsonl', the first file of a day.
-spec file_name(calendar:date()) -> string().
file_name(Date) ->
    cell_web_audit_rules:file_name(Date, 1).

%% The parts of a day, in order, as long as they follow on.
read_day(Dir, Date) ->
    read_parts(Dir, Date, 1).

read_parts(Dir, Date, Part) ->
    Path = filename:join(Dir, cell_web_audit_rules:file_name(Date, Part)),
    case filelib:is_regular(Path) of
        true -> read(Path) ++ read_parts(Dir, Date, Part + 1);
        false -> []
    end.

read(Path) ->
    case file:read_file(Path) of
        {ok, Bin} ->
            [E || L <- binary:split(Bin, <<"\n">>, [global]), {ok, E} <- [decode_line(L)]];
        {error, _} ->
            []
    end.

%% @doc One line back into an entry; a torn or foreign line is `error'.
-spec decode_line(binary()) -> {ok, entry()} | error.
decode_line(Line) ->
    try jsx:decode(Line, [return_maps]) of
        #{<<"time">> := T, <<"who">> := W, <<"action">> := A} = M
          when is_integer(T), is_binary(W), is_binary(A) ->
            {ok, maps:from_list([{K, V} || {KB, V} <- maps:to_list(M),
                                           K <- keys(), atom_to_binary(K, utf8) =:= KB])};
        _ ->
            error
    catch
        error:_ -> error
    end.

keys() -> [time, who, role, address, action, target, outcome, detail].

dates(From, To) ->
    First = calendar:date_to_gregorian_days(local_date(From)),
    Last = calendar:date_to_gregorian_days(local_date(max(From, To - 1))),
    [calendar:gregorian_days_to_date(D) || D <- lists:seq(First, Last)].

local_date(Ms) ->
    {Date, _} = calendar:system_time_to_local_time(Ms div 1000, second),
    Date.

-spec init([]) -> {ok, #state{}}.
init([]) ->
    process_flag(trap_exit, true),
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({record, Entry}, _From, State) ->
    write(Entry, State);
handle_call({refused, Entry}, _From, #state{refusals = R0} = State0) ->
    State = armed(State0),
    case cell_web_audit_rules:refused(Entry, R0) of
        {write, R} -> write(Entry, State#state{refusals = R});
        {counted, R} -> {reply, ok, State#state{refusals = R}}
    end;
handle_call(flush, _From, #state{timer = Timer} = State) ->
    _ = Timer =/= undefined andalso erlang:cancel_timer(Timer),
    flush(State#state{timer = undefined}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({timeout, Ref, flush}, #state{timer = Ref} = State) ->
    {reply, _, State1} = flush(State#state{timer = undefined}),
    {noreply, State1};
handle_info({timeout, _Cancelled, flush}, State) ->
    %% A minute ended early by flush/0 whose timer had already fired.
    {noreply, State}.

%% The minute of the refusals starts with the first one.
armed(#state{timer = undefined} = State) ->
    State#state{timer = erlang:start_timer(?REFUSED_INTERVAL_S * 1000, self(), flush)};
armed(State) ->
    State.

flush(#state{refusals = R0} = State) ->
    {Lines, R} = cell_web_audit_rules:flush(?REFUSED_INTERVAL_S, R0),
    Now = os:system_time(millisecond),
    lists:foldl(fun(Entry, {reply, ok, St}) -> write(Entry#{time => Now}, St);
                   (_, Failed) -> Failed
                end, {reply, ok, State#state{refusals = R}}, Lines).

write(#{time := Ms} = Entry, State0) ->
    Clipped = clipped(maps:with(keys(), Entry)),
    Line = [jsx:encode(Clipped), $\n],
    case open(local_date(Ms), State0) of
        {ok, #state{fd = Fd, bytes = Bytes} = State} ->
            case file:write(Fd, Line) of
                ok ->
                    case file:datasync(Fd) of
                        ok -> {reply, ok, rotated(State#state{bytes = Bytes + iolist_size(Line)})};
                        {error, R} -> failed(R, State)
                    end;
                {error, R} ->
                    failed(R, State)
            end;
        {error, R} ->
            failed(R, State0)
    end.

clipped(Entry) ->
    maps:map(fun(target, V) when is_binary(V) -> cell_web_audit_rules:clip(V, ?TARGET_MAX);
                (detail, V) when is_binary(V) -> cell_web_audit_rules:clip(V, ?DETAIL_MAX);
                (_, V) -> V
             end, Entry).

%% A day's file that has reached its limit goes on in the next part.
rotated(#state{bytes = Bytes, part = Part} = State) ->
    case Bytes >= max_bytes() of
        true -> _ = close(State), State#state{fd = undefined, part = Part + 1, bytes = 0};
        false -> State
    end.

max_bytes() -> application:get_env(cell_web, audit_file_max_bytes, 10485760).

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, State0) ->
    %% What was counted is written before the trail closes.
    {reply, _, State} = flush(State0),
    _ = close(State),
    ok.

open(Date, #state{date = Date, fd = Fd} = State) when Fd =/= undefined ->
    {ok, State};
open(Date, #state{date = Date, part = Part} = State) ->
    open_part(Date, Part, State);
open(Date, State) ->
    _ = close(State),
    Dir = cell_config:dir(logs),
    ok = delete_expired(Dir, Date),
    open_part(Date, last_part(Dir, Date, 1), State).

open_part(Date, Part, State) ->
    Path = filename:join(cell_config:dir(logs), cell_web_audit_rules:file_name(Date, Part)),
    case file:open(Path, [append, raw, binary]) of
        {ok, Fd} ->
            Bytes = filelib:file_size(Path),
            rotated_open(State#state{date = Date, part = Part, bytes = Bytes, fd = Fd});
        {error, R} ->
            {error, {Path, R}}
    end.

%% A part found full when it is opened (the limit was lowered): on to the next.
rotated_open(State) ->
    case rotated(State) of
        #state{fd = undefined, date = Date, part = Part} = S -> open_part(Date, Part, S);
        S -> {ok, S}
    end.

last_part(Dir, Date, Part) ->
    case filelib:is_regular(filename:join(Dir, cell_web_audit_rules:file_name(Date, Part + 1))) of
        true -> last_part(Dir, Date, Part + 1);
        false -> Part
    end.

delete_expired(Dir, Today) ->
    Keep = application:get_env(cell_web, audit_keep_days, 365),
    case file:list_dir(Dir) of
        {ok, Names} ->
            lists:foreach(
              fun(N) ->
                      case file:delete(filename:join(Dir, N)) of
                          ok -> cell_log:notice(web, "audit file ~ts deleted: older than ~p days",
                                                [N, Keep]);
                          {error, R} -> cell_log:warning(web, "old audit file ~ts cannot be "
                                                         "deleted: ~ts", [N, file:format_error(R)])
                      end
              end, cell_web_audit_rules:expired(Names, Today, Keep));
        {error, _} ->
            ok
    end.

close(#state{fd = undefined}) -> ok;
close(#state{fd = Fd}) -> file:close(Fd).

%% The entry could not be written: say so where people look, and open the file again
%% for the next one.
failed(Reason, State) ->
    cell_log:error(web, "the audit trail cannot be written (~tp); the panel goes on", [Reason]),
    _ = close(State),
    {reply, {error, Reason}, State#state{date = undefined, fd = undefined}}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

decode_line_test_() ->
    Good = <<"{\"time\":1,\"who\":\"op\",\"role\":\"operator\",\"address\":\"127.0.0.1\","
             "\"action\":\"start\",\"target\":\"cell\",\"outcome\":\"ok\",\"extra\":1}">>,
    [?_assertMatch({ok, #{time := 1, who := <<"op">>, action := <<"start">>,
                          outcome := <<"ok">>}}, decode_line(Good)),
     ?_assertEqual(false, maps:is_key(extra, element(2, decode_line(Good)))),
     ?_assertEqual(error, decode_line(binary:part(Good, 0, 40))),
     ?_assertEqual(error, decode_line(<<>>)),
     ?_assertEqual(error, decode_line(<<"[1,2]">>)),
     ?_assertEqual(error, decode_line(<<"{\"time\":\"x\",\"who\":\"a\",\"action\":\"b\"}">>))].

file_name_test() ->
    ?assertEqual("audit 2026-01-02.jsonl", file_name({2026, 1, 2})).
-endif.
