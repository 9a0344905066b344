%% What a virtual PLC serves of a cell spec, without processes: the router's real-mode
%% HAL resolved as the Modbus driver resolves it, and the specs it cannot serve.
-module(cell_vplc_tests).

-include_lib("eunit/include/eunit.hrl").

router(Machine) ->
    router_cell:cell_spec(Machine#{simulation_mode => false},
                          cell_settings_schema:defaults(router_settings)).

router_test() ->
    {ok, #{conn := router_plc, points := Points, hal := Hal}} =
        cell_vplc:setup(router(#{dual_lane => false}), undefined),
    %% Every point of the front lane's three segments and its fixture's clamps, the
    %% two robots (of the lower one, the spindle and the bit: its X and Y are NC axes;
    %% of the upper one, the gripper, its five in-position signals and its NC axes'
    %% positions), the general IO and the three drives (the front conveyors', the
    %% robots'); the lane's inspection block's S7 UDT and the PLC program's side of it;
    %% its code reader's.
    ?assertEqual(6 + 3 + 5 + 8 + 4 + 10 + 12 + 3 * 4 + 34 + 18 + 5, length(Points)),
    ?assertMatch({{clamps_front_io, a_is_closed}, bool,
                  #{table := discrete_input, address := 440}},
                 lists:keyfind({clamps_front_io, a_is_closed}, 1, Points)),
    ?assertMatch({{clamps_front_io, b_open}, bool, #{table := coil, address := 443}},
                 lists:keyfind({clamps_front_io, b_open}, 1, Points)),
    %% The UDT's BOOLs are bits of its holding registers: TriggerInspection at byte
    %% 174.0, register 480 + 87, the high byte's bit 0.
    ?assertMatch({{inspect_front, trigger_inspection}, bool,
                  #{table := holding_register, address := 567, bit := 8}},
                 lists:keyfind({inspect_front, trigger_inspection}, 1, Points)),
    ?assertMatch({{general_io, air_pressure}, lreal,
                  #{unit := 1, table := input_register, address := 300, word_order := big}},
                 lists:keyfind({general_io, air_pressure}, 1, Points)),
    ?assertMatch({{upper_io, x_actual}, real, #{table := holding_register, address := 260}},
                 lists:keyfind({upper_io, x_actual}, 1, Points)),
    ?assertMatch({{upper_io, at_nest_front}, bool, #{table := discrete_input, address := 263}},
                 lists:keyfind({upper_io, at_nest_front}, 1, Points)),
    %% The same connection and groups, on the simulated PLC.
    ?assertMatch(#{connections := [#{id := router_plc, driver := cell_hal_sim}]}, Hal),
    ?assertMatch({{general_io, estop_ok}, bool, #{table := discrete_input, address := 300}},
                 lists:keyfind({general_io, estop_ok}, 1, Points)),
    ?assertMatch({{drives_io, lower_reset}, bool, #{table := coil, address := 341}},
                 lists:keyfind({drives_io, lower_reset}, 1, Points)),
    ?assertEqual(11, length(maps:get(groups, Hal))),
    {ok, Image} = cell_vplc_image:new(Points),
    ?assertEqual([1], cell_vplc_image:units(Image)),
    {ok, #{points := Dual}} = cell_vplc:setup(router(#{dual_lane => true}), router_plc),
    %% The rear lane's three segments, its clamps (at 460), its conveyors' drive, its
    %% inspection block and its code reader.
    ?assertEqual(length(Points) + 14 + 8 + 4 + 34 + 18 + 5, length(Dual)),
    ?assertMatch({{clamps_rear_io, a_close}, bool, #{table := coil, address := 460}},
                 lists:keyfind({clamps_rear_io, a_close}, 1, Dual)).

refused_test_() ->
    Real = router(#{dual_lane => false}),
    #{hal := #{connections := [Conn]} = Hal} = Real,
    Sim = Real#{hal := Hal#{connections := [Conn#{driver := cell_hal_sim}]}},
    Two = Real#{hal := Hal#{connections := [Conn, Conn#{id := plc2}]}},
    [?_assertEqual({error, no_modbus_connection}, cell_vplc:setup(Sim, undefined)),
     ?_assertEqual({error, {no_modbus_connection, plc9}}, cell_vplc:setup(Real, plc9)),
     ?_assertEqual({error, {several_modbus_connections, [router_plc, plc2]}},
                   cell_vplc:setup(Two, undefined)),
     ?_assertMatch({ok, #{conn := plc2, points := []}}, cell_vplc:setup(Two, plc2)),
     ?_assertEqual({error, no_hal}, cell_vplc:setup(#{tasks => []}, undefined))].

%% How `make run' points the cell at its virtual PLC: the fields set, the others kept,
%% a missing file made, a file that is no JSON object refused and left as it was.
merge_settings_test() ->
    Root = filename:join(os:getenv("TMPDIR", "/tmp"),
                         "cell_vplc_merge_" ++ os:getpid() ++ "_"
                         ++ integer_to_list(erlang:unique_integer([positive]))),
    Dir = filename:join(Root, "Settings"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Machine = filename:join(Dir, "machine.json"),
    ok = file:write_file(Machine, <<"{\"dual_lane\": true, \"simulation_mode\": true}">>),
    try
        ok = cell_vplc:merge_settings(Root, #{machine => #{simulation_mode => false},
                                              router => #{plc_host => <<"127.0.0.1">>,
                                                          plc_port => 1502}}),
        ?assertEqual(#{<<"dual_lane">> => true, <<"simulation_mode">> => false},
                     jsx:decode(element(2, file:read_file(Machine)), [return_maps])),
        {ok, Router} = file:read_file(filename:join(Dir, "router.json")),
        ?assertEqual(#{<<"plc_host">> => <<"127.0.0.1">>, <<"plc_port">> => 1502},
                     jsx:decode(Router, [return_maps])),
        ok = file:write_file(Machine, <<"[1,">>),
        ?assertMatch({error, {not_a_json_object, _}},
                     cell_vplc:merge_settings(Root, #{machine => #{simulation_mode => true}})),
        ?assertEqual({ok, <<"[1,">>}, file:read_file(Machine))
    after
        _ = file:del_dir_r(Root)
    end.
