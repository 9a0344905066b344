%% The monitor's decisions, without a process: each observation in, the effects out.
-module(cell_monitor_core_tests).
-include_lib("eunit/include/eunit.hrl").

%% The spec, for prop_cell_monitor too.
-export([spec/0]).

-define(ESTOP, {general, estop_voltage}).
-define(KEY, {general, service_key}).
-define(DOOR, {general, door_locked}).
-define(AIR, {general, air_ok}).
-define(X_ERROR, {axes, x_error}).
-define(X_WARNING, {axes, x_warning}).
-define(X_CODE, {axes, x_code}).
-define(X_RESET, {axes, x_reset}).
-define(X_OVERRIDE, {axes, x_override}).
-define(Y_OVERRIDE, {axes, y_override}).
-define(GREEN, {general, beacon_green}).
-define(RED, {general, beacon_red}).
-define(PLC, {connection, plc1}).
-define(CAM, {hardware, camera}).

spec() ->
    {ok, Spec} = cell_monitor_spec:validate(
                   #{hal => #{connections => [#{id => plc1, driver => cell_hal_sim}],
                              groups => [#{id => general, module => cell_monitor_test_io,
                                           connection => plc1, opts => #{part => general}},
                                         #{id => axes, module => cell_monitor_test_io,
                                           connection => plc1, opts => #{part => axes}}],
                              hardware => [#{id => camera, kind => camera, type => sim}]},
                     monitor => #{io => #{estop_ok => ?ESTOP, service_key => ?KEY,
                                          door_locked => ?DOOR, air_ok => ?AIR,
                                          beacon_red => ?RED,
                                          beacon_yellow => {general, beacon_yellow},
                                          beacon_green => ?GREEN,
                                          beacon_blue => {general, beacon_blue}},
                                  drives => [#{id => x, caption => <<"X axis">>,
                                               error => ?X_ERROR, warning => ?X_WARNING,
                                               code => ?X_CODE, reset => ?X_RESET,
                                               override => ?X_OVERRIDE},
                                             #{id => y, override => ?Y_OVERRIDE,
                                               override_scale => 0.01}]}}),
    Spec.

settings() -> cell_settings_schema:defaults(cell_monitor_settings).

cell() ->
    #{state => off, request => stop, estop => false, service_mode => false,
      has_alarm => false, has_error => false, has_warning => false}.

new() ->
    {Core, _} = cell_monitor_core:new(spec(), #{settings => settings(), speed => 50,
                                                cell => cell()}),
    Core.

%% A monitor that has seen its inputs good and its devices up.
healthy() ->
    {Core, _} = run([{device, ?PLC, up}, {device, ?CAM, up}, {point, ?ESTOP, true},
                     {point, ?KEY, false}, {point, ?DOOR, true}, {point, ?AIR, true},
                     {point, ?X_ERROR, false}, {point, ?X_WARNING, false},
                     {point, ?X_CODE, 0}, start], new()),
    Core.

run(Events, Core) ->
    lists:foldl(fun(E, {C, Acc}) ->
                        {C1, Eff} = cell_monitor_core:handle(E, C),
                        {C1, Acc ++ Eff}
                end, {Core, []}, Events).

effects(Events, Core) ->
    element(2, run(Events, Core)).

writes(Effects) -> [{P, V} || {write, P, V} <- Effects].

kinds(Effects) -> [element(1, E) || E <- Effects, element(1, E) =/= log].

%% -------------------------------------------------------------------------------------

first_outputs_test() ->
    {_, Effects} = cell_monitor_core:new(spec(), #{settings => settings(), speed => 50,
                                                   cell => cell()}),
    ?assertEqual(lists:sort([{?X_RESET, false}, {?RED, false}, {{general, beacon_yellow}, false},
                             {?GREEN, false}, {{general, beacon_blue}, false},
                             {?X_OVERRIDE, 50}, {?Y_OVERRIDE, 0.5}]),
                 lists:sort(writes(Effects))),
    ?assertEqual([], [T || {timer, T, _} <- Effects]).

same_value_twice_does_nothing_test() ->
    C = healthy(),
    ?assertEqual([], effects([{point, ?DOOR, true}, {point, ?ESTOP, true},
                              {device, ?PLC, up}], C)).

