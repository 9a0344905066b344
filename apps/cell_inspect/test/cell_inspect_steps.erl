%% Seed 004's numbered steps as the PLC drives them, with the codes it must read back
%% in the order it must see them, whatever the block's layout: the suites of both
%% layouts run these against their PLC (cell_inspect_plc), on a block with the
%% settings of cell_inspect_test_cell:block_settings/1 (its camera `cam1').
-module(cell_inspect_steps).
-include_lib("stdlib/include/assert.hrl").
-include("cell_inspect_suite.hrl").

-export([trigger_pass/1, unknown_point/1, override_found/1, override_not_found/1]).

%% @doc Trigger steps 1 to 9: Requesting when the echo comes, Processing on the image,
%% Complete with the results written before it.
trigger_pass(Plc) ->
    ok = cell_inspect_camera_sim:subscribe(?CAM),
    Seen = ?P:trigger(Plc, <<"STATION1">>, <<"SN-PASS">>),
    %% Step 6: when the PLC reads the echo, InspectionStatus already says Requesting.
    ?assertEqual(3, maps:get(inspection_status, Seen)),
    {request, #{point := <<"STATION1">>, serial := <<"SN-PASS">>}} =
        ?T:request_seen(?CAM),
    ?assertEqual(3, ?P:tag(Plc, inspection_status)),
    ok = cell_inspect_camera_sim:shoot(?CAM),
    ok = ?P:await(Plc, inspection_status, 2),
    ?assertEqual([3, 4, 2], ?P:written(Plc, inspection_status)),
    ?assertMatch(#{inspection_pass := true, inspection_fail := false, error_code := 0,
                   inspection_string := <<>>}, ?P:tags(Plc)),
    %% Step 9: the results are written before Complete.
    ok = ?P:before(Plc, {inspection_pass, true}, {inspection_status, 2}).

%% @doc Trigger step 6: the point does not exist: Error (5) and InspectionNotFound (2),
%% the code first.
unknown_point(Plc) ->
    Seen = ?P:trigger(Plc, <<"NOSUCH">>, <<"SN-X">>),
    ?assertMatch(#{inspection_status := 5, error_code := 2}, Seen),
    ?assertEqual([3, 5], ?P:written(Plc, inspection_status)),
    ok = ?P:before(Plc, {error_code, 2}, {inspection_status, 5}).

%% @doc Override steps 1 to 4: a result exists for point and serial: Processing (4),
%% then Complete (2) once the override is recorded.
override_found(Plc) ->
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false, scene => <<"FAIL">>}),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-OV">>),
    ok = ?P:await(Plc, inspection_status, 2),
    ok = ?P:values(Plc, [{override_employee_id, <<"E-1001">>}]),
    ok = ?P:forget(Plc),
    _ = ?P:command(Plc, log_override),
    ok = ?P:await(Plc, inspection_status, 2),
    ?assertEqual([4, 2], ?P:written(Plc, inspection_status)),
    {ok, #{overrides := [#{employee := <<"E-1001">>, point := <<"STATION1">>,
                           serial := <<"SN-OV">>, block := line1}]}} =
        cell_inspect:traceability(<<"SN-OV">>).

%% @doc Override step 4: no result for that serial: Error (5), InspectionNotFound (2).
override_not_found(Plc) ->
    ok = ?P:values(Plc, [{override_employee_id, <<"E-1">>},
                         {inspection_point_id, <<"STATION1">>}, {part_serial, <<"SN-NEVER">>}]),
    ok = ?P:forget(Plc),
    _ = ?P:command(Plc, log_override),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(2, ?P:tag(Plc, error_code)),
    ?assertEqual([4, 5], ?P:written(Plc, inspection_status)),
    {ok, #{overrides := []}} = cell_inspect:traceability(<<"SN-NEVER">>).
