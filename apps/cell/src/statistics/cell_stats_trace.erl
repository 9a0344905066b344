%% @doc The decisions of {@link cell_stats} about a product's way, without processes:
%% which record of the trace journal is still to apply, and when a product no task
%% holds is taken for scrapped.
%%
%% A record of the journal ({@link cell_trace_journal}) is applied once: the
%% statistics write, with their counters, the id of the last record applied, once
%% what the records wrote to the histories is durable; a record at or before that id
%% is never applied again. Ids grow in the order of the journal, across restarts.
-module(cell_stats_trace).

-export([fresh/2, latest/2, unheld/2, left_after_scrap/1, left_failed/2, journal_level/3,
         from_history/2]).

-export_type([unheld/0]).

-type unheld() :: held | {wait, pos_integer()} | scrap.

%% @doc Whether the record `Id' is still to apply: after `Saved', the last durable one
%% (the statistics take every record from the journal, in its order, once each).
-spec fresh(cell_trace_journal:id(), cell_trace_journal:id() | undefined) -> boolean().
fresh(Id, Saved) ->
    Saved =:= undefined orelse Id > Saved.

%% @doc The later of two ids (either may be none yet).
-spec latest(cell_trace_journal:id() | undefined, cell_trace_journal:id() | undefined) ->
          cell_trace_journal:id() | undefined.
latest(undefined, B) -> B;
latest(A, undefined) -> A;
latest(A, B) -> max(A, B).

%% @doc A product no task of the statistics' records holds, seen so `N' writes in a row
%% before, with the tasks the registry has holding it now: `held' when one does (its
%% event is on its way), `{wait, N + 1}' the first time, `scrap' the second (about two
%% seconds with no holder: a hand-over takes far less).
-spec unheld(non_neg_integer(), [term()]) -> unheld().
unheld(_N, [_ | _]) -> held;
unheld(0, []) -> {wait, 1};
unheld(_N, []) -> scrap.