estop_circuit_test_() ->
    C = healthy(),
    {Open, E1} = run([{point, ?ESTOP, false}], C),
    [?_assertEqual([{estop, true}], E1),
     %% The connection drops while it is open: nothing changes; back, open: raised again.
     ?_assertEqual([], effects([{point, ?ESTOP, unknown}], Open)),
     ?_assertEqual([{estop, true}],
                   effects([{point, ?ESTOP, unknown}, {point, ?ESTOP, false}], Open)),
     ?_assertEqual([{estop, false}], effects([{point, ?ESTOP, true}], Open)),
     %% Closed after being unknown: released only because the monitor raised it.
     ?_assertEqual([{estop, false}],
                   effects([{point, ?ESTOP, unknown}, {point, ?ESTOP, true}], Open)),
     ?_assertMatch(#{estop_raised := true}, cell_monitor_core:info(Open)),
     %% An emergency stop somebody else raised is never released by the circuit.
     ?_assertEqual([], [E || {estop, _} = E
                                 <- effects([{cell, (cell())#{estop := true}},
                                             {point, ?ESTOP, unknown}, {point, ?ESTOP, true}], C)]),
     %% At start, a closed circuit releases nothing.
     ?_assertEqual([], [E || {estop, _} = E <- effects([{point, ?ESTOP, true}], new())]),
     %% A monitor started while the circuit's emergency stop is active (the one before
     %% it raised it and was replaced): the circuit read closed releases it; read open,
     %% it stays raised and is released when the circuit closes.
     ?_assertEqual([{estop, false}],
                   [E || {estop, _} = E <- effects([{point, ?ESTOP, true}], adopted())]),
     ?_assertEqual([{estop, true}, {estop, false}],
                   [E || {estop, _} = E <- effects([{point, ?ESTOP, false},
                                                    {point, ?ESTOP, true}], adopted())])].

%% A monitor that starts with the circuit's emergency stop active.
adopted() ->
    {Core, _} = cell_monitor_core:new(spec(), #{settings => settings(), speed => 50,
                                                cell => (cell())#{estop := true},
                                                estop_raised => true}),
    Core.

service_key_test_() ->
    C = healthy(),
    InService = (cell())#{service_mode := true},
    [?_assertEqual([{service_mode, true}],
                   [E || {service_mode, _} = E <- effects([{point, ?KEY, true}], C)]),
     ?_assertEqual([{service_mode, true}, {service_mode, false}],
                   [E || {service_mode, _} = E <- effects([{point, ?KEY, true},
                                                           {point, ?KEY, false}], C)]),
     %% Known for the first time (at start, after a reconnect): applied only if it
     %% differs from the service mode in force.
     ?_assertEqual([], [E || {service_mode, _} = E <- effects([{point, ?KEY, false}], new())]),
     ?_assertEqual([{service_mode, true}],
                   [E || {service_mode, _} = E <- effects([{point, ?KEY, true}], new())]),
     ?_assertEqual([], [E || {service_mode, _} = E
                                 <- effects([{cell, InService}, {point, ?KEY, true}], new())]),
     ?_assertEqual([{service_mode, false}],
                   [E || {service_mode, _} = E
                             <- effects([{cell, InService}, {point, ?KEY, false}], new())])].

