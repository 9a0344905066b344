%% @doc The decisions of a task's hand-over patterns ({@link cell_handover}), without
%% processes, files or IO: each takes what the task knows and says what it is to do.
%% `cell_handover' reads the facts, calls these, and carries the answer out.
-module(cell_handover_core).

-export([take/2, offered/1, finished/1, interrupted/2, reset_chosen/3, reconcile/2,
         unheld/3, unheld_anywhere/2]).

-export_type([reset_pending/0, answer/0]).

%% What a task said Reset is to mean, pending while its error waits: the error's id,
%% when it was raised (ms), the meaning.
-type reset_pending() :: {binary(), integer(), atom()}.
%% An operator's answer as the task's step or reconcile sees it.
-type answer() :: cell_alarms:solution() | undefined.

%% @doc Downstream, empty: whether to commit to the partner's offer (Available seen)
%% and, once the commit is answered, what follows: `commit' to try it; then `{ok, _}'
%% from the link is `committed', `not_available' is `wait_offer' (withdrawn first).
-spec take(boolean(), none | ok | not_available) -> commit | committed | wait_offer.
take(false, _) -> wait_offer;
take(true, none) -> commit;
take(true, ok) -> committed;
take(true, not_available) -> wait_offer.

%% @doc Upstream, offered: an offer still open waits for the partner's commit; any
%% other phase of the link means the offer is gone (the link restarted, a Pause
%% withdrew it) and is made again.
-spec offered(cell_handshake_link:phase()) -> wait | again.
offered(offered) -> wait;
offered(_) -> again.

%% @doc Upstream, released: what the outcome of the transfer (seed §2.3.6, phase 4)
%% means for the task: on to its `done' phase, `again' (the product given back, to be
%% offered again), settle an interruption, or wait for the partner's NotBusy off.
-spec finished(completed | aborted | interrupted | pending) -> done | again | interrupted | wait.
finished(completed) -> done;
finished(aborted) -> again;
finished(interrupted) -> interrupted;
finished(pending) -> wait.

%% @doc After a transfer ended early: with no product the task is empty; a product
%% that had not moved (not marked in transit) stays with it; one that was moving is
%% the operator's to settle, unless the task's own sensors show it here.
-spec interrupted(boolean(), boolean()) -> empty | have | moving.
interrupted(false, _) -> empty;
interrupted(true, false) -> have;
interrupted(true, true) -> moving.

