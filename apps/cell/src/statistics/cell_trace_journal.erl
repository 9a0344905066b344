%% @doc The trace journal: the records of a product's way through the cell (taken by a
%% task, transferred in, transferred out, an operator's answer) made durable before
%% the cell acts on them, so that the statistics ({@link cell_stats}) can rebuild what
%% a crash took from them.
%%
%% A task appends a record and waits, as it waits for its product file, until the
%% record is on the disk ({@link append/1}); only then does it publish the event and
%% go on. Records are appended to `Databases/cell_trace.journal' in frames (a mark, a
%% length, a CRC-32, the term), and flushed by group commit: every record that came
%% while the last flush was under way is written with one write and one flush, and
%% each caller is answered when its own record is on the disk. In a folder held in RAM
%% nothing is flushed (see {@link cell_file:in_ram/1}).
%%
%% Each record gets an id, `{Incarnation, N}': the incarnation is the wall time at
%% which the journal was opened, above every incarnation found in the file, so ids
%% grow in the order of the file across restarts and no two records share one. The
%% statistics apply each record once by its id (see {@link cell_stats}).
%%
%% The statistics attach ({@link attach/0}): they get every record kept (those not yet
%% trimmed), then every new record as soon as it is durable, in the order of the file,
%% before its writer is answered; so they see a record before the event its task
%% publishes after it. Once what the records changed is durable in the database they
%% trim the journal up to an id ({@link trim/1}): the file is rewritten with the
%% records after it (usually none).
%%
%% <b>Its bound.</b> The journal holds what the database has not taken yet; while the
%% database cannot be opened it only grows. It is bounded (the `statistics' settings'
%% `journal_max_mb', told by the statistics with {@link bound/1}; its default until
%% they do): a record that would take it past the bound is refused, `{error,
%% journal_full}', and never written, so its task stops as for a disk that refuses a
%% write and nothing kept is ever dropped. The log says so once, when the bound is
%% reached and when records are taken again. The statistics warn from 80 % of it (see
%% {@link cell_stats_trace:journal_level/3}).
%%
%% At start the file is read whole and its frames checked; a last frame cut short or
%% damaged (a crash in the middle of a write) is dropped, the log says so and the file
%% is rewritten with the whole frames. A frame's term is read only when the statistics
%% attach, once the tasks' modules are loaded (the atoms of a product's fields are
%% known then, and no atom is made from the file); one that still cannot be read (an
%% atom of a task no longer in the cell) is left out, and the log says so.
-module(cell_trace_journal).
-behaviour(gen_server).

-export([start_link/0, child_spec/0, append/1, attach/0, trim/1, bound/1, path/0,
         default_bound/0]).
-export([encode/1, decode/1, read/1]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-export_type([id/0, record/0]).

-type id() :: {integer(), pos_integer()}.
-type record() :: #{id := id(), type := atom(), task := atom(), at := integer(),
                    atom() => term()}.
%% A record: its id, its type (`product_saved', `item_transfer_in',
%% `item_transfer_out', `alarm_answered'), the task, the wall time in microseconds,
%% and the fields of the event it stands for.

-define(MARK, 16#C7A1).
-define(NAME, "cell_trace.journal").

-record(st, {path :: binary() | undefined,
             file :: cell_file:append_file() | undefined,
             inc = 0 :: integer(),
             n = 0 :: non_neg_integer(),
             kept = [] :: [{id(), binary()}],            %% frames not trimmed, newest first
             bytes = 0 :: non_neg_integer(),             %% ... their size: the file's
             batch = [] :: [{gen_server:from(), record(), binary()}],  %% newest first
             batch_bytes = 0 :: non_neg_integer(),
             max :: pos_integer(),                       %% the bound, in bytes
             full = false :: boolean(),                  %% a record was refused
             commit = false :: boolean(),                %% a commit message is queued
             reader :: {pid(), reference()} | undefined}).

%%====================================================================
%% API
%%====================================================================

-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

-spec child_spec() -> supervisor:child_spec().
child_spec() ->
    #{id => ?MODULE, start => {?MODULE, start_link, []}}.

%% @doc Appends a record (its id and time are added) and returns when it is durable.
%% `{error, not_running}' when no journal runs (a task outside a cell's supervisor);
%% `{error, journal_full}' when it would take the journal past its bound (nothing is
%% written); `{error, Why}' when the disk refused the write.
-spec append(#{type := atom(), task := atom(), atom() => term()}) ->
          {ok, id()} | {error, term()}.
append(Record) when is_map(Record) ->
    case whereis(?MODULE) of
        undefined -> {error, not_running};
        Pid -> gen_server:call(Pid, {append, Record}, infinity)
    end.

%% @doc Makes the caller the journal's reader: answers the records kept, oldest first;
%% every record made durable later is sent to it as `{cell_trace_journal, [record()]}'.
-spec attach() -> [record()].
attach() ->
    gen_server:call(?MODULE, attach, infinity).

