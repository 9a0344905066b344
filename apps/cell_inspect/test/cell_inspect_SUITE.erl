%% The inspection block against a PLC played by the test through a real Modbus server
%% (Debian's pymodbus, holding the block's S7 UDT in holding registers on 127.0.0.1):
%% the test writes what the PLC writes and checks what the block answers, code by
%% code and in the order the PLC sees the codes, for each numbered step of the seed's
%% Trigger, Override and Send Message logic and every error path; the heartbeat, the
%% echoes, the whole UDT byte for byte, a crash of the block and a lost link.
-module(cell_inspect_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").
-include("cell_inspect_suite.hrl").

-export([all/0, groups/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([heartbeat_toggles/1, echoes/1, udt_bytes/1, trigger_pass/1, trigger_fail_with_string/1,
         trigger_without_processing/1, unknown_point/1, no_client/1, camera_for_other_points/1,
         cancel_while_waiting/1, cancel_ignored_when_idle/1, trigger_ignored_unless_ready/1,
         clear_results/1, processing_error/1, configuration_error/1, workspace_load_fails/1,
         processing_not_available/1, waiting_for_ipm/1, several_cameras/1,
         cameras_disconnect_while_waiting/1, override_found/1, override_not_found/1,
         override_ignored_while_busy/1, message_yes/1, message_no/1, message_text/1,
         message_text_too_long/1, message_not_found/1, message_no_clients/1,
         message_clients_disconnect/1, message_replaced/1, restart_while_requesting/1,
         restart_while_waiting_for_an_answer/1, link_lost_and_back/1,
         command_raised_while_link_down/1, settings_change_applies_at_once/1,
         two_blocks_two_plcs/1, traceability_by_serial/1,
         hal_server_away_as_the_block_starts/1]).

all() ->
    [heartbeat_toggles, echoes, udt_bytes, trigger_pass, trigger_fail_with_string,
     trigger_without_processing, unknown_point, no_client, camera_for_other_points,
     cancel_while_waiting, cancel_ignored_when_idle, trigger_ignored_unless_ready,
     clear_results, processing_error, configuration_error, workspace_load_fails,
     processing_not_available, waiting_for_ipm, several_cameras,
     cameras_disconnect_while_waiting, override_found, override_not_found,
     override_ignored_while_busy, message_yes, message_no, message_text,
     message_text_too_long, message_not_found, message_no_clients,
     message_clients_disconnect, message_replaced, restart_while_requesting,
     restart_while_waiting_for_an_answer, link_lost_and_back,
     command_raised_while_link_down, settings_change_applies_at_once,
     two_blocks_two_plcs, traceability_by_serial, hal_server_away_as_the_block_starts].

groups() -> [].

init_per_suite(Config) ->
    Apps = ?T:start(Config, ?MODULE,
                    [{cell_inspect, processing_types, #{<<"gate">> => cell_inspect_test_ipm}}]),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    ?T:stop(?config(apps, Config)).

init_per_testcase(Case, Config) ->
    %% The gated workspace's loader reports to the test case's process.
    _ = Case =:= waiting_for_ipm andalso register(cell_inspect_test_gate, self()),
    Log = filename:join(?config(priv_dir, Config), atom_to_list(Case) ++ ".plc.log"),
    {ok, Plc} = ?P:start(?config(data_dir, Config), Log),
    ok = application:set_env(cell_inspect, connections, [connection(plc, ?P:port(Plc))]),
    ok = application:set_env(cell_inspect, blocks,
                             [#{id => line1, connection => plc, io => #{layout => s7}}]),
    ok = put_settings([block_settings(line1, Case)]),
    {ok, _} = application:ensure_all_started(cell_inspect),
    ok = cell_inspect:subscribe(),
    ok = ?P:await(Plc, inspection_status, expected_start(Case)),
    [{plc, Plc} | Config].

end_per_testcase(_Case, Config) ->
    _ = [unregister(cell_inspect_test_gate) || whereis(cell_inspect_test_gate) =:= self()],
    ok = application:stop(cell_inspect),
    [ok = cell_hal:remove_connection(C) || C <- cell_hal:connections()],
    ?P:stop(?config(plc, Config)),
    [?P:stop(P) || P <- proplists:get_value(more_plcs, Config, [])],
    ok.

expected_start(waiting_for_ipm) -> 0;
expected_start(_) -> 1.

connection(Id, Port) ->
    #{id => Id, driver => cell_hal_modbus,
      opts => #{host => "127.0.0.1", port => Port, poll_ms => 20, reconnect_ms => 50,
                max_reconnect_ms => 400, timeout_ms => 500, connect_timeout_ms => 2000}}.

put_settings(Blocks) ->
    cell_settings:put(inspect, #{blocks => Blocks}, <<"inspect suite">>).

%% New settings, and a wait until block line1 has applied them.
change_settings(Blocks) ->
    {ok, #{settings_version := V}} = cell_inspect_block:view(line1),
    ok = put_settings(Blocks),
    await_view(line1, fun(#{settings_version := V1}) -> V1 > V end).

block_settings(Id, Case) ->
    (?T:block_settings(Id))#{
      heartbeat_ms => case Case of udt_bytes -> 60000; _ -> 300 end,
      points => [#{id => <<"STATION1">>, processing => <<"sim">>, workspace => <<"ws1">>},
                 #{id => <<"NOIPM">>, processing => <<"none">>},
                 #{id => <<"TOP">>, processing => <<"sim">>, workspace => <<"ws-top">>},
                 #{id => <<"BROKEN">>, processing => <<"sim">>},
                 #{id => <<"BADWS">>, processing => <<"sim">>, workspace => <<"fail">>}]
          ++ [#{id => <<"GATED">>, processing => <<"gate">>, workspace => <<"g">>}
              || Case =:= waiting_for_ipm]}.

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

plc(Config) -> ?config(plc, Config).

subscribe_cam(Id) ->
    ok = cell_inspect_camera_sim:subscribe(Id).

status_codes(Plc) ->
    ?P:written(Plc, inspection_status).

%%--------------------------------------------------------------------
%% Heartbeat, echoes, the UDT
%%--------------------------------------------------------------------

%% Heartbeat Logic: it toggles, every heartbeat_ms (300 here), never faster.
heartbeat_toggles(Config) ->
    Plc = plc(Config),
    First = ?P:tag(Plc, heartbeat),
    T0 = erlang:monotonic_time(millisecond),
    ok = ?P:await(Plc, heartbeat, not First),
    T1 = erlang:monotonic_time(millisecond),
    ok = ?P:await(Plc, heartbeat, First),
    T2 = erlang:monotonic_time(millisecond),
    ok = ?P:await(Plc, heartbeat, not First),
    T3 = erlang:monotonic_time(millisecond),
    %% The first wait may start anywhere in a period; the next ones are whole periods.
    ?assert(T1 - T0 =< 300 + 2000),
    ?assert(T2 - T1 >= 200 andalso T3 - T2 >= 200, {T2 - T1, T3 - T2}).

%% Echo Tags: every value the PLC writes is echoed, strings with their S7 lengths.
echoes(Config) ->
    Plc = plc(Config),
    ok = ?P:values(Plc, [{inspection_point_id, <<"STATION1">>}, {part_serial, <<"SN 0001">>},
                         {override_employee_id, <<"EMP-7">>}, {message_id, -5}]),
    ok = ?P:values(Plc, [{part_serial, <<"SN 2">>}, {inspection_point_id, <<>>}]),
    %% Latin-1 from the PLC, as a byte a character.
    ok = ?P:values(Plc, [{part_serial, <<"Grün"/utf8>>}]),
    Bytes = ?P:bytes(Plc),
    %% PartSerial_ECHO at 24: STRING[48], length 4, "Gr\xFCn".
    ?assertEqual(<<48, 4, "Gr", 252, "n">>, binary:part(Bytes, 24, 6)),
    ?assertEqual(<<16, 0>>, binary:part(Bytes, 6, 2)),
    ?assertEqual(<<-5:16/signed>>, binary:part(Bytes, 296, 2)),
    ?assertEqual(<<48, 5, "EMP-7">>, binary:part(Bytes, 74, 7)).

%% The whole UDT, byte for byte at the seed's offsets, after a complete inspection.
udt_bytes(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{scene => <<"PASS OCR-12">>}),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-BYTES">>),
    _ = ?T:request_seen(?CAM),
    ok = cell_inspect_camera_sim:shoot(?CAM),
    ok = ?P:await(Plc, inspection_status, 2),
    ok = ?P:values(Plc, [{message_id, 7}]),
    Regs = ?P:registers(Plc, 0, 175),
    Bin = << <<R:16>> || R <- Regs >>,
    ?assertEqual(Bin, ?P:bytes(Plc)),
    HB = case ?P:tag(Plc, heartbeat) of true -> 1; false -> 0 end,
    %% Byte 0: Heartbeat .0, Inspection_PASS .5.
    <<B0, _, 0, 2, 0, 0, _/binary>> = Bin,
    ?assertEqual(HB bor 32, B0),
    ?assertEqual(<<16, 8, "STATION1">>, binary:part(Bin, 6, 10)),
    ?assertEqual(<<48, 8, "SN-BYTES">>, binary:part(Bin, 24, 10)),
    ?assertEqual(<<48, 6, "OCR-12">>, binary:part(Bin, 124, 8)),
    ?assertEqual(<<0>>, binary:part(Bin, 174, 1)),
    ?assertEqual(<<16, 8, "STATION1">>, binary:part(Bin, 176, 10)),
    ?assertEqual(<<48, 8, "SN-BYTES">>, binary:part(Bin, 194, 10)),
    ?assertEqual(<<0, 7, 0, 7, 0, 0>>, binary:part(Bin, 294, 6)),
    Layout = cell_inspect_udt:layout(cell_inspect_udt:default_lengths()),
    ?assertMatch(#{inspection_status := 2, inspection_pass := true, inspection_fail := false,
                   inspection_string := <<"OCR-12">>, message_id_echo := 7},
                 cell_inspect_udt:decode(Layout, Bin)).

%%--------------------------------------------------------------------
%% Trigger Command Logic
%%--------------------------------------------------------------------

%% Trigger steps 1 to 9 (cell_inspect_steps).
trigger_pass(Config) ->
    ?S:trigger_pass(plc(Config)).

trigger_fail_with_string(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false, scene => <<"FAIL DMC 1234">>}),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-FAIL">>),
    ok = ?P:await(Plc, inspection_status, 2),
    ?assertMatch(#{inspection_pass := false, inspection_fail := true,
                   inspection_string := <<"DMC 1234">>}, ?P:tags(Plc)),
    ok = ?P:before(Plc, {inspection_fail, true}, {inspection_status, 2}),
    ok = ?P:before(Plc, {inspection_string, <<"DMC 1234">>}, {inspection_status, 2}).

%% A point without image processing: the image is recorded, the inspection passes.
trigger_without_processing(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false}),
    _ = ?P:trigger(Plc, <<"NOIPM">>, <<"SN-NOIPM">>),
    ok = ?P:await(Plc, inspection_status, 2),
    ?assert(?P:tag(Plc, inspection_pass)).

%% Step 6: the point does not exist: Error, InspectionNotFound.
unknown_point(Config) ->
    ?S:unknown_point(plc(Config)).

%% Step 6: no camera connected for the point: Error, DeviceNotFound.
no_client(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:disconnect(?CAM),
    Seen = ?P:trigger(Plc, <<"STATION1">>, <<"SN-X">>),
    ?assertMatch(#{inspection_status := 5, error_code := 1}, Seen),
    ?assertEqual([3, 5], status_codes(Plc)).

%% A camera configured for other points is no camera for this one.
camera_for_other_points(Config) ->
    Plc = plc(Config),
    [B] = cell_settings:get(inspect, blocks),
    ok = change_settings([B#{clients => [#{id => ?CAM, type => <<"sim">>, manual => true,
                                           points => [<<"TOP">>]}]}]),
    ok = cell_inspect_block_ready(line1, ?CAM),
    Seen = ?P:trigger(Plc, <<"STATION1">>, <<"SN-X">>),
    ?assertMatch(#{inspection_status := 5, error_code := 1}, Seen),
    ok = command_and_status(Plc, clear_results, 1),
    subscribe_cam(?CAM),
    Seen2 = ?P:trigger(Plc, <<"TOP">>, <<"SN-X">>),
    ?assertMatch(#{inspection_status := 3}, Seen2),
    _ = ?T:request_seen(?CAM).

%% Step 7: CancelInspection while waiting for the image: Canceled.
cancel_while_waiting(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-C">>),
    {request, #{ref := Ref}} = ?T:request_seen(?CAM),
    Seen = ?P:command(Plc, cancel_inspection),
    ?assertEqual(6, maps:get(inspection_status, Seen)),
    {cancel, Ref} = ?T:await_cam(?CAM, fun({cancel, _}) -> true; (_) -> false end),
    %% A late image changes nothing.
    ?assertEqual({error, nothing_requested}, cell_inspect_camera_sim:shoot(?CAM)),
    ?assertEqual([3, 6], status_codes(Plc)),
    %% Canceled accepts a new trigger.
    Seen2 = ?P:trigger(Plc, <<"STATION1">>, <<"SN-C2">>),
    ?assertEqual(3, maps:get(inspection_status, Seen2)).

cancel_ignored_when_idle(Config) ->
    Plc = plc(Config),
    ok = ?P:forget(Plc),
    Seen = ?P:command(Plc, cancel_inspection),
    ?assertEqual(1, maps:get(inspection_status, Seen)),
    ?assertEqual([], status_codes(Plc)).

%% Step 1: a trigger is ignored unless Ready, Complete or Canceled (here: Error, then
%% Requesting); its echo is written all the same.
trigger_ignored_unless_ready(Config) ->
    Plc = plc(Config),
    _ = ?P:trigger(Plc, <<"NOSUCH">>, <<>>),
    ok = ?P:await(Plc, inspection_status, 5),
    subscribe_cam(?CAM),
    Seen = ?P:trigger(Plc, <<"STATION1">>, <<"SN-I">>),
    ?assertMatch(#{inspection_status := 5, error_code := 2}, Seen),
    ?assertEqual([], status_codes(Plc)),
    ?assertEqual(#{requests => [], messages => []}, cell_inspect_camera_sim:pending(?CAM)),
    ok = command_and_status(Plc, clear_results, 1),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-I">>),
    _ = ?T:request_seen(?CAM),
    %% Requesting: ignored too.
    Seen3 = ?P:command(Plc, trigger_inspection),
    ?assertEqual(3, maps:get(inspection_status, Seen3)),
    ?assertMatch(#{requests := [_]}, cell_inspect_camera_sim:pending(?CAM)).

%% ClearResults: PASS 0, FAIL 0, ErrorCode 0, Ready.
clear_results(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false, scene => <<"FAIL">>}),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-CL">>),
    ok = ?P:await(Plc, inspection_status, 2),
    true = ?P:tag(Plc, inspection_fail),
    Seen = ?P:command(Plc, clear_results),
    ?assertMatch(#{inspection_pass := false, inspection_fail := false, error_code := 0,
                   inspection_status := 1}, Seen),
    _ = ?P:trigger(Plc, <<"NOSUCH">>, <<>>),
    Seen2 = ?P:command(Plc, clear_results),
    ?assertMatch(#{error_code := 0, inspection_status := 1}, Seen2).

command_and_status(Plc, Cmd, Status) ->
    Seen = ?P:command(Plc, Cmd),
    ?assertEqual(Status, maps:get(inspection_status, Seen)),
    ok.

%% An image the processing cannot read: ProcessingError.
processing_error(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false, scene => <<"BLURRED">>}),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-PE">>),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(3, ?P:tag(Plc, error_code)),
    ?assertEqual([3, 4, 5], status_codes(Plc)).

%% A point whose processing has no workspace: InspectionConfigurationError.
configuration_error(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false}),
    _ = ?P:trigger(Plc, <<"BROKEN">>, <<"SN-CE">>),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(5, ?P:tag(Plc, error_code)).

%% A workspace that cannot be loaded: InspectionConfigurationError too.
workspace_load_fails(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false}),
    _ = ?P:trigger(Plc, <<"BADWS">>, <<"SN-WF">>),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(5, ?P:tag(Plc, error_code)).

%% A point added while Ready, its workspace still loading when the image comes:
%% ProcessingNotAvailable.
processing_not_available(Config) ->
    Plc = plc(Config),
    true = register(cell_inspect_test_gate, self()),
    [B] = cell_settings:get(inspection_settings_name(), blocks),
    ok = change_settings([B#{points => maps:get(points, B) ++
                              [#{id => <<"GATED">>, processing => <<"gate">>,
                                 workspace => <<"g">>}]}]),
    Loader = receive {cell_inspect_test_ipm, loading, P} -> P after ?WAIT -> ct:fail(no_load) end,
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false}),
    _ = ?P:trigger(Plc, <<"GATED">>, <<"SN-NA">>),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(6, ?P:tag(Plc, error_code)),
    Loader ! release,
    unregister(cell_inspect_test_gate).

inspection_settings_name() -> inspect.

%% WaitingForIPM until the workspaces are loaded; meanwhile a point without image
%% processing may be triggered, one with processing is ignored, and ClearResults
%% leaves WaitingForIPM (the system is loading).
waiting_for_ipm(Config) ->
    Plc = plc(Config),
    Loader = receive {cell_inspect_test_ipm, loading, P} -> P after ?WAIT -> ct:fail(no_load) end,
    ok = cell_inspect_block_ready(line1, ?CAM),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false}),
    Seen = ?P:trigger(Plc, <<"STATION1">>, <<"SN-W">>),
    ?assertEqual(0, maps:get(inspection_status, Seen)),
    _ = ?P:trigger(Plc, <<"NOIPM">>, <<"SN-W">>),
    ok = ?P:await(Plc, inspection_status, 2),
    Seen2 = ?P:command(Plc, clear_results),
    ?assertEqual(0, maps:get(inspection_status, Seen2)),
    Loader ! release,
    ok = ?P:await(Plc, inspection_status, 1).

%% Several cameras: all are asked; the first image wins, the others are told to stop.
several_cameras(Config) ->
    Plc = plc(Config),
    [B] = cell_settings:get(inspect, blocks),
    Cams = [#{id => <<"camA">>, type => <<"sim">>, manual => true},
            #{id => <<"camB">>, type => <<"sim">>, manual => true}],
    ok = change_settings([B#{clients => Cams}]),
    [ok = cell_inspect_block_ready(line1, C) || C <- [<<"camA">>, <<"camB">>]],
    [subscribe_cam(C) || C <- [<<"camA">>, <<"camB">>]],
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-M">>),
    _ = ?T:request_seen(<<"camA">>),
    {request, #{ref := Ref}} = ?T:request_seen(<<"camB">>),
    ok = cell_inspect_camera_sim:shoot(<<"camB">>),
    {cancel, Ref} = ?T:await_cam(<<"camA">>, fun({cancel, _}) -> true; (_) -> false end),
    ok = ?P:await(Plc, inspection_status, 2).

%% Every camera asked leaves before sending an image: DeviceNotFound.
cameras_disconnect_while_waiting(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-D">>),
    _ = ?T:request_seen(?CAM),
    ok = cell_inspect_camera_sim:disconnect(?CAM),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(1, ?P:tag(Plc, error_code)).

%%--------------------------------------------------------------------
%% PLC Override Logic
%%--------------------------------------------------------------------

%% Override steps 1 to 4: a result exists for point and serial.
override_found(Config) ->
    ?S:override_found(plc(Config)).

%% Override step 4: no result for that serial: Error, InspectionNotFound.
override_not_found(Config) ->
    ?S:override_not_found(plc(Config)).

%% Step 1: ignored while not Ready, Complete or Canceled.
override_ignored_while_busy(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-B">>),
    _ = ?T:request_seen(?CAM),
    ok = ?P:forget(Plc),
    Seen = ?P:command(Plc, log_override),
    ?assertEqual(3, maps:get(inspection_status, Seen)),
    ?assertEqual([], status_codes(Plc)).

%%--------------------------------------------------------------------
%% Send Message Logic
%%--------------------------------------------------------------------

%% Steps 1 to 9: Waiting, then AffirmativeResponse.
message_yes(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    Seen = ?P:send_message(Plc, 7),
    ?assertEqual(1, maps:get(message_status, Seen)),
    {message, #{id := 7, text := <<"Part OK?">>, kind := yes_no}} = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, yes),
    ok = ?P:await(Plc, message_status, 5).

message_no(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:send_message(Plc, 7),
    _ = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, no),
    ok = ?P:await(Plc, message_status, 6).

%% Step 11: a text goes to MessageResult, then AffirmativeResponse; the next message
%% empties MessageResult before it says Waiting.
message_text(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:send_message(Plc, 8),
    _ = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, {text, <<"LOT-42">>}),
    ok = ?P:await(Plc, message_status, 5),
    ?assertEqual(<<"LOT-42">>, ?P:tag(Plc, message_result)),
    ok = ?P:before(Plc, {message_result, <<"LOT-42">>}, {message_status, 5}),
    Seen = ?P:send_message(Plc, 7),
    ?assertMatch(#{message_status := 1, message_result := <<>>}, Seen).

%% A text the PLC cannot hold is refused; the message keeps waiting.
message_text_too_long(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:send_message(Plc, 8),
    _ = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, {text, binary:copy(<<"x">>, 49)}),
    {answer_refused, _, {too_long, 48}} =
        ?T:await_cam(?CAM, fun({answer_refused, _, _}) -> true; (_) -> false end),
    ?assertEqual(1, ?P:tag(Plc, message_status)).

%% Step 5: an unknown MessageID: MessageNotFound.
message_not_found(Config) ->
    Plc = plc(Config),
    Seen = ?P:send_message(Plc, 99),
    ?assertEqual(2, maps:get(message_status, Seen)).

%% Step 4 (before step 5): no client: NoAvailableClients, even for an unknown id.
message_no_clients(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:disconnect(?CAM),
    ?assertEqual(3, maps:get(message_status, ?P:send_message(Plc, 7))),
    ?assertEqual(3, maps:get(message_status, ?P:send_message(Plc, 99))).

%% Step 6: every client disconnects before an answer: NoAvailableClients.
message_clients_disconnect(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:send_message(Plc, 7),
    _ = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:disconnect(?CAM),
    ok = ?P:await(Plc, message_status, 3).

%% SendMessage overrides a message not answered yet.
message_replaced(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:send_message(Plc, 7),
    {message, #{ref := Ref7}} = ?T:message_seen(?CAM),
    _ = ?P:send_message(Plc, 8),
    {withdrawn, Ref7} = ?T:await_cam(?CAM, fun({withdrawn, _}) -> true; (_) -> false end),
    {message, #{id := 8}} = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, {text, <<"B">>}),
    ok = ?P:await(Plc, message_result, <<"B">>),
    ok = ?P:await(Plc, message_status, 5).

%%--------------------------------------------------------------------
%% Crashes and a lost link
%%--------------------------------------------------------------------

%% The block crashes while Requesting: it comes back, the PLC gets Error with
%% InternalError instead of waiting for ever; the heartbeat goes on.
restart_while_requesting(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-R">>),
    _ = ?T:request_seen(?CAM),
    Old = cell_inspect_block:whereis(line1),
    exit(Old, kill),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(4, ?P:tag(Plc, error_code)),
    HB = ?P:tag(Plc, heartbeat),
    ok = ?P:await(Plc, heartbeat, not HB),
    ok = command_and_status(Plc, clear_results, 1).

restart_while_waiting_for_an_answer(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:send_message(Plc, 7),
    _ = ?T:message_seen(?CAM),
    exit(cell_inspect_block:whereis(line1), kill),
    ok = ?P:await(Plc, message_status, 4).

%% The HAL's server is away (it restarts) as the block starts again while
%% Requesting: the block does not crash again; it takes its PLC as lost (offline:
%% nothing written, the heartbeat still) and, woken by the HAL when its server is back,
%% follows the PLC again and answers it as after any restart: Error with InternalError
%% instead of waiting for ever, the heartbeat going again.
hal_server_away_as_the_block_starts(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-H">>),
    _ = ?T:request_seen(?CAM),
    ok = supervisor:terminate_child(cell_hal_sup, cell_hal_server),
    %% The block starts again while the HAL is away: it comes up offline. What the
    %% block before it said is dropped, so that only the new one's view counts.
    Old = cell_inspect_block:whereis(line1),
    ok = supervisor:terminate_child(cell_inspect_block_sup, line1),
    ok = drop_views(line1),
    {ok, New} = supervisor:restart_child(cell_inspect_block_sup, line1),
    ok = await_view(line1, fun(#{state := S}) -> S =:= offline end),
    ?assertNotEqual(Old, New),
    ?assertEqual(New, cell_inspect_block:whereis(line1)),
    ?assertEqual(3, ?P:tag(Plc, inspection_status)),
    {ok, _} = supervisor:restart_child(cell_hal_sup, cell_hal_server),
    ok = ?P:await(Plc, inspection_status, 5),
    ?assertEqual(4, ?P:tag(Plc, error_code)),
    HB = ?P:tag(Plc, heartbeat),
    ok = ?P:await(Plc, heartbeat, not HB),
    ok = command_and_status(Plc, clear_results, 1),
    ?assertEqual(New, cell_inspect_block:whereis(line1)),
    %% The HAL's server killed while the block runs: its worker restarts with it, the
    %% PLC is lost and back; the block goes offline and online and works on.
    exit(whereis(cell_hal_server), kill),
    ok = next_view(line1, fun(#{state := S}) -> S =:= offline end),
    ok = next_view(line1, fun(#{state := S}) -> S =:= online end),
    HB2 = ?P:tag(Plc, heartbeat),
    ok = ?P:await(Plc, heartbeat, not HB2),
    ?assertMatch(#{inspection_status := 3}, ?P:trigger(Plc, <<"STATION1">>, <<"SN-H2">>)),
    _ = ?T:request_seen(?CAM),
    ?assertEqual(New, cell_inspect_block:whereis(line1)).

%% The PLC stops answering while the camera sends its image: the block goes on and
%% writes Complete when the PLC is back.
link_lost_and_back(Config) ->
    Plc = plc(Config),
    subscribe_cam(?CAM),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-L">>),
    _ = ?T:request_seen(?CAM),
    ok = cell_hal_subscribe(plc),
    ok = ?P:silent(Plc, true),
    ok = await_conn(plc, down),
    ok = cell_inspect_camera_sim:shoot(?CAM),
    ok = await_view(line1, fun(#{status := S}) -> S =:= complete end),
    ?assertEqual(3, ?P:tag(Plc, inspection_status)),
    ok = ?P:silent(Plc, false),
    ok = ?P:await(Plc, inspection_status, 2),
    ?assert(?P:tag(Plc, inspection_pass)).

%% A command raised while the link is down is taken when the PLC is read again.
command_raised_while_link_down(Config) ->
    Plc = plc(Config),
    ok = ?P:values(Plc, [{inspection_point_id, <<"STATION1">>}, {part_serial, <<"SN-LD">>}]),
    ok = cell_hal_subscribe(plc),
    ok = ?P:silent(Plc, true),
    ok = await_conn(plc, down),
    ok = ?P:set(Plc, trigger_inspection, true),
    ok = ?P:silent(Plc, false),
    ok = ?P:await(Plc, trigger_inspection_echo, true),
    ?assertEqual(3, ?P:tag(Plc, inspection_status)).

%% A new inspection point in the settings is usable at the next trigger.
settings_change_applies_at_once(Config) ->
    Plc = plc(Config),
    [B] = cell_settings:get(inspect, blocks),
    ok = change_settings([B#{points => [#{id => <<"NEW">>, processing => <<"none">>}]}]),
    ok = cell_inspect_block_ready(line1, ?CAM),
    subscribe_cam(?CAM),
    Seen = ?P:trigger(Plc, <<"NEW">>, <<"SN-N">>),
    ?assertEqual(3, maps:get(inspection_status, Seen)),
    _ = ?T:request_seen(?CAM).

%% Two blocks on two PLCs, each with its own cameras: a camera serves its block only.
two_blocks_two_plcs(Config) ->
    Plc1 = plc(Config),
    Log = filename:join(?config(priv_dir, Config), "second.plc.log"),
    {ok, Plc2} = ?P:start(?config(data_dir, Config), Log, 500),
    ok = application:stop(cell_inspect),
    ok = application:set_env(cell_inspect, connections,
                             [connection(plc, ?P:port(Plc1)), connection(plc2, ?P:port(Plc2))]),
    ok = application:set_env(cell_inspect, blocks,
                             [#{id => line1, connection => plc, io => #{layout => s7}},
                              #{id => line2, connection => plc2, io => #{layout => s7, base => 500}}]),
    B2 = (block_settings(line2, x))#{clients => [#{id => <<"cam2">>, type => <<"sim">>,
                                                   manual => true}]},
    ok = put_settings([block_settings(line1, x), B2]),
    {ok, _} = application:ensure_all_started(cell_inspect),
    ok = cell_inspect:subscribe(),
    ok = ?P:await(Plc2, inspection_status, 1),
    ok = cell_inspect_camera_sim:disconnect(?CAM),
    %% line1 has no camera left; line2's camera is not line1's.
    ?assertMatch(#{inspection_status := 5, error_code := 1},
                 ?P:trigger(Plc1, <<"STATION1">>, <<"SN-2B">>)),
    subscribe_cam(<<"cam2">>),
    ?assertMatch(#{inspection_status := 3}, ?P:trigger(Plc2, <<"STATION1">>, <<"SN-2B">>)),
    _ = ?T:request_seen(<<"cam2">>),
    ok = cell_inspect_camera_sim:shoot(<<"cam2">>),
    ok = ?P:await(Plc2, inspection_status, 2),
    ?assertEqual(5, ?P:tag(Plc1, inspection_status)),
    {ok, #{inspections := [#{block := line2}]}} = cell_inspect:traceability(<<"SN-2B">>),
    ?P:stop(Plc2).

%% Every inspection and override by serial, with its image saved under Data/.
traceability_by_serial(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false, scene => <<"PASS 77">>}),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-T">>),
    ok = ?P:await(Plc, inspection_status, 2),
    ok = cell_inspect_camera_sim:set(?CAM, #{scene => <<"FAIL">>}),
    _ = ?P:trigger(Plc, <<"TOP">>, <<"SN-T">>),
    ok = ?P:await(Plc, trigger_inspection_echo, false),
    ok = await_view(line1, fun(#{status := S}) -> S =:= complete end),
    _ = ?P:command(Plc, log_override),
    ok = ?P:await(Plc, inspection_status, 2),
    {ok, #{inspections := [I1, I2], overrides := [O]}} = cell_inspect:traceability(<<"SN-T">>),
    ?assertMatch(#{point := <<"STATION1">>, result := pass, text := <<"77">>, client := ?CAM}, I1),
    ?assertMatch(#{point := <<"TOP">>, result := fail}, I2),
    ?assertMatch(#{point := <<"TOP">>, employee := <<>>}, O),
    #{image := Image, time := T} = I1,
    {ok, <<"P5\n# cellrt-sim PASS 77", _/binary>>} =
        file:read_file(filename:join(cell_config:dir(data), Image)),
    ?assert(abs(os:system_time(millisecond) - T) < 60000),
    %% The part's history in the cell's traceability has them too, oldest first.
    ok = cell_stats:flush(),
    {ok, #{events := Events}} = cell_stats:product(<<"SN-T">>),
    ?assertMatch([#{event := inspection, detail := #{block := line1, point := <<"STATION1">>,
                                                      result := pass, image := Image}},
                  #{event := inspection, detail := #{point := <<"TOP">>, result := fail}},
                  #{event := inspection_override, detail := #{point := <<"TOP">>}}],
                 Events).

%%--------------------------------------------------------------------

%% Waits until the block counts a client as connected.
cell_inspect_block_ready(Block, Client) ->
    await_view(Block, fun(#{clients := Cs}) -> lists:member(Client, Cs) end).

%% Waits for a block's view to satisfy `Cond': the test is subscribed to every change
%% (cell_inspect:subscribe/0 in init_per_testcase).
await_view(Block, Cond) ->
    case cell_inspect_block:view(Block) of
        {ok, V} ->
            case Cond(V) of
                true -> ok;
                false -> next_view(Block, Cond)
            end;
        {error, _} -> next_view(Block, Cond)
    end.

drop_views(Block) ->
    receive {cell_inspect, view, #{id := Block}} -> drop_views(Block)
    after 0 -> ok
    end.

next_view(Block, Cond) ->
    receive
        {cell_inspect, view, #{id := Block} = V} ->
            case Cond(V) of
                true -> ok;
                false -> next_view(Block, Cond)
            end
    after ?WAIT -> ct:fail({view_never, Block, cell_inspect_block:view(Block)})
    end.

cell_hal_subscribe(Conn) ->
    {ok, _} = cell_hal:subscribe_connection(Conn),
    ok.

await_conn(Conn, Status) ->
    case cell_hal:status(Conn) of
        Status -> ok;
        _ ->
            receive {cell_hal_conn, Conn, Status} -> ok
            after ?WAIT -> ct:fail({connection_never, Conn, Status})
            end
    end.