door_and_air_test_() ->
    C = healthy(),
    S = settings(),
    {LowAir, _} = run([{point, ?AIR, false}], C),
    [?_assertEqual([{warning, <<"door">>, maps:get(door_caption, S), maps:get(door_text, S)}],
                   effects([{point, ?DOOR, false}], C)),
     ?_assertEqual([{reset_warning, <<"door">>}],
                   effects([{point, ?DOOR, true}], element(1, run([{point, ?DOOR, false}], C)))),
     ?_assertEqual([], effects([{point, ?DOOR, unknown}], C)),
     ?_assertEqual([{warning, <<"air">>, <<"Air pressure low">>, maps:get(air_text, S)}],
                   effects([{point, ?AIR, false}], C)),
     %% A new text applies to the warning on show, and only to it.
     ?_assertEqual([{warning, <<"air">>, <<"Low air">>, maps:get(air_text, S)}],
                   [W || {warning, _, _, _} = W
                             <- effects([{settings, S#{air_caption := <<"Low air">>}}], LowAir)]),
     ?_assertEqual([], [W || {warning, _, _, _} = W
                                 <- effects([{settings, S#{air_caption := <<"Low air">>}}], C)])].

drive_reset_sequence_test() ->
    {C1, E1} = run([{point, ?X_CODE, 17}, {point, ?X_ERROR, true}], healthy()),
    ?assertEqual([{?X_RESET, true}], writes(E1)),
    ?assertMatch([{warning, <<"drive.x">>, <<"Drive X axis in error">>, _}],
                 [W || {warning, _, _, _} = W <- E1]),
    [{warning, _, _, Text}] = [W || {warning, _, _, _} = W <- E1],
    ?assertNotEqual(nomatch, binary:match(Text, <<"code 17, 0x11">>)),
    ?assertNotEqual(nomatch, binary:match(Text, <<"reset 1 of 3">>)),
    ?assert(lists:member({timer, {reset_pulse, x}, 200}, E1)),
    %% The pulse ends; the first wait; the second and third pulse, waits doubling.
    {C2, E2} = run([{timeout, {reset_pulse, x}}], C1),
    ?assertEqual([{?X_RESET, false}], writes(E2)),
    ?assert(lists:member({timer, {reset_wait, x}, 1000}, E2)),
    {C3, E3} = run([{timeout, {reset_wait, x}}, {timeout, {reset_pulse, x}}], C2),
    ?assertEqual([{?X_RESET, true}, {?X_RESET, false}], writes(E3)),
    ?assert(lists:member({timer, {reset_wait, x}, 2000}, E3)),
    {C4, E4} = run([{timeout, {reset_wait, x}}, {timeout, {reset_pulse, x}}], C3),
    ?assert(lists:member({timer, {reset_wait, x}, 4000}, E4)),
    %% After the third: handed to the operator, no more pulses.
    {C5, E5} = run([{timeout, {reset_wait, x}}], C4),
    ?assertEqual([], writes(E5)),
    ?assertMatch([{reset_warning, <<"drive.x">>},
                  {error, <<"drive.x.failed">>, <<"Drive X axis cannot be reset">>, _}],
                 [E || E <- E5, element(1, E) =/= log]),
    ?assertMatch(#{drives := #{x := #{reset := failed, attempt := 3}}},
                 cell_monitor_core:info(C5)),
    %% A late timer does nothing.
    ?assertEqual([], effects([{timeout, {reset_pulse, x}}, {timeout, {reset_wait, x}}], C5)),
    %% Retry: the pulses start again.
    {C6, E6} = run([{answer, <<"drive.x.failed">>, retry}], C5),
    ?assertEqual([{?X_RESET, true}], writes(E6)),
    %% The error clears during the pulse: output off, timer cancelled, all shown goes.
    E7 = effects([{point, ?X_ERROR, false}], C6),
    ?assertEqual([{?X_RESET, false}], writes(E7)),
    ?assert(lists:member({cancel, {reset_pulse, x}}, E7)),
    ?assert(lists:member({reset_warning, <<"drive.x">>}, E7)),
    %% Once answered, the failed error is the operator's business no more.
    ?assertNot(lists:member({withdraw, <<"drive.x.failed">>}, E7)).

drive_failed_error_withdrawn_when_cleared_test() ->
    {C, _} = run([{point, ?X_ERROR, true}] ++
                     lists:append(lists:duplicate(3, [{timeout, {reset_pulse, x}},
                                                      {timeout, {reset_wait, x}}])),
                 healthy()),
    E = effects([{point, ?X_ERROR, false}], C),
    ?assert(lists:member({withdraw, <<"drive.x.failed">>}, E)),
    ?assertEqual([], writes(E)).

drive_waits_for_the_estop_release_test() ->
    EStop = (cell())#{estop := true, has_alarm := true},
    {C1, E1} = run([{cell, EStop}, {point, ?X_ERROR, true}], healthy()),
    ?assertNot(lists:member({?X_RESET, true}, writes(E1))),
    [{warning, <<"drive.x">>, _, Text}] = [W || {warning, <<"drive.x">>, _, _} = W <- E1],
    ?assertNotEqual(nomatch, binary:match(Text, <<"emergency stop is released">>)),
    E2 = effects([{cell, cell()}], C1),
    ?assert(lists:member({?X_RESET, true}, writes(E2))).

%% The operator's Retry can reach the monitor before the controller's event about the
%% emergency stop the monitor itself raised: no reset either way.
retry_before_the_estop_event_test() ->
    Steps = [{point, ?X_ERROR, true}]
        ++ lists:append(lists:duplicate(3, [{timeout, {reset_pulse, x}},
                                            {timeout, {reset_wait, x}}])),
    {C1, _} = run(Steps, healthy()),
    {C2, E2} = run([{point, ?ESTOP, false}, {answer, <<"drive.x.failed">>, retry}], C1),
    ?assertEqual([], [W || {?X_RESET, true} = W <- writes(E2)]),
    %% The controller's event changes nothing; its release starts the resets.
    {C3, E3} = run([{cell, (cell())#{estop := true}}], C2),
    ?assertEqual([], writes(E3)),
    {C4, E4} = run([{point, ?ESTOP, true}], C3),
    ?assertEqual([], writes(E4)),
    ?assert(lists:member({?X_RESET, true}, writes(effects([{cell, cell()}], C4)))).

estop_circuit_opens_during_a_pulse_test() ->
    {C1, _} = run([{point, ?X_ERROR, true}], healthy()),
    E = effects([{point, ?ESTOP, false}], C1),
    ?assertEqual([{?X_RESET, false}], writes(E)),
    ?assert(lists:member({cancel, {reset_pulse, x}}, E)).

estop_during_a_pulse_test() ->
    {C1, _} = run([{point, ?X_ERROR, true}], healthy()),
    E = effects([{cell, (cell())#{estop := true}}], C1),
    ?assertEqual([{?X_RESET, false}], writes(E)),
    ?assert(lists:member({cancel, {reset_pulse, x}}, E)).

drive_unknown_stops_resets_test() ->
    {C1, _} = run([{point, ?X_ERROR, true}, {timeout, {reset_pulse, x}}], healthy()),
    E = effects([{point, ?X_ERROR, unknown}], C1),
    ?assert(lists:member({cancel, {reset_wait, x}}, E)),
    ?assertNot(lists:member({reset_warning, <<"drive.x">>}, E)).

drive_warning_test_() ->
    C = healthy(),
    {C1, E1} = run([{point, ?X_WARNING, true}], C),
    [?_assertMatch([{warning, <<"drive.x.warning">>, <<"Drive X axis warns">>, _}], E1),
     ?_assertEqual([], writes(E1)),
     ?_assertEqual([{reset_warning, <<"drive.x.warning">>}],
                   effects([{point, ?X_WARNING, false}], C1))].

devices_at_start_test_() ->
    {C1, E1} = run([{device, ?PLC, {down, <<"refused">>}}, start], new()),
    {Up, _} = run([{device, ?PLC, up}], C1),
    [?_assertEqual([{timer, {grace, ?PLC}, 5000}, {timer, {grace, ?CAM}, 5000}],
                   [T || {timer, {grace, _}, _} = T <- E1]),
     ?_assertEqual([], [E || E <- E1, element(1, E) =:= error]),
     %% Up within the grace: never reported.
     ?_assertEqual([{cancel, {grace, ?PLC}}],
                   [E || {cancel, _} = E <- effects([{device, ?PLC, up}], C1)]),
     ?_assertMatch([{error, <<"connection.plc1">>, <<"Cannot connect to plc1">>, _}],
                   [E || {error, _, _, _} = E <- effects([{timeout, {grace, ?PLC}}], C1)]),
     ?_assertMatch([{warning, <<"hardware.camera">>, <<"Camera camera not connected">>, _}],
                   effects([{timeout, {grace, ?CAM}}], C1)),
     %% A late grace timer finds it up.
     ?_assertEqual([], effects([{timeout, {grace, ?PLC}}], Up))].

connection_lost_and_back_test() ->
    {C1, E1} = run([{device, ?PLC, {down, <<"no answer within 500 ms (simulated PLC plc1)">>}}],
                   healthy()),
    [{error, <<"connection.plc1">>, <<"Connection to plc1 lost">>, Text}] = E1,
    ?assertNotEqual(nomatch, binary:match(Text, <<"no answer within 500 ms">>)),
    %% Retry while down: asked again; answered otherwise: forgotten.
    ?assertMatch([{error, <<"connection.plc1">>, _, _}],
                 effects([{answer, <<"connection.plc1">>, retry}], C1)),
    %% Back: withdrawn, and every output of the connection written again.
    E2 = effects([{device, ?PLC, up}], C1),
    ?assert(lists:member({withdraw, <<"connection.plc1">>}, E2)),
    ?assertEqual(lists:sort([{?X_RESET, false}, {?RED, false}, {{general, beacon_yellow}, false},
                             {?GREEN, false}, {{general, beacon_blue}, false},
                             {?X_OVERRIDE, 50}, {?Y_OVERRIDE, 0.5}]),
                 lists:sort(writes(E2))),
    %% Retried while down, so raised again: withdrawn when back.
    {C3, _} = run([{answer, <<"connection.plc1">>, retry}], C1),
    ?assertEqual([{withdraw, <<"connection.plc1">>}],
                 [W || {withdraw, _} = W <- effects([{device, ?PLC, up}], C3)]).

hardware_warning_test_() ->
    {C1, E1} = run([{device, ?CAM, {down, <<>>}}], healthy()),
    [?_assertMatch([{warning, <<"hardware.camera">>, _, _}], E1),
     ?_assertEqual([{reset_warning, <<"hardware.camera">>}],
                   [E || E <- effects([{device, ?CAM, up}], C1), element(1, E) =/= log]),
     ?_assertEqual([], writes(effects([{device, ?CAM, up}], C1)))].

beacon_test() ->
    C = healthy(),
    Starved = (cell())#{state := {ready, idle, starved}},
    {C1, E1} = run([{cell, Starved}], C),
    ?assertEqual([{?GREEN, true}], writes(E1)),
    ?assert(lists:member({timer, blink, 500}, E1)),
    {C2, E2} = run([{timeout, blink}], C1),
    ?assertEqual([{?GREEN, false}], writes(E2)),
    ?assertEqual([{timer, blink, 500}], [T || {timer, _, _} = T <- E2]),
    %% Executing: steady; the blink timer stops.
    {C3, E3} = run([{cell, (cell())#{state := {ready, processing, executing}}}], C2),
    ?assertEqual([{?GREEN, true}], writes(E3)),
    ?assert(lists:member({cancel, blink}, E3)),
    ?assertEqual([], effects([{timeout, blink}], C3)),
    %% An alarm: red blinks from its first phase, green goes out with the stop.
    E4 = effects([{cell, (cell())#{estop := true, has_alarm := true}}], C3),
    ?assertEqual(lists:sort([{?RED, true}, {?GREEN, false}]), lists:sort(writes(E4))),
    ?assertMatch(#{beacon := #{green := steady}}, cell_monitor_core:info(C3)).

beacon_rules_from_settings_test() ->
    C = healthy(),
    Rules = [#{lamp => red, condition => off, mode => steady}],
    E = effects([{settings, (settings())#{beacon := Rules}}], C),
    ?assertEqual([{?RED, true}], writes(E)).

speed_override_test() ->
    C = healthy(),
    {C1, E1} = run([{speed, 80}], C),
    ?assertEqual([{?X_OVERRIDE, 80}, {?Y_OVERRIDE, 0.8}], writes(E1)),
    ?assertMatch([{log, brief, _, [80, "", 2]}], [L || {log, _, _, _} = L <- E1]),
    %% Service mode caps it; a new cap applies at once; out of service mode it is back.
    {C2, E2} = run([{cell, (cell())#{service_mode := true}}], C1),
    ?assertEqual([{?X_OVERRIDE, 10}, {?Y_OVERRIDE, 0.1}], writes(E2)),
    {C3, E3} = run([{settings, (settings())#{service_speed_limit := 25}}], C2),
    ?assertEqual([{?X_OVERRIDE, 25}, {?Y_OVERRIDE, 0.25}], writes(E3)),
    ?assertEqual([{?X_OVERRIDE, 80}, {?Y_OVERRIDE, 0.8}],
                 writes(effects([{cell, cell()}], C3))),
    %% A speed under the cap is not raised to it.
    ?assertEqual([{?X_OVERRIDE, 5}, {?Y_OVERRIDE, 0.05}], writes(effects([{speed, 5}], C3))).

%% Axes and interpolation channels take the speed override as a command: at start, as
%% it changes (the service mode's cap included), and again when one comes back.
axis_override_test() ->
    {ok, Spec} = cell_monitor_spec:validate(
                   #{hal => #{connections => [], groups => [],
                              hardware => [#{id => x, kind => axis, type => sim},
                                           #{id => xy, kind => channel, type => sim},
                                           #{id => camera, kind => camera, type => sim}]},
                     monitor => #{io => #{}, drives => []}}),
    {C0, E0} = cell_monitor_core:new(Spec, #{settings => settings(), speed => 50,
                                            cell => cell()}),
    Overrides = fun(E) -> [O || {override, _, _, _} = O <- E] end,
    ?assertEqual([{override, axis, x, 50}, {override, channel, xy, 50}], Overrides(E0)),
    {C1, E1} = run([{device, {hardware, x}, up}, {speed, 80}], C0),
    ?assertEqual([{override, axis, x, 50}, {override, axis, x, 80},
                  {override, channel, xy, 80}], Overrides(E1)),
    ?assertMatch([{log, brief, _, [80, "", 2]}], [L || {log, _, _, _} = L <- E1]),
    {C2, E2} = run([{cell, (cell())#{service_mode := true}}], C1),
    ?assertEqual([{override, axis, x, 10}, {override, channel, xy, 10}], Overrides(E2)),
    %% The axis object restarted (down, then up): told again, at the cap.
    ?assertEqual([{override, axis, x, 10}],
                 Overrides(effects([{device, {hardware, x}, {down, <<>>}},
                                    {device, {hardware, x}, up}], C2))),
    %% A camera coming back is told nothing of it.
    ?assertEqual([], Overrides(effects([{device, ?CAM, up}], healthy()))).

answer_for_something_else_test() ->
    ?assertEqual([], effects([{answer, <<"door">>, retry}, {answer, <<"nothing">>, close}],
                             healthy())).

kinds_test() ->
    %% Everything the monitor decides is one of the effects it knows how to carry out.
    {_, E} = run([{point, ?X_ERROR, true}, {point, ?ESTOP, false}, {point, ?DOOR, false},
                  {device, ?PLC, {down, <<>>}}, {cell, (cell())#{state := down}}],
                 healthy()),
    Known = [estop, service_mode, warning, reset_warning, error, withdraw, write, timer,
             cancel, override],
    ?assertEqual([], [K || K <- kinds(E), not lists:member(K, Known)]),
    ?assert(length(kinds(E)) > 5).

%% A monitor that crashed may have left warnings; its successor resets them when it
%% first sees things are fine, without telling the log anything happened.
first_sight_resets_stale_warnings_test() ->
    E = effects([{device, ?CAM, up}, {device, ?PLC, up}, {point, ?X_ERROR, false},
                 {point, ?X_WARNING, false}, {point, ?DOOR, true}, {point, ?AIR, true}], new()),
    ?assertEqual([{reset_warning, <<"hardware.camera">>}, {reset_warning, <<"drive.x">>},
                  {reset_warning, <<"drive.x.warning">>}, {reset_warning, <<"door">>},
                  {reset_warning, <<"air">>}],
                 [R || {reset_warning, _} = R <- E]),
    ?assertEqual([], [L || {log, _, _, _} = L <- E]),
    ?assertEqual([], [W || {withdraw, _} = W <- E]).

drive_error_cleared_is_logged_test() ->
    {C, _} = run([{point, ?X_ERROR, true}], healthy()),
    ?assertMatch([{log, brief, "drive ~ts: error cleared", [<<"X axis">>]}],
                 [L || {log, _, _, _} = L <- effects([{point, ?X_ERROR, false}], C)]),
    %% Also when it clears while the connection was down.
    ?assertMatch([{log, brief, _, _}],
                 [L || {log, _, _, _} = L <- effects([{point, ?X_ERROR, unknown},
                                                      {point, ?X_ERROR, false}], C)]).
