%% Properties of the trace journal's frames ({@link cell_trace_journal}) and of the
%% statistics' replay of it ({@link cell_stats_trace}).
-module(prop_cell_trace_journal).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

cut_test_() -> prop(prop_a_cut_file_keeps_the_whole_records()).
replay_test_() -> prop(prop_replay_counts_each_record_once()).

prop(P) ->
    {timeout, 120, ?_assert(proper:quickcheck(P, [{to_file, user}, {numtests, 300}]))}.

%% A file cut anywhere (a crash in the middle of an append) reads as the records written
%% whole before the cut, and the bytes after them are the torn tail.
prop_a_cut_file_keeps_the_whole_records() ->
    ?FORALL({Records, Cut}, {list(record()), nat()},
            begin
                Frames = [cell_trace_journal:encode(R) || R <- Records],
                Bin = iolist_to_binary(Frames),
                At = Cut rem (byte_size(Bin) + 1),
                {Read, Good, Torn} = cell_trace_journal:decode(binary:part(Bin, 0, At)),
                Whole = whole(Frames, At, 0, 0),
                Good =:= lists:sum([byte_size(F) || F <- lists:sublist(Frames, Whole)])
                    andalso Torn =:= At - Good
                    andalso [cell_trace_journal:read(F) || {_, F} <- Read]
                            =:= [{ok, R} || R <- lists:sublist(Records, Whole)]
            end).

%% How many frames lie whole before the cut.
whole([F | Fs], At, Used, N) when Used + byte_size(F) =< At ->
    whole(Fs, At, Used + byte_size(F), N + 1);
whole(_, _At, _Used, N) ->
    N.

record() ->
    ?LET({I, N, Type, Task, At, Item},
         {pos_integer(), pos_integer(), elements([product_saved, item_transfer_in,
                                                  item_transfer_out, alarm_answered]),
          elements([load, work, unload]), integer(), binary()},
         #{id => {I, N}, type => Type, task => Task, at => At, item => Item}).

%% Restarts at any point, each replaying the journal: every record's effects are in the
%% durable books exactly once. A run applies the fresh records in order and may save its
%% books (counters and the id of the last record applied, together) before it crashes;
%% what it applied after its last save is lost with it. The model: the books hold each
%% id of the journal once at the end.
prop_replay_counts_each_record_once() ->
    ?FORALL({Incs, Runs}, {non_empty(list(range(1, 4))), list({nat(), nat()})},
            begin
                Ids = [{I, N} || {I, Count} <- lists:zip(lists:seq(1, length(Incs)), Incs),
                                 N <- lists:seq(1, Count)],
                All = length(Ids),
                {_, Counted} = lists:foldl(fun({SaveAt, CrashAt}, Books) ->
                                                   run(Ids, Books, SaveAt, CrashAt)
                                           end, {undefined, []}, Runs ++ [{All, All}]),
                Counted =:= Ids
            end).

%% One run from the durable books {Saved, Counted}: applies the fresh records and saves
%% after SaveAt of them, unless it crashes first (after CrashAt).
run(Ids, {Saved, Counted}, SaveAt, CrashAt) ->
    Fresh = [Id || Id <- Ids, cell_stats_trace:fresh(Id, Saved)],
    case lists:sublist(Fresh, SaveAt) of
        Applied when SaveAt =< CrashAt, Applied =/= [] ->
            {lists:foldl(fun cell_stats_trace:latest/2, Saved, Applied), Counted ++ Applied};
        _ ->
            {Saved, Counted}
    end.
