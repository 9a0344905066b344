%% Conformance of the SHDR adapter over real TCP, against a running cell of scripted
%% device tasks: the snapshot at connect, changes only after, duplicate filtering,
%% conditions (several codes, mark and sweep, clear all), time series and relative
%% time, HAL samples, multiline assets, PING/PONG and the heartbeat, a slow client,
%% a flood of clients, garbage input, the adapter's crash and the cell's restarts,
%% the Devices.xml against the stream and the MTConnect schema, and the stream read
%% field by field as the reference agent (cppagent) reads it.
%%
%% Every wait is on a message or a reply with a deadline. A barrier makes "every line
%% sent so far" observable: the cell's and the cache's sync calls, then a PING, whose
%% PONG the client process writes only after the log entries that woke it before.
-module(cell_shdr_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").
-include_lib("xmerl/include/xmerl.hrl").
-include_lib("kernel/include/file.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([snapshot_at_connect/1, changes_only_after/1, duplicates_filtered/1,
         task_items_follow_products/1, conditions_mark_and_sweep/1, clear_all/1,
         hal_samples_and_events/1, time_series/1, relative_time/1, multiline_assets/1,
         ping_pong/1, silent_agent_disconnected/1, slow_client_dropped/1,
         flood_of_clients/1, garbage_input/1, adapter_crash_spares_the_cell/1,
         cell_services_restart/1, identity_changes_announced/1,
         devices_xml_matches_stream/1, stream_reads_as_agent/1,
         taken_port_waited_for_and_moved/1, a_unit_is_a_path_like_a_task/1,
         client_limit_exact/1, idle_flood_cannot_lock_out/1, idle_client_closed/1,
         assets_sent_as_they_are/1, stop_streamed/1, same_millisecond_coalesced/1,
         closed_socket_in_words/1, node_stop_streams_the_cell_stop/1,
         two_cells_one_agent/1, part_counts_go_on_after_restart/1,
         points_unavailable_while_link_down/1, faulted_point_unavailable/1,
         work_items_for_working_tasks_only/1, axes_streamed/1]).
-export([peer_tasks/0]).

-define(TASKS, [load, robot]).
-define(PLC, shdr_suite_plc).
-define(REAL_HAL_CASES, [points_unavailable_while_link_down, faulted_point_unavailable]).
-define(WAIT, 20000).
-define(TS, "^\\d{4}-\\d\\d-\\d\\dT\\d\\d:\\d\\d:\\d\\d\\.\\d{3}Z$").

all() ->
    [snapshot_at_connect, changes_only_after, duplicates_filtered,
     task_items_follow_products, conditions_mark_and_sweep, clear_all,
     hal_samples_and_events, time_series, relative_time, multiline_assets, ping_pong,
     silent_agent_disconnected, slow_client_dropped, flood_of_clients, garbage_input,
     adapter_crash_spares_the_cell, cell_services_restart, identity_changes_announced,
     devices_xml_matches_stream, stream_reads_as_agent, taken_port_waited_for_and_moved,
     a_unit_is_a_path_like_a_task, client_limit_exact, idle_flood_cannot_lock_out,
     idle_client_closed, assets_sent_as_they_are, stop_streamed, same_millisecond_coalesced,
     closed_socket_in_words, node_stop_streams_the_cell_stop, two_cells_one_agent,
     part_counts_go_on_after_restart, points_unavailable_while_link_down,
     faulted_point_unavailable, work_items_for_working_tasks_only, axes_streamed].

