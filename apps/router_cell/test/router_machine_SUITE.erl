%% The simulated router's general IO and drives, watched by the cell's own monitor,
%% and the monitor's reactions as seed 000 §2.4 has them: the emergency-stop circuit
%% stops every task at once; the service key switches service mode; a safety door
%% opened (or its lock released) and low air are warnings; a drive fault is reset up
%% to three times, then handed to the operator, whose Retry resets it again.
%%
%% The machine is poked as the operator would (router_sim's functions); every wait is
%% for an event with a deadline.
-module(router_machine_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([monitor_sees_the_machine/1, estop_stops_every_task/1, service_key/1,
         doors_and_air_warn/1, drive_fault_reset/1, drive_fault_to_operator/1]).

-define(DEADLINE_MS, 60000).
-define(EVENTS, [item_transfer_out, alarm_raised, alarm_cleared, cell_state, estop,
                 service_mode]).

all() ->
    [monitor_sees_the_machine, estop_stops_every_task, service_key, doors_and_air_warn,
     drive_fault_reset, drive_fault_to_operator].

init_per_testcase(Case, Config) ->
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = router_test_settings:write(
           Root, #{machine => #{},
                   router_sim => #{time_scale => 0.02, arrival_ms => 0,
                                   product_lost_rate => 0.0, jam_rate => 0.0, no_read_rate => 0.0,
                                   magazine_low_s => 0},
                   router => #{hal_poll_ms => 5, transfer_timeout_ms => 3000,
                               motion_timeout_ms => 3000},
                   monitor => #{drive_reset_pulse_ms => 20, drive_reset_wait_ms => 100}}),
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = cell_testkit:await_connection(router_plc, ?DEADLINE_MS),
    ok = router_sim:ready(?DEADLINE_MS),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:unset_env(cell, shutdown_wait_ms),
    cell_testkit:stop(router_cell, [router_plc]).

%% -------------------------------------------------------------------------------------

%% The monitor watches the router's general IO and its drives, all good at the start:
%% no alarm. The drives' ready follow the e-stop circuit; the doors' lock output
%% unlocks the doors (a warning), and locks them again.
monitor_sees_the_machine(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    await_monitor(fun(#{inputs := In}) ->
                          In =:= #{estop_ok => true, service_key => false,
                                   door_locked => true, air_ok => true}
                  end),
    #{drives := Drives, devices := #{router_plc := up}} = cell_monitor:info(),
    ?assertEqual([conveyor_front, lower, upper], lists:sort(maps:keys(Drives))),
    [?assertMatch(#{error := false, code := 0, reset := idle}, D) || D <- maps:values(Drives)],
    ?assertEqual([], cell_alarms:list()),
    [?assertEqual({ok, true}, cell_hal:read(drives_io, P))
     || P <- [conveyor_front_ready, lower_ready, upper_ready]],
    ?assertEqual({ok, 6.0}, cell_hal:read(general_io, air_pressure)),
    %% One lane: no rear conveyors to fault.
    ?assertEqual({error, no_such_drive}, router_sim:fault_drive(conveyor_rear)),
    %% The beacon's lamps are outputs the monitor drives.
    #{outputs := Outs} = cell_monitor:info(),
    ?assert(maps:is_key({general_io, beacon_green}, Outs)),
    %% The lock released: the doors no longer report locked.
    ok = cell_hal:write(general_io, door_unlock, true),
    await_alarm(raised, warning, <<"cell:door">>),
    ok = cell_hal:write(general_io, door_unlock, false),
    await_alarm(cleared, warning, <<"cell:door">>).

%% The circuit opens while panels flow: every task is OFF at once, the drives lose
%% their ready, Start is refused; closed again, the emergency stop is released and a
%% Start lets panels flow again.
estop_stops_every_task(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(2),
    ok = router_sim:press_estop(),
    await(fun(#{type := estop, active := true}) -> true; (_) -> false end),
    %% The event follows the barrier: every task has secured its outputs, and each is
    %% told to announce OFF; sync waits until each has.
    ok = cell_controller:sync(),
    ?assertEqual([], [T || #{id := T, state := St} <- cell_controller:tasks(), St =/= off]),
    ?assertMatch(#{estop := true}, cell_controller:flags()),
    ?assertEqual({error, estop_active}, cell_controller:start(<<"suite">>)),
    ?assertEqual({ok, false}, cell_hal:read(drives_io, lower_ready)),
    ok = router_sim:release_estop(),
    await(fun(#{type := estop, active := false}) -> true; (_) -> false end),
    ok = await_ready(lower_ready),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(2),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% Each turn of the key switches service mode.
service_key(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = router_sim:service_key(true),
    await(fun(#{type := service_mode, active := true}) -> true; (_) -> false end),
    ?assertMatch(#{service_mode := true}, cell_controller:flags()),
    ok = router_sim:service_key(false),
    await(fun(#{type := service_mode, active := false}) -> true; (_) -> false end),
    ?assertMatch(#{service_mode := false}, cell_controller:flags()).

%% A door opened and low air are warnings: the cell runs on with them; each is
%% cleared when the door is closed, the air back.
doors_and_air_warn(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = router_sim:open_door(unloading),
    await_alarm(raised, warning, <<"cell:door">>),
    ok = router_sim:drop_air(),
    await_alarm(raised, warning, <<"cell:air">>),
    ?assertEqual({ok, 2.5}, cell_hal:read(general_io, air_pressure)),
    ?assertMatch(#{request := start, estop := false, has_error := false},
                 cell_controller:flags()),
    _ = collect_out(2),
    ok = router_sim:close_door(unloading),
    await_alarm(cleared, warning, <<"cell:door">>),
    ok = router_sim:restore_air(),
    await_alarm(cleared, warning, <<"cell:air">>),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% A fault one reset clears: a warning while the monitor resets it, gone after, and
%% the conveyors run again.
drive_fault_reset(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(1),
    ok = router_sim:fault_drive(conveyor_front),
    await_alarm(raised, warning, <<"cell:drive.conveyor_front">>),
    await_alarm(cleared, warning, <<"cell:drive.conveyor_front">>),
    ?assertEqual(#{}, faults()),
    _ = collect_out(2),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% A fault that five resets clear: three resets, then an error for the operator; the
%% Retry resets again (twice more) and the drive runs.
drive_fault_to_operator(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = router_sim:fault_drive(lower, 5),
    await_alarm(raised, warning, <<"cell:drive.lower">>),
    await_alarm(raised, error, <<"cell:drive.lower.failed">>),
    ?assertEqual(#{lower => 2}, faults()),
    ?assertMatch(#{lower := #{error := true, code := 8611, attempt := 3}},
                 maps:get(drives, cell_monitor:info())),
    ok = cell_alarms:answer(<<"cell:drive.lower.failed">>, retry, <<"suite">>),
    await_alarm(cleared, warning, <<"cell:drive.lower">>),
    ?assertEqual(#{}, faults()),
    ok = await_ready(lower_ready),
    ?assertEqual([], [A || #{kind := error} = A <- cell_alarms:list()]).

%% -------------------------------------------------------------------------------------

faults() ->
    #{general := #{faults := F}} = router_sim:world(),
    F.

collect_out(N) ->
    cell_testkit:collect(N, fun(#{type := item_transfer_out, task := unloading_front,
                                  item := S}) -> {true, S};
                               (_) -> false
                            end, fun never_answer/1, ?DEADLINE_MS).

never_answer(#{kind := error} = A) -> ct:fail({unexpected_error, A});
never_answer(_) -> ok.

await(Match) ->
    cell_testkit:await_event(Match, ?DEADLINE_MS).

%% An alarm of the cell raised (or cleared) by the monitor.
await_alarm(How, Kind, Id) ->
    Type = case How of raised -> alarm_raised; cleared -> alarm_cleared end,
    await(fun(#{type := T, alarm := #{id := I, kind := K}}) ->
                  T =:= Type andalso I =:= Id andalso K =:= Kind;
             (_) -> false
          end).

%% A drive's ready input as the HAL reads it.
await_ready(Point) ->
    {ok, Ref} = cell_hal:watch(drives_io, Point, {eq, true}),
    receive {cell_hal_watch, Ref, _} -> ok
    after ?DEADLINE_MS -> ct:fail({not_ready, Point})
    end.

%% The monitor has seen the inputs: it publishes no event of them, so the wait is on
%% the HAL's watches of the same points, then the monitor's own view, synchronously.
await_monitor(Pred) ->
    Refs = [begin {ok, R} = cell_hal:watch(general_io, P, {eq, true}), R end
            || P <- [estop_ok, doors_locked, air_ok]],
    [receive {cell_hal_watch, R, _} -> ok after ?DEADLINE_MS -> ct:fail(no_inputs) end
     || R <- Refs],
    Info = cell_monitor:info(),
    Pred(Info) orelse ct:fail({monitor_sees, Info}).
