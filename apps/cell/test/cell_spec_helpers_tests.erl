%% The helpers a cell spec is written with: each builds what the spec's checks accept,
%% the machine setting chooses between simulated and real, settings are read as saved.
-module(cell_spec_helpers_tests).
-include_lib("eunit/include/eunit.hrl").

-define(H, cell_spec_helpers).

sim() -> #{simulation_mode => true}.
real() -> #{simulation_mode => false}.

modbus() -> {cell_hal_modbus, #{host => "10.0.0.5", port => 502}}.

%% -------------------------------------------------------------------------------------
%% Machine settings
%% -------------------------------------------------------------------------------------

mode_test_() ->
    [?_assert(?H:simulated(sim())),
     ?_assertNot(?H:simulated(real())),
     %% A new installation runs simulated until someone says the hardware is there.
     ?_assert(?H:simulated(#{})),
     ?_assertError({bad_machine_setting, simulation_mode, "yes"},
                   ?H:simulated(#{simulation_mode => "yes"})),
     ?_assert(?H:dual_lane(#{dual_lane => true})),
     ?_assertNot(?H:dual_lane(#{dual_lane => false})),
     ?_assertNot(?H:dual_lane(#{})),
     ?_assertEqual(sim, ?H:sim_or_real(sim(), sim, real)),
     ?_assertEqual(real, ?H:sim_or_real(real(), sim, real)),
     ?_assertEqual(sim, ?H:sim_or_real(#{}, sim, real))].

%% The files as saved in the cell root's Settings/: defaults where missing or invalid.
saved_settings_test_() ->
    {setup,
     fun() ->
             Old = os:getenv("CELLRT_ROOT"),
             Root = cell_test_dir:new("cell_spec_helpers_tests", "root"),
             true = os:putenv("CELLRT_ROOT", Root),
             ok = filelib:ensure_dir(filename:join([Root, "Settings", "x"])),
             {Old, filename:join(Root, "Settings")}
     end,
     fun({Old, _}) ->
             case Old of
                 false -> os:unsetenv("CELLRT_ROOT");
                 _ -> os:putenv("CELLRT_ROOT", Old)
             end
     end,
     fun({_, Dir}) ->
             Machine = filename:join(Dir, "machine.json"),
             Defaults = cell_settings_schema:defaults(cell_machine_settings),
             Saved = Defaults#{simulation_mode => false, dual_lane => true},
             [?_assertEqual(Defaults, ?H:machine_settings()),
              ?_test(begin
                         ok = file:write_file(Machine,
                                              cell_settings_schema:to_json(cell_machine_settings,
                                                                           Saved)),
                         ?assertEqual(Saved, ?H:machine_settings()),
                         ?assertNot(?H:simulated(?H:machine_settings())),
                         ?assertEqual(Saved, ?H:saved_settings(cell_machine_settings))
                     end),
              ?_test(begin
                         ok = file:write_file(Machine, <<"{\"simulation_mode\": 7">>),
                         ?assertEqual(Defaults, ?H:machine_settings())
                     end)]
     end}.

is_configured_cell_test_() ->
    {setup,
     fun() -> application:get_env(cell, cell_module) end,
     fun(undefined) -> application:unset_env(cell, cell_module);
        ({ok, V}) -> application:set_env(cell, cell_module, V)
     end,
     fun(_) ->
             Is = fun(Value, Mod) ->
                          ok = application:set_env(cell, cell_module, Value),
                          ?H:is_configured_cell(Mod)
                  end,
             [?_assert(Is(my_cell, my_cell)),
              %% As the release's configuration gives it, from CELLRT_CELL.
              ?_assert(Is("my_cell", my_cell)),
              ?_assert(Is(<<"my_cell">>, my_cell)),
              ?_assertNot(Is("router_cell", my_cell)),
              ?_assertNot(Is(router_cell, my_cell)),
              ?_assertNot(Is("", my_cell))]
     end}.

%% -------------------------------------------------------------------------------------
%% Simulated or real
%% -------------------------------------------------------------------------------------

connection_test_() ->
    Choice = #{real => modbus(), sim => #{latency_ms => 2}, opts => #{poll_ms => 20}},
    [?_assertEqual(#{id => plc, driver => cell_hal_sim,
                     opts => #{latency_ms => 2, poll_ms => 20}},
                   ?H:connection(plc, sim(), Choice)),
     ?_assertEqual(#{id => plc, driver => cell_hal_modbus,
                     opts => #{host => "10.0.0.5", port => 502, poll_ms => 20}},
                   ?H:connection(plc, real(), Choice)),
     ?_assertEqual(#{id => plc, driver => cell_hal_sim, opts => #{}},
                   ?H:connection(plc, sim(), #{real => modbus()})),
     %% The driver's options win over the common ones.
     ?_assertMatch(#{opts := #{poll_ms := 5}},
                   ?H:connection(plc, real(), #{real => {cell_hal_modbus, #{poll_ms => 5}},
                                                opts => #{poll_ms => 20}})),
     ?_assertError(function_clause, ?H:connection(plc, sim(), #{sim => #{}})),
     %% Either way, the drivers take the options.
     ?_assertMatch({ok, _}, cell_hal_sim:check_opts(
                              maps:without([poll_ms], maps:get(opts, ?H:connection(plc, sim(), Choice))))),
     ?_assertMatch({ok, _}, cell_hal_modbus:check_opts(
                              maps:without([poll_ms], maps:get(opts, ?H:connection(plc, real(), Choice)))))].

hardware_test_() ->
    Cam = #{real => {gige, #{address => "10.0.0.7"}}, sim => #{width => 320}},
    [?_assertEqual(#{id => top, kind => camera, type => sim, opts => #{width => 320}},
                   ?H:hardware(top, camera, sim(), Cam)),
     ?_assertEqual(#{id => top, kind => camera, type => gige,
                     opts => #{address => "10.0.0.7"}},
                   ?H:hardware(top, camera, real(), Cam)),
     ?_assertEqual(#{id => reader, kind => code_reader, type => sim, opts => #{}},
                   ?H:hardware(reader, code_reader, sim(), #{real => none})),
     ?_assertEqual(#{id => reader, kind => code_reader, type => none},
                   ?H:hardware(reader, code_reader, real(), #{real => none})),
     ?_assertEqual(#{id => marker, kind => laser_marker, type => none},
                   ?H:hardware(marker, laser_marker, sim(), #{real => none, sim => none})),
     ?_assertError(function_clause, ?H:hardware(top, camera, sim(), #{sim => #{}})),
     ?_assertError({bad_hardware, top, {bad_option, real}},
                   ?H:hardware(top, camera, real(), #{real => gige}))].

%% -------------------------------------------------------------------------------------
%% The monitor, and a whole spec through the checks
%% -------------------------------------------------------------------------------------

general_io_test_() ->
    [?_assertEqual(#{estop_ok => {general, estop_voltage}, beacon_red => {lamps, red}},
                   ?H:general_io(general, #{estop_ok => estop_voltage,
                                            beacon_red => {lamps, red}})),
     ?_assertEqual(#{}, ?H:general_io(general, #{})),
     ?_assertError(function_clause, ?H:general_io(general, #{estop_ok => "estop"}))].

drive_test_() ->
    [?_assertEqual(#{id => x, error => {axes, x_error}, reset => {axes, x_reset},
                     code => {other, code}, caption => <<"X axis">>, override_scale => 0.01},
                   ?H:drive(x, axes, #{error => x_error, reset => x_reset,
                                       code => {other, code}, caption => <<"X axis">>,
                                       override_scale => 0.01})),
     ?_assertEqual(#{id => x}, ?H:drive(x, axes, #{}))].

%% A cell's spec written with the helpers passes the checks the controller makes at
%% boot, simulated and real alike; what the helpers cannot see is still refused there.
whole_spec_test_() ->
    Spec = fun(Machine) ->
                   Conn = ?H:connection(plc1, Machine, #{real => modbus(),
                                                         opts => #{poll_ms => 20}}),
                   #{name => <<"Test">>,
                     tasks => [?H:task(feeder, cell_test_task,
                                       #{zone => <<"Feeder">>, lane => <<"Front">>}),
                               ?H:unit(picker, cell_picker_unit,
                                       #{zone => <<"Picker">>, lane => <<"Front">>,
                                         io => [picker_io]})],
                     hal => #{connections => [Conn],
                              groups => [#{id => general, module => cell_monitor_test_io,
                                           connection => plc1, opts => #{part => general}},
                                         #{id => axes, module => cell_monitor_test_io,
                                           connection => plc1, opts => #{part => axes}},
                                         #{id => picker_io, module => cell_picker_io,
                                           connection => plc1}],
                              hardware => [?H:hardware(camera, camera, Machine,
                                                       #{real => {gige, #{}}}),
                                           ?H:hardware(reader, code_reader, Machine,
                                                       #{real => none, sim => none})]},
                     monitor => #{io => ?H:general_io(general,
                                                      #{estop_ok => estop_voltage,
                                                        service_key => service_key,
                                                        door_locked => door_locked,
                                                        air_ok => air_ok,
                                                        beacon_red => beacon_red}),
                                  drives => [?H:drive(x, axes, #{error => x_error,
                                                                 code => x_code,
                                                                 reset => x_reset,
                                                                 override => x_override})]}}
           end,
    {ok, Sim} = cell_spec:validate(Spec(sim())),
    {ok, Real} = cell_spec:validate(Spec(real())),
    [?_assertMatch(#{hal := #{connections := [#{driver := cell_hal_sim}],
                              hardware := [#{type := sim}, #{type := none}]},
                     monitor := #{io := #{estop_ok := {general, estop_voltage}},
                                  drives := [#{id := x, caption := <<"x">>}]},
                     tasks := [#{id := feeder}, #{id := picker}]}, Sim),
     ?_assertMatch(#{hal := #{connections := [#{driver := cell_hal_modbus}],
                              hardware := [#{type := gige}, #{type := none}]}}, Real),
     %% A point the group does not have, a role the monitor does not know.
     ?_assertEqual({error, {bad_monitor, {io, estop_ok}, {unknown_point, {general, estop}}}},
                   cell_spec:validate((Spec(sim()))#{monitor => #{io => ?H:general_io(
                                                                            general,
                                                                            #{estop_ok => estop})}})),
     ?_assertEqual({error, {bad_monitor, io, {unknown_keys, [horn]}}},
                   cell_spec:validate((Spec(sim()))#{monitor => #{io => ?H:general_io(
                                                                            general,
                                                                            #{horn => beacon_red})}}))].

task_and_unit_test_() ->
    Where = #{zone => <<"Z">>, lane => <<"L">>},
    [?_assertEqual(Where#{id => a, module => cell_test_task},
                   ?H:task(a, cell_test_task, Where)),
     ?_assertEqual(Where#{id => p, module => cell_picker_unit, args => #{}},
                   ?H:unit(p, cell_picker_unit, Where#{args => #{}})),
     %% Each says what kind it declares: the other kind is refused by name.
     ?_assertError({bad_task, a, {not_a_unit, cell_test_task}},
                   ?H:unit(a, cell_test_task, Where)),
     ?_assertError({bad_task, p, {not_a_device_task, cell_picker_unit}},
                   ?H:task(p, cell_picker_unit, Where)),
     ?_assertError({bad_task, p, {not_a_unit, no_such_module}},
                   ?H:unit(p, no_such_module, Where))].

%% A refusal raised while the cell module builds its spec stops the boot as the checks'
%% own errors do, naming the task.
refused_at_load_test_() ->
    {setup,
     fun() -> {application:get_env(cell, cell_spec), application:get_env(cell, cell_module)} end,
     fun({Spec, Mod}) ->
             [case Old of
                  undefined -> application:unset_env(cell, K);
                  {ok, V} -> application:set_env(cell, K, V)
              end || {K, Old} <- [{cell_spec, Spec}, {cell_module, Mod}]]
     end,
     fun(_) ->
             ok = application:unset_env(cell, cell_spec),
             ok = application:set_env(cell, cell_module, cell_test_helper_cell),
             ?_assertEqual({error, {bad_task, picker, {not_a_unit, cell_test_task}}},
                           cell_spec:load())
     end}.