init_per_testcase(Case, Config) ->
    %% A root of its own: settings saved by one case never reach the next.
    Root = filename:join(?config(priv_dir, Config), "root-" ++ atom_to_list(Case)),
    Tab = ets:new(cell_shdr_suite, [public]),
    Specs = [works(Case, Id, cell_test_task:spec(Id, Tab, self())) || Id <- ?TASKS]
        ++ case Case of
               a_unit_is_a_path_like_a_task ->
                   [cell_test_unit:spec(picker, #{tab => Tab, booting => false})];
               _ ->
                   []
           end,
    {ok, _} = cell_shdr_test_hal:start(),
    _ = [application:load(A) || A <- [cell_base, cell, cell_shdr]],
    ok = application:set_env(cell_base, root, Root),
    %% cell_base may be running from an earlier case: make this case's folders.
    ok = cell_config:ensure_root(),
    ok = application:set_env(cell, cell_spec, (hal_spec(Case))#{name => <<"suite">>,
                                                              tasks => Specs}),
    ok = application:set_env(cell_shdr, port, 0),
    ok = application:set_env(cell_shdr, hal_module, hal_module(Case)),
    {ok, _} = application:ensure_all_started(cell_shdr),
    ok = hal_points(Case),
    %% The listener listens once its continue has run: it answers after that.
    _ = sys:get_state(cell_shdr_listener),
    Refs = maps:from_list([{Id, Ref} || #{id := Id, args := #{ref := Ref}} <- Specs]),
    [{refs, Refs}, {root, Root}, {tab, Tab} | Config].

end_per_testcase(Case, _Config) ->
    _ = application:stop(cell_shdr),
    _ = [begin
             %% The simulated PLC would outlive the case with its image.
             _ = cell_hal_sim:stop_device(?PLC),
             _ = cell_hal:remove_group(conv),
             cell_hal:remove_connection(?PLC)
         end || hal_module(Case) =:= cell_hal],
    _ = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    cell_shdr_test_hal:stop(),
    ok.

%% The cell's spec for a case: an axis among its hardware for the cases that stream one.
hal_spec(Case) when Case =:= axes_streamed; Case =:= devices_xml_matches_stream;
                    Case =:= stream_reads_as_agent ->
    #{hal => #{connections => [], groups => [],
               hardware => [#{id => gantry, kind => axis, type => sim,
                              opts => #{home_ms => 1, limits => {-10.0, 500.0}}},
                            %% A turning table: a Rotary component.
                            #{id => table, kind => axis, type => sim,
                              opts => #{home_ms => 1, rotary => true}}]}};
hal_spec(_Case) ->
    #{}.

%% -------------------------------------------------------------------------------------
%% Cases
%% -------------------------------------------------------------------------------------

%% A client gets the adapter's announcements, then every item's current value, every
%% condition and the assets, all stamped in UTC, before anything else.
snapshot_at_connect(_Config) ->
    S = connect(),
    Lines = snapshot(S),
    Uuid = maps:get(uuid, cell_settings:get(shdr)),
    ?assertMatch([<<"* shdrVersion: 2">>, <<"* adapterVersion: ", _/binary>>,
                  <<"* device: cell">>, <<"* uuid: ", Uuid:36/binary>> | _], Lines),
    ?assertEqual(36, byte_size(Uuid)),
    V = values(Lines),
    [?assertEqual(Exp, maps:get(K, V), K)
     || {K, Exp} <- [{<<"avail">>, <<"AVAILABLE">>}, {<<"estop">>, <<"ARMED">>},
                     {<<"mode">>, <<"AUTOMATIC">>}, {<<"execution">>, <<"STOPPED">>},
                     {<<"wait_state">>, <<"UNAVAILABLE">>}, {<<"part_count">>, <<"0">>},
                     {<<"robot_execution">>, <<"STOPPED">>}, {<<"load_serial">>, <<"UNAVAILABLE">>},
                     {<<"robot_part_count">>, <<"0">>}]],
    %% Every plain item the adapter declares is in the snapshot, every condition too.
    Items = cell_shdr_cache:items(),
    Plain = [K || #{key := K, category := C} = I <- Items, C =/= condition,
                  not maps:is_key(time_series, I)],
    ?assertEqual(lists:sort(Plain), lists:sort(maps:keys(V))),
    Conds = [K || #{key := K, category := condition} <- Items],
    ?assertEqual(lists:sort([[K, <<"NORMAL">>, <<>>, <<>>, <<>>, <<>>] || K <- Conds]),
                 lists:sort([F || {_, F} <- conditions(Lines)])),
    %% Assets as they are: nothing removed to be sent again (see assets_sent_as_they_are).
    ?assertEqual([], [L || L <- Lines, has(L, <<"@REMOVE_ALL_ASSETS@">>)]),
    [?assertMatch({match, _}, re:run(Ts, ?TS), L) || L <- Lines, {Ts, _} <- [split(L)],
                                                     Ts =/= <<"*">>],
    ok = gen_tcp:close(S).

%% After the snapshot only changes come, each once, in the order they happened.
changes_only_after(Config) ->
    S = connect(),
    _ = snapshot(S),
    ok = cell_controller:start(),
    Lines = barrier(S),
    V = pairs(Lines),
    %% The robot's init is over at once: its WAIT may have lasted no time (not sent).
    ?assert(lists:member([X || {<<"robot_execution">>, X} <- V],
                         [[<<"WAIT">>, <<"READY">>], [<<"READY">>]])),
    ?assert(lists:member([X || {<<"robot_wait_state">>, X} <- V],
                         [[<<"POWERING_UP">>, <<"UNAVAILABLE">>], []])),
    ?assertEqual(<<"READY">>, lists:last([X || {<<"execution">>, X} <- V])),
    %% Nothing unchanged came again.
    ?assertEqual([], [K || {K, _} <- V, lists:member(K, [<<"avail">>, <<"estop">>, <<"mode">>,
                                                          <<"load_serial">>])]),
    no_repeats(V),
    cmd(Config, robot, {event, unstarved}),
    cmd(Config, robot, {event, work_start}),
    V2 = pairs(barrier(S)),
    ?assertEqual([<<"ACTIVE">>], [X || {<<"robot_execution">>, X} <- V2]),
    ?assertEqual([<<"IN_PROCESS">>], [X || {<<"robot_part_state">>, X} <- V2]),
    ?assertEqual([<<"ACTIVE">>], [X || {<<"execution">>, X} <- V2]),
    ?assertEqual([], barrier(S)),
    ok = gen_tcp:close(S).

%% A value set again to what it is sends nothing; several clients see the same.
duplicates_filtered(Config) ->
    S1 = connect(),
    _ = snapshot(S1),
    ok = cell_controller:service_mode(false),
    ok = cell_controller:estop(false),
    ok = cell_controller:stop(),
    ?assertEqual([], barrier(S1)),
    ok = cell_controller:service_mode(true),
    ok = cell_controller:service_mode(true),
    ?assertEqual([{<<"mode">>, <<"MANUAL">>}], pairs(barrier(S1))),
    S2 = connect(),
    ?assertEqual(<<"MANUAL">>, maps:get(<<"mode">>, values(snapshot(S2)))),
    ok = cell_controller:service_mode(false),
    %% A third client sees each change arrive before the next is made, so that each
    %% lasts (a value that lasted no time is not sent: same_millisecond_coalesced).
    Clock = connect(),
    _ = snapshot(Clock),
    ok = cell_controller:start(),
    await_pair(Clock, <<"load_execution">>, <<"READY">>),
    [begin
         cmd(Config, load, {event, Ev}),
         await_pair(Clock, <<"load_execution">>, Exec)
     end || {Ev, Exec} <- [{unstarved, <<"ACTIVE">>}, {starved, <<"READY">>},
                           {unstarved, <<"ACTIVE">>}]],
    ok = cell_controller:sync(),
    P1 = pairs(barrier(S1)),
    P2 = pairs(barrier(S2)),
    ?assertEqual(P1, P2),
    no_repeats(P1),
    %% The init's WAIT is over at once: it may have lasted no time.
    ?assert(lists:member([X || {<<"load_execution">>, X} <- P1],
                         [[<<"WAIT">>, <<"READY">>, <<"ACTIVE">>, <<"READY">>, <<"ACTIVE">>],
                          [<<"READY">>, <<"ACTIVE">>, <<"READY">>, <<"ACTIVE">>]])),
    ok = gen_tcp:close(Clock),
    ok = gen_tcp:close(S1),
    ok = gen_tcp:close(S2).

%% A task's product: serial, recipe (program), part state, part count, cycle time.
task_items_follow_products(Config) ->
    S = connect(),
    _ = snapshot(S),
    ok = cell_controller:start(),
    _ = barrier(S),
    Clock = connect(),
    _ = snapshot(Clock),
    cmd(Config, robot, {product, cell_product:new(<<"SN-0001">>, <<"Panel 4711">>)}),
    cmd(Config, robot, {event, {transfer_in, <<"SN-0001">>}}),
    %% Seen before the next change, so that it lasts (see same_millisecond_coalesced).
    await_pair(Clock, <<"robot_part_state">>, <<"NEEDS_PROCESSING">>),
    ok = gen_tcp:close(Clock),
    cmd(Config, robot, {event, work_start}),
    V = pairs(barrier(S)),
    ?assertEqual([<<"SN-0001">>], [X || {<<"robot_serial">>, X} <- V]),
    ?assertEqual([<<"Panel 4711">>], [X || {<<"robot_program">>, X} <- V]),
    ?assertEqual([<<"Panel 4711">>], [X || {<<"program">>, X} <- V]),
    ?assertEqual([<<"NEEDS_PROCESSING">>, <<"IN_PROCESS">>], [X || {<<"robot_part_state">>, X} <- V]),
    cmd(Config, robot, {event, work_complete}),
    V2 = pairs(barrier(S)),
    ?assertEqual([<<"PROCESSING_ENDED_COMPLETE">>], [X || {<<"robot_part_state">>, X} <- V2]),
    ?assertEqual([<<"1">>], [X || {<<"robot_part_count">>, X} <- V2]),
    ?assertEqual([<<"1">>], [X || {<<"part_count">>, X} <- V2]),
    ?assertEqual([<<"1">>], [X || {<<"part_count_good">>, X} <- V2]),
    [Cycle] = [binary_to_float(X) || {<<"robot_cycle_time">>, X} <- V2],
    ?assert(Cycle >= 0.0 andalso Cycle < 60.0),
    cmd(Config, robot, {product, undefined}),
    cmd(Config, robot, {event, {transfer_out, <<"SN-0001">>}}),
    V3 = pairs(barrier(S)),
    ?assertEqual([<<"UNAVAILABLE">>], [X || {<<"robot_serial">>, X} <- V3]),
    ?assertEqual([<<"UNAVAILABLE">>], [X || {<<"robot_program">>, X} <- V3]),
    ?assertEqual([<<"TRANSIT_COMPLETE">>], [X || {<<"robot_part_state">>, X} <- V3]),
    ok = gen_tcp:close(S).

%% Several codes active at once on one condition item; a code cleared is sent NORMAL
%% for that code; the last one cleared sends one NORMAL with no code.
conditions_mark_and_sweep(_Config) ->
    S = connect(),
    _ = snapshot(S),
    ok = cell_alarms:warning(robot, <<"w1">>, "Gripper air low", "Check the air"),
    ok = cell_alarms:warning(robot, <<"w2">>, "Vacuum | weak", ""),
    ok = cell_alarms:alarm(robot, <<"a1">>, "Door open", "Close the door"),
    %% The sweep sends what is active when it looks, each code once, whatever the
    %% order the events came in.
    ?assertEqual(lists:sort([[<<"robot_system">>, <<"WARNING">>, <<"robot.w1">>, <<"warning">>,
                              <<>>, <<"Gripper air low: Check the air">>],
                             [<<"robot_system">>, <<"WARNING">>, <<"robot.w2">>, <<"warning">>,
                              <<>>, <<"Vacuum | weak">>],
                             [<<"robot_system">>, <<"FAULT">>, <<"robot.a1">>, <<"alarm">>, <<>>,
                              <<"Door open: Close the door">>]]),
                 lists:sort([F || {_, F} <- conditions(barrier(S))])),
    %% The same warning again changes nothing; new text is sent again for its code.
    ok = cell_alarms:warning(robot, <<"w1">>, "Gripper air low", "Check the air"),
    ?assertEqual([], barrier(S)),
    ok = cell_alarms:warning(robot, <<"w1">>, "Gripper air very low", "Check the air"),
    ?assertEqual([[<<"robot_system">>, <<"WARNING">>, <<"robot.w1">>, <<"warning">>, <<>>,
                   <<"Gripper air very low: Check the air">>]],
                 [F || {_, F} <- conditions(barrier(S))]),
    %% A client connecting now gets every active code.
    S2 = connect(),
    Snap = [F || {_, [<<"robot_system">> | _] = F} <- conditions(snapshot(S2))],
    ?assertEqual([<<"robot.a1">>, <<"robot.w1">>, <<"robot.w2">>], [C || [_, _, C | _] <- Snap]),
    ok = cell_alarms:reset_warning(robot, <<"w1">>),
    ?assertEqual([[<<"robot_system">>, <<"NORMAL">>, <<"robot.w1">>, <<>>, <<>>, <<>>]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ok = cell_alarms:clear_alarm(robot, <<"a1">>),
    ?assertEqual([[<<"robot_system">>, <<"NORMAL">>, <<"robot.a1">>, <<>>, <<>>, <<>>]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ok = cell_alarms:reset_warning(robot, <<"w2">>),
    ?assertEqual([[<<"robot_system">>, <<"NORMAL">>, <<>>, <<>>, <<>>, <<>>]],
                 [F || {_, F} <- conditions(barrier(S))]),
    %% The other task's condition was never touched.
    ?assertEqual([], [F || {_, [<<"load_system">> | _] = F} <- conditions(barrier(S2))]),
    %% A value beyond its limit: the qualifier says on which side, and goes when the
    %% warning is set again without one.
    ok = cell_alarms:warning(robot, <<"oil">>, "Oil hot", "60 C", #{qualifier => high}),
    ?assertEqual([[<<"robot_system">>, <<"WARNING">>, <<"robot.oil">>, <<"warning">>, <<"HIGH">>,
                   <<"Oil hot: 60 C">>]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ok = cell_alarms:warning(robot, <<"oil">>, "Oil hot", "60 C", #{qualifier => low}),
    ?assertMatch([[<<"robot_system">>, <<"WARNING">>, <<"robot.oil">>, _, <<"LOW">>, _]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ok = cell_alarms:warning(robot, <<"oil">>, "Oil hot", "60 C"),
    ?assertMatch([[<<"robot_system">>, <<"WARNING">>, <<"robot.oil">>, _, <<>>, _]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ?assertError({bad_options, {bad_qualifier, hot}},
                 cell_alarms:warning(robot, <<"oil">>, "Oil hot", "", #{qualifier => hot})),
    %% An error may carry one too.
    Spec = #{id => <<"pressure">>, caption => "Pressure low", solutions => [retry]},
    ?assertMatch({error, {bad_spec, {{bad_qualifier, hot}, _}}},
                 cell_alarms:raise_error(robot, Spec#{qualifier => hot}, self())),
    {ok, Err} = cell_alarms:raise_error(robot, Spec#{qualifier => low}, self()),
    ?assertEqual([[<<"robot_system">>, <<"FAULT">>, <<"robot.pressure">>, <<"error">>, <<"LOW">>,
                   <<"Pressure low">>]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ok = cell_alarms:withdraw(Err),
    ok = gen_tcp:close(S),
    ok = gen_tcp:close(S2).

%% Two codes cleared at once (the emergency stop's alarm and an error withdrawn by
%% the stop): the sweep ends in one NORMAL for the item.
clear_all(Config) ->
    S = connect(),
    _ = snapshot(S),
    ok = cell_controller:start(),
    cmd(Config, robot, {error, [retry, reset]}),
    ?assertMatch([[<<"robot_system">>, <<"FAULT">>, <<"robot.step">>, <<"error">>, <<>>, _]],
                 [F || {_, F} <- conditions(barrier(S))]),
    ok = cell_controller:estop(true),
    L = barrier(S),
    ?assertMatch([_ | _], [F || {_, [<<"system">>, <<"FAULT">>, <<"cell.estop">> | _] = F}
                                <- conditions(L)]),
    ?assertEqual([<<"TRIGGERED">>], [X || {<<"estop">>, X} <- pairs(L)]),
    %% The stop withdrew the robot's error: its item is cleared as a whole.
    ?assertEqual([[<<"robot_system">>, <<"NORMAL">>, <<>>, <<>>, <<>>, <<>>]],
                 [F || {_, [<<"robot_system">> | _] = F} <- conditions(L)]),
    ok = cell_controller:estop(false),
    L2 = barrier(S),
    ?assertEqual([[<<"system">>, <<"NORMAL">>, <<>>, <<>>, <<>>, <<>>]],
                 [F || {_, [<<"system">> | _] = F} <- conditions(L2)]),
    ?assertEqual([<<"ARMED">>], [X || {<<"estop">>, X} <- pairs(L2)]),
    ?assertEqual([], cell_alarms:list()),
    ok = gen_tcp:close(S).

%% HAL points as samples and events: every change once, UNAVAILABLE when unreadable.
hal_samples_and_events(_Config) ->
    ok = cell_shdr_test_hal:set(oven, temp, 21.5),
    ok = cell_shdr_test_hal:set(oven, door, false),
    ok = put_settings(#{points => [point(<<"oven_temp">>, <<"oven">>, <<"temp">>, sample,
                                         <<"TEMPERATURE">>, <<"CELSIUS">>),
                                   point(<<"oven_door">>, <<"oven">>, <<"door">>, event,
                                         <<"DOOR_STATE">>, <<>>),
                                   point(<<"nowhere">>, <<"oven">>, <<"nowhere">>, sample,
                                         <<"PRESSURE">>, <<"PASCAL">>)]}),
    S = connect(),
    V = values(snapshot(S)),
    ?assertEqual(<<"21.5">>, maps:get(<<"oven_temp">>, V)),
    ?assertEqual(<<"false">>, maps:get(<<"oven_door">>, V)),
    ?assertEqual(<<"UNAVAILABLE">>, maps:get(<<"nowhere">>, V)),
    ok = cell_shdr_test_hal:set(oven, temp, 22.0),
    ok = cell_shdr_test_hal:set(oven, temp, 22.0),
    ok = cell_shdr_test_hal:set(oven, door, true),
    ?assertEqual([{<<"oven_temp">>, <<"22.0">>}, {<<"oven_door">>, <<"true">>}], pairs(barrier(S))),
    ok = gen_tcp:close(S).

%% A time series: `count|rate|v1 ... vN', every sample once, stamped with the last.
time_series(_Config) ->
    ok = cell_shdr_test_hal:counter(spindle, current),
    S = connect(),
    _ = snapshot(S),
    ok = put_settings(#{points => [(point(<<"current">>, <<"spindle">>, <<"current">>, sample,
                                          <<"AMPERAGE">>, <<"AMPERE">>))#{time_series => true,
                                                                          rate => 50.0,
                                                                          count => 5}]}),
    Series = read_series(S, <<"current">>, 4, deadline()),
    %% A batch has 5 samples; one cut short by a deadline the busy machine missed goes
    %% out with fewer, and says so: a line's count is always the number of its values.
    Batches = [begin
                   ?assertMatch([<<"current">>, _, <<"50">>, _], F),
                   ?assertMatch({match, _}, re:run(Ts, ?TS)),
                   [_, Count, _, Vs] = F,
                   Values = [binary_to_integer(X) || X <- binary:split(Vs, <<" ">>, [global])],
                   ?assertEqual(binary_to_integer(Count), length(Values)),
                   ?assert(length(Values) =< 5),
                   Values
               end || {Ts, F} <- Series],
    Samples = lists:append(Batches),
    %% Consecutive samples of the counter, in order (a late deadline may restart a
    %% series, never reorder or repeat it).
    ?assertEqual(Samples, lists:usort(Samples)),
    Stamps = [Ts || {Ts, _} <- Series],
    ?assertEqual(Stamps, lists:sort(Stamps)),
    ok = gen_tcp:close(S).

%% Relative time: announced, and every line starts with a millisecond tick.
relative_time(_Config) ->
    ok = cell_shdr_test_hal:counter(spindle, current),
    ok = put_settings(#{relative_time => true,
                        points => [(point(<<"current">>, <<"spindle">>, <<"current">>, sample,
                                          <<"AMPERAGE">>, <<"AMPERE">>))#{time_series => true,
                                                                          rate => 100.0,
                                                                          count => 10}]}),
    S = connect(),
    Snap = snapshot(S),
    ?assert(lists:member(<<"* relativeTime: true">>, Snap)),
    [?assertMatch({match, _}, re:run(Ts, "^\\d+$")) || L <- Snap, {Ts, _} <- [split(L)],
                                                      Ts =/= <<"*">>],
    Series = read_series(S, <<"current">>, 3, deadline()),
    Ticks = [binary_to_integer(Ts) || {Ts, _} <- Series],
    ?assertEqual(Ticks, lists:sort(Ticks)),
    ok = gen_tcp:close(S).

%% Recipes as File assets: multiline documents, changed ones sent again, removed
%% ones removed; a new client is told of the removal too.
multiline_assets(Config) ->
    ok = cell_recipe:save(<<"Panel 4711">>, #{description => <<"Two up\nfront | rear">>},
                          <<"anna">>),
    ok = cell_shdr:refresh_assets(),
    S = connect(),
    Snap = snapshot(S),
    [Doc] = assets(Snap, <<"Panel 4711">>),
    ?assertNotEqual(nomatch, binary:match(Doc, <<"applicationType=\"PRODUCTION_PROGRAM\"">>)),
    ?assertNotEqual(nomatch, binary:match(Doc, <<"Two up">>)),
    ?assertNotEqual(nomatch, binary:match(Doc, <<"&#124;">>)),
    ?assertEqual(nomatch, binary:match(Doc, <<"|">>)),
    {#xmlElement{name = 'File'} = File, []} = xmerl_scan:string(binary_to_list(Doc)),
    %% The reference agent refuses a File asset without a destination: the cell itself.
    Uuid = binary_to_list(maps:get(uuid, cell_settings:get(shdr))),
    ?assertMatch([#xmlText{value = Uuid}],
                 xmerl_xpath:string("/File/Destinations/Destination/text()", File)),
    schema_check("MTConnectAssets_2.0_1.0.xsd", assets_document(Doc), Config),
    ok = cell_recipe:save(<<"Panel 4712">>, #{description => <<"One up">>}, <<"bert">>),
    ok = cell_shdr:refresh_assets(),
    L = barrier(S),
    ?assertEqual([], assets(L, <<"Panel 4711">>)),
    [_] = assets(L, <<"Panel 4712">>),
    ok = cell_recipe:delete(<<"Panel 4711">>),
    ok = cell_shdr:refresh_assets(),
    ?assertEqual([<<"@REMOVE_ASSET@|Panel 4711">>], [strip_ts(X) || X <- barrier(S)]),
    S2 = connect(),
    Snap2 = [strip_ts(X) || X <- snapshot(S2)],
    {_, [<<"@REMOVE_ASSET@|Panel 4711">> | After]} =
        lists:splitwith(fun(X) -> X =/= <<"@REMOVE_ASSET@|Panel 4711">> end, Snap2),
    ?assertMatch([<<"@ASSET@|Panel 4712|File|--multiline--", _/binary>> | _], After),
    ok = gen_tcp:close(S),
    ok = gen_tcp:close(S2).

%% `* PING' is answered at once with the configured period.
ping_pong(_Config) ->
    S = connect(),
    _ = snapshot(S),
    Times = [begin
                 T0 = erlang:monotonic_time(microsecond),
                 ok = gen_tcp:send(S, <<"* PING\n">>),
                 {[], <<"* PONG 10000">>} = read_until(S, fun(L) -> L =:= <<"* PONG 10000">> end,
                                                       deadline()),
                 erlang:monotonic_time(microsecond) - T0
             end || _ <- lists:seq(1, 50)],
    #{median := Median} = stats(Times),
    ct:pal("PING to PONG over loopback: median ~p us, max ~p us", [Median, lists:max(Times)]),
    ?assert(Median < 200000),
    ok = put_settings(#{ping_period => 2500}),
    S2 = connect(),
    _ = snapshot(S2),
    ok = gen_tcp:send(S2, <<"  * PING  \r\n">>),
    {[], _} = read_until(S2, fun(L) -> L =:= <<"* PONG 2500">> end, deadline()),
    ok = gen_tcp:close(S),
    ok = gen_tcp:close(S2).

%% An agent that started heartbeats and then falls silent is disconnected after two
%% periods; one that never pinged is not.
silent_agent_disconnected(_Config) ->
    ok = put_settings(#{ping_period => 1000}),
    Quiet = connect(),
    S = connect(),
    ok = gen_tcp:send(S, <<"* PING\n">>),
    {_, _} = read_until(S, fun(L) -> L =:= <<"* PONG 1000">> end, deadline()),
    T0 = erlang:monotonic_time(millisecond),
    ?assertEqual({error, closed}, drain(S, deadline())),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 1900),
    ok = gen_tcp:send(Quiet, <<"* PING\n">>),
    {_, _} = read_until(Quiet, fun(L) -> L =:= <<"* PONG 1000">> end, deadline()),
    ok = gen_tcp:close(Quiet).

%% A client that stops reading is dropped with a log line; the cell and the other
%% client never wait for it, and the other client gets every change.
slow_client_dropped(_Config) ->
    N = 5000,
    ok = cell_shdr_test_hal:set(plc, flood, <<>>),
    ok = put_settings(#{max_client_buffer => 8 bsl 20,
                        points => [point(<<"flood">>, <<"plc">>, <<"flood">>, event,
                                         <<"MESSAGE">>, <<>>)]}),
    ok = cell_log:subscribe(),
    %% The slow client reads its snapshot, then nothing more. Its PONG also says the
    %% adapter has registered it, so both are among the clients monitored below.
    Slow = connect([{recbuf, 512}]),
    _ = snapshot(Slow),
    Fast = connect(),
    _ = snapshot(Fast),
    Refs = [monitor(process, P) || P <- cell_shdr:clients()],
    ?assertEqual(2, length(Refs)),
    Text = binary:copy(<<"x">>, 300),
    T0 = erlang:monotonic_time(microsecond),
    [ok = cell_shdr_test_hal:set(plc, flood, <<Text/binary, (integer_to_binary(I))/binary>>)
     || I <- lists:seq(1, N)],
    %% The cell answers at once while a client reads nothing.
    ok = cell_controller:sync(),
    ct:pal("~p changes of ~p bytes sent, the cell answered after ~p ms",
           [N, byte_size(Text), (erlang:monotonic_time(microsecond) - T0) div 1000]),
    %% A client behind by more than a batch may see a PONG before the rest: read up
    %% to the last change instead of to a barrier.
    LastValue = <<Text/binary, (integer_to_binary(N))/binary>>,
    {Before, LastLine} = read_until(Fast, fun(L) -> has(L, LastValue) end, deadline()),
    Got = [V || {_, [<<"flood">>, <<>>, V]} <- [split(L) || L <- Before ++ [LastLine]]],
    ?assert(Got =:= [<<Text/binary, (integer_to_binary(I))/binary>> || I <- lists:seq(1, N)]),
    %% The slow one is gone, and the log says why.
    ?assertEqual(1, length(await_down(Refs, 1, deadline()))),
    ?assert(await_log(<<"disconnected">>, deadline())),
    ?assertEqual(1, length(cell_shdr:clients())),
    ok = gen_tcp:close(Slow),
    ok = gen_tcp:close(Fast).

%% Many clients at once: each gets its snapshot and then the same changes.
flood_of_clients(_Config) ->
    N = 150,
    ok = put_settings(#{max_clients => 200}),
    Socks = [connect() || _ <- lists:seq(1, N)],
    [_ = snapshot(S) || S <- Socks],
    ?assertEqual(N, length(cell_shdr:clients())),
    ok = cell_controller:service_mode(true),
    Got = [pairs(barrier(S)) || S <- Socks],
    ?assertEqual(lists:duplicate(N, [{<<"mode">>, <<"MANUAL">>}]), Got),
    Refs = [monitor(process, P) || P <- cell_shdr:clients()],
    [ok = gen_tcp:close(S) || S <- Socks],
    ?assertEqual(N, length(await_down(Refs, N, deadline()))),
    ?assertEqual([], cell_shdr:clients()).

%% Garbage is ignored, an oversized line ends only its own connection; the listener
%% and the other clients carry on.
garbage_input(_Config) ->
    ok = cell_log:subscribe(),
    Good = connect(),
    _ = snapshot(Good),
    G = connect(),
    _ = snapshot(G),
    ok = gen_tcp:send(G, <<"* FOO\nhello|world\n", 0, 255, 254, "\n* PONG 1\n\n">>),
    ok = gen_tcp:send(G, <<"* PING\n">>),
    {_, _} = read_until(G, fun(L) -> L =:= <<"* PONG 10000">> end, deadline()),
    ?assert(await_log(<<"does not understand">>, deadline())),
    Big = connect(),
    _ = snapshot(Big),
    ok = gen_tcp:send(Big, binary:copy(<<"A">>, 5000)),
    ?assertEqual({error, closed}, drain(Big, deadline())),
    ?assert(await_log(<<"longer than">>, deadline())),
    ok = cell_controller:service_mode(true),
    ?assertEqual([{<<"mode">>, <<"MANUAL">>}], pairs(barrier(Good))),
    ?assertEqual([{<<"mode">>, <<"MANUAL">>}], pairs(barrier(G))),
    New = connect(),
    ?assertEqual(<<"MANUAL">>, maps:get(<<"mode">>, values(snapshot(New)))),
    [ok = gen_tcp:close(S) || S <- [Good, G, New]].

%% The adapter's crash touches no task; agents reconnect to a fresh snapshot.
adapter_crash_spares_the_cell(Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    Tasks = [cell_task_proc:whereis(T) || T <- ?TASKS],
    S = connect(),
    _ = snapshot(S),
    exit(whereis(cell_shdr_cache), kill),
    ?assertEqual({error, closed}, drain(S, deadline())),
    S2 = reconnect(),
    ?assertEqual(<<"READY">>, maps:get(<<"robot_execution">>, values(snapshot(S2)))),
    ?assertEqual(Tasks, [cell_task_proc:whereis(T) || T <- ?TASKS]),
    cmd(Config, robot, {event, unstarved}),
    ?assertEqual([<<"ACTIVE">>], [X || {<<"robot_execution">>, X} <- pairs(barrier(S2))]),
    ok = gen_tcp:close(S2).

%% The cell's own services restart (their subscribers and registrations go with
%% them): the adapter says UNAVAILABLE, attaches again, registers its settings again
%% and recomputes every item.
cell_services_restart(_Config) ->
    S = connect(),
    _ = snapshot(S),
    Settings = whereis(cell_settings),
    exit(Settings, kill),
    {_, _} = read_until(S, fun(L) -> has(L, <<"|avail|AVAILABLE">>) end, deadline()),
    ?assertNotEqual(Settings, whereis(cell_settings)),
    ?assertMatch(#{uuid := <<_:36/binary>>}, cell_settings:get(shdr)),
    exit(whereis(cell_events), kill),
    {Between, _} = read_until(S, fun(L) -> has(L, <<"|avail|AVAILABLE">>) end, deadline()),
    ?assert(lists:any(fun(L) -> has(L, <<"|avail|UNAVAILABLE">>) end, Between)),
    %% Subscribed again: changes flow.
    ok = cell_controller:service_mode(true),
    ?assertEqual([{<<"mode">>, <<"MANUAL">>}], pairs(barrier(S))),
    ok = gen_tcp:close(S).

%% A change of the device's identity in the settings is announced to connected agents.
identity_changes_announced(_Config) ->
    S = connect(),
    _ = snapshot(S),
    ok = put_settings(#{station => <<"Line 3 | cell 7">>, manufacturer => <<"ACME">>}),
    ?assertEqual([<<"* manufacturer: ACME">>, <<"* station: Line 3 | cell 7">>], barrier(S)),
    ok = gen_tcp:close(S).

%% Devices.xml declares exactly the items the stream carries, and is valid against the
%% MTConnect 2.0 schema (XSD 1.0 edition) when xmllint and the schema are at hand.
%% Points configured on an axis sit on a Linear or Rotary component of the Axes.
devices_xml_matches_stream(Config) ->
    ok = put_settings(#{manufacturer => <<"ACME & Sons">>, station => <<"7">>,
                        points => [point(<<"oven_temp">>, <<"oven">>, <<"temp">>, sample,
                                         <<"TEMPERATURE">>, <<"CELSIUS">>),
                                   (point(<<"current">>, <<"spindle">>, <<"current">>, sample,
                                          <<"AMPERAGE">>, <<"AMPERE">>))#{time_series => true},
                                   (point(<<"x_pos">>, <<"axes">>, <<"x_pos">>, sample,
                                          <<"POSITION">>, <<"MILLIMETER">>))#{
                                     sub_type => <<"ACTUAL">>, component => linear,
                                     axis => <<"X">>},
                                   (point(<<"x_feed">>, <<"axes">>, <<"x_vel">>, sample,
                                          <<"AXIS_FEEDRATE">>, <<"MILLIMETER/SECOND">>))#{
                                     sub_type => <<"ACTUAL">>, component => linear,
                                     axis => <<"X">>},
                                   (point(<<"c_angle">>, <<"axes">>, <<"c_pos">>, sample,
                                          <<"ANGLE">>, <<"DEGREE">>))#{
                                     sub_type => <<"ACTUAL">>, component => rotary,
                                     axis => <<"C">>}]}),
    File = filename:join(?config(priv_dir, Config), "Devices.xml"),
    ok = cell_shdr:devices_xml(File),
    {Doc, _} = xmerl_scan:file(File),
    %% The stream's keys are the items' names (an agent finds an item by its name;
    %% ids are the cell's own: two_cells_one_agent).
    Declared = [{attr(E, name), attr(E, type), attr(E, category)}
                || E <- xmerl_xpath:string("//DataItem", Doc)],
    [?assertEqual("cell_" ++ attr(E, name), attr(E, id))
     || E <- xmerl_xpath:string("//DataItem", Doc)],
    S = connect(),
    Snap = snapshot(S),
    Streamed = maps:keys(values(Snap)) ++ [K || {_, [K | _]} <- conditions(Snap)],
    ?assertEqual(lists:sort([I || {I, _, _} <- Declared, I =/= "current"]),
                 lists:sort([binary_to_list(K) || K <- Streamed])),
    ?assertMatch([{"current", "AMPERAGE", "SAMPLE"}], [D || {"current", _, _} = D <- Declared]),
    Uuid = binary_to_list(maps:get(uuid, cell_settings:get(shdr))),
    ?assertMatch([_], xmerl_xpath:string("//Device[@uuid='" ++ Uuid ++ "']", Doc)),
    [?assertMatch([_], xmerl_xpath:string("//Path[@name='" ++ atom_to_list(T) ++ "']", Doc))
     || T <- ?TASKS],
    ?assertMatch([_, _], xmerl_xpath:string(
                           "//Axes/Components/Linear[@name='X']/DataItems/DataItem", Doc)),
    ?assertMatch([_], xmerl_xpath:string("//Axes/Components/Rotary[@name='C']/DataItems/"
                                         "DataItem[@name='c_angle']", Doc)),
    %% The cell's own axis, beside the configured points' ones.
    ?assertEqual(["gantry_position", "gantry_feedrate", "gantry_state"],
                 [attr(E, name) || E <- xmerl_xpath:string(
                                          "//Axes/Components/Linear[@name='gantry']/DataItems/"
                                          "DataItem", Doc)]),
    ?assertEqual([{"table_position", "ANGLE", "DEGREE"},
                  {"table_feedrate", "ANGULAR_VELOCITY", "DEGREE/SECOND"},
                  {"table_state", "AXIS_STATE", undefined}],
                 [{attr(E, name), attr(E, type), attr_or(E, units)}
                  || E <- xmerl_xpath:string("//Axes/Components/Rotary[@name='table']/"
                                             "DataItems/DataItem", Doc)]),
    {ok, Xml} = file:read_file(File),
    schema_check("MTConnectDevices_2.0_1.0.xsd", Xml, Config),
    ok = gen_tcp:close(S).

%% Every line as the reference agent (cppagent) reads it with SHDR version 2: each key
%% is a data item of Devices.xml and takes as many fields as its kind, so no value is
%% read as a key or a key as a value. A MESSAGE carries a native code and a text on a
%% line of its own; a sample is a number (a boolean point 1 or 0) or UNAVAILABLE.
stream_reads_as_agent(Config) ->
    ok = cell_shdr_test_hal:set(oven, temp, 21.5),
    ok = cell_shdr_test_hal:set(oven, heating, true),
    ok = cell_shdr_test_hal:set(oven, door, <<"OPEN">>),
    ok = cell_shdr_test_hal:set(oven, note, <<"Preheat | done">>),
    ok = cell_shdr_test_hal:counter(spindle, current),
    %% A line of the document starting `* PONG' is a heartbeat to the agent.
    ok = cell_recipe:save(<<"Panel 4711">>, #{description => <<"Two up:\n* PONG 5">>},
                          <<"anna">>),
    ok = put_settings(#{points => [point(<<"oven_temp">>, <<"oven">>, <<"temp">>, sample,
                                         <<"TEMPERATURE">>, <<"CELSIUS">>),
                                   point(<<"oven_heating">>, <<"oven">>, <<"heating">>, sample,
                                         <<"POWER">>, <<"WATT">>),
                                   point(<<"oven_door">>, <<"oven">>, <<"door">>, event,
                                         <<"DOOR_STATE">>, <<>>),
                                   point(<<"oven_note">>, <<"oven">>, <<"note">>, event,
                                         <<"MESSAGE">>, <<>>),
                                   (point(<<"current">>, <<"spindle">>, <<"current">>, sample,
                                          <<"AMPERAGE">>, <<"AMPERE">>))#{time_series => true,
                                                                          rate => 50.0,
                                                                          count => 5}]}),
    ok = cell_shdr:refresh_assets(),
    File = filename:join(?config(priv_dir, Config), "Devices-agent.xml"),
    ok = cell_shdr:devices_xml(File),
    Declared = declared(File),
    S = connect(),
    Snap = agent_read(snapshot(S), Declared),
    Read = fun(Key, Obs) -> [F || {K, F} <- Obs, K =:= Key] end,
    %% Every declared item but the time series has its value in the snapshot.
    ?assertEqual(lists:sort([K || {K, Kind} <- maps:to_list(Declared), Kind =/= time_series]),
                 lists:usort([K || {K, _} <- Snap, binary:first(K) =/= $@])),
    ?assertEqual([[<<>>, <<"Preheat | done">>]], Read(<<"oven_note">>, Snap)),
    ?assertEqual([[<<"1">>]], Read(<<"oven_heating">>, Snap)),
    ?assertEqual([[<<"21.5">>]], Read(<<"oven_temp">>, Snap)),
    ?assertEqual([[<<"OPEN">>]], Read(<<"oven_door">>, Snap)),
    [[<<"Panel 4711">>, <<"File">>, <<"<File ", _/binary>> = Asset]] =
        Read(<<"@ASSET@">>, Snap),
    ?assertNotEqual(nomatch, binary:match(Asset, <<"Two up:\n&#42; PONG 5 (by anna)">>)),
    %% Changes read the same way: a message alone, conditions with all five fields.
    ok = cell_shdr_test_hal:set(oven, note, <<"Door | open">>),
    ok = cell_shdr_test_hal:set(oven, heating, false),
    ok = cell_shdr_test_hal:set(oven, door, <<"CLOSED">>),
    ok = cell_alarms:warning(robot, <<"w1">>, "Vacuum | weak", "check \"air\""),
    ok = cell_alarms:alarm(robot, <<"a1">>, "Door open", ""),
    %% Text holding --multiline-- would start an asset in the agent and stop the stream.
    ok = cell_alarms:warning(load, <<"w2">>, "see --multiline--X", ""),
    Changes = agent_read(barrier(S) ++ read_until_series(S, <<"current">>), Declared),
    ?assertEqual([[<<>>, <<"Door | open">>]], Read(<<"oven_note">>, Changes)),
    ?assertEqual([[<<"0">>]], Read(<<"oven_heating">>, Changes)),
    ?assertEqual([[<<"CLOSED">>]], Read(<<"oven_door">>, Changes)),
    ?assertEqual(lists:sort([[<<"WARNING">>, <<"robot.w1">>, <<"warning">>, <<>>,
                              <<"Vacuum | weak: check \"air\"">>],
                             [<<"FAULT">>, <<"robot.a1">>, <<"alarm">>, <<>>, <<"Door open">>]]),
                 lists:sort(Read(<<"robot_system">>, Changes))),
    ?assertEqual([[<<"WARNING">>, <<"load.w2">>, <<"warning">>, <<>>,
                   <<"see --multi-line--X">>]], Read(<<"load_system">>, Changes)),
    [[Count, <<"50">>, Values] | _] = Read(<<"current">>, Changes),
    ?assertEqual(binary_to_integer(Count), length(binary:split(Values, <<" ">>, [global]))),
    %% Samples read as numbers (or UNAVAILABLE), as the agent converts them.
    [?assert(V =:= <<"UNAVAILABLE">> orelse is_number(catch binary_to_float(V))
             orelse is_integer(catch binary_to_integer(V)), {K, V})
     || {K, [V]} <- Snap ++ Changes, maps:get(K, Declared, none) =:= sample],
    ok = gen_tcp:close(S).

%% The limit is exact however many acceptors ranch runs: a client beyond it is refused
%% at once (the connection closed, nothing sent, a log line), never left waiting in the
%% kernel's queue; a place freed is taken by the next client.
client_limit_exact(_Config) ->
    ok = cell_log:subscribe(),
    ok = put_settings(#{max_clients => 3}),
    In = [connect() || _ <- lists:seq(1, 3)],
    [_ = snapshot(S) || S <- In],
    Refs = [monitor(process, P) || P <- cell_shdr:clients()],
    ?assertEqual(3, length(Refs)),
    %% Refused with a plain end of the stream, also when the client PINGs at once as
    %% an agent does (its PING is never read).
    [begin
         Out = connect(),
         _ = Ping andalso gen_tcp:send(Out, <<"* PING\n">>),
         ?assertEqual({error, closed}, gen_tcp:recv(Out, 0, left(deadline(5000)))),
         ok = gen_tcp:close(Out)
     end || Ping <- [false, true, true]],
    ?assert(await_log(<<"refused: 3 clients are connected">>, deadline())),
    ?assertEqual(3, length(cell_shdr:clients())),
    [First | Rest] = In,
    ok = gen_tcp:close(First),
    ?assertEqual(1, length(await_down(Refs, 1, deadline()))),
    ok = cell_shdr_cache:sync(),
    Next = connect(),
    ?assertMatch([<<"* shdrVersion: 2">> | _], snapshot(Next)),
    [ok = gen_tcp:close(S) || S <- [Next | Rest]].

%% Connections that never PING and never read cannot hold the adapter: a client
%% arriving when they fill every place takes the place of the oldest of them, and gets
%% its snapshot at once.
idle_flood_cannot_lock_out(_Config) ->
    Max = maps:get(max_clients, cell_shdr_cache:settings()),
    Idle = [connect([{recbuf, 1024}]) || _ <- lists:seq(1, 200)],
    T0 = erlang:monotonic_time(millisecond),
    Agent = connect(),
    ok = gen_tcp:send(Agent, <<"* PING\n">>),
    {Snap, _} = read_until(Agent, fun(L) -> binary:match(L, <<"* PONG">>) =:= {0, 6} end,
                           deadline(5000)),
    ?assertMatch([<<"* shdrVersion: 2">> | _], Snap),
    ?assert(erlang:monotonic_time(millisecond) - T0 < 5000),
    ?assert(length(cell_shdr:clients()) =< Max),
    %% Its place is kept while the idle ones keep coming.
    More = [connect([{recbuf, 1024}]) || _ <- lists:seq(1, 100)],
    ok = cell_shdr_cache:sync(),
    ?assertEqual([], snapshot(Agent)),
    ?assert(length(cell_shdr:clients()) =< Max),
    [ok = gen_tcp:close(S) || S <- [Agent | Idle ++ More]].

%% A client that shows no life (no PING) within `life_timeout' of its connect is
%% closed; one that PINGs in time stays.
idle_client_closed(_Config) ->
    ok = cell_log:subscribe(),
    ok = put_settings(#{life_timeout => 1000}),
    T0 = erlang:monotonic_time(millisecond),
    Idle = connect(),
    Alive = connect(),
    ok = gen_tcp:send(Alive, <<"* PING\n">>),
    ?assertEqual({error, closed}, drain(Idle, deadline(10000))),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 1000),
    ?assert(await_log(<<"sent no PING within 1000 ms of its connect">>, deadline())),
    ?assertMatch([<<"* shdrVersion: 2">> | _], snapshot(Alive)),
    ?assertEqual([], snapshot(Alive)),
    ?assertEqual(1, length(cell_shdr:clients())),
    ok = gen_tcp:close(Alive).

%% Assets at connect as they are: no @REMOVE_ALL_ASSETS@, each stamped with its recipe
%% file's modification time, the same for every client; a recipe removed while an
%% agent was away is removed for the next client too.
assets_sent_as_they_are(_Config) ->
    ok = cell_recipe:save(<<"Panel 4711">>, #{description => <<"Two up">>}, <<"anna">>),
    ok = cell_recipe:save(<<"Panel 4712">>, #{description => <<"One up">>}, <<"bert">>),
    File = filename:join(cell_config:dir(products), "Panel 4711.zprd"),
    Mtime = 1767323045,                 % 2026-01-02T03:04:05Z
    ok = file:write_file_info(File, #file_info{mtime = Mtime}, [{time, posix}]),
    ok = cell_shdr:refresh_assets(),
    S1 = connect(),
    Snap1 = snapshot(S1),
    S2 = connect(),
    Snap2 = snapshot(S2),
    Assets = fun(Lines) -> [L || L <- Lines, has(L, <<"|@">>)] end,
    ?assertEqual([], [L || L <- Snap1, has(L, <<"@REMOVE_ALL_ASSETS@">>)]),
    [Head | _] = [L || L <- Snap1, has(L, <<"|@ASSET@|Panel 4711|">>)],
    ?assertMatch(<<"2026-01-02T03:04:05.000Z|@ASSET@|", _/binary>>, Head),
    [Doc] = assets(Snap1, <<"Panel 4711">>),
    ?assertNotEqual(nomatch, binary:match(Doc, <<"timestamp=\"2026-01-02T03:04:05.000Z\"">>)),
    %% Asset lines are the same bytes for every client (the body lines hold no time).
    ?assertEqual(Assets(Snap1), Assets(Snap2)),
    ?assertEqual([Doc], assets(Snap2, <<"Panel 4711">>)),
    ok = cell_recipe:delete(<<"Panel 4711">>),
    ok = cell_shdr:refresh_assets(),
    ?assertEqual([<<"@REMOVE_ASSET@|Panel 4711">>], [strip_ts(X) || X <- barrier(S1)]),
    S3 = connect(),
    Snap3 = [strip_ts(X) || X <- snapshot(S3)],
    ?assert(lists:member(<<"@REMOVE_ASSET@|Panel 4711">>, Snap3)),
    ?assertEqual([], [L || L <- Snap3, has(L, <<"@REMOVE_ALL_ASSETS@">>)]),
    ?assertMatch([<<"@ASSET@|Panel 4712|File|--multiline--", _/binary>>],
                 [L || L <- Snap3, has(L, <<"@ASSET@|">>)]),
    [ok = gen_tcp:close(S) || S <- [S1, S2, S3]].

%% The adapter stopping sends avail UNAVAILABLE to its clients before it closes them.
stop_streamed(_Config) ->
    S = connect(),
    _ = snapshot(S),
    Stopper = spawn_link(fun() -> ok = application:stop(cell_shdr) end),
    Ref = monitor(process, Stopper),
    {Before, _} = read_until(S, fun(L) -> has(L, <<"|avail|UNAVAILABLE">>) end, deadline()),
    ?assertEqual([], Before),
    ?assertEqual({error, closed}, drain(S, deadline())),
    receive {'DOWN', Ref, process, Stopper, normal} -> ok
    after ?WAIT -> ct:fail("the adapter did not stop")
    end.

%% A value that lasted no time is not sent: of two changes of an item within the same
%% millisecond only the last goes out (none when it is back to what was sent); a
%% change that lasted a millisecond is sent.
same_millisecond_coalesced(_Config) ->
    S = connect(),
    _ = snapshot(S),
    Cache = whereis(cell_shdr_cache),
    Ms = os:system_time(millisecond) - 1000,
    Mono = erlang:monotonic_time(microsecond) - 1000000,
    Ev = fun(State, Dt) -> Cache ! {cell_event, #{type => task_state, task => robot,
                                                   state => State, time => Ms + Dt,
                                                   mono => Mono + Dt * 1000}}
         end,
    Ev(setup, 0),
    Ev({ready, processing, active}, 0),
    ?assertEqual([<<"ACTIVE">>], [X || {<<"robot_execution">>, X} <- pairs(barrier(S))]),
    Ev({ready, idle, blocked}, 5),
    Ev({ready, processing, active}, 5),
    ?assertEqual([], [X || {<<"robot_execution">>, X} <- pairs(barrier(S))]),
    Ev({ready, idle, blocked}, 6),
    Ev({ready, processing, active}, 7),
    ?assertEqual([<<"WAIT">>, <<"ACTIVE">>],
                 [X || {<<"robot_execution">>, X} <- pairs(barrier(S))]),
    ok = gen_tcp:close(S).

%% The node going down (init:stop, as at Ctrl-C or a service stop): the agent sees the
%% cell's Stop (every task and the cell STOPPED), then avail UNAVAILABLE, then the end
%% of the connection. The adapter stops before the cell (it depends on it), so it has
%% the cell stop first.
node_stop_streams_the_cell_stop(Config) ->
    Root = filename:join(?config(priv_dir, Config), "root-node-stop"),
    Paths = [P || P <- code:get_path(), string:find(P, "_build") =/= nomatch
                                            orelse string:find(P, "_debdeps") =/= nomatch],
    Name = list_to_atom("cell_shdr_stop_" ++ os:getpid()),
    {ok, Peer, _Node} = peer:start(#{name => Name, host => "localhost",
                                     args => lists:append([["-pa", P] || P <- Paths]),
                                     connection => standard_io}),
    PeerRef = monitor(process, Peer),
    Call = fun(M, F, A) -> peer:call(Peer, M, F, A, ?WAIT) end,
    Specs = Call(?MODULE, peer_tasks, []),
    _ = [ok = Call(application, load, [A]) || A <- [cell_base, cell, cell_shdr]],
    [ok = Call(application, set_env, [A, K, V])
     || {A, K, V} <- [{cell_base, root, Root}, {cell, shutdown_wait_ms, 10000},
                      {cell, cell_spec, #{name => <<"peer">>, tasks => Specs}},
                      {cell_shdr, port, 0}, {cell_shdr, hal_module, cell_shdr_test_hal}]],
    {ok, _} = Call(application, ensure_all_started, [cell_shdr]),
    _ = Call(sys, get_state, [cell_shdr_listener]),
    Port = Call(cell_shdr, port, []),
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}, {packet, line},
                                                     {buffer, 1 bsl 20}]),
    _ = snapshot(S),
    ok = Call(cell_controller, start, []),
    await_pair(S, <<"robot_execution">>, <<"READY">>),
    ok = Call(init, stop, []),
    {Lines, Last} = read_until(S, fun(L) -> has(L, <<"|avail|UNAVAILABLE">>) end, deadline()),
    P = pairs(Lines ++ [Last]),
    ?assertMatch({<<"avail">>, <<"UNAVAILABLE">>}, lists:last(P)),
    [?assert(lists:member({K, <<"STOPPED">>}, P), K)
     || K <- [<<"robot_execution">>, <<"load_execution">>, <<"execution">>]],
    ?assertEqual({error, closed}, drain(S, deadline())),
    receive {'DOWN', PeerRef, process, Peer, _} -> ok
    after ?WAIT -> ct:fail("the node did not stop")
    end.

%% On a test node: the suite's scripted tasks, their table kept by a process of its own.
peer_tasks() ->
    Self = self(),
    _ = spawn(fun() ->
                      Tab = ets:new(cell_shdr_suite, [public]),
                      Self ! {tab, Tab},
                      receive stop -> ok end
              end),
    receive {tab, Tab} -> [cell_test_task:spec(Id, Tab, self()) || Id <- ?TASKS]
    after ?WAIT -> error(no_table)
    end.

%% Two cells feed one agent: their Devices.xml merged into one file declare no id
%% twice (the reference agent refuses a second device holding an id already taken),
%% and each cell's ids stay the same across restarts (derived from its device name).
two_cells_one_agent(Config) ->
    Items = cell_shdr_cache:items(),
    Settings = cell_shdr_cache:settings(),
    Xml = fun(Name, Uuid) ->
                  cell_shdr_devices:xml(Items, Settings#{device_name => Name, uuid => Uuid},
                                        1767323045000)
          end,
    A = Xml(<<"cell_a">>, <<"0e1c7a52-8d0e-4a53-9d3b-3c5c8e1f0a01">>),
    ?assertEqual(A, Xml(<<"cell_a">>, <<"0e1c7a52-8d0e-4a53-9d3b-3c5c8e1f0a01">>)),
    B = Xml(<<"cell_b">>, <<"5b0f7d3e-2a61-4c1e-8f55-6d7a9b2c4e02">>),
    %% One document holding both devices, as an agent's configuration would.
    [HeadA, DeviceA] = binary:split(A, <<"<Devices>\n">>),
    [DeviceA1, _] = binary:split(DeviceA, <<"  </Devices>">>),
    [_, DeviceB] = binary:split(B, <<"<Devices>\n">>),
    Merged = <<HeadA/binary, "<Devices>\n", DeviceA1/binary, DeviceB/binary>>,
    {Doc, _} = xmerl_scan:string(binary_to_list(Merged)),
    Ids = [V || #xmlAttribute{value = V} <- xmerl_xpath:string("//@id", Doc)],
    ?assertEqual(length(Ids), length(lists:usort(Ids)),
                 Ids -- lists:usort(Ids)),
    ?assertEqual(2, length(xmerl_xpath:string("//Device", Doc))),
    %% The stream's keys are the items' names, the same in every cell.
    Names = [V || #xmlAttribute{value = V} <- xmerl_xpath:string("//DataItem/@name", Doc)],
    ?assertEqual(2 * length(Items), length(Names)),
    ?assertEqual(lists:sort([binary_to_list(K) || #{key := K} <- Items]), lists:usort(Names)),
    schema_check("MTConnectDevices_2.0_1.0.xsd", Merged, Config).

%% Part counts go on from the statistics the cell keeps when the adapter starts
%% again, not from zero.
part_counts_go_on_after_restart(Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    %% The statistics count the work done on a product.
    cmd(Config, robot, {product, cell_product:new(<<"SN-0001">>, <<"Panel 4711">>)}),
    cmd(Config, robot, {event, {transfer_in, <<"SN-0001">>}}),
    [begin
         cmd(Config, robot, {event, work_start}),
         cmd(Config, robot, {event, Ev})
     end || Ev <- [work_complete, work_complete, {work_abort, <<"scratched">>}]],
    ok = cell_controller:sync(),
    S = connect(),
    V = values(snapshot(S)),
    Counts = [{K, maps:get(K, V)} || K <- [<<"robot_part_count">>, <<"part_count">>,
                                           <<"part_count_good">>, <<"part_count_bad">>]],
    ?assertEqual([{<<"robot_part_count">>, <<"3">>}, {<<"part_count">>, <<"3">>},
                  {<<"part_count_good">>, <<"2">>}, {<<"part_count_bad">>, <<"1">>}], Counts),
    ok = gen_tcp:close(S),
    ok = application:stop(cell_shdr),
    {ok, _} = application:ensure_all_started(cell_shdr),
    _ = sys:get_state(cell_shdr_listener),
    S2 = connect(),
    V2 = values(snapshot(S2)),
    ?assertEqual(Counts, [{K, maps:get(K, V2)} || {K, _} <- Counts]),
    ?assertEqual(<<"0">>, maps:get(<<"load_part_count">>, V2)),
    cmd(Config, robot, {event, work_start}),
    cmd(Config, robot, {event, work_complete}),
    ?assertEqual([{<<"robot_part_count">>, <<"4">>}, {<<"part_count">>, <<"4">>},
                  {<<"part_count_good">>, <<"3">>}],
                 [{K, X} || {K, X} <- pairs(barrier(S2)),
                            lists:member(K, [<<"robot_part_count">>, <<"part_count">>,
                                             <<"part_count_good">>])]),
    ok = gen_tcp:close(S2).

%% A client that closes its connection is logged in words.
closed_socket_in_words(_Config) ->
    ok = cell_log:subscribe(),
    S = connect(),
    _ = snapshot(S),
    [Client] = cell_shdr:clients(),
    Ref = monitor(process, Client),
    ok = gen_tcp:close(S),
    ok = cell_controller:service_mode(true),
    ?assertEqual([Ref], await_down([Ref], 1, deadline())),
    ?assert(await_log(<<"the agent closed the connection">>, deadline())).

%% The HAL's own points, a simulated PLC's: while their connection is down they read
%% as nothing, and the agent sees UNAVAILABLE at once, not the last value as if it
%% were current; once the connection is up again, their values.
points_unavailable_while_link_down(_Config) ->
    S = connect(),
    V = values(snapshot(S)),
    ?assertEqual({<<"5">>, <<"false">>},
                 {maps:get(<<"conv_count">>, V), maps:get(<<"conv_sensor">>, V)}),
    ok = cell_hal_sim:link(?PLC, down),
    await_pairs(S, [{<<"conv_count">>, <<"UNAVAILABLE">>},
                    {<<"conv_sensor">>, <<"UNAVAILABLE">>}]),
    ok = cell_hal_sim:link(?PLC, up),
    await_pairs(S, [{<<"conv_count">>, <<"5">>}, {<<"conv_sensor">>, <<"false">>}]),
    ok = gen_tcp:close(S).

%% A point the PLC cannot serve (the HAL marks it faulty, as for a Modbus exception):
%% its item goes UNAVAILABLE at once, the others stay; once the fault is cleared, its
%% value again.
faulted_point_unavailable(_Config) ->
    S = connect(),
    V = values(snapshot(S)),
    ?assertEqual(<<"5">>, maps:get(<<"conv_count">>, V)),
    Why = <<"the PLC refuses this address (illegal data address, Modbus exception 2)">>,
    true = cell_hal_store:set_fault({conv, count}, Why),
    {Before, Line} = await_pairs(S, [{<<"conv_count">>, <<"UNAVAILABLE">>}]),
    ?assertEqual([], [P || {<<"conv_sensor">>, _} = P <- pairs([Line | Before])]),
    true = cell_hal_store:set_fault({conv, count}, undefined),
    await_pairs(S, [{<<"conv_count">>, <<"5">>}]),
    ?assertEqual({ok, 5}, cell_hal:read(conv, count)),
    ok = gen_tcp:close(S).

%% A task that does no work (here `load', whose module calls no work start: its spec
%% says nothing, so the cell takes it from the code) has no part count and no cycle
%% time, neither in Devices.xml nor on the stream: they would never carry data. A
%% task that does (`robot', declared so) has both.
work_items_for_working_tasks_only(Config) ->
    File = filename:join(?config(priv_dir, Config), "Devices-work.xml"),
    ok = cell_shdr:devices_xml(File),
    {Doc, _} = xmerl_scan:file(File),
    Declared = [attr(E, name) || E <- xmerl_xpath:string("//DataItem", Doc)],
    Own = ["part_count", "cycle_time"],
    ?assertEqual([], [D || D <- Declared, S <- Own, D =:= "load_" ++ S]),
    ?assertEqual(["robot_" ++ S || S <- Own],
                 [D || S <- Own, D <- Declared, D =:= "robot_" ++ S]),
    ?assert(lists:member("load_execution", Declared)),
    S = connect(),
    V = values(snapshot(S)),
    ?assertEqual([], [K || K <- [<<"load_part_count">>, <<"load_cycle_time">>],
                           maps:is_key(K, V)]),
    ?assertEqual(<<"0">>, maps:get(<<"robot_part_count">>, V)),
    ?assertEqual(<<"UNAVAILABLE">>, maps:get(<<"robot_cycle_time">>, V)),
    ?assertEqual([{load, false}, {robot, true}],
                 [{Id, W} || #{id := Id, work := W} <- cell_registry:tasks()]),
    ok = gen_tcp:close(S).

%% The suite's tasks do work when told to (the test task starts work by a command),
%% so they say so; but for the case that shows a task doing none, whose `load' leaves
%% it to its module's code.
works(work_items_for_working_tasks_only, load, Spec) -> Spec;
works(_Case, _Id, Spec) -> Spec#{work => true}.

hal_module(Case) ->
    case lists:member(Case, ?REAL_HAL_CASES) of
        true -> cell_hal;
        false -> cell_shdr_test_hal
    end.

%% The real HAL's cases: a simulated PLC with a conveyor's points, two of them items.
hal_points(Case) ->
    case hal_module(Case) of
        cell_hal ->
            ok = cell_hal:add_connection(#{id => ?PLC, driver => cell_hal_sim,
                                           opts => #{poll_ms => 10}}),
            {ok, _} = cell_hal:subscribe_connection(?PLC),
            ok = cell_hal:add_group(#{id => conv, module => cell_io_test_group,
                                      connection => ?PLC}),
            ok = cell_hal_sim:set({conv, sensor}, false),
            ok = cell_hal_sim:set({conv, count}, 5),
            %% Up already (a simulated PLC may come up before the subscription), or
            %% told when it comes: its status is read after subscribing.
            case cell_hal:status(?PLC) of
                up -> ok;
                _ -> receive {cell_hal_conn, ?PLC, up} -> ok
                     after ?WAIT -> ct:fail("the simulated PLC did not come up")
                     end
            end,
            ok = cell_hal:unsubscribe_connection(?PLC),
            %% The HAL has read what the simulated PLC was given (its first read may
            %% have come before).
            _ = [begin
                     {ok, Ref} = cell_hal:watch(conv, P, {eq, V}),
                     receive {cell_hal_watch, Ref, V} -> ok
                     after ?WAIT -> ct:fail("the HAL did not read ~p", [P])
                     end
                 end || {P, V} <- [{sensor, false}, {count, 5}]],
            put_settings(#{points => [point(<<"conv_count">>, <<"conv">>, <<"count">>,
                                            sample, <<"COUNT">>, <<>>),
                                      point(<<"conv_sensor">>, <<"conv">>, <<"sensor">>,
                                            event, <<"PRESENCE">>, <<>>)]});
        cell_shdr_test_hal ->
            ok
    end.

%% Reads lines until every pair expected was seen (in any order); returns the lines
%% before the last one and that line.
await_pairs(S, Expected) ->
    Seen = ets:new(seen, [bag]),
    Done = fun(L) ->
                   true = ets:insert(Seen, pairs([L])),
                   lists:all(fun({K, V}) -> ets:match_object(Seen, {K, V}) =/= [] end,
                             Expected)
           end,
    Result = read_until(S, Done, deadline()),
    true = ets:delete(Seen),
    Result.

%% An axis of the cell's spec streams its position, feedrate and state: at rest where it
%% stands, STOPPED; moving, TRAVEL with its position read again while it moves (a move
%% of 2.5 s, read every 100 ms), and where it ends, STOPPED at its target.
axes_streamed(_Config) ->
    S = connect(),
    Snap = snapshot(S),
    case maps:get(<<"gantry_state">>, values(Snap)) of
        <<"STOPPED">> -> ok;
        _ -> _ = read_until(S, fun(L) -> has_pair(L, <<"gantry_state">>, <<"STOPPED">>) end,
                            deadline())
    end,
    ok = axis_done(cell_hal_axis:power(gantry, true)),
    ok = axis_done(cell_hal_axis:home(gantry, 0.0)),
    %% A homing moves too: its TRAVEL and STOPPED are read before the move starts.
    _ = axis_told(S),
    {ok, _} = cell_hal_axis:move_absolute(gantry, 50.0, #{velocity => 20, acceleration => 200,
                                                         deceleration => 200}),
    {Before, Last} = read_until(S, fun(L) -> has_pair(L, <<"gantry_state">>, <<"STOPPED">>) end,
                                deadline()),
    Seen = pairs(Before ++ [Last]),
    ?assert(lists:member({<<"gantry_state">>, <<"TRAVEL">>}, Seen), Seen),
    %% Read while it moved: positions on the way, in order, at a speed above zero.
    Between = [X || {<<"gantry_position">>, P} <- Seen, X <- [num(P)], X > 0.0, X < 50.0],
    ?assertNotEqual([], Between, Seen),
    ?assertEqual(lists:sort(Between), Between),
    ?assertNotEqual([], [F || {<<"gantry_feedrate">>, F} <- Seen, num(F) > 0.0]),
    %% At rest at its target, with nothing after.
    V = values(Before ++ [Last]),
    ?assertEqual([], [P || {<<"gantry_", _/binary>>, _} = P <- pairs(barrier(S))]),
    ?assertEqual({50.0, 0.0, <<"STOPPED">>},
                 {num(maps:get(<<"gantry_position">>, V)), num(maps:get(<<"gantry_feedrate">>, V)),
                  maps:get(<<"gantry_state">>, V)}),
    ok = gen_tcp:close(S).

%% -------------------------------------------------------------------------------------
%% Helpers
%% -------------------------------------------------------------------------------------

deadline() ->
    deadline(?WAIT).

deadline(Ms) ->
    erlang:monotonic_time(millisecond) + Ms.

left(Deadline) ->
    max(0, Deadline - erlang:monotonic_time(millisecond)).

%% A unit (the Zeugwerk lifecycle) is a Path of the controller like any task: its
%% IPC-2541 state reaches the agent as EXECUTION and WAIT_STATE the same way.
a_unit_is_a_path_like_a_task(Config) ->
    Tab = ?config(tab, Config),
    S = connect(),
    V0 = values(snapshot(S)),
    ?assertEqual(<<"STOPPED">>, maps:get(<<"picker_execution">>, V0)),
    ?assertEqual(<<"0">>, maps:get(<<"picker_part_count">>, V0)),
    ok = cell_controller:start(),
    %% GoHome is SETUP: the agent sees the unit powering up.
    await_pair(S, <<"picker_wait_state">>, <<"POWERING_UP">>),
    _ = cell_unit:info(picker),
    go_home = cell_test_seq:complete(Tab, picker),
    %% Automatic: READY-PROCESSING-ACTIVE.
    await_pair(S, <<"picker_execution">>, <<"ACTIVE">>),
    ok = cell_controller:stop(),
    _ = cell_unit:info(picker),
    stop = cell_test_seq:complete(Tab, picker),
    await_pair(S, <<"picker_execution">>, <<"STOPPED">>),
    ok = gen_tcp:close(S).

%% Reads lines until one sets `Key' to `Value'.
await_pair(S, Key, Value) ->
    read_until(S, fun(L) -> lists:member({Key, Value}, pairs([L])) end, deadline()).

%% A port another program holds: the adapter says so and tries again until it is free;
%% a new port in the settings moves the listener, and the old port is let go.
taken_port_waited_for_and_moved(_Config) ->
    ok = cell_log:subscribe(),
    {ok, Holder} = gen_tcp:listen(0, [{ip, {127, 0, 0, 1}}, {reuseaddr, false}]),
    {ok, Taken} = inet:port(Holder),
    ok = application:unset_env(cell_shdr, port),
    put_settings(#{port => Taken, bind => <<"127.0.0.1">>}),
    Busy = iolist_to_binary(io_lib:format("cannot listen on 127.0.0.1:~p (address already "
                                          "in use); trying again in 1 s", [Taken])),
    ?assert(await_log(Busy, deadline())),
    ?assertEqual(undefined, cell_shdr:port()),
    %% The cell is not disturbed meanwhile.
    ?assertEqual(ok, cell_controller:sync()),
    ok = gen_tcp:close(Holder),
    Listening = iolist_to_binary(io_lib:format("listening on 127.0.0.1:~p", [Taken])),
    ?assert(await_log(Listening, deadline())),
    ?assertEqual(Taken, cell_shdr:port()),
    S1 = connect(),
    ?assertMatch([<<"* shdrVersion: 2">> | _], snapshot(S1)),
    %% Moved: its clients are closed and reconnect to the new port.
    {ok, Free} = gen_tcp:listen(0, [{ip, {127, 0, 0, 1}}]),
    {ok, Other} = inet:port(Free),
    ok = gen_tcp:close(Free),
    put_settings(#{port => Other}),
    ?assertEqual(Other, cell_shdr:port()),
    ?assertEqual({error, closed}, gen_tcp:recv(S1, 0, 5000)),
    ?assertEqual({error, econnrefused},
                 gen_tcp:connect({127, 0, 0, 1}, Taken, [binary, {active, false}])),
    S2 = connect(),
    ?assertMatch([<<"* shdrVersion: 2">> | _], snapshot(S2)),
    ok = gen_tcp:close(S2).

connect() ->
    connect([]).

%% A client reading lines, with more socket options (a small receive buffer, say).
connect(Opts) ->
    Port = cell_shdr:port(),
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false},
                                                      {packet, line}, {buffer, 1 bsl 20}
                                                      | Opts]),
    S.

%% After the adapter restarted (its clients were closed while its supervisor was
%% restarting it): the supervisor answers once it is done, the listener once it
%% listens.
reconnect() ->
    _ = sys:get_state(cell_shdr_sup),
    _ = sys:get_state(cell_shdr_listener),
    connect().

cmd(Config, Task, Command) ->
    cell_test_task:command(Task, maps:get(Task, ?config(refs, Config)), Command).

put_settings(Changes) ->
    ok = cell_settings:put(shdr, Changes, <<"suite">>),
    ok = cell_shdr_cache:sync(),
    _ = sys:get_state(cell_shdr_sampler),
    _ = sys:get_state(cell_shdr_listener),
    ok.

point(Name, Group, Point, Category, Type, Units) ->
    #{name => Name, group => Group, point => Point, category => Category, type => Type,
      units => Units}.

%% Every line up to the PONG of a PING sent now: the snapshot, when sent first.
snapshot(S) ->
    ok = gen_tcp:send(S, <<"* PING\n">>),
    {Lines, _} = read_until(S, fun(L) -> binary:match(L, <<"* PONG">>) =:= {0, 6} end,
                            deadline()),
    Lines.

%% Every line sent so far, once the cell and the cache have handled what came before.
barrier(S) ->
    ok = cell_controller:sync(),
    ok = cell_alarms:sync(),
    ok = cell_shdr_cache:sync(),
    snapshot(S).

read_until(S, Done, Deadline) ->
    read_until(S, Done, Deadline, []).

%% Whether a line sets item `Key' to `Value'.
has_pair(Line, Key, Value) ->
    lists:member({Key, Value}, pairs([Line])).

%% A sample's number as the adapter writes it.
num(B) ->
    try binary_to_float(B)
    catch error:badarg -> float(binary_to_integer(B))
    end.

%% The lines sent up to the gantry's last job's end. The axis tells its watchers after
%% its owner (its status asked has seen it tell them), and the adapter then reads the
%% axis and hands the cache what it read.
axis_told(S) ->
    {ok, _} = cell_hal_axis:status(gantry),
    _ = sys:get_state(cell_shdr_axes),
    barrier(S).

%% An axis's command accepted and its job done.
axis_done({ok, Ref}) ->
    receive {Ref, done} -> ok; {Ref, Other} -> ct:fail({axis_job, Other})
    after ?WAIT -> ct:fail(axis_job_not_done)
    end;
axis_done(Refused) ->
    ct:fail({axis_refused, Refused}).

read_until(S, Done, Deadline, Acc) ->
    case gen_tcp:recv(S, 0, left(Deadline)) of
        {ok, Line0} ->
            Line = string:trim(Line0, trailing, "\r\n"),
            case Done(Line) of
                true -> {lists:reverse(Acc), Line};
                false -> read_until(S, Done, Deadline, [Line | Acc])
            end;
        {error, Why} ->
            ct:fail("no line matched before ~p; got ~p lines: ~p", [Why, length(Acc),
                                                                  lists:reverse(Acc)])
    end.

%% Reads until the server closes the connection.
drain(S, Deadline) ->
    case gen_tcp:recv(S, 0, left(Deadline)) of
        {ok, _} -> drain(S, Deadline);
        {error, closed} -> {error, closed};
        {error, timeout} -> {error, timeout}
    end.

read_series(S, Key, N, Deadline) ->
    read_series(S, Key, N, Deadline, []).

read_series(_S, _Key, 0, _Deadline, Acc) ->
    lists:reverse(Acc);
read_series(S, Key, N, Deadline, Acc) ->
    {_, Line} = read_until(S, fun(L) -> case split(L) of
                                            {_, [Key, _, _, _]} -> true;
                                            _ -> false
                                        end
                              end, Deadline),
    read_series(S, Key, N - 1, Deadline, [split(Line) | Acc]).

split(Line) ->
    [Ts | Fields] = tokens(Line),
    case Ts of
        <<"* ", _/binary>> -> {<<"*">>, Fields};
        _ -> {Ts, Fields}
    end.

strip_ts(Line) ->
    case binary:split(Line, <<"|">>) of
        [_, Rest] -> Rest;
        [Only] -> Only
    end.

ends_with(L, Suffix) ->
    byte_size(L) >= byte_size(Suffix) andalso
        binary:part(L, byte_size(L) - byte_size(Suffix), byte_size(Suffix)) =:= Suffix.

%% Fields as an agent reads them: a field in double quotes runs to its closing quote,
%% `\' taking the next character as it is.
tokens(Line) ->
    tokens(Line, <<>>, []).

tokens(<<>>, Field, Acc) ->
    lists:reverse([Field | Acc]);
tokens(<<$|, Rest/binary>>, Field, Acc) ->
    tokens(Rest, <<>>, [Field | Acc]);
tokens(<<$", Rest/binary>>, <<>>, Acc) ->
    {Field, After} = quoted(Rest, <<>>),
    tokens(After, Field, Acc);
tokens(<<C, Rest/binary>>, Field, Acc) ->
    tokens(Rest, <<Field/binary, C>>, Acc).

quoted(<<$\\, C, Rest/binary>>, F) -> quoted(Rest, <<F/binary, C>>);
quoted(<<$", Rest/binary>>, F) -> {F, Rest};
quoted(<<C, Rest/binary>>, F) -> quoted(Rest, <<F/binary, C>>).

has(L, Part) ->
    binary:match(L, Part) =/= nomatch.

is_condition(Key) ->
    Key =:= <<"system">> orelse ends_with(Key, <<"_system">>).

%% The plain {Key, Value} pairs of data lines, in order.
pairs(Lines) ->
    lists:append([kv(Fields) || L <- Lines, {Ts, [K | _] = Fields} <- [split(L)],
                                Ts =/= <<"*">>, not is_condition(K),
                                binary:first(K) =/= $@, K =/= <<"current">>]).

kv([K, V | Rest]) -> [{K, V} | kv(Rest)];
kv([]) -> [].

values(Lines) ->
    maps:from_list(pairs(Lines)).

conditions(Lines) ->
    [{Ts, Fields} || L <- Lines, {Ts, [K | _] = Fields} <- [split(L)], Ts =/= <<"*">>,
                     is_condition(K)].

%% The documents of an asset's @ASSET@ lines (multiline ones joined).
assets(Lines, Id) ->
    assets(Lines, Id, []).

assets([], _Id, Acc) ->
    lists:reverse(Acc);
assets([L | Rest], Id, Acc) ->
    case binary:split(strip_ts(L), <<"|">>, [global]) of
        [<<"@ASSET@">>, Id, <<"File">>, <<"--multiline--", _/binary>> = Tag] ->
            {Body, [Tag | After]} = lists:splitwith(fun(X) -> X =/= Tag end, Rest),
            assets(After, Id, [iolist_to_binary(lists:join($\n, Body)) | Acc]);
        [<<"@ASSET@">>, Id, <<"File">>, Doc] ->
            assets(Rest, Id, [Doc | Acc]);
        _ ->
            assets(Rest, Id, Acc)
    end.

%% No key carries the same value twice in a row.
no_repeats(Pairs) ->
    lists:foldl(fun({K, V}, Last) ->
                        ?assertNotEqual({ok, V}, maps:find(K, Last), K),
                        Last#{K => V}
                end, #{}, Pairs),
    ok.

await_down(_Refs, 0, _Deadline) ->
    [];
await_down(Refs, N, Deadline) ->
    receive
        {'DOWN', Ref, process, _, _} ->
            case lists:member(Ref, Refs) of
                true -> [Ref | await_down(Refs -- [Ref], N - 1, Deadline)];
                false -> await_down(Refs, N, Deadline)
            end
    after left(Deadline) ->
        []
    end.

await_log(Text, Deadline) ->
    receive
        {cell_log, #{text := T}} ->
            case binary:match(T, Text) of
                nomatch -> await_log(Text, Deadline);
                _ -> true
            end
    after left(Deadline) ->
        false
    end.

%% Validates a document against an MTConnect schema with xmllint: the schemas shipped in
%% the suite's data folder (mtconnect/, see its README.md), or those of MTCONNECT_XSD_DIR
%% when it is set. A missing xmllint or schema fails the case: the check never passes
%% unchecked.
schema_check(Xsd, Xml, Config) ->
    XsdDir = case os:getenv("MTCONNECT_XSD_DIR") of
                 false -> filename:join(?config(data_dir, Config), "mtconnect");
                 Dir -> Dir
             end,
    Schema = filename:join(XsdDir, Xsd),
    case {os:find_executable("xmllint"), filelib:is_regular(Schema)} of
        {false, _} -> ct:fail("xmllint is missing: scripts/setup test installs libxml2-utils");
        {_, false} -> ct:fail("MTConnect schema ~s is missing", [Schema]);
        {Lint, true} ->
            N = integer_to_list(erlang:unique_integer([positive])),
            File = filename:join(?config(priv_dir, Config), "schema-check-" ++ N ++ ".xml"),
            ok = file:write_file(File, Xml),
            Out = os:cmd(Lint ++ " --nonet --noout --schema " ++ Schema ++ " " ++ File
                         ++ " 2>&1"),
            ?assertNotEqual(nomatch, string:find(Out, File ++ " validates"), Out)
    end.

%% An asset document as the agent's assets response carries it, so the schema can
%% check it.
assets_document(Doc) ->
    [<<"<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n"
       "<MTConnectAssets xmlns=\"urn:mtconnect.org:MTConnectAssets:2.0\">\n"
       "  <Header creationTime=\"2026-01-01T00:00:00Z\" sender=\"suite\" instanceId=\"1\" "
       "version=\"2.0\" assetBufferSize=\"1024\" assetCount=\"1\" "
       "deviceModelChangeTime=\"2026-01-01T00:00:00Z\"/>\n  <Assets>\n">>,
     Doc, <<"\n  </Assets>\n</MTConnectAssets>\n">>].

%% The data items of a Devices.xml by name (the agent finds an item of the device by
%% it), each with the fields an agent reads after its key: condition, message,
%% time_series, sample or event.
declared(File) ->
    {Doc, _} = xmerl_scan:file(File),
    maps:from_list(
      [{list_to_binary(attr(E, name)),
        case {attr(E, category), attr(E, type),
              [V || #xmlAttribute{value = V} <- xmerl_xpath:string("@representation", E)]} of
            {"CONDITION", _, _} -> condition;
            {_, "MESSAGE", _} -> message;
            {_, _, ["TIME_SERIES"]} -> time_series;
            {"SAMPLE", _, _} -> sample;
            {"EVENT", _, _} -> event
        end} || E <- xmerl_xpath:string("//DataItem", Doc)]).

%% Lines as the reference agent reads them with SHDR version 2: protocol lines aside,
%% any line holding --multiline-- starts an asset joined up to its end tag (heartbeats
%% left out); then after the timestamp each key takes the fields of its kind: a
%% condition five (level, native code, native severity, qualifier, text), a message two
%% (native code, text), a time series three (count, rate, values), @ASSET@ three,
%% @REMOVE_ASSET@ one, @REMOVE_ALL_ASSETS@ one (its type), anything else one. A key
%% that is no declared item fails the case.
agent_read(Lines, Declared) ->
    agent_read(Lines, Declared, []).

agent_read([], _Declared, Acc) ->
    lists:append(lists:reverse(Acc));
agent_read([<<"*", _/binary>> | Rest], Declared, Acc) ->
    agent_read(Rest, Declared, Acc);
agent_read([Line | Rest], Declared, Acc) ->
    case binary:match(Line, <<"--multiline--">>) of
        nomatch ->
            agent_read(Rest, Declared, [agent_fields(agent_tokens(Line), Declared) | Acc]);
        {Pos, _} ->
            Tag = binary:part(Line, Pos, byte_size(Line) - Pos),
            {Body, [Tag | After]} = lists:splitwith(fun(L) -> L =/= Tag end, Rest),
            Joined = iolist_to_binary(lists:join($\n, [binary:part(Line, 0, Pos)
                                                       | [L || L <- Body, not pong(L)]])),
            agent_read(After, Declared, [agent_fields(agent_tokens(Joined), Declared) | Acc])
    end.

%% The agent takes a line starting `* PONG' for a heartbeat wherever it comes.
pong(Line) ->
    binary:longest_common_prefix([Line, <<"* PONG">>]) =:= 6.

%% The fields after the timestamp, blanks and line breaks at both ends dropped as the
%% agent drops them.
agent_tokens(Line) ->
    [string:trim(F) || F <- tl(tokens(Line))].

agent_fields([], _Declared) ->
    [];
agent_fields([<<"@", _/binary>> = Command | Rest], Declared) ->
    N = case Command of
            <<"@ASSET@">> -> 3;
            <<"@REMOVE_ASSET@">> -> 1;
            <<"@REMOVE_ALL_ASSETS@">> -> min(1, length(Rest))
        end,
    take(Command, N, Rest, Declared);
agent_fields([Key | Rest], Declared) ->
    N = case Declared of
            #{Key := condition} -> 5;
            #{Key := message} -> 2;
            #{Key := time_series} -> 3;
            #{Key := _} -> 1;
            _ -> ct:fail("the agent finds no data item ~ts (declared: ~p)",
                         [Key, lists:sort(maps:keys(Declared))])
        end,
    take(Key, N, Rest, Declared).

take(Key, N, Fields, Declared) when length(Fields) >= N ->
    {Mine, Rest} = lists:split(N, Fields),
    [{Key, Mine} | agent_fields(Rest, Declared)];
take(Key, N, Fields, _Declared) ->
    ct:fail("~ts has ~p fields where the agent reads ~p: ~p", [Key, length(Fields), N, Fields]).

%% Lines up to and with the next time series line of an item.
read_until_series(S, Key) ->
    {Before, Line} = read_until(S, fun(L) -> case split(L) of
                                                 {_, [Key | _]} -> true;
                                                 _ -> false
                                             end
                                   end, deadline()),
    Before ++ [Line].

attr(E, Name) ->
    [#xmlAttribute{value = V}] = xmerl_xpath:string("@" ++ atom_to_list(Name), E),
    V.

%% An attribute an element may lack.
attr_or(E, Name) ->
    case xmerl_xpath:string("@" ++ atom_to_list(Name), E) of
        [#xmlAttribute{value = V}] -> V;
        [] -> undefined
    end.

stats(Samples) ->
    Sorted = lists:sort(Samples),
    #{median => lists:nth(max(1, length(Sorted) div 2), Sorted)}.
