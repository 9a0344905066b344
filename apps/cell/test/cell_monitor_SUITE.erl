%% The monitor driven through the simulated PLC, as an operator meets it: the
%% emergency-stop voltage drops and every task stops; the service key; door and air
%% warnings; a PLC that drops off and comes back; a camera unplugged, crashed and
%% lost; drives in error reset, or handed to the operator; the speed override applied
%% (to the drives' points and the axes)
%% while the cell runs; the beacon following the cell; the HAL taken down when the
%% cell stops, and kept when the monitor crashes.
%%
%% Waiting is for conditions, woken by the messages the suite subscribes to (cell
%% events, log lines, the points it watches): never for a fixed time.
-module(cell_monitor_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([estop_voltage_drop_reaches_every_task/1, manual_estop_is_left_alone/1,
         service_key_toggles_service_mode/1, door_and_air_warnings/1,
         plc_disconnect_and_reconnect/1, camera_loss_crash_and_removal/1,
         drive_error_is_reset/1, drive_error_for_the_operator/1,
         speed_override_applied_while_running/1, beacon_follows_the_cell/1,
         hal_disconnected_when_the_cell_stops/1, monitor_crash_keeps_the_hal/1,
         hal_refusal_is_an_alarm/1, hal_server_away_as_the_monitor_starts/1,
         a_refused_input_is_unknown/1, replaced_monitor_releases_its_estop/1]).

-define(IDS, [load, work, unload]).
-define(WAIT, 10000).
-define(STARVED, {ready, idle, starved}).

all() ->
    [estop_voltage_drop_reaches_every_task, manual_estop_is_left_alone,
     service_key_toggles_service_mode, door_and_air_warnings, plc_disconnect_and_reconnect,
     camera_loss_crash_and_removal, drive_error_is_reset, drive_error_for_the_operator,
     speed_override_applied_while_running, beacon_follows_the_cell,
     hal_disconnected_when_the_cell_stops, monitor_crash_keeps_the_hal,
     hal_refusal_is_an_alarm, hal_server_away_as_the_monitor_starts,
     a_refused_input_is_unknown, replaced_monitor_releases_its_estop].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Tab = ets:new(cell_monitor_suite, [public]),
    Tasks = [cell_test_task:spec(Id, Tab, self()) || Id <- ?IDS],
    Spec = #{name => <<"monitor suite">>, tasks => Tasks, hal => hal(Case),
             monitor => monitor()},
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe(),
    ok = cell_log:subscribe(),
    %% Every commanded output wakes the waits below.
    [ok = cell_hal:subscribe(G, P)
     || G <- [general, axes],
        #{name := P, dir := out} <- cell_monitor_test_io:points(#{part => G})],
    %% Quick timings, so a case takes well under a second of them.
    ok = cell_settings:put(monitor, #{blink_period_ms => 200, drive_reset_pulse_ms => 50,
                                      drive_reset_wait_ms => 100}, <<"suite">>),
    Refs = maps:from_list([{Id, maps:get(ref, maps:get(args, S))} || #{id := Id} = S <- Tasks]),
    Config1 = [{tab, Tab}, {refs, Refs}, {root, Root} | Config],
    case Case of
        hal_refusal_is_an_alarm -> Config1;
        _ -> healthy_plc(), Config1
    end.

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    %% The simulated PLC outlives the HAL's connections (a real PLC keeps its memory):
    %% each case starts from a blank one.
    [ok = cell_hal_sim_sup:stop_device(D) || D <- [plc1, plc2]],
    ok = application:unset_env(cell, cell_spec),
    ok.

hal(hal_refusal_is_an_alarm) ->
    cell_monitor_test_cell:hal([#{id => plc2, driver => cell_hal_sim, opts => #{timeout_ms => 0}}]);
hal(speed_override_applied_while_running) ->
    %% An axis too: the override is applied to it as to the drives.
    Hal = cell_monitor_test_cell:hal([]),
    Hal#{hardware := maps:get(hardware, Hal) ++ [#{id => z_axis, kind => axis, type => sim}]};
hal(_) ->
    cell_monitor_test_cell:hal([]).

monitor() ->
    cell_monitor_test_cell:monitor().

%% A blank simulated PLC reads all inputs false: the circuit open, doors unlocked, no
%% air. The cell starts in an emergency stop; a healthy machine puts everything right.
healthy_plc() ->
    await(plc1_up, fun() -> cell_hal:status(plc1) =:= up end),
    await(estop_at_start, fun() -> maps:get(estop, cell_controller:flags()) end),
    [ok = cell_hal_sim:set({general, P}, true) || P <- [estop_voltage, door_locked, air_ok]],
    await(healthy, fun() -> not maps:get(estop, cell_controller:flags())
                                andalso cell_alarms:list() =:= [] end).

%% -------------------------------------------------------------------------------------

estop_voltage_drop_reaches_every_task(Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ?assertEqual(lists:duplicate(3, ?STARVED), states()),
    cmd(Config, work, {event, unstarved}),
    ok = cell_controller:sync(),
    %% The voltage drops: every task goes OFF through uninit, the flag is up, the
    %% alarm is shown, Start is refused.
    ok = cell_hal_sim:set({general, estop_voltage}, false),
    await(every_task_off, fun() -> states() =:= [off, off, off]
                                       andalso has_alarm(<<"cell:estop">>) end),
    [?assertMatch(#{uninit := 1}, counts(Config, Id)) || Id <- ?IDS],
    ?assertMatch(#{estop := true, request := stop, has_alarm := true}, cell_controller:flags()),
    ?assertMatch([#{id := <<"cell:estop">>, kind := alarm}], cell_alarms:list()),
    ?assertEqual({error, estop_active}, cell_controller:start()),
    ?assertMatch(#{inputs := #{estop_ok := false}, estop_raised := true}, cell_monitor:info()),
    %% The voltage returns: released, and the cell waits for a new Start.
    ok = cell_hal_sim:set({general, estop_voltage}, true),
    await(released, fun() -> not maps:get(estop, cell_controller:flags()) end),
    await(alarm_cleared, fun() -> cell_alarms:list() =:= [] end),
    ?assertEqual([off, off, off], states()),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ?assertEqual(lists:duplicate(3, ?STARVED), states()).

manual_estop_is_left_alone(Config) ->
    %% An emergency stop from the shell or the panel is not the circuit's: the monitor
    %% (which has seen its event by the time it answers) neither raised nor releases it.
    ok = cell_controller:estop(true, <<"operator">>),
    ?assertMatch(#{estop_raised := false, inputs := #{estop_ok := true}}, cell_monitor:info()),
    ?assertMatch(#{estop := true}, cell_controller:flags()),
    ok = cell_controller:estop(false, <<"operator">>),
    ?assertMatch(#{estop := false}, cell_controller:flags()),
    %% The circuit opening while it is active makes it the circuit's too: there is one
    %% emergency stop, and the circuit closing releases it.
    ok = cell_controller:estop(true, <<"operator">>),
    ok = cell_hal_sim:set({general, estop_voltage}, false),
    await(monitor_saw_the_drop, fun() -> maps:get(estop_raised, cell_monitor:info()) end),
    ok = cell_hal_sim:set({general, estop_voltage}, true),
    await(released, fun() -> not maps:get(estop, cell_controller:flags()) end),
    ?assertMatch(#{estop_raised := false}, cell_monitor:info()),
    _ = Config.

service_key_toggles_service_mode(Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_hal_sim:set({general, service_key}, true),
    await(service_mode_on, fun() -> maps:get(service_mode, cell_controller:flags()) end),
    ok = cell_controller:sync(),
    %% Service mode pauses the tasks; a Start runs them with the service flag set.
    ?assertEqual([down, down, down], states()),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ?assertMatch(#{service_mode := true}, cell_task_proc:info(work)),
    ok = cell_hal_sim:set({general, service_key}, false),
    await(service_mode_off, fun() -> not maps:get(service_mode, cell_controller:flags()) end),
    ok = cell_controller:sync(),
    ?assertMatch(#{service_mode := false}, cell_task_proc:info(work)),
    %% Turned on from the panel, the key turning again still decides.
    ok = cell_controller:service_mode(true, <<"operator">>),
    ok = set_seen({general, service_key}, true),
    ?assert(input(service_key)),
    ok = cell_hal_sim:set({general, service_key}, false),
    await(key_decides, fun() -> not maps:get(service_mode, cell_controller:flags()) end),
    _ = Config.

door_and_air_warnings(_Config) ->
    ok = cell_hal_sim:set({general, door_locked}, false),
    await(door_warning, fun() -> has_alarm(<<"cell:door">>) end),
    {ok, Door} = cell_alarms:get(<<"cell:door">>),
    ?assertMatch(#{kind := warning, caption := <<"Door not locked">>, solutions := [close]}, Door),
    ?assertMatch(#{has_warning := true, has_error := false}, cell_controller:flags()),
    ok = cell_hal_sim:set({general, air_ok}, false),
    await(air_warning, fun() -> has_alarm(<<"cell:air">>) end),
    {ok, Air} = cell_alarms:get(<<"cell:air">>),
    ?assertMatch(#{kind := warning, caption := <<"Air pressure low">>}, Air),
    %% The texts are settings; a warning on show takes the new text at once.
    ok = cell_settings:put(monitor, #{door_caption => <<"Safety door open">>}, <<"service">>),
    await(new_caption, fun() -> caption(<<"cell:door">>) =:= <<"Safety door open">> end),
    ok = cell_hal_sim:set({general, door_locked}, true),
    await(door_warning_gone, fun() -> not has_alarm(<<"cell:door">>) end),
    ?assert(has_alarm(<<"cell:air">>)),
    ok = cell_hal_sim:set({general, air_ok}, true),
    await(air_warning_gone, fun() -> not has_alarm(<<"cell:air">>) end),
    ?assertMatch(#{has_warning := false}, cell_controller:flags()),
    %% Closed by the operator while the door is still open, it comes back with the next
    %% opening, not before.
    ok = cell_hal_sim:set({general, door_locked}, false),
    await(door_warning_again, fun() -> has_alarm(<<"cell:door">>) end),
    ok = cell_alarms:close(<<"cell:door">>, <<"operator">>),
    ?assertNot(has_alarm(<<"cell:door">>)),
    ok = set_seen({general, door_locked}, true),
    ?assert(input(door_locked)),
    ?assertNot(has_alarm(<<"cell:door">>)),
    ok = cell_hal_sim:set({general, door_locked}, false),
    await(door_warning_next_time, fun() -> has_alarm(<<"cell:door">>) end).

plc_disconnect_and_reconnect(Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    await(green_blinking, fun() -> lamp(green) =:= blinking end),
    ok = cell_hal_sim:set({general, air_ok}, false),
    await(air_warning, fun() -> has_alarm(<<"cell:air">>) end),
    %% The cable is pulled: reported as an error naming the PLC, the reason and
    %% where it was; the e-stop is not raised for it.
    ok = cell_hal_sim:link(plc1, down),
    await(loss_reported, fun() -> has_alarm(<<"cell:connection.plc1">>) end),
    {ok, Lost} = cell_alarms:get(<<"cell:connection.plc1">>),
    ?assertMatch(#{kind := error, caption := <<"Connection to plc1 lost">>,
                   solutions := [retry]}, Lost),
    Text = maps:get(description, Lost),
    ?assertNotEqual(nomatch, binary:match(Text, <<"simulated PLC plc1">>)),
    ?assertMatch(#{estop := false, has_error := true}, cell_controller:flags()),
    ?assertMatch(#{devices := #{plc1 := down}, inputs := #{estop_ok := unknown}},
                 cell_monitor:info()),
    %% Retry while it is still down: asked again.
    ok = cell_alarms:answer(<<"cell:connection.plc1">>, retry, <<"operator">>),
    await(asked_again, fun() -> has_alarm(<<"cell:connection.plc1">>) end),
    %% Meanwhile the PLC put its outputs in a safe state, the air came back and a door
    %% was unlocked.
    [ok = cell_hal_sim:set({general, L}, false) || L <- [beacon_green, beacon_yellow]],
    ok = cell_hal_sim:set({general, air_ok}, true),
    ok = cell_hal_sim:set({general, door_locked}, false),
    %% Plugged back: the error goes, the inputs are read again, the outputs written again.
    ok = cell_hal_sim:link(plc1, up),
    await(back, fun() -> not has_alarm(<<"cell:connection.plc1">>) end),
    await(inputs_read_again, fun() -> has_alarm(<<"cell:door">>)
                                          andalso not has_alarm(<<"cell:air">>) end),
    await(yellow_written_again, fun() -> device(beacon_yellow) =:= {ok, true} end),
    await(green_blinks_again, fun() -> device(beacon_green) =:= {ok, true} end),
    await(green_blinks_again, fun() -> device(beacon_green) =:= {ok, false} end),
    ?assertMatch(#{devices := #{plc1 := up}}, cell_monitor:info()),
    ?assertMatch(#{estop := false}, cell_controller:flags()),
    _ = Config.

camera_loss_crash_and_removal(_Config) ->
    ?assertMatch(#{devices := #{camera := up}}, cell_monitor:info()),
    ?assertNot(maps:is_key(reader, maps:get(devices, cell_monitor:info()))),
    %% Unplugged: a warning naming it; plugged back: gone.
    ok = cell_hal_camera_sim:set_link(camera, down),
    await(camera_reported, fun() -> has_alarm(<<"cell:hardware.camera">>) end),
    ?assertEqual(<<"Camera camera not connected">>, caption(<<"cell:hardware.camera">>)),
    ok = cell_hal_camera_sim:set_link(camera, up),
    await(camera_back, fun() -> not has_alarm(<<"cell:hardware.camera">>) end),
    %% Its process crashes: the HAL restarts it and the monitor follows the new one.
    Old = camera_pid(),
    exit(Old, kill),
    await(camera_restarted, fun() -> is_pid(camera_pid()) andalso camera_pid() =/= Old end),
    await(camera_up_again, fun() -> device_status(camera) =:= up end),
    ok = cell_hal_camera_sim:set_link(camera, down),
    await(new_camera_watched, fun() -> has_alarm(<<"cell:hardware.camera">>) end),
    ok = cell_hal_camera_sim:set_link(camera, up),
    await(camera_back, fun() -> not has_alarm(<<"cell:hardware.camera">>) end),
    %% Taken out of the HAL altogether: the monitor creates it again.
    ok = cell_hal_hw:remove(camera),
    await(camera_created_again, fun() -> cell_hal_hw:present(camera)
                                             andalso device_status(camera) =:= up end),
    {ok, #{width := 320}} = cell_hal_camera:grab(camera, 5000).

drive_error_is_reset(_Config) ->
    Self = self(),
    %% The drive clears its error on the reset's rising edge; the suite sees each
    %% edge as the PLC does.
    ok = cell_hal_sim:on_change({axes, x_reset},
                                fun(V) -> Self ! {x_reset, V},
                                          [{0, {axes, x_error}, false} || V] end),
    ok = cell_hal_sim:set({axes, x_code}, 17),
    ok = cell_hal_sim:set({axes, x_error}, true),
    receive {x_reset, true} -> ok after ?WAIT -> ct:fail(no_reset_pulse) end,
    receive {x_reset, false} -> ok after ?WAIT -> ct:fail(reset_not_released) end,
    await(error_cleared, fun() -> not has_alarm(<<"cell:drive.x_axis">>) end),
    ?assertMatch(#{drives := #{x_axis := #{error := false, reset := idle}}},
                 cell_monitor:info()),
    %% The warning bit: a warning naming the drive, no reset.
    ok = cell_hal_sim:set({axes, x_warning}, true),
    await(drive_warning, fun() -> has_alarm(<<"cell:drive.x_axis.warning">>) end),
    ?assertEqual(<<"Drive X axis warns">>, caption(<<"cell:drive.x_axis.warning">>)),
    ok = cell_hal_sim:set({axes, x_warning}, false),
    await(drive_warning_gone, fun() -> not has_alarm(<<"cell:drive.x_axis.warning">>) end),
    receive {x_reset, V} -> ct:fail({unexpected_reset, V}) after 0 -> ok end.

drive_error_for_the_operator(_Config) ->
    Self = self(),
    ok = cell_hal_sim:on_change({axes, x_reset}, fun(V) -> Self ! {x_reset, V}, [] end),
    ok = cell_hal_sim:set({axes, x_code}, 16#2310),
    ok = cell_hal_sim:set({axes, x_error}, true),
    await(shown, fun() -> has_alarm(<<"cell:drive.x_axis">>) end),
    ?assertNotEqual(nomatch, binary:match(description(<<"cell:drive.x_axis">>),
                                          <<"code 8976">>)),
    %% Three resets do not help: the operator is asked.
    [receive {x_reset, true} -> receive {x_reset, false} -> ok after ?WAIT -> ct:fail(stuck) end
     after ?WAIT -> ct:fail({no_reset, N})
     end || N <- [1, 2, 3]],
    await(handed_over, fun() -> has_alarm(<<"cell:drive.x_axis.failed">>) end),
    ?assertNot(has_alarm(<<"cell:drive.x_axis">>)),
    ?assertMatch({ok, #{kind := error, solutions := [retry],
                        caption := <<"Drive X axis cannot be reset">>}},
                 cell_alarms:get(<<"cell:drive.x_axis.failed">>)),
    ?assertMatch(#{has_error := true}, cell_controller:flags()),
    ?assertMatch(#{drives := #{x_axis := #{reset := failed, attempt := 3}}}, cell_monitor:info()),
    receive {x_reset, V} -> ct:fail({reset_after_giving_up, V}) after 0 -> ok end,
    %% No resets during an emergency stop; Retry starts them once it is released.
    ok = cell_hal_sim:set({general, estop_voltage}, false),
    await(estop, fun() -> maps:get(estop, cell_controller:flags()) end),
    ok = cell_alarms:answer(<<"cell:drive.x_axis.failed">>, retry, <<"service">>),
    await(waits_for_release, fun() -> has_alarm(<<"cell:drive.x_axis">>) end),
    ?assertNotEqual(nomatch, binary:match(description(<<"cell:drive.x_axis">>),
                                          <<"emergency stop is released">>)),
    receive {x_reset, V2} -> ct:fail({reset_during_estop, V2}) after 0 -> ok end,
    ok = cell_hal_sim:set({general, estop_voltage}, true),
    receive {x_reset, true} -> ok after ?WAIT -> ct:fail(no_reset_after_release) end,
    %% Someone fixed the drive: everything about it goes.
    ok = cell_hal_sim:set({axes, x_error}, false),
    await(all_clear, fun() -> not has_alarm(<<"cell:drive.x_axis">>)
                                  andalso not has_alarm(<<"cell:drive.x_axis.failed">>) end),
    await(reset_released, fun() -> device(x_reset) =:= {ok, false} end).

speed_override_applied_while_running(Config) ->
    %% The machine's default 50 %: the X drive takes percent, the Y drive a factor.
    await(default_override, fun() -> device(x_override) =:= {ok, 50}
                                          andalso axis_override() =:= 50 end),
    ?assertEqual({ok, 0.5}, device(y_override)),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    cmd(Config, work, {event, unstarved}),
    cmd(Config, work, {event, work_start}),
    ok = cell_controller:sync(),
    ?assertEqual({ready, processing, executing}, cell_controller:state()),
    %% Changed while executing: applied at once (the tasks' settings wait for the next
    %% Start; the override does not).
    ok = cell_settings:put(machine, #{speed_override => 80}, <<"service">>),
    %% Two drives, two writes: the test waits for both, in either order.
    await(new_override, fun() ->
                                device(x_override) =:= {ok, 80} andalso
                                    axis_override() =:= 80 andalso
                                    case device(y_override) of
                                        {ok, Factor} -> abs(Factor - 0.8) < 1.0e-12;
                                        _ -> false
                                    end
                        end),
    ?assertEqual({ready, processing, executing}, cell_controller:state()),
    %% Service mode caps it at the service limit, and gives it back after.
    ok = cell_hal_sim:set({general, service_key}, true),
    await(capped, fun() -> device(x_override) =:= {ok, 10} andalso axis_override() =:= 10 end),
    ok = cell_settings:put(monitor, #{service_speed_limit => 25}, <<"service">>),
    await(new_cap, fun() -> device(x_override) =:= {ok, 25} end),
    ok = cell_hal_sim:set({general, service_key}, false),
    await(uncapped, fun() -> device(x_override) =:= {ok, 80} andalso axis_override() =:= 80 end).

%% The simulated axis's override (seed 000 §2.4: the monitor applies the speed override
%% to the axes too).
axis_override() ->
    case cell_hal_axis:status(z_axis) of
        {ok, #{override := Pct}} -> Pct;
        Other -> Other
    end.

beacon_follows_the_cell(Config) ->
    Self = self(),
    ok = cell_hal_sim:on_change({general, beacon_green}, fun(V) -> Self ! {green, V}, [] end),
    %% OFF, nothing wrong: dark.
    await(dark, fun() -> lamps() =:= #{red => off, yellow => off, green => off, blue => off} end),
    await(dark_at_the_plc, fun() -> [device(L) || L <- lamp_points()]
                                        =:= [{ok, false} || _ <- lamp_points()] end),
    %% Running and starved: green blinks, at the PLC too.
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    await(green_blinks, fun() -> lamp(green) =:= blinking end),
    [receive {green, V} -> ok after ?WAIT -> ct:fail({no_blink, V}) end
     || V <- [true, false, true, false]],
    %% Executing: steady green.
    cmd(Config, work, {event, unstarved}),
    cmd(Config, work, {event, work_start}),
    ok = cell_controller:sync(),
    await(green_steady, fun() -> lit(green, steady, true) end),
    %% A warning: yellow, steady.
    ok = cell_alarms:warning(work, <<"low">>, "Material low", "Refill soon."),
    await(yellow, fun() -> lit(yellow, steady, true) end),
    ok = cell_alarms:reset_warning(work, <<"low">>),
    await(yellow_off, fun() -> lit(yellow, off, false) end),
    %% An error waits for the operator: blue.
    cmd(Config, load, {error, [retry]}),
    await(blue, fun() -> lit(blue, steady, true) end),
    [#{id := ErrorId}] = [A || #{kind := error} = A <- cell_alarms:list()],
    ok = cell_alarms:answer(ErrorId, retry, <<"operator">>),
    await(blue_off, fun() -> lamp(blue) =:= off end),
    %% The emergency stop: red blinks, green goes out with the tasks.
    ok = cell_hal_sim:set({general, estop_voltage}, false),
    await(red, fun() -> lamp(red) =:= blinking andalso lamp(green) =:= off end),
    await(green_dark, fun() -> device(beacon_green) =:= {ok, false} end),
    %% The rules are settings: red steady on the emergency stop as well, and the
    %% strongest wins.
    ok = cell_settings:put(monitor, #{beacon => cell_beacon:default_rules() ++
                                          [#{lamp => red, condition => estop, mode => steady},
                                           #{lamp => yellow, condition => estop, mode => steady}]},
                           <<"service">>),
    await(new_rules, fun() -> lamp(yellow) =:= steady andalso lamp(red) =:= blinking end),
    ok = cell_hal_sim:set({general, estop_voltage}, true),
    await(dark_again, fun() -> lamps() =:= #{red => off, yellow => off, green => off,
                                             blue => off} end),
    await(dark_at_the_plc, fun() -> [device(L) || L <- lamp_points()]
                                        =:= [{ok, false} || _ <- lamp_points()] end).

hal_disconnected_when_the_cell_stops(_Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    await(green_on, fun() -> device(beacon_green) =:= {ok, true} end),
    ?assertEqual([plc1], cell_hal:connections()),
    ?assertEqual([axes, general], cell_hal:groups()),
    ?assertMatch([{camera, camera, _}], cell_hal_hw:list()),
    ?assertEqual(1, sim_clients(plc1)),
    ok = application:stop(cell),
    %% Taken down by the monitor as it stopped: nothing left, the beacon dark, the
    %% PLC without clients.
    ?assertEqual([], cell_hal:connections()),
    ?assertEqual([], cell_hal:groups()),
    ?assertEqual([], cell_hal_hw:list()),
    ?assertEqual(0, sim_clients(plc1)),
    ?assertEqual([false, false, false, false, false],
                 [sim_image(plc1, {general, L}) || L <- lamp_points()]
                 ++ [sim_image(plc1, {axes, x_reset})]),
    ?assert(lists:member(true, [binary:match(T, <<"HAL disconnected">>) =/= nomatch
                                || {cell_log, #{text := T}} <- drain()])).

monitor_crash_keeps_the_hal(_Config) ->
    Worker = worker_pid(plc1),
    Old = whereis(cell_monitor),
    exit(Old, kill),
    await(restarted, fun() -> lists:member(whereis(cell_monitor), [undefined, Old]) =:= false end),
    %% The new monitor took the HAL over as it was: same connection, no reconnect.
    #{hal := Hal} = cell_monitor:info(),
    ?assertEqual([{connection, plc1}, {group, general}, {group, axes}, {hardware, camera}], Hal),
    ?assertEqual(Worker, worker_pid(plc1)),
    ?assertEqual(up, cell_hal:status(plc1)),
    %% And watches it: the door, the circuit.
    ok = cell_hal_sim:set({general, door_locked}, false),
    await(door_warning, fun() -> has_alarm(<<"cell:door">>) end),
    ok = cell_hal_sim:set({general, estop_voltage}, false),
    await(estop, fun() -> maps:get(estop, cell_controller:flags()) end),
    ok = cell_hal_sim:set({general, estop_voltage}, true),
    await(released, fun() -> not maps:get(estop, cell_controller:flags()) end),
    %% What it took over, it takes down.
    ok = application:stop(cell),
    ?assertEqual([], cell_hal:connections()).

%% The HAL's server is away (it restarts) as the monitor starts after a crash: the
%% monitor does not crash again; it takes the PLC for lost (its inputs unknown, so
%% nothing is decided on them; the operator told once the start's grace is over) and,
%% woken by the HAL when its server is back, takes over the connection and the groups
%% and follows the inputs again.
hal_server_away_as_the_monitor_starts(_Config) ->
    ok = cell_settings:put(monitor, #{connect_grace_ms => 100}, <<"suite">>),
    ok = supervisor:terminate_child(cell_hal_sup, cell_hal_server),
    Old = whereis(cell_monitor),
    exit(Old, kill),
    await(restarted, fun() -> lists:member(whereis(cell_monitor), [undefined, Old]) =:= false end),
    New = whereis(cell_monitor),
    ?assertMatch(#{inputs := #{estop_ok := unknown, door_locked := unknown, air_ok := unknown},
                   hal := [{hardware, camera}]}, cell_monitor:info()),
    await(loss_reported, fun() -> has_alarm(<<"cell:connection.plc1">>) end),
    ?assertNotEqual(nomatch, binary:match(maps:get(description, element(2, cell_alarms:get(
                                                                         <<"cell:connection.plc1">>))),
                                          <<"the HAL is restarting">>)),
    ?assertEqual(down, device_status(plc1)),
    %% Its server back: taken over as it was, followed again; the same monitor.
    {ok, _} = supervisor:restart_child(cell_hal_sup, cell_hal_server),
    await(back, fun() -> device_status(plc1) =:= up andalso input(estop_ok) =:= true
                             andalso not has_alarm(<<"cell:connection.plc1">>) end),
    ?assertEqual(New, whereis(cell_monitor)),
    ?assertMatch(#{hal := [{hardware, camera}, {connection, plc1}, {group, general},
                           {group, axes}]}, cell_monitor:info()),
    ok = cell_hal_sim:set({general, door_locked}, false),
    await(door_warning, fun() -> has_alarm(<<"cell:door">>) end),
    ?assertEqual(New, whereis(cell_monitor)),
    %% The HAL's server killed while the monitor runs (its workers and hardware objects
    %% restart with it): the monitor follows the PLC and the camera back.
    {ok, up} = cell_hal:subscribe_connection(plc1),
    exit(whereis(cell_hal_server), kill),
    receive {cell_hal_conn, plc1, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    receive {cell_hal_conn, plc1, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    ok = cell_hal_sim:set({general, door_locked}, true),
    await(door_locked_again, fun() -> not has_alarm(<<"cell:door">>)
                                          andalso device_status(plc1) =:= up
                                          andalso device_status(camera) =:= up end),
    ?assertEqual(New, whereis(cell_monitor)).

hal_refusal_is_an_alarm(_Config) ->
    %% plc2's options are refused by its driver: the cell runs, the operator is told.
    await(alarm, fun() -> has_alarm(<<"cell:hal.plc2">>) end),
    {ok, #{kind := alarm, caption := <<"IO configuration refused">>, description := Text}} =
        cell_alarms:get(<<"cell:hal.plc2">>),
    ?assertNotEqual(nomatch, binary:match(Text, <<"timeout_ms">>)),
    ?assertEqual([plc1], cell_hal:connections()),
    await(plc1_up, fun() -> cell_hal:status(plc1) =:= up end).

%% -------------------------------------------------------------------------------------

%% Waits until `Cond' holds, checking again after each event, log line or HAL change
%% this process is told of.
%% An input the PLC refuses (a Modbus exception on its address) is unknown to the
%% monitor while it cannot be read, not its last value; served again, it is read again.
%% The HAL tells the monitor before the test's next call reaches it (one sender).
a_refused_input_is_unknown(_Config) ->
    ?assert(input(air_ok)),
    Why = <<"the PLC refuses this address (illegal data address, Modbus exception 2)">>,
    true = cell_hal_store:set_fault({general, air_ok}, Why),
    ?assertEqual(unknown, input(air_ok)),
    true = cell_hal_store:set_fault({general, air_ok}, undefined),
    ?assert(input(air_ok)).

await(What, Cond) ->
    await(What, Cond, erlang:monotonic_time(millisecond) + ?WAIT).

await(What, Cond, Deadline) ->
    case Cond() of
        true ->
            ok;
        false ->
            Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
            receive
                {cell_event, _} -> await(What, Cond, Deadline);
                {cell_log, _} -> await(What, Cond, Deadline);
                {cell_hal, _, _} -> await(What, Cond, Deadline)
            after Left ->
                ct:fail({timeout, What, catch cell_monitor:info(), cell_alarms:list()})
            end
    end.

%% Sets an input at the simulated PLC and returns once the monitor has seen it: the
%% HAL tells subscribers (the monitor) before it fires watches (the suite's), so a call
%% to the monitor after the watch fired is answered after it handled the change.
set_seen({G, P} = Point, V) ->
    ok = cell_hal_sim:set(Point, V),
    {ok, Ref} = cell_hal:watch(G, P, {eq, V}),
    receive {cell_hal_watch, Ref, V} -> ok after ?WAIT -> ct:fail({never_read, Point, V}) end,
    _ = cell_monitor:info(),
    ok.

drain() ->
    receive Msg -> [Msg | drain()] after 0 -> [] end.

states() -> [cell_task_proc:state(Id) || Id <- ?IDS].

counts(Config, Id) -> cell_test_task:counts(?config(tab, Config), Id).

cmd(Config, Id, Command) ->
    ok = cell_test_task:command(Id, maps:get(Id, ?config(refs, Config)), Command).

has_alarm(Id) -> element(1, cell_alarms:get(Id)) =:= ok.

caption(Id) ->
    case cell_alarms:get(Id) of
        {ok, #{caption := C}} -> C;
        {error, _} -> none
    end.

description(Id) ->
    {ok, #{description := D}} = cell_alarms:get(Id),
    D.

lamps() -> maps:get(beacon, cell_monitor:info()).

lamp(L) -> maps:get(L, lamps()).

input(Role) -> maps:get(Role, maps:get(inputs, cell_monitor:info())).

lamp_points() -> [beacon_red, beacon_yellow, beacon_green, beacon_blue].

%% A lamp's mode at the monitor and its output at the PLC.
lit(Lamp, Mode, Output) ->
    lamp(Lamp) =:= Mode andalso device(lamp_point(Lamp)) =:= {ok, Output}.

lamp_point(red) -> beacon_red;
lamp_point(yellow) -> beacon_yellow;
lamp_point(green) -> beacon_green;
lamp_point(blue) -> beacon_blue.

device_status(Id) -> maps:get(Id, maps:get(devices, cell_monitor:info()), none).

%% A point as the simulated PLC holds it (what the HAL wrote to it).
device(P) when P =:= x_reset; P =:= x_override; P =:= y_override -> cell_hal_sim:get({axes, P});
device(P) -> cell_hal_sim:get({general, P}).

camera_pid() ->
    case [Pid || {camera, Pid, _, _} <- supervisor:which_children(cell_hal_hw_sup)] of
        [Pid] when is_pid(Pid) -> Pid;
        _ -> none
    end.

worker_pid(Conn) ->
    [Pid] = [Pid || {Id, Pid, _, _} <- supervisor:which_children(cell_hal_conn_sup),
                    Id =:= Conn],
    Pid.

%% The simulated PLC, once the HAL no longer knows its connection.
sim_clients(Device) ->
    gen_server:call(cell_hal_sim_device:whereis(Device), clients).

sim_image(Device, Key) ->
    case gen_server:call(cell_hal_sim_device:whereis(Device), {get, Key}) of
        {ok, V} -> V;
        error -> undefined
    end.

%% The circuit opens and its monitor raises the emergency stop; the circuit closes
%% while that monitor can no longer act (it hangs, and is then replaced): the monitor
%% that replaces it finds the circuit closed and releases the circuit's emergency stop
%% rather than leave the cell in it for good. (One raised from the panel or the shell
%% is left alone: manual_estop_is_left_alone.)
replaced_monitor_releases_its_estop(_Config) ->
    ok = cell_hal_sim:set({general, estop_voltage}, false),
    await(estop, fun() -> maps:get(estop, cell_controller:flags()) end),
    ?assertEqual(<<"emergency stop circuit">>, cell_controller:estop_by()),
    Old = whereis(cell_monitor),
    ok = sys:suspend(Old),
    ok = cell_hal_sim:set({general, estop_voltage}, true),
    exit(Old, kill),
    await(restarted, fun() -> lists:member(whereis(cell_monitor), [undefined, Old]) =:= false end),
    await(released, fun() -> not maps:get(estop, cell_controller:flags()) end),
    await(alarm_cleared, fun() -> not has_alarm(<<"cell:estop">>) end),
    ?assertEqual(undefined, cell_controller:estop_by()),
    ?assertMatch(#{estop_raised := false, inputs := #{estop_ok := true}}, cell_monitor:info()).