%% @doc The records up to `Id' are no longer needed: what they changed is durable.
-spec trim(id()) -> ok.
trim(Id) ->
    gen_server:cast(?MODULE, {trim, Id}).

%% @doc Sets the most bytes the journal may hold; answers how many it holds now.
-spec bound(pos_integer()) -> non_neg_integer().
bound(Max) when is_integer(Max), Max > 0 ->
    gen_server:call(?MODULE, {bound, Max}, infinity).

%% @doc The bound until the statistics tell one: the settings' default.
-spec default_bound() -> pos_integer().
default_bound() ->
    #{journal_max_mb := Mb} = cell_settings_schema:defaults(cell_stats_settings),
    Mb * 1024 * 1024.

%% @doc The journal's file.
-spec path() -> file:filename().
path() ->
    filename:join(cell_db:dir(), ?NAME).

%%====================================================================
%% Frames (pure)
%%====================================================================

%% @doc A record as a frame of the file: a mark, its id, the length and CRC-32 of its
%% id and term, the term.
-spec encode(record()) -> binary().
encode(#{id := {Inc, N}} = Record) ->
    Body = term_to_binary(Record),
    Crc = erlang:crc32([<<Inc:64/signed, N:64>>, Body]),
    <<?MARK:16, Inc:64/signed, N:64, (byte_size(Body)):32, Crc:32, Body/binary>>.

%% @doc The whole frames of a file's content with their ids, oldest first; how many
%% bytes of it they hold; how many bytes after the last whole frame were cut short or
%% damaged.
-spec decode(binary()) -> {[{id(), binary()}], Good :: non_neg_integer(),
                           Torn :: non_neg_integer()}.
decode(Bin) ->
    decode(Bin, 0, []).

decode(<<?MARK:16, Inc:64/signed, N:64, Len:32, Crc:32, Body:Len/binary, Rest/binary>> = Bin,
       Good, Acc) when N > 0 ->
    case erlang:crc32([<<Inc:64/signed, N:64>>, Body]) of
        Crc ->
            Size = byte_size(Bin) - byte_size(Rest),
            decode(Rest, Good + Size, [{{Inc, N}, binary:part(Bin, 0, Size)} | Acc]);
        _ ->
            {lists:reverse(Acc), Good, byte_size(Bin)}
    end;
decode(Bin, Good, Acc) ->
    {lists:reverse(Acc), Good, byte_size(Bin)}.

%% @doc The record of a whole frame; `error' when its term names an atom this node does
%% not know (no atom is made from a file) or is not a record of this id.
-spec read(binary()) -> {ok, record()} | error.
read(<<?MARK:16, Inc:64/signed, N:64, Len:32, _Crc:32, Body:Len/binary>>) ->
    try binary_to_term(Body, [safe]) of
        #{id := {Inc, N}, type := T, task := K, at := At} = R
          when is_atom(T), is_atom(K), is_integer(At) -> {ok, R};
        _ -> error
    catch error:badarg -> error
    end;
read(_) ->
    error.

%%====================================================================
%% gen_server
%%====================================================================

