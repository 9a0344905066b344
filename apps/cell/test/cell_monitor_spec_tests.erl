%% The `hal' and `monitor' keys of the cell spec, checked at the door: each fault named,
%% alone and through cell_spec:validate/1.
-module(cell_monitor_spec_tests).
-include_lib("eunit/include/eunit.hrl").

conn() -> #{id => plc1, driver => cell_hal_sim}.

groups() ->
    [#{id => general, module => cell_monitor_test_io, connection => plc1,
       opts => #{part => general}},
     #{id => axes, module => cell_monitor_test_io, connection => plc1,
       opts => #{part => axes}}].

hal() -> #{connections => [conn()], groups => groups()}.

drive() ->
    #{id => x, error => {axes, x_error}, warning => {axes, x_warning}, code => {axes, x_code},
      reset => {axes, x_reset}, override => {axes, x_override}}.

v(Hal, Monitor) -> cell_monitor_spec:validate(#{hal => Hal, monitor => Monitor}).

v_hal(Hal) -> cell_monitor_spec:validate(#{hal => Hal}).

v_mon(Monitor) -> v(hal(), Monitor).

empty_test_() ->
    [?_assertEqual({ok, #{hal => cell_monitor_spec:empty_hal(),
                          monitor => cell_monitor_spec:empty_monitor()}},
                   cell_monitor_spec:validate(#{})),
     ?_assert(cell_monitor_spec:is_empty(cell_monitor_spec:empty_hal(),
                                         cell_monitor_spec:empty_monitor()))].

defaults_test_() ->
    {ok, #{hal := Hal, monitor := #{drives := [D]}}} =
        v((hal())#{hardware => [#{id => cam, kind => camera, type => sim}]},
          #{drives => [drive()]}),
    [?_assertMatch(#{connections := [#{opts := #{}}], groups := [#{opts := _}, _],
                     hardware := [#{opts := #{}}]}, Hal),
     ?_assertMatch(#{caption := <<"x">>, override_scale := 1}, D)].

hal_test_() ->
    G = hd(groups()),
    [?_assertEqual({error, {bad_connection, plc1, {bad_option, driver}}},
                   v_hal(#{connections => [(conn())#{driver => lists}]})),
     ?_assertEqual({error, {bad_connection, plc1, {bad_option, driver}}},
                   v_hal(#{connections => [maps:remove(driver, conn())]})),
     ?_assertEqual({error, {bad_connection, plc1, {unknown_keys, [colour]}}},
                   v_hal(#{connections => [(conn())#{colour => red}]})),
     ?_assertEqual({error, {bad_connection, plc1, {bad_option, opts}}},
                   v_hal(#{connections => [(conn())#{opts => []}]})),
     ?_assertEqual({error, {bad_connection, plc1, duplicate_id}},
                   v_hal(#{connections => [conn(), conn()]})),
     ?_assertMatch({error, {bad_cell_spec, hal, _}},
                   v_hal(#{connections => [#{id => "plc1", driver => cell_hal_sim}]})),
     ?_assertMatch({error, {bad_cell_spec, hal, {unknown_keys, [drives]}}},
                   v_hal(#{drives => []})),
     ?_assertMatch({error, {bad_cell_spec, hal, _}}, v_hal(not_a_map)),
     ?_assertEqual({error, {bad_group, general, {bad_option, connection}}},
                   v_hal(#{connections => [conn()], groups => [G#{connection => plc9}]})),
     ?_assertEqual({error, {bad_group, general, {bad_option, module}}},
                   v_hal(#{connections => [conn()], groups => [G#{module => lists}]})),
     ?_assertMatch({error, {bad_group, general, {points_failed, cell_monitor_test_io, _}}},
                   v_hal(#{connections => [conn()], groups => [G#{opts => #{}}]})),
     ?_assertEqual({error, {bad_group, general, duplicate_id}},
                   v_hal(#{connections => [conn()], groups => [G, G]})),
     ?_assertEqual({error, {bad_hardware, cam, {bad_option, kind}}},
                   v_hal(#{hardware => [#{id => cam, kind => scanner, type => sim}]})),
     ?_assertEqual({error, {bad_hardware, cam, {bad_option, type}}},
                   v_hal(#{hardware => [#{id => cam, kind => camera}]})),
     ?_assertEqual({error, {bad_hardware, plc1, {id_of_a_connection, plc1}}},
                   v_hal(#{connections => [conn()],
                           hardware => [#{id => plc1, kind => camera, type => sim}]}))].

io_test_() ->
    [?_assertMatch({ok, #{monitor := #{io := #{estop_ok := {general, estop_voltage}}}}},
                   v_mon(#{io => #{estop_ok => {general, estop_voltage},
                                   beacon_red => {general, beacon_red}}})),
     ?_assertEqual({error, {bad_monitor, io, {unknown_keys, [start_button]}}},
                   v_mon(#{io => #{start_button => {general, estop_voltage}}})),
     ?_assertEqual({error, {bad_monitor, {io, estop_ok}, {unknown_point, {general, estop}}}},
                   v_mon(#{io => #{estop_ok => {general, estop}}})),
     ?_assertEqual({error, {bad_monitor, {io, estop_ok}, {unknown_point, {nowhere, estop}}}},
                   v_mon(#{io => #{estop_ok => {nowhere, estop}}})),
     ?_assertEqual({error, {bad_monitor, {io, beacon_red}, {not_an_output, {general, air_ok}}}},
                   v_mon(#{io => #{beacon_red => {general, air_ok}}})),
     ?_assertEqual({error, {bad_monitor, {io, air_ok}, {not_an_input, {general, beacon_red}}}},
                   v_mon(#{io => #{air_ok => {general, beacon_red}}})),
     ?_assertEqual({error, {bad_monitor, {io, air_ok}, {wrong_type, {axes, x_code}, uint16}}},
                   v_mon(#{io => #{air_ok => {axes, x_code}}})),
     ?_assertEqual({error, {bad_monitor, {io, air_ok}, {bad_point, "general.air_ok"}}},
                   v_mon(#{io => #{air_ok => "general.air_ok"}})),
     ?_assertMatch({error, {bad_cell_spec, monitor, {unknown_keys, [beacon]}}},
                   v_mon(#{beacon => []}))].

drives_test_() ->
    D = drive(),
    [?_assertMatch({ok, _}, v_mon(#{drives => [D, #{id => y, override => {axes, y_override},
                                                     override_scale => 0.01}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, duplicate_id}},
                   v_mon(#{drives => [D, D]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, no_points}},
                   v_mon(#{drives => [#{id => x}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, {bad_option, caption}}},
                   v_mon(#{drives => [D#{caption => "X"}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, {bad_option, override_scale}}},
                   v_mon(#{drives => [D#{override_scale => 0}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, {unknown_keys, [brake]}}},
                   v_mon(#{drives => [D#{brake => {axes, x_reset}}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, {wrong_type, {axes, x_error}, bool}}},
                   v_mon(#{drives => [D#{code => {axes, x_error}}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, {not_an_output, {axes, x_error}}}},
                   v_mon(#{drives => [D#{reset => {axes, x_error}}]})),
     ?_assertEqual({error, {bad_monitor, {drive, x}, {wrong_type, {axes, x_reset}, bool}}},
                   v_mon(#{drives => [D#{override => {axes, x_reset}}]})),
     %% 100 % times 1000 does not fit an INT.
     ?_assertEqual({error, {bad_monitor, {drive, x},
                            {override_out_of_range, {axes, x_override}, int16}}},
                   v_mon(#{drives => [D#{override_scale => 1000}]})),
     ?_assertMatch({error, {bad_monitor, drives, _}}, v_mon(#{drives => [#{caption => <<"X">>}]})),
     ?_assertMatch({error, {bad_monitor, drives, _}}, v_mon(#{drives => #{}}))].

severity_test_() ->
    Hal = (hal())#{hardware => [#{id => cam, kind => camera, type => sim},
                                #{id => reader, kind => code_reader, type => none}]},
    {ok, Spec} = v(Hal, #{severity => #{cam => error}}),
    [?_assertEqual([{{connection, plc1}, error}, {{hardware, cam}, error}],
                   cell_monitor_spec:devices(Spec)),
     ?_assertMatch({ok, _}, v(Hal, #{severity => #{plc1 => warning}})),
     ?_assertEqual({error, {bad_monitor, severity, {unknown_device, plc9}}},
                   v(Hal, #{severity => #{plc9 => warning}})),
     ?_assertEqual({error, {bad_monitor, severity, {bad_severity, cam, fatal}}},
                   v(Hal, #{severity => #{cam => fatal}})),
     ?_assertMatch({error, {bad_monitor, severity, _}}, v(Hal, #{severity => [cam]}))].

points_test() ->
    {ok, #{hal := Hal, monitor := Mon}} =
        v_mon(#{io => #{estop_ok => {general, estop_voltage}}, drives => [drive()]}),
    Points = cell_monitor_spec:points(Hal, Mon),
    ?assertEqual(lists:sort([{general, estop_voltage}, {axes, x_error}, {axes, x_warning},
                             {axes, x_code}, {axes, x_reset}, {axes, x_override}]),
                 lists:sort(maps:keys(Points))),
    ?assertMatch(#{dir := in, type := bool, connection := plc1},
                 maps:get({general, estop_voltage}, Points)),
    ?assertMatch(#{dir := out, type := int16}, maps:get({axes, x_override}, Points)).

override_value_test_() ->
    [?_assertEqual(80, cell_monitor_spec:override_value(int16, 80, 1)),
     ?_assertEqual(8000, cell_monitor_spec:override_value(uint32, 80, 100)),
     ?_assertEqual(1, cell_monitor_spec:override_value(byte, 50, 0.01)),
     ?_assertEqual(0.5, cell_monitor_spec:override_value(lreal, 50, 0.01)),
     ?_assertEqual(50.0, cell_monitor_spec:override_value(real, 50, 1))].

%% Through the cell spec: the keys filled in, faults passed on.
cell_spec_test_() ->
    Task = #{id => a, module => cell_test_task, zone => <<"Z">>, lane => <<"L">>},
    [?_assertMatch({ok, #{hal := #{connections := []}, monitor := #{io := #{}}}},
                   cell_spec:validate(#{tasks => [Task]})),
     ?_assertMatch({ok, #{hal := #{connections := [#{id := plc1}]},
                          monitor := #{io := #{air_ok := {general, air_ok}}}}},
                   cell_spec:validate(#{tasks => [Task], hal => hal(),
                                        monitor => #{io => #{air_ok => {general, air_ok}}}})),
     ?_assertEqual({error, {bad_monitor, {io, air_ok}, {unknown_point, {general, air}}}},
                   cell_spec:validate(#{tasks => [Task], hal => hal(),
                                        monitor => #{io => #{air_ok => {general, air}}}})),
     ?_assertEqual({error, {bad_task, a, {bad_option, zone}}},
                   cell_spec:validate(#{tasks => [Task#{zone => "Z"}],
                                        monitor => #{io => #{air_ok => {general, air}}}})),
     ?_assertMatch({ok, #{hal := #{groups := []}, monitor := #{drives := []}}},
                   {ok, cell_spec:empty()})].