%% @doc What to do when a product leaves the cell that the statistics do not hold any
%% more, by its summary as written: one taken for scrapped is corrected (its exit is
%% durable, so it left); one already out is counted once only.
-spec left_after_scrap(map() | undefined) -> count | {uncount_scrap, atom()} | already_out.
left_after_scrap(#{status := scrapped, exit_task := By}) -> {uncount_scrap, By};
left_after_scrap(#{status := out}) -> already_out;
left_after_scrap(_) -> count.

%% @doc Whether a product left failed: as its exit record says (`Record', the failed
%% flag of the product its task sent out), whatever the statistics know of it
%% (`Known'); that record applied again after a crash then gives the same `left' entry
%% and the same count, though the saves that marked the product failed are not in the
%% journal and the statistics may have lost them. `Known' only for a record without the
%% flag (made before records had it).
-spec left_failed(boolean() | undefined, boolean()) -> boolean().
left_failed(Record, _Known) when is_boolean(Record) -> Record;
left_failed(undefined, Known) -> Known.

%% @doc The trace journal holds `Bytes' of its bound `Max' (see {@link
%% cell_trace_journal:bound/1}); `Warned' tells whether the warning is up (`unknown'
%% at a start of the statistics): `warn' from 80 % of the bound, `clear' once below
%% 70 % again (the gap keeps a journal near 80 % from warning at every write), `same'
%% otherwise.
-spec journal_level(non_neg_integer(), pos_integer(), boolean() | unknown) ->
          warn | clear | same.
journal_level(Bytes, Max, Warned) when Warned =/= true, Bytes * 10 >= Max * 8 -> warn;
journal_level(Bytes, Max, Warned) when Warned =/= false, Bytes * 10 < Max * 7 -> clear;
journal_level(_Bytes, _Max, unknown) -> clear;
journal_level(_Bytes, _Max, _Warned) -> same.

%% @doc A product's summary as its history (oldest first, each entry with its `time'
%% in ms and its `task') tells it, for a product whose summary is not written yet: it
%% entered with its first `entered', and left as its last `left' or `scrapped' says;
%% `unknown' without an entry.
-spec from_history(binary(), [map()]) -> map().
from_history(Serial, History) ->
    case [E || #{event := entered} = E <- History] of
        [] ->
            #{serial => Serial, status => unknown};
        [#{time := At, task := Entry} = In | _] ->
            Product = maps:get(product, In, #{}),
            Failed = is_map(Product) andalso maps:get(failed, Product, false) =:= true,
            Base = #{serial => Serial, recipe => maps:get(recipe, In, <<>>),
                     entered => At, entry_task => Entry},
            case [E || #{event := Ev} = E <- History, Ev =:= left orelse Ev =:= scrapped] of
                [] ->
                    Base#{status => in_cell, failed => Failed, left => undefined,
                          exit_task => undefined};
                Ends ->
                    #{time := Left, task := By} = End = lists:last(Ends),
                    Base#{status => case End of
                                        #{event := left} -> out;
                                        #{event := scrapped} -> scrapped
                                    end,
                          failed => case End of
                                        #{quality := Q} -> Q =:= failed;
                                        _ -> maps:get(failed, End, Failed) =:= true
                                    end,
                          left => Left, exit_task => By}
            end
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

fresh_test_() ->
    [?_assert(fresh({1, 1}, undefined)),
     ?_assertNot(fresh({1, 1}, {1, 1})),
     ?_assertNot(fresh({1, 1}, {1, 2})),
     ?_assert(fresh({1, 3}, {1, 2})),
     %% A later incarnation's ids come after every id of an earlier one.
     ?_assert(fresh({2, 1}, {1, 900}))].

latest_test_() ->
    [?_assertEqual(undefined, latest(undefined, undefined)),
     ?_assertEqual({1, 2}, latest(undefined, {1, 2})),
     ?_assertEqual({1, 2}, latest({1, 2}, undefined)),
     ?_assertEqual({2, 1}, latest({1, 9}, {2, 1}))].

unheld_test_() ->
    [?_assertEqual(held, unheld(0, [{t, 1}])),
     ?_assertEqual(held, unheld(1, [{t, 1}])),
     ?_assertEqual({wait, 1}, unheld(0, [])),
     ?_assertEqual(scrap, unheld(1, []))].

journal_level_test_() ->
    [?_assertEqual(same, journal_level(0, 1000, false)),
     ?_assertEqual(same, journal_level(799, 1000, false)),
     ?_assertEqual(warn, journal_level(800, 1000, false)),
     ?_assertEqual(warn, journal_level(1000, 1000, false)),
     ?_assertEqual(same, journal_level(800, 1000, true)),
     ?_assertEqual(same, journal_level(700, 1000, true)),
     ?_assertEqual(clear, journal_level(699, 1000, true)),
     ?_assertEqual(clear, journal_level(0, 1000, true)),
     ?_assertEqual(same, journal_level(699, 1000, false)),
     %% At a start: up or down at once.
     ?_assertEqual(warn, journal_level(800, 1000, unknown)),
     ?_assertEqual(clear, journal_level(799, 1000, unknown)),
     ?_assertEqual(clear, journal_level(0, 1000, unknown))].

from_history_test_() ->
    In = #{event => entered, time => 10, task => load, recipe => <<"r">>,
           product => #{failed => false}},
    Out = #{event => left, time => 30, task => unload, quality => failed},
    Work = #{event => item_work_start, time => 20, task => work},
    Scrap = #{event => scrapped, time => 40, task => work, failed => true},
    [?_assertEqual(#{serial => <<"S">>, status => unknown}, from_history(<<"S">>, [])),
     ?_assertEqual(#{serial => <<"S">>, status => unknown}, from_history(<<"S">>, [Work])),
     ?_assertEqual(#{serial => <<"S">>, status => in_cell, recipe => <<"r">>, entered => 10,
                     entry_task => load, failed => false, left => undefined,
                     exit_task => undefined},
                   from_history(<<"S">>, [In, Work])),
     ?_assertEqual(#{serial => <<"S">>, status => out, recipe => <<"r">>, entered => 10,
                     entry_task => load, failed => true, left => 30, exit_task => unload},
                   from_history(<<"S">>, [In, Work, Out])),
     ?_assertMatch(#{status := scrapped, failed := true, left := 40, exit_task := work},
                   from_history(<<"S">>, [In, Work, Scrap])),
     %% Marked failed at its entry, still in the cell.
     ?_assertMatch(#{status := in_cell, failed := true},
                   from_history(<<"S">>, [In#{product => #{failed => true}}]))].

left_failed_test_() ->
    [?_assert(left_failed(true, false)),
     ?_assertNot(left_failed(false, true)),
     ?_assert(left_failed(undefined, true)),
     ?_assertNot(left_failed(undefined, false))].

left_after_scrap_test_() ->
    [?_assertEqual(count, left_after_scrap(undefined)),
     ?_assertEqual({uncount_scrap, t}, left_after_scrap(#{status => scrapped,
                                                          exit_task => t})),
     ?_assertEqual(already_out, left_after_scrap(#{status => out, exit_task => t}))].

-endif.