%% @doc Whether the operator answered the task's pending error with Reset: an answer
%% `reset' to the same error (`GlobalId', `Task:Id') given at or after the time it was
%% raised, in the alarms' history.
-spec reset_chosen(reset_pending(), binary(), [cell_alarms:answer_record()]) -> boolean().
reset_chosen({_Id, Since, _OnReset}, GlobalId, History) ->
    lists:any(fun(#{id := I, what := reset, time := At}) -> I =:= GlobalId andalso At >= Since;
                 (_) -> false
              end, History).

%% @doc In `reconcile', the record against what the station sees: holding no product,
%% `empty'; holding one, `look' at the sensor first (and again at Retry); the
%% operator's Ignore says it is `here', Reset that it is `gone' (taken out).
-spec reconcile(boolean(), answer()) -> empty | look | here | gone.
reconcile(false, _) -> empty;
reconcile(true, undefined) -> look;
reconcile(true, retry) -> look;
reconcile(true, ignore) -> here;
reconcile(true, reset) -> gone;
reconcile(true, _Close) -> look.

%% @doc Whether what a station's sensor sees (its own task holding no product) is in no
%% record: none of the tasks `Takers' (those whose product may lie there) holds a
%% product of `Lane'; a product without a lane counts as of every lane. `Others' is
%% what the other tasks hold ({@link cell_task:others_products/1}).
-spec unheld(term(), [atom()], [{atom(), cell_product:product()}]) -> boolean().
unheld(Lane, Takers, Others) ->
    [x || {Task, P} <- Others, lists:member(Task, Takers),
          maps:get(lane, P, Lane) =:= Lane] =:= [].

%% @doc As {@link unheld/3}, for a station any lane's products may reach.
-spec unheld_anywhere([atom()], [{atom(), cell_product:product()}]) -> boolean().
unheld_anywhere(Takers, Others) ->
    [x || {Task, _P} <- Others, lists:member(Task, Takers)] =:= [].

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

take_test_() ->
    [?_assertEqual(wait_offer, take(false, none)),
     ?_assertEqual(commit, take(true, none)),
     ?_assertEqual(committed, take(true, ok)),
     %% TryAbortOffering won the race: the offer went before the commit.
     ?_assertEqual(wait_offer, take(true, not_available))].

offered_test_() ->
    [?_assertEqual(wait, offered(offered))] ++
        [?_assertEqual(again, offered(P)) || P <- [idle, committed, released, aborting]].

finished_test_() ->
    [?_assertEqual(done, finished(completed)), ?_assertEqual(again, finished(aborted)),
     ?_assertEqual(interrupted, finished(interrupted)), ?_assertEqual(wait, finished(pending))].

interrupted_test_() ->
    [?_assertEqual(empty, interrupted(false, false)),
     ?_assertEqual(empty, interrupted(false, true)),
     ?_assertEqual(have, interrupted(true, false)),
     ?_assertEqual(moving, interrupted(true, true))].

reset_chosen_test_() ->
    Pending = {<<"transfer">>, 1000, forget},
    Answer = fun(Id, What, At) -> #{id => Id, task => t, caption => <<"c">>, what => What,
                                    who => <<"op">>, time => At} end,
    [?_assertNot(reset_chosen(Pending, <<"t:transfer">>, [])),
     ?_assert(reset_chosen(Pending, <<"t:transfer">>, [Answer(<<"t:transfer">>, reset, 1000)])),
     ?_assert(reset_chosen(Pending, <<"t:transfer">>, [Answer(<<"t:transfer">>, reset, 1001)])),
     %% An older answer to the same error id is not this one's.
     ?_assertNot(reset_chosen(Pending, <<"t:transfer">>, [Answer(<<"t:transfer">>, reset, 999)])),
     %% Another answer, or another task's error.
     ?_assertNot(reset_chosen(Pending, <<"t:transfer">>, [Answer(<<"t:transfer">>, ignore, 1001)])),
     ?_assertNot(reset_chosen(Pending, <<"t:transfer">>, [Answer(<<"u:transfer">>, reset, 1001)])),
     ?_assert(reset_chosen(Pending, <<"t:transfer">>, [Answer(<<"x">>, retry, 2000),
                                                       Answer(<<"t:transfer">>, reset, 2000)]))].

reconcile_test_() ->
    [?_assertEqual(empty, reconcile(false, A)) || A <- [undefined, retry, ignore, reset]] ++
        [?_assertEqual(look, reconcile(true, undefined)),
         ?_assertEqual(look, reconcile(true, retry)),
         ?_assertEqual(look, reconcile(true, close)),
         ?_assertEqual(here, reconcile(true, ignore)),
         ?_assertEqual(gone, reconcile(true, reset))].

unheld_test_() ->
    P = fun(Lane) -> #{serial => <<"P1">>, recipe => <<"r">>, failed => false, lane => Lane} end,
    [%% Nobody holds anything: in no record.
     ?_assert(unheld(front, [lower, upper], [])),
     %% A taker holds a product of this lane: it may be the one seen.
     ?_assertNot(unheld(front, [lower, upper], [{lower, P(front)}])),
     ?_assertNot(unheld(front, [lower, upper], [{upper, P(front)}])),
     %% Of the other lane, or held by a task that is not a taker: in no record.
     ?_assert(unheld(front, [lower, upper], [{lower, P(rear)}])),
     ?_assert(unheld(front, [lower, upper], [{loading_front, P(front)}])),
     %% A product without a lane may be of any lane.
     ?_assertNot(unheld(rear, [upper], [{upper, maps:remove(lane, P(front))}])),
     %% A taker whose sensor sees its product elsewhere is left out by the caller.
     ?_assert(unheld(front, [], [{upper, P(front)}])),
     %% Anywhere: any lane's product of a taker.
     ?_assertNot(unheld_anywhere([unloading_rear], [{unloading_rear, P(rear)}])),
     ?_assert(unheld_anywhere([unloading_rear], [{unloading_front, P(front)}])),
     ?_assert(unheld_anywhere([], [{unloading_front, P(front)}]))].

-endif.
