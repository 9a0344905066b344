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
    %% Every point of the front lane's three segments and the two robots.
    ?assertEqual(7 + 5 + 5 + 12 + 6, length(Points)),
    ?assertMatch({{lower_io, target_x}, lreal,
                  #{unit := 1, table := holding_register, address := 200, word_order := big}},
                 lists:keyfind({lower_io, target_x}, 1, Points)),
    ?assertMatch({{upper_io, done}, int32, #{table := input_register, address := 260}},
                 lists:keyfind({upper_io, done}, 1, Points)),
    %% The same connection and groups, on the simulated PLC.
    ?assertMatch(#{connections := [#{id := router_plc, driver := cell_hal_sim}]}, Hal),
    ?assertEqual(5, length(maps:get(groups, Hal))),
    {ok, Image} = cell_vplc_image:new(Points),
    ?assertEqual([1], cell_vplc_image:units(Image)),
    {ok, #{points := Dual}} = cell_vplc:setup(router(#{dual_lane => true}), router_plc),
    ?assertEqual(length(Points) + 17, length(Dual)).

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
