%% The inspection block over ADS: seed 004's Allen-Bradley names as the members of the
%% structure MVSCAMERA on a TwinCAT PLC, reached through the HAL's ADS driver. The PLC
%% is played by the test through the fake TwinCAT PLC of the ADS tests (proven against
%% Beckhoff's AdsLib), on 127.0.0.1, declaring the members with the seed's types and
%% string lengths: BOOL, INT for Short, STRING(16) and STRING(32) for DATA/16 and
%% DATA/32. The test writes what the PLC writes and checks what the block answers,
%% code by code and in the order the PLC sees them; the PLC-written members reach the
%% block by device notifications, so that a command pulse too short for any poll is
%% still taken.
-module(cell_inspect_ads_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").
-include("cell_inspect_suite.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([symbols_and_notifications/1, heartbeat_toggles/1, echoes/1, trigger_pass/1,
         trigger_fail_with_string/1, unknown_point/1, override_found/1,
         override_not_found/1, message_yes_no/1, message_text/1,
         pulse_in_one_notification/1, pulse_over_before_the_block_looks/1,
         connection_dropped/1, polled_without_notifications/1, member_missing/1]).

all() ->
    [symbols_and_notifications, heartbeat_toggles, echoes, trigger_pass,
     trigger_fail_with_string, unknown_point, override_found, override_not_found,
     message_yes_no, message_text, pulse_in_one_notification,
     pulse_over_before_the_block_looks, connection_dropped, polled_without_notifications,
     member_missing].

init_per_suite(Config) ->
    [{apps, ?T:start(Config, ?MODULE, [])} | Config].

end_per_suite(Config) ->
    ?T:stop(?config(apps, Config)).

init_per_testcase(Case, Config) ->
    {ok, Plc} = ?P:start_ads(),
    %% Polls a minute apart: nothing the block does may rely on them. Where polling
    %% is what a case looks at, they are 20 ms apart.
    {Io, PollMs} = case Case of
                       polled_without_notifications -> {#{layout => ads, notify => false}, 20};
                       symbols_and_notifications -> {#{layout => ads}, 20};
                       _ -> {#{layout => ads}, 60000}
                   end,
    ok = application:set_env(cell_inspect, connections,
                             [#{id => plc, driver => cell_hal_ads,
                                opts => #{host => "127.0.0.1", port => ?P:port(Plc),
                                          target_net_id => "127.0.0.1.1.1", poll_ms => PollMs,
                                          reconnect_ms => 50, max_reconnect_ms => 400,
                                          timeout_ms => 2000}}]),
    ok = application:set_env(cell_inspect, blocks,
                             [#{id => line1, connection => plc, io => Io}]),
    ok = cell_settings:put(inspect, #{blocks => [?T:block_settings(line1)]},
                           <<"inspect ads suite">>),
    {ok, _} = application:ensure_all_started(cell_inspect),
    ok = ?P:await(Plc, inspection_status, 1),
    [{plc, Plc} | Config].

end_per_testcase(_Case, Config) ->
    ok = application:stop(cell_inspect),
    [ok = cell_hal:remove_connection(C) || C <- cell_hal:connections()],
    ?P:stop(?config(plc, Config)).

%%--------------------------------------------------------------------
%% The PLC and what it was asked
%%--------------------------------------------------------------------

plc(Config) -> ?config(plc, Config).

%% The InspectionStatus codes the block wrote, oldest first.
status_codes(Plc) ->
    ?P:written(Plc, inspection_status).

%% The PLC's statistics of what it was asked.
stats(Plc) ->
    {ok, Stats} = cell_hal_ads_peer:cmd(?P:peer(Plc), "stats"),
    Stats.

%%--------------------------------------------------------------------
%% The structure, the heartbeat, the echoes
%%--------------------------------------------------------------------

%% Every member of the seed's table resolves with its type and size; each of the
%% nine the PLC writes is a device notification, and nothing is polled: while values
%% are echoed and the heartbeat toggles twice (thirty poll periods) the PLC is asked
%% for no read.
symbols_and_notifications(Config) ->
    Plc = plc(Config),
    ?assertMatch({ok, #{status := up, faults := []}}, cell_hal:info(plc)),
    %% nine members, and the symbol version the connection watches
    ?assertMatch(#{notes := 10}, stats(Plc)),
    ok = cell_hal_ads_peer:cmd(?P:peer(Plc), "clear"),
    ok = ?P:values(Plc, [{inspection_point_id, <<"STATION1">>}, {message_id, 8}]),
    ok = heartbeat_toggled_twice(Plc),
    ?assertEqual(0, maps:get(sums, stats(Plc), 0)),
    ?assertEqual(0, maps:get(reads, stats(Plc), 0)).

%% Heartbeat Logic: the application toggles HEARTBEAT (every 300 ms here).
heartbeat_toggles(Config) ->
    heartbeat_toggled_twice(plc(Config)).

%% Returns once HEARTBEAT has been written both ways, each write a toggle.
heartbeat_toggled_twice(Plc) ->
    ok = ?P:forget(Plc),
    [ok = ?P:await(Plc, heartbeat, V) || V <- [true, false, true]],
    Written = ?P:written(Plc, heartbeat),
    ?assert(length(Written) >= 2),
    ?assertEqual([], [A || {A, A} <- lists:zip(lists:droplast(Written), tl(Written))]),
    ok.

%% Echo Tags: every value the PLC writes is echoed, strings up to their declared
%% lengths (STRING(16), STRING(32)) in Latin-1 with their terminator.
echoes(Config) ->
    Plc = plc(Config),
    ok = ?P:values(Plc, [{inspection_point_id, <<"0123456789ABCDEF">>},
                         {part_serial, <<"SN-0001-ABCDEFGHIJKLMNOPQRSTUVWX">>},
                         {override_employee_id, <<"EMP-7">>}, {message_id, -5}]),
    ?assertEqual(<<"0123456789ABCDEF", 0>>, ?P:raw(Plc, inspection_point_id_echo)),
    ?assertEqual(<<"SN-0001-ABCDEFGHIJKLMNOPQRSTUVWX", 0>>, ?P:raw(Plc, part_serial_echo)),
    ?assertEqual(<<"EMP-7", 0:(28 * 8)>>, ?P:raw(Plc, employee_override_echo)),
    ?assertEqual(<<-5:16/little-signed>>, ?P:raw(Plc, message_id_echo)),
    %% shorter again: the rest of the string is NUL
    ok = ?P:values(Plc, [{part_serial, <<"Grün"/utf8>>}, {inspection_point_id, <<>>}]),
    ?assertEqual(<<"Gr", 252, "n", 0:(29 * 8)>>, ?P:raw(Plc, part_serial_echo)),
    ?assertEqual(<<0:(17 * 8)>>, ?P:raw(Plc, inspection_point_id_echo)).

%%--------------------------------------------------------------------
%% Trigger and Override Logic
%%--------------------------------------------------------------------

%% The seed's numbered steps as over Modbus (cell_inspect_steps): a PASS, an unknown
%% point, an override with and without a result, each code as the seed's tables say.
trigger_pass(Config) -> ?S:trigger_pass(plc(Config)).
unknown_point(Config) -> ?S:unknown_point(plc(Config)).
override_found(Config) -> ?S:override_found(plc(Config)).
override_not_found(Config) -> ?S:override_not_found(plc(Config)).

%% Step 9 with a FAIL and a string longer than INSPECTION_STRING holds: its first 32
%% characters.
trigger_fail_with_string(Config) ->
    Plc = plc(Config),
    Text = <<"DMC-0123456789-0123456789-0123456789">>,
    ok = cell_inspect_camera_sim:set(?CAM, #{manual => false, scene => <<"FAIL ", Text/binary>>}),
    _ = ?P:trigger(Plc, <<"STATION1">>, <<"SN-FAIL">>),
    ok = ?P:await(Plc, inspection_status, 2),
    Held = binary:part(Text, 0, 32),
    ?assertMatch(#{inspection_pass := false, inspection_fail := true,
                   inspection_string := Held}, ?P:tags(Plc)),
    ?assertEqual(<<Held/binary, 0>>, ?P:raw(Plc, inspection_string)),
    ok = ?P:before(Plc, {inspection_fail, true}, {inspection_status, 2}),
    ok = ?P:before(Plc, {inspection_string, Held}, {inspection_status, 2}).

%%--------------------------------------------------------------------
%% Send Message Logic
%%--------------------------------------------------------------------

%% Waiting (1) when the echo comes, then AffirmativeResponse (5) or NegativeResponse (6)
%% as the client's user answers.
message_yes_no(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:subscribe(?CAM),
    ?assertEqual(1, maps:get(message_status, ?P:send_message(Plc, 7))),
    {message, #{id := 7, text := <<"Part OK?">>, kind := yes_no}} = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, yes),
    ok = ?P:await(Plc, message_status, 5),
    _ = ?P:send_message(Plc, 7),
    _ = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, no),
    ok = ?P:await(Plc, message_status, 6),
    ?assertEqual(<<>>, ?P:tag(Plc, message_result)).

%% Step 11: a text goes to MESSAGERESULT (a STRING(32)) before AffirmativeResponse; a
%% longer one is refused, the message waiting still.
message_text(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:subscribe(?CAM),
    _ = ?P:send_message(Plc, 8),
    _ = ?T:message_seen(?CAM),
    ok = cell_inspect_camera_sim:answer(?CAM, {text, binary:copy(<<"x">>, 33)}),
    {answer_refused, _, {too_long, 32}} =
        ?T:await_cam(?CAM, fun(E) -> element(1, E) =:= answer_refused end),
    ?assertMatch({ok, #{message_status := waiting}}, cell_inspect_block:view(line1)),
    ?assertEqual(1, ?P:tag(Plc, message_status)),
    %% asked again (the simulated client forgot the message it refused to answer)
    _ = ?P:send_message(Plc, 8),
    _ = ?T:message_seen(?CAM),
    Lot = <<"LOT-42-", (binary:copy(<<"9">>, 25))/binary>>,
    ok = cell_inspect_camera_sim:answer(?CAM, {text, Lot}),
    ok = ?P:await(Plc, message_status, 5),
    ?assertEqual(<<Lot/binary, 0>>, ?P:raw(Plc, message_result)),
    ok = ?P:before(Plc, {message_result, Lot}, {message_status, 5}).

%%--------------------------------------------------------------------
%% Rising edges shorter than any poll
%%--------------------------------------------------------------------

%% The PLC raises TriggerInspection for one cycle without waiting for its echo: the
%% notification brings 1 and 0 together, and the block takes the edge (its echo
%% follows the bit: 1, then 0).
pulse_in_one_notification(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:subscribe(?CAM),
    ok = ?P:values(Plc, [{inspection_point_id, <<"STATION1">>}, {part_serial, <<"SN-P1">>}]),
    ok = ?P:forget(Plc),
    ok = ?P:pulse(Plc, trigger_inspection),
    {request, #{serial := <<"SN-P1">>}} = ?T:request_seen(?CAM),
    ok = ?P:await_written(Plc, trigger_inspection_echo, [true, false]),
    ?assertEqual([3], status_codes(Plc)),
    ok = cell_inspect_camera_sim:shoot(?CAM),
    ok = ?P:await(Plc, inspection_status, 2).

%% The bit rises and falls in two notifications, both in before the block looks at
%% the first (it is held meanwhile): the edge is still taken.
pulse_over_before_the_block_looks(Config) ->
    Plc = plc(Config),
    ok = cell_inspect_camera_sim:subscribe(?CAM),
    ok = ?P:values(Plc, [{inspection_point_id, <<"STATION1">>}, {part_serial, <<"SN-P2">>}]),
    ok = ?P:forget(Plc),
    ok = cell_hal:subscribe(line1, trigger_inspection),
    Block = cell_inspect_block:whereis(line1),
    ok = sys:suspend(Block),
    ok = ?P:set(Plc, trigger_inspection, true),
    ok = ?P:set(Plc, trigger_inspection, false),
    [receive {cell_hal, {line1, trigger_inspection}, V} -> ok
     after ?WAIT -> ct:fail({not_published, V})
     end || V <- [true, false]],
    ok = sys:resume(Block),
    {request, #{serial := <<"SN-P2">>}} = ?T:request_seen(?CAM),
    ok = ?P:await_written(Plc, trigger_inspection_echo, [true, false]),
    ?assertEqual([3], status_codes(Plc)).

%%--------------------------------------------------------------------
%% The connection
%%--------------------------------------------------------------------

%% The PLC drops the connection: the HAL connects again, its notifications come back,
%% and the next trigger is taken.
connection_dropped(Config) ->
    Plc = plc(Config),
    {ok, up} = cell_hal:subscribe_connection(plc),
    ok = cell_hal_ads_peer:cmd(?P:peer(Plc), "drop"),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(never_down) end,
    receive {cell_hal_conn, plc, up} -> ok after ?WAIT -> ct:fail(never_up) end,
    ?assertMatch(#{notes := 10}, stats(Plc)),
    Seen = ?P:trigger(Plc, <<"NOSUCH">>, <<"SN-DROP">>),
    ?assertMatch(#{inspection_status := 5, error_code := 2}, Seen).

%% `notify => false': the members are polled (every 20 ms here); the echo handshake
%% works the same.
polled_without_notifications(Config) ->
    Plc = plc(Config),
    ?assertEqual(1, maps:get(notes, stats(Plc))),
    ok = cell_inspect_camera_sim:subscribe(?CAM),
    Seen = ?P:trigger(Plc, <<"STATION1">>, <<"SN-POLL">>),
    ?assertEqual(3, maps:get(inspection_status, Seen)),
    _ = ?T:request_seen(?CAM),
    ?assert(maps:get(sums, stats(Plc)) > 0).

%%--------------------------------------------------------------------
%% The PLC's program
%%--------------------------------------------------------------------

%% A download takes PARTSERIAL out of the structure. The trigger that follows waits:
%% the operator is shown an alarm of the block naming the member, until a download
%% puts it back; the block then reads the PLC whole again, the alarm is cleared, and
%% the trigger the PLC still holds is taken.
member_missing(Config) ->
    Plc = plc(Config),
    ok = cell_events:subscribe([alarm_raised, alarm_cleared]),
    ok = cell_log:subscribe(),
    ok = ?P:values(Plc, [{inspection_point_id, <<"STATION1">>}]),
    ok = ?P:program_without(Plc, part_serial),
    %% The HAL has found the member gone before the PLC triggers.
    {ok, _} = cell_hal_ads_peer:await(
                fun({cell_log, #{text := T}}) ->
                        binary:match(T, <<"MVSCAMERA.PARTSERIAL">>) =/= nomatch
                            andalso binary:match(T, <<"cannot be used">>) =/= nomatch
                            andalso {true, T};
                   (_) -> false
                end, ?WAIT),
    ok = cell_log:unsubscribe(),
    ok = ?P:set(Plc, trigger_inspection, true),
    Alarm = await_alarm(alarm_raised),
    ct:log("the operator sees: ~ts", [maps:get(description, Alarm)]),
    ?assertMatch(#{kind := alarm, caption := <<"Inspection block: PLC tags missing">>}, Alarm),
    ?assertNotEqual(nomatch, binary:match(maps:get(description, Alarm),
                                          <<"MVSCAMERA.PARTSERIAL">>)),
    ?assertMatch([#{local_id := <<"plc_tags">>}], cell_alarms:list(line1)),
    %% The alarms' owner restarts alone: the alarm stays, as it was.
    Alarms = whereis(cell_alarms),
    ok = kill(Alarms),
    _ = supervisor:which_children(cell_service_sup),
    ?assertNotEqual(Alarms, whereis(cell_alarms)),
    ?assertMatch([#{local_id := <<"plc_tags">>, description := Text}]
                   when Text =:= map_get(description, Alarm), cell_alarms:list(line1)),
    %% The controller's tree restarts (the registry first, the events, the alarms and
    %% the settings afresh after it): the block sets its alarm again once it is
    %% attached again, as the log (outside the tree) tells.
    ok = cell_log:subscribe(),
    ok = kill(whereis(cell_registry)),
    Caption = maps:get(caption, Alarm),
    {ok, _} = cell_hal_ads_peer:await(
                fun({cell_log, #{text := T}}) ->
                        binary:match(T, Caption) =/= nomatch andalso {true, T};
                   (_) -> false
                end, ?WAIT),
    ok = cell_log:unsubscribe(),
    ?assertMatch([#{local_id := <<"plc_tags">>, description := Text}]
                   when Text =:= map_get(description, Alarm), cell_alarms:list(line1)),
    ok = cell_events:subscribe([alarm_raised, alarm_cleared]),
    ok = ?P:program_with(Plc, part_serial),
    _ = await_alarm(alarm_cleared),
    ?assertEqual([], cell_alarms:list(line1)),
    ok = ?P:await(Plc, trigger_inspection_echo, true).

kill(Pid) ->
    Ref = monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', Ref, process, Pid, _} -> ok
    after ?WAIT -> ct:fail({not_stopped, Pid})
    end.

await_alarm(Type) ->
    receive
        {cell_event, #{type := Type, task := line1,
                       alarm := #{local_id := <<"plc_tags">>} = A}} -> A
    after ?WAIT ->
        ct:fail({no_event, Type, cell_alarms:list(line1)})
    end.
