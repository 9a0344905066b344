%% @doc The audit trail of the operator panel: every command, every answer to an
%% error, every change of settings, recipes and users, every login — who, what, when,
%% from which address, and how it ended.
%%
%% One file a day, `Logs/audit YYYY-MM-DD.jsonl' (local date, like the task log), one
%% JSON object a line, only ever appended to. Each line is flushed to the disk
%% (datasync) before the request that caused it is answered, so a power cut loses no
%% answered request; a line cut short by a power cut is skipped when read back. A text
%% file needs no database to read it on the cell's PC and rotates like the task log;
%% `Databases/' is left to the statistics.
%%
%% Writes go through this process, in order; reads ({@link query/1}) read the files
%% from the caller.
-module(cell_web_audit).
-behaviour(gen_server).

-export([start_link/0, record/1, query/1, file_name/1, decode_line/1]).
-export([init/1, handle_call/3, handle_cast/2, terminate/2]).

-export_type([entry/0]).

-type entry() :: #{time := integer(), who := binary(), role := binary(),
                   address := binary(), action := binary(), target := binary(),
                   outcome := binary(), detail => binary()}.

-record(state, {date :: calendar:date() | undefined,
                fd :: file:io_device() | undefined}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Appends an entry (`time' is set here); returns once it is on the disk.
-spec record(#{atom() => binary()}) -> ok | {error, term()}.
record(Entry) ->
    gen_server:call(?MODULE, {record, Entry#{time => os:system_time(millisecond)}}, 30000).

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
    Entries = lists:append([read(filename:join(Dir, file_name(D))) || D <- dates(From, To)]),
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

%% @doc `audit 2026-11-21.jsonl'.
-spec file_name(calendar:date()) -> string().
file_name({Y, M, D}) ->
    lists:flatten(io_lib:format("audit ~4..0w-~2..0w-~2..0w.jsonl", [Y, M, D])).

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
handle_call({record, #{time := Ms} = Entry}, _From, State0) ->
    Line = [jsx:encode(maps:with(keys(), Entry)), $\n],
    case open(local_date(Ms), State0) of
        {ok, #state{fd = Fd} = State} ->
            case file:write(Fd, Line) of
                ok ->
                    case file:datasync(Fd) of
                        ok -> {reply, ok, State};
                        {error, R} -> failed(R, State)
                    end;
                {error, R} ->
                    failed(R, State)
            end;
        {error, R} ->
            failed(R, State0)
    end.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, State) ->
    _ = close(State),
    ok.

open(Date, #state{date = Date, fd = Fd} = State) when Fd =/= undefined ->
    {ok, State};
open(Date, State) ->
    _ = close(State),
    Path = filename:join(cell_config:dir(logs), file_name(Date)),
    case file:open(Path, [append, raw, binary]) of
        {ok, Fd} -> {ok, #state{date = Date, fd = Fd}};
        {error, R} -> {error, {Path, R}}
    end.

close(#state{fd = undefined}) -> ok;
close(#state{fd = Fd}) -> file:close(Fd).

%% The entry could not be written: say so where people look, and open the file again
%% for the next one.
failed(Reason, State) ->
    cell_log:error(web, "the audit trail cannot be written (~tp); the panel goes on", [Reason]),
    _ = close(State),
    {reply, {error, Reason}, #state{}}.

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
