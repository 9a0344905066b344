%% @doc What the router's device tasks share: their phase, the IPC-2541 events they
%% raise when they start or stop waiting, watchdogs, and errors whose Reset forgets
%% something.
%%
%% The engine answers Reset by re-initialising the task (the seed's ResetException:
%% uninit, then init). The seed lets the task catch it first, to forget its product
%% ("Select RESET to delete product data"); here a task says with {@link error/6} what
%% Reset is to mean, and its `init' asks {@link reset_chosen/1} whether Reset was the
%% answer (the registry of errors records every answer before the task hears it). A
%% task that re-initialises for another reason (a Stop, then Start) finds no Reset and
%% keeps what it holds.
-module(router_task).

-export([phase/2, phase/1, starved/1, unstarved/1, blocked/1, unblocked/1]).
-export([watch/5, watchdog/3, error/6, reset_chosen/1, after_reset/1, interrupted/3,
         interrupted/4, lane/1]).
-export([take/3, take/4, offered/3, finish/4, finish/5, finish/6]).
-export([unheld/3, unheld_anywhere/2, unheld_error/4, fixture/1]).

-export_type([located/0, fixture_facts/0, fixture/0]).

%% Whether the task's own sensors show the product of an interrupted transfer at its
%% station (see interrupted/4).
-type located() :: fun((cell_task:task()) -> boolean()).

%% @doc Sets the task's phase (its own state within its IPC-2541 state).
-spec phase(cell_task:task(), atom()) -> cell_task:task().
phase(T, Phase) ->
    cell_task:put(T, phase, Phase).

-spec phase(cell_task:task()) -> atom().
phase(T) ->
    cell_task:get(T, phase, undefined).

%% @doc EquipmentStarved, unless the task is already STARVED.
-spec starved(cell_task:task()) -> cell_task:task().
starved(T) -> idle(T, starved, fun cell_task:starved/1).

%% @doc EquipmentUnstarved, if the task is STARVED.
-spec unstarved(cell_task:task()) -> cell_task:task().
unstarved(T) -> not_idle(T, starved, fun cell_task:unstarved/1).

%% @doc EquipmentBlocked, unless the task is already BLOCKED.
-spec blocked(cell_task:task()) -> cell_task:task().
blocked(T) -> idle(T, blocked, fun cell_task:blocked/1).

%% @doc EquipmentUnblocked, if the task is BLOCKED.
-spec unblocked(cell_task:task()) -> cell_task:task().
unblocked(T) -> not_idle(T, blocked, fun cell_task:unblocked/1).

%% The event once, when the task enters or leaves that idle state.
idle(T, Why, Event) ->
    case cell_task:state(T) of
        {ready, idle, Why} -> T;
        _ -> Event(T)
    end.

not_idle(T, Why, Event) ->
    case cell_task:state(T) of
        {ready, idle, Why} -> Event(T);
        _ -> T
    end.

%% @doc Waits in a phase for an IO point to take a value, or for a watchdog (a setting
%% in milliseconds) to run out: the step is woken by `{timer, _}' then.
-spec watch(cell_task:task(), atom(), atom(), cell_hal_type:value(), atom()) ->
          cell_task:step_result().
watch(T, Phase, Point, Value, Watchdog) ->
    {wait, [{io, Point, {eq, Value}}, watchdog(T, Watchdog, 10000)], phase(T, Phase)}.

%% @doc The watchdog wait of a setting.
-spec watchdog(cell_task:task(), atom(), pos_integer()) -> cell_task:wait().
watchdog(T, Setting, Default) ->
    {timer, cell_task:setting(T, Setting, Default)}.

%% @doc An error for the operator; `OnReset' is what the task is to do if the answer
%% is Reset (its `init' learns it from {@link reset_chosen/1}).
-spec error(cell_task:task(), binary(), iodata(), iodata(), [cell_alarms:solution()], atom()) ->
          {error, cell_alarms:spec(), cell_task:task()}.
