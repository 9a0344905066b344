%% @doc What the router's device tasks share beyond the framework's hand-over patterns
%% ({@link cell_handover}): the IPC-2541 events they raise when they start or stop
%% waiting on the machine (SMEMA, a robot), watchdogs, their lane, and whose a whole
%% panel in a work fixture is.
-module(router_task).

-export([starved/1, unstarved/1, blocked/1, unblocked/1]).
-export([watch/5, watchdog/3, lane/1, fixture/1, nest_holder/3]).
-export([upper_position/3]).


-export_type([fixture_facts/0, fixture/0]).

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
    {wait, [{io, Point, {eq, Value}}, watchdog(T, Watchdog, 10000)],
     cell_handover:phase(T, Phase)}.

%% @doc The watchdog wait of a setting.
-spec watchdog(cell_task:task(), atom(), pos_integer()) -> cell_task:wait().
watchdog(T, Setting, Default) ->
    {timer, cell_task:setting(T, Setting, Default)}.

%% What the work segment knows when a whole panel lies in its fixture (its module nest
%% full) and it holds no product itself: its lane; what the other tasks hold
%% ({@link cell_task:others_products/1}); which task is the lane's loading segment;
%% whether that segment's stopper sensor sees a panel; the serial the loading segment
%% offers on the link to the fixture now (`none'); whether the upper robot's gripper
%% sensor sees modules, and whether it is away from this lane's module nest (the
%% machine's in-position signal for that nest off); whether the machine has had time to settle since an
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
%% <li>the upper robot leaves the nest with the modules gripped: the modules leave the
%%     nest as its in-position signal goes, but the nest's sensor and the robot's are
%%     read one after the other, and between the two the robot can look away with the
%%     modules while they still lie in the nest.</li>
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

%% @doc Whose the modules in the module nest of a lane's work fixture are when the
%% upper robot holds a product of that lane whose modules its gripper sensor does not
%% see: its own (`ours') only if no other record puts a product of that lane in the
%% fixture, or `{other, Task, Serial}' for the record that does. The work segment
%% holding a product holds the panel in its fixture (the upper robot's panel left it,
%% the next one came in); the routing robot holding one routes it there. `Stations'
%% are those tasks (the lane's work segment, the routing robot); `Others' is what the
%% other tasks hold ({@link cell_task:others_products/1}). The robot takes modules in
%% the nest as its product's only when this says `ours'.
-spec nest_holder(front | rear, [atom()], [{atom(), cell_product:product()}]) ->
          ours | {other, atom(), binary()}.
nest_holder(Lane, Stations, Others) ->
    case [{Task, S} || {Task, #{serial := S} = P} <- Others, lists:member(Task, Stations),
                       maps:get(lane, P, Lane) =:= Lane] of
        [] -> ours;
        [{Task, S} | _] -> {other, Task, S}
    end.

%% @doc The upper robot's taught position (X, Y of its axes, mm) at `home' or over a
%% lane's module `nest' or `unloading' segment, from the router settings (`upper_*',
%% `rear_lane_offset').
-spec upper_position(cell_task:task(), home | nest | unloading, front | rear) ->
          {float(), float()}.
upper_position(_T, home, _Lane) ->
    {0.0, 0.0};
upper_position(T, Where, Lane) ->
    X = case Where of
            nest -> cell_task:setting(T, upper_nest_x, 250.0);
            unloading -> cell_task:setting(T, upper_unloading_x, 1100.0)
        end,
    Front = cell_task:setting(T, upper_front_y, 150.0),
    Y = case Lane of
            front -> Front;
            rear -> Front + cell_task:setting(T, rear_lane_offset, 350.0)
        end,
    {float(X), float(Y)}.

%% @doc The task's lane: `front' or `rear'.
-spec lane(cell_task:task()) -> front | rear.
lane(T) ->
    cell_task:arg(T, lane, front).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

nest_holder_test_() ->
    P = fun(S, L) -> #{serial => S, lane => L} end,
    Stations = [work_front, lower],
    [%% Nothing else of the lane in the fixture: the upper robot's modules.
     ?_assertEqual(ours, nest_holder(front, Stations, [])),
     ?_assertEqual(ours, nest_holder(front, Stations, [{work_rear, P(<<"B">>, rear)},
                                                       {loading_front, P(<<"C">>, front)}])),
     %% The work segment holds the next panel: the nest holds its modules.
     ?_assertEqual({other, work_front, <<"B">>},
                   nest_holder(front, Stations, [{work_front, P(<<"B">>, front)}])),
     %% The routing robot routes a panel of this lane there.
     ?_assertEqual({other, lower, <<"C">>},
                   nest_holder(front, Stations, [{lower, P(<<"C">>, front)}])),
     ?_assertEqual(ours, nest_holder(front, Stations, [{lower, P(<<"C">>, rear)}]))].

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