-spec init([]) -> {ok, #st{}, {continue, open}}.
init([]) ->
    {ok, #st{max = default_bound()}, {continue, open}}.

-spec handle_continue(open, #st{}) -> {noreply, #st{}}.
handle_continue(open, St) ->
    Path = unicode:characters_to_binary(path()),
    ok = filelib:ensure_dir(Path),
    Content = case file:read_file(Path) of
                  {ok, Bin} -> Bin;
                  {error, enoent} -> <<>>;
                  {error, Why} -> erlang:error({journal_unreadable, Path, Why})
              end,
    {Frames, _Good, Torn} = decode(Content),
    _ = Torn =:= 0 orelse
        cell_log:warning(cell, "trace journal ~ts: the last record was cut short by a "
                         "crash or power cut while it was written (~b bytes); it was "
                         "never confirmed to its task and is dropped", [Path, Torn]),
    _ = Torn > 0 andalso rewrite(Path, Frames),
    LastInc = lists:max([0 | [I || {{I, _}, _} <- Frames]]),
    Inc = max(erlang:system_time(microsecond), LastInc + 1),
    {noreply, St#st{path = Path, file = open_append(Path), inc = Inc,
                    kept = lists:reverse(Frames), bytes = frames_size(Frames)}}.

-spec handle_call(term(), gen_server:from(), #st{}) ->
          {reply, term(), #st{}} | {noreply, #st{}}.
handle_call({append, Record}, From, #st{inc = Inc, n = N, batch = B, bytes = Bytes,
                                        batch_bytes = BB, max = Max} = St) ->
    R = Record#{id => {Inc, N + 1}, at => maps:get(at, Record,
                                                   erlang:system_time(microsecond))},
    Frame = encode(R),
    case Bytes + BB + byte_size(Frame) =< Max of
        true ->
            St1 = St#st{n = N + 1, batch = [{From, R, Frame} | B],
                        batch_bytes = BB + byte_size(Frame)},
            %% The commit runs once every append already in the mailbox has joined the
            %% batch: at once when none is there (nothing to wait for), otherwise
            %% behind them.
            case St#st.commit orelse erlang:process_info(self(), message_queue_len) of
                true -> {noreply, St1};
                {message_queue_len, 0} -> commit(St1);
                _ -> self() ! commit, {noreply, St1#st{commit = true}}
            end;
        false ->
            _ = St#st.full orelse
                cell_log:error(cell, "trace journal ~ts is full (~ts of ~ts): the database "
                               "has not taken its records; no new record is kept, so the "
                               "tasks that must record a product's way stop, and nothing "
                               "recorded is lost. Make the database work again (see the "
                               "statistics' lines in the log) or raise journal_max_mb in "
                               "the statistics settings", [St#st.path, mb(Bytes + BB),
                                                           mb(Max)]),
            {reply, {error, journal_full}, St#st{full = true}}
    end;
handle_call({bound, Max}, _From, #st{bytes = Bytes} = St) ->
    {reply, Bytes, taking_again(St#st{max = Max})};
handle_call(attach, {Pid, _}, #st{reader = Old} = St) ->
    _ = case Old of
            {_, Ref} -> demonitor(Ref, [flush]);
            undefined -> true
        end,
    Read = [{Id, read(F)} || {Id, F} <- lists:reverse(St#st.kept)],
    case [Id || {Id, error} <- Read] of
        [] -> ok;
        Unreadable -> cell_log:warning(cell, "trace journal ~ts: ~b records could not be "
                                       "read (of a task no longer in the cell?) and are "
                                       "left out", [St#st.path, length(Unreadable)])
    end,
    {reply, [R || {_, {ok, R}} <- Read], St#st{reader = {Pid, monitor(process, Pid)}}}.

-spec handle_cast({trim, id()}, #st{}) -> {noreply, #st{}}.
handle_cast({trim, Upto}, #st{kept = Kept} = St) ->
    case lists:partition(fun({Id, _}) -> Id > Upto end, Kept) of
        {_, []} ->
            {noreply, St};
        {After, _Done} ->
            ok = cell_file:close_append(St#st.file),
            ok = rewrite(St#st.path, lists:reverse(After)),
            {noreply, taking_again(St#st{file = open_append(St#st.path), kept = After,
                                         bytes = frames_size(After)})}
    end.

-spec handle_info(term(), #st{}) -> {noreply, #st{}}.
handle_info(commit, St) ->
    commit(St);
handle_info({'DOWN', Ref, process, _, _}, #st{reader = {_, Ref}} = St) ->
    {noreply, St#st{reader = undefined}}.

-spec terminate(term(), #st{}) -> ok.
terminate(_Reason, #st{file = undefined}) ->
    ok;
terminate(_Reason, #st{file = File}) ->
    cell_file:close_append(File).

%% The batch written with one write and one flush, its records sent to the reader, then
%% each writer answered.
commit(#st{batch = Batch} = St) ->
    Records = [R || {_, R, _} <- lists:reverse(Batch)],
    Frames = [{Id, F} || {_, #{id := Id}, F} <- lists:reverse(Batch)],
    Result = cell_file:append(St#st.file, [F || {_, F} <- Frames], #{}),
    St1 = St#st{batch = [], batch_bytes = 0, commit = false},
    case Result of
        ok ->
            _ = case St#st.reader of
                    {Reader, _} -> Reader ! {?MODULE, Records};
                    undefined -> ok
                end,
            _ = [gen_server:reply(From, {ok, Id}) || {From, #{id := Id}, _} <- Batch],
            {noreply, St1#st{kept = lists:reverse(Frames, St#st.kept),
                             bytes = St#st.bytes + St#st.batch_bytes}};
        {error, {_, Why}} ->
            cell_log:error(cell, "trace journal ~ts: ~b records could not be written "
                           "(~ts); their tasks stop", [St#st.path, length(Records),
                                                        file:format_error(Why)]),
            _ = [gen_server:reply(From, {error, Why}) || {From, _, _} <- Batch],
            %% What was written of the batch is cut off by writing the file anew.
            ok = cell_file:close_append(St#st.file),
            ok = rewrite(St#st.path, lists:reverse(St#st.kept)),
            {noreply, St1#st{file = open_append(St#st.path)}}
    end.

%%====================================================================
%% The file
%%====================================================================

open_append(Path) ->
    case cell_file:append_file(Path) of
        {ok, File} -> File;
        {error, {_, Why}} -> erlang:error({journal_not_opened, Path, Why})
    end.

frames_size(Frames) ->
    lists:sum([byte_size(F) || {_, F} <- Frames]).

%% Below the bound again after it refused a record (the database took the records, or
%% the bound was raised): the log says so.
taking_again(#st{full = true, bytes = Bytes, max = Max} = St) when Bytes < Max ->
    cell_log:notice(cell, "trace journal ~ts: ~ts of ~ts kept, new records are taken "
                    "again", [St#st.path, mb(Bytes), mb(Max)]),
    St#st{full = false};
taking_again(St) ->
    St.

mb(Bytes) ->
    io_lib:format("~.1f MB", [Bytes / (1024 * 1024)]).

%% Replaced whole with the frames, durably (a crash leaves the old file or the new).
rewrite(Path, Frames) ->
    case cell_file:write(Path, [F || {_, F} <- Frames]) of
        ok -> ok;
        {error, {_, Why}} -> erlang:error({journal_not_written, Path, Why})
    end.

%%====================================================================
%% Tests
%%====================================================================

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

rec(N) ->
    #{id => {1, N}, type => item_transfer_out, task => t, at => N, item => <<"S">>}.

frames(Rs) ->
    [{Id, encode(R)} || #{id := Id} = R <- Rs].

roundtrip_test() ->
    Rs = [rec(N) || N <- lists:seq(1, 5)],
    Bin = iolist_to_binary([encode(R) || R <- Rs]),
    ?assertEqual({frames(Rs), byte_size(Bin), 0}, decode(Bin)),
    ?assertEqual([{ok, R} || R <- Rs], [read(F) || {_, F} <- frames(Rs)]),
    ?assertEqual({[], 0, 0}, decode(<<>>)).

torn_tail_test_() ->
    Rs = [rec(N) || N <- lists:seq(1, 3)],
    Whole = iolist_to_binary([encode(R) || R <- Rs]),
    Last = encode(rec(4)),
    [?_assertEqual({frames(Rs), byte_size(Whole), Cut},
                   decode(<<Whole/binary, (binary:part(Last, 0, Cut))/binary>>))
     || Cut <- [1, 2, 9, 10, 29, byte_size(Last) - 1]].

damaged_tail_test_() ->
    Rs = [rec(1), rec(2)],
    Whole = iolist_to_binary([encode(R) || R <- Rs]),
    Frame = encode(rec(3)),
    %% A bit flipped in the id, in the length's field or in the term.
    [?_assertEqual({frames(Rs), byte_size(Whole), byte_size(Frame)},
                   decode(<<Whole/binary, (flip(Frame, At))/binary>>))
     || At <- [5, 12, byte_size(Frame) - 4]].

flip(Bin, At) ->
    <<Head:At/binary, B, Tail/binary>> = Bin,
    <<Head/binary, (B bxor 1), Tail/binary>>.

unreadable_frame_test() ->
    %% A whole frame of a term that is not a record of its id, or names an atom this
    %% node does not know: read as such, never an atom made.
    Unknown = <<131, 119, 20, "cell_never_an_atom_x">>,    %% SMALL_ATOM_UTF8_EXT
    ?assertEqual(error, read(frame({1, 1}, Unknown))),
    ?assertEqual(error, read(frame({1, 2}, term_to_binary(foo)))),
    ?assertEqual(error, read(frame({1, 3}, term_to_binary(rec(4))))),
    ?assertEqual(error, read(<<"not a frame">>)).

frame({Inc, N}, Body) ->
    Crc = erlang:crc32([<<Inc:64/signed, N:64>>, Body]),
    <<?MARK:16, Inc:64/signed, N:64, (byte_size(Body)):32, Crc:32, Body/binary>>.

-endif.