error(T, Id, Caption, Text, Solutions, OnReset) ->
    Pending = {Id, os:system_time(millisecond), OnReset},
    {error, cell_task:error_spec(Id, Caption, Text, Solutions),
     cell_task:put(T, on_reset, Pending)}.

%% @doc In `init': what the task said Reset would mean, if the operator answered its
%% last error with Reset; `none' otherwise. Either way the question is settled.
-spec reset_chosen(cell_task:task()) -> {atom(), cell_task:task()}.
reset_chosen(T) ->
    case cell_task:get(T, on_reset, undefined) of
        undefined ->
            {none, T};
        {Id, Since, OnReset} ->
            Global = <<(atom_to_binary(cell_task:id(T), utf8))/binary, ":", Id/binary>>,
            Chosen = lists:any(fun(#{id := I, what := reset, time := At}) ->
                                       I =:= Global andalso At >= Since;
                                  (_) ->
                                       false
                               end, cell_alarms:history()),
            T1 = cell_task:put(T, on_reset, undefined),
            case Chosen of
                true -> {OnReset, T1};
                false -> {none, T1}
            end
    end.

%% @doc In `init': the task as it is, or without its product if the operator answered
%% its last error with a Reset that forgets it.
-spec after_reset(cell_task:task()) -> cell_task:task().
after_reset(T0) ->
    case reset_chosen(T0) of
        {forget, T} -> cell_task:clear_product(T);
        {_, T} -> T
    end.

%%--------------------------------------------------------------------
%% The steps of a hand-over every station writes alike (seed §2.3.6)
%%--------------------------------------------------------------------

%% @doc Downstream, empty: commits to the partner's offer if it makes one (phase 2),
%% then waits in `Phase' for it to let go (phase 3); else waits for an offer.
-spec take(cell_task:task(), atom(), atom()) -> cell_task:step_result().
take(T, Prev, Phase) ->
    take(T, Prev, Phase, fun(T1) -> T1 end).

%% @doc As {@link take/3}, `OnCommit' applied once committed (a belt started).
-spec take(cell_task:task(), atom(), atom(), fun((cell_task:task()) -> cell_task:task())) ->
          cell_task:step_result().
take(T, Prev, Phase, OnCommit) ->
    case cell_handshake:available(T, Prev) andalso cell_handshake:commit(T, Prev) of
        {ok, T1} -> {wait, {handshake, Prev, available, false}, phase(OnCommit(T1), Phase)};
        {not_available, T1} -> {wait, {handshake, Prev, available, true}, T1};
        false -> {wait, {handshake, Prev, available, true}, T}
    end.

%% @doc Upstream, offered: an offer still open waits for the partner's commit; one
%% that is gone (the link restarted) is made again from `Again'.
-spec offered(cell_task:task(), atom(), atom()) -> cell_task:step_result().
offered(T, Next, Again) ->
    case cell_handshake:phase(T, Next) of
        offered -> {wait, {handshake, Next, not_busy, true}, T};
        _ -> {continue, phase(T, Again)}
    end.

%% @doc Upstream, released: the end of the transfer (phase 4). Completed: on in
%% `Done'; aborted (the partner gave the product back): again from `Again';
%% interrupted: {@link interrupted/3}; else it waits.
-spec finish(cell_task:task(), atom(), atom(), atom()) -> cell_task:step_result().
finish(T, Next, Done, Again) ->
    finish(T, Next, Done, Again, fun(_, T1) -> T1 end).

%% @doc As {@link finish/4}, `Settle(Outcome, T)' applied first once it has ended.
-spec finish(cell_task:task(), atom(), atom(), atom(),
             fun((completed | aborted | interrupted, cell_task:task()) -> cell_task:task())) ->
          cell_task:step_result().
finish(T, Next, Done, Again, Settle) ->
    finish(T, Next, Done, Again, Settle, fun(_) -> false end).

%% @doc As {@link finish/5}; an interruption is settled by {@link interrupted/4} with
%% `Here'.
-spec finish(cell_task:task(), atom(), atom(), atom(),
             fun((completed | aborted | interrupted, cell_task:task()) -> cell_task:task()),
             located()) ->
          cell_task:step_result().
finish(T, Next, Done, Again, Settle, Here) ->
    case cell_handshake:finish(T, Next) of
        {completed, T1} -> {continue, phase(Settle(completed, T1), Done)};
        {aborted, T1} -> {continue, phase(Settle(aborted, T1), Again)};
        {interrupted, T1} -> interrupted(Settle(interrupted, T1), Again, Done, Here);
        {pending, T1} -> {wait, {handshake, Next, not_busy, false}, T1}
    end.

%% @doc After a transfer ended early (seed §2.3.6): a product that had not moved stays
%% with the task (`Have' phase), one that was moving is the operator's to settle:
%% Ignore, it is here (`Have'); Reset, it is not (forgotten: `init' takes `forget').
-spec interrupted(cell_task:task(), atom(), atom()) -> cell_task:step_result().
interrupted(T, Have, Empty) ->
    interrupted(T, Have, Empty, fun(_) -> false end).

%% @doc As {@link interrupted/3}, but a product that was moving and that the task's own
%% sensors show at its station (`Here') is confirmed here without a question. `Have'
%% is kept for the task's `in_transit' step (`transit_have'), where an operator's
%% Ignore goes on.
-spec interrupted(cell_task:task(), atom(), atom(), located()) -> cell_task:step_result().
interrupted(T0, Have, Empty, Here) ->
    T = cell_task:put(T0, transit_have, Have),
    case {cell_task:product(T), cell_handshake:in_transit(T)} of
        {undefined, _} ->
            {continue, phase(T, Empty)};
        {_, false} ->
            {continue, phase(T, Have)};
        {#{serial := S}, true} ->
            case Here(T) of
                true ->
                    cell_task:log(T, brief, "the transfer of product ~ts was interrupted; "
                                  "this station's sensors show where it is: it goes on from here",
                                  [S]),
                    {continue, phase(cell_handshake:confirm_here(T), Have)};
                false ->
                    transfer_question(T, S)
            end
    end.

transfer_question(T, S) ->
    error(phase(T, in_transit), <<"transfer">>, "Transfer interrupted",
          io_lib:format("Product ~ts was moving when its transfer was interrupted.~n"
                        "Check where it is. Select IGNORE if it is at this station, "
                        "RESET if it is not (the station forgets it).", [S]),
          [ignore, reset], forget).

%%--------------------------------------------------------------------
%% A product a station's sensor sees that no record holds
%%--------------------------------------------------------------------

%% @doc Whether what a station's sensor sees (its own task holding no product) is in no
%% record: none of the tasks `Takers' (those that may hold it there, a robot that took
%% charge of it in place, say) holds a product of `Lane' (a product without a lane
%% counts as of every lane). `Others' is what the other tasks hold
%% ({@link cell_task:others_products/1}).
-spec unheld(front | rear, [atom()], [{atom(), cell_product:product()}]) -> boolean().
unheld(Lane, Takers, Others) ->
    [x || {Task, P} <- Others, lists:member(Task, Takers),
          maps:get(lane, P, Lane) =:= Lane] =:= [].

%% What the work segment knows when a whole panel lies in its fixture (its module nest
%% full) and it holds no product itself: its lane; what the other tasks hold
%% ({@link cell_task:others_products/1}); which task is the lane's loading segment;
%% whether that segment's stopper sensor sees a panel; the serial the loading segment
%% offers on the link to the fixture now (`none'); whether the upper robot's gripper
%% sensor sees modules, and whether it is away from this lane's module nest (its last
%% move, to another place, done); whether the machine has had time to settle since an
%% earlier look found the panel in no record (`again': a transfer time later, or the
%% operator's answer since).
-type fixture_facts() :: #{lane := front | rear,
                           others := [{atom(), cell_product:product()}],
                           loading := atom(),
                           stopper := boolean(),
                           offered := binary() | none,
                           gripper := boolean(),
                           upper_away := boolean(),
                           again := boolean()}.
%% Whose that panel is: a robot's that took charge of it where it lies; the one the
%% loading segment offers, arrived ahead of its hand-over (`arrived'); the one the
%% loading segment holds away from its stopper without offering it (its question to
%% the operator pending, say); or nobody's (`unheld'), which only a look taken once the
%% machine has settled tells: a first look that finds no record is `look_again'.
-type fixture() :: {robot, lower | upper} | {arrived, binary()} | {loading, binary()} |
                   look_again | unheld.

%% @doc Whose the whole panel in a work fixture is, when the work segment holds none
%% (see `fixture_facts()'). A record explains the panel only where that record's
%% product physically can be in the fixture:
%%
%% <ul>
%% <li>the routing robot's product of this lane: it routes panels where they lie;</li>
%% <li>the upper robot's product of this lane, unless its gripper sensor sees modules
%%     and the robot is away from this nest (they left the nest as it left): it takes
%%     charge of them in the nest and grips them there, and they may have stuck
%%     there. While it moves, they may not have left yet;</li>
%% <li>the loading segment's product of this lane, only once its stopper sensor sees no
%%     panel: at the stopper it is on the loading segment, not here. Offered on the
%%     link to the fixture, it is that panel, arrived before the hand-over ended (a
%%     restart cut it off): the work segment takes it in through the hand-over, as it
%%     lies. Held without an offer, the loading segment's record is still being
%%     settled.</li>
%% </ul>
%%
%% In the normal hand-over the work segment holds the product from its commit on, so
%% this is not asked.
%%
%% The records and the sensors are read one after the other while the other tasks run
%% on, and two moments of the machine look, in such a snapshot, like a panel in no
%% record, though the panel is a robot's:
%%
%% <ul>
%% <li>the routing robot hands the routed panel to the upper robot: the routing robot's
%%     record is gone at its release, the upper robot's is there only once saved, a
%%     moment later (a Stop that came as the upper robot committed waits for the
%%     hand-over, while this segment, stopped at once, starts again and
%%     reconciles);</li>
%% <li>the upper robot leaves the nest with the modules gripped: its new position is
%%     written before the command to move there, and between the two the robot looks
%%     away with the modules (its last move done), while they still lie in the
%%     nest.</li>
%% </ul>
%%
%% Neither lasts: so no record found at a first look is `look_again', and only a look
%% taken once the machine has settled (`again': a transfer time later, or after the
%% operator's answer) tells `unheld'.
-spec fixture(fixture_facts()) -> fixture().
fixture(#{lane := Lane, others := Others, loading := Loading, stopper := Stopper,
          offered := Offered, gripper := Gripper, upper_away := Away, again := Again}) ->
    Of = fun(Task) -> [S || {T, #{serial := S} = P} <- Others, T =:= Task,
                            maps:get(lane, P, Lane) =:= Lane] end,
    %% A sensor that sees the product elsewhere rules its record out.
    Elsewhere = fun(true, _Task) -> []; (false, Task) -> Of(Task) end,
    case {Of(lower), Elsewhere(Gripper andalso Away, upper),
          Elsewhere(Stopper, Loading)} of
        {[_ | _], _, _} -> {robot, lower};
        {[], [_ | _], _} -> {robot, upper};
        {[], [], [S | _]} when S =:= Offered -> {arrived, S};
        {[], [], [S | _]} -> {loading, S};
        {[], [], []} when Again -> unheld;
        {[], [], []} -> look_again
    end.

%% @doc As {@link unheld/3}, for a station any lane's products may reach (the upper
%% robot's gripper): none of the tasks `Takers' holds a product.
-spec unheld_anywhere([atom()], [{atom(), cell_product:product()}]) -> boolean().
unheld_anywhere(Takers, Others) ->
    [x || {Task, _P} <- Others, lists:member(Task, Takers)] =:= [].

%% @doc The operator's error for it: `Where' says what lies where ("a panel lies in the
%% work fixture of lane front"); the operator takes it out of the machine and selects
%% RETRY, and the task looks again.
-spec unheld_error(cell_task:task(), iodata(), iodata(), [term()]) ->
          {error, cell_alarms:spec(), cell_task:task()}.
unheld_error(T, Caption, Where, Args) ->
    {error, cell_task:error_spec(
              <<"unheld">>, Caption,
              [io_lib:format(Where, Args),
               " and no record holds it: take it out of the machine, then select RETRY."],
              [retry]),
     T}.

%% @doc The task's lane: `front' or `rear'.
-spec lane(cell_task:task()) -> front | rear.
lane(T) ->
    cell_task:arg(T, lane, front).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

unheld_test_() ->
    P = fun(Lane) -> #{serial => <<"P1">>, recipe => <<"r">>, failed => false, lane => Lane} end,
    [%% Nobody holds anything: in no record.
     ?_assert(unheld(front, [lower, upper], [])),
     %% A robot holds a product of this lane: it may be the one seen.
     ?_assertNot(unheld(front, [lower, upper], [{lower, P(front)}])),
     ?_assertNot(unheld(front, [lower, upper], [{upper, P(front)}])),
     %% Of the other lane, or held by a task that is not a taker (the loading segment
     %% before the fixture): in no record.
     ?_assert(unheld(front, [lower, upper], [{lower, P(rear)}])),
     ?_assert(unheld(front, [lower, upper], [{loading_front, P(front)}])),
     %% A product without a lane may be of any lane.
     ?_assertNot(unheld(rear, [upper], [{upper, maps:remove(lane, P(front))}])),
     %% A taker whose sensor sees its product elsewhere is left out by the caller: its
     %% record explains nothing here.
     ?_assert(unheld(front, [], [{upper, P(front)}])),
     %% Anywhere: any lane's product of a taker.
     ?_assertNot(unheld_anywhere([unloading_rear], [{unloading_rear, P(rear)}])),
     ?_assert(unheld_anywhere([unloading_rear], [{unloading_front, P(front)}])),
     ?_assert(unheld_anywhere([], [{unloading_front, P(front)}]))].

fixture_test_() ->
    P = fun(S, Lane) -> #{serial => S, recipe => <<"r">>, failed => false, lane => Lane} end,
    F = fun(Others, More) ->
                fixture(maps:merge(#{lane => front, others => Others, loading => loading_front,
                                     stopper => false, offered => none, gripper => false,
                                     upper_away => false, again => true},
                                   More))
        end,
    [%% Nobody holds anything: in no record.
     ?_assertEqual(unheld, F([], #{})),
     %% The routing robot routes panels of its lane where they lie; of the other lane
     %% it does not explain this one.
     ?_assertEqual({robot, lower}, F([{lower, P(<<"P1">>, front)}], #{})),
     ?_assertEqual(unheld, F([{lower, P(<<"P1">>, rear)}], #{})),
     ?_assertEqual({robot, lower}, F([{lower, maps:remove(lane, P(<<"P1">>, rear))}], #{})),
     %% The upper robot: its product is in the nest while its gripper sees nothing, or
     %% gripped there, or on its way out; in the gripper once the robot is away with
     %% modules in it.
     ?_assertEqual({robot, upper}, F([{upper, P(<<"P1">>, front)}], #{})),
     ?_assertEqual({robot, upper}, F([{upper, P(<<"P1">>, front)}], #{upper_away => true})),
     ?_assertEqual({robot, upper}, F([{upper, P(<<"P1">>, front)}], #{gripper => true})),
     ?_assertEqual(unheld, F([{upper, P(<<"P1">>, front)}],
                             #{gripper => true, upper_away => true})),
     ?_assertEqual(unheld, F([{upper, P(<<"P1">>, rear)}], #{})),
     %% The wedge: the loading segment holds and offers the panel, its stopper sees
     %% it: the panel in the fixture is another one, in no record, whatever the upper
     %% robot carries in its gripper.
     ?_assertEqual(unheld, F([{loading_front, P(<<"P2">>, front)}],
                             #{stopper => true, offered => <<"P2">>})),
     ?_assertEqual(unheld, F([{loading_front, P(<<"P2">>, front)},
                              {upper, P(<<"P1">>, front)}],
                             #{stopper => true, offered => <<"P2">>, gripper => true,
                               upper_away => true})),
     %% Past its stopper and offered: it is the panel in the fixture, taken in.
     ?_assertEqual({arrived, <<"P2">>}, F([{loading_front, P(<<"P2">>, front)}],
                                          #{offered => <<"P2">>})),
     ?_assertEqual({arrived, <<"P2">>}, F([{loading_front, P(<<"P2">>, front)},
                                           {upper, P(<<"P1">>, front)}],
                                          #{offered => <<"P2">>, gripper => true,
                                            upper_away => true})),
     %% Past its stopper, not offered (or another serial offered): still being settled.
     ?_assertEqual({loading, <<"P2">>}, F([{loading_front, P(<<"P2">>, front)}], #{})),
     ?_assertEqual({loading, <<"P2">>}, F([{loading_front, P(<<"P2">>, front)}],
                                          #{offered => <<"P3">>})),
     %% Another lane's loading segment, or its product of the other lane: no record here.
     ?_assertEqual(unheld, F([{loading_rear, P(<<"P2">>, front)}], #{offered => <<"P2">>})),
     ?_assertEqual(unheld, F([{loading_front, P(<<"P2">>, rear)}], #{offered => <<"P2">>})),
     %% The stopper sees a panel the loading segment does not hold: no record here.
     ?_assertEqual(unheld, F([], #{stopper => true})),
     %% A first look that finds no record looks again once the machine has settled;
     %% one that finds a record needs no second look.
     ?_assertEqual(look_again, F([], #{again => false})),
     ?_assertEqual(look_again, F([{loading_front, P(<<"P2">>, front)}],
                                 #{stopper => true, offered => <<"P2">>, again => false})),
     ?_assertEqual({robot, lower}, F([{lower, P(<<"P1">>, front)}], #{again => false})),
     ?_assertEqual({arrived, <<"P2">>}, F([{loading_front, P(<<"P2">>, front)}],
                                          #{offered => <<"P2">>, again => false})),
     %% What misfired: a Stop as the routing robot finished routing P1 and offered it,
     %% the upper robot committed; the two hand it over (a transfer holds the Stop)
     %% while the work segment, off at once, starts again and reconciles. The routing
     %% robot's record is gone at its release, the upper robot's not yet saved; the nest
     %% full, the gripper empty, the robot's last move (away from the nest) done; the
     %% loading segment offers the next panel, P2, held at its stopper. Looked at again,
     %% the upper robot holds P1.
     ?_assertEqual(look_again, F([{loading_front, P(<<"P2">>, front)}],
                                 #{stopper => true, offered => <<"P2">>, gripper => false,
                                   upper_away => true, again => false})),
     ?_assertEqual({robot, upper}, F([{loading_front, P(<<"P2">>, front)},
                                      {upper, P(<<"P1">>, front)}],
                                     #{stopper => true, offered => <<"P2">>,
                                       gripper => false, upper_away => true,
                                       again => true})),
     %% The upper robot, the modules of P1 gripped in the nest, has written its next
     %% position (the unloading segment) but not yet the command to go: its last move
     %% (to the nest) done, it reads as away with modules, and its record is ruled out
     %% while the modules still lie in the nest. Looked at again, it has left with them
     %% (the nest empty: the frame, not asked here) or is still seen moving.
     ?_assertEqual(look_again, F([{upper, P(<<"P1">>, front)}],
                                 #{gripper => true, upper_away => true, again => false})),
     ?_assertEqual({robot, upper}, F([{upper, P(<<"P1">>, front)}],
                                     #{gripper => true, upper_away => false,
                                       again => true}))].

-endif.
