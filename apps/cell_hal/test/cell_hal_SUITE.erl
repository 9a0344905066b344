%% The HAL end to end against the simulated PLC: configuration checked at the door,
%% reads without a process hop, writes in order, watches and subscriptions, the
%% connectivity a task goes DOWN on, a stale input never presented as fresh, and
%% recovery from crashes of the HAL's own processes.
-module(cell_hal_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([configuration_is_checked_at_the_door/1, every_type_reads_and_writes/1,
         reads_before_the_first_poll/1, subscribers_see_every_change/1,
         watches_fire_once/1, watches_fire_once_under_load/1, watch_conditions_are_checked/1,
         sensor_follows_output/1,
         link_down_and_back/1, silent_device_goes_down/1, stale_inputs_never_fresh/1,
         watch_placed_while_down_fires_after_reconnect/1, outputs_read_back_after_reconnect/1,
         writes_keep_their_order/1, write_sync_waits_for_the_device/1,
         group_added_while_up/1, groups_added_back_to_back/1,
         group_added_during_the_first_read/1, inputs_read_once_a_group_is_added/1,
         inputs_of_a_group_added_during_the_first_read/1, remove_group_and_connection/1,
         subscribers_are_cleaned_up/1, worker_crash_goes_down_and_recovers/1,
         server_crash_keeps_configuration/1, io_while_the_server_restarts/1,
         io_while_a_worker_restarts/1, killed_worker_reads_down_until_replaced/1,
         logs_speak_to_operators/1,
         backoff_grows_then_resets/1, connection_info/1,
         device_killed_comes_back_with_its_memory/1, told_when_the_server_is_back/1, initial_image/1,
         dropped_connection_takes_nothing/1]).

-define(WAIT, 5000).

all() ->
    [configuration_is_checked_at_the_door, every_type_reads_and_writes,
     reads_before_the_first_poll, subscribers_see_every_change, watches_fire_once,
     watches_fire_once_under_load,
     watch_conditions_are_checked, sensor_follows_output, link_down_and_back,
     silent_device_goes_down, stale_inputs_never_fresh,
     watch_placed_while_down_fires_after_reconnect, outputs_read_back_after_reconnect,
     writes_keep_their_order, write_sync_waits_for_the_device, group_added_while_up,
     groups_added_back_to_back, group_added_during_the_first_read,
     inputs_read_once_a_group_is_added, inputs_of_a_group_added_during_the_first_read,
     remove_group_and_connection, subscribers_are_cleaned_up,
     worker_crash_goes_down_and_recovers, server_crash_keeps_configuration,
     io_while_the_server_restarts, io_while_a_worker_restarts,
     killed_worker_reads_down_until_replaced, logs_speak_to_operators,
     backoff_grows_then_resets, connection_info, device_killed_comes_back_with_its_memory,
     told_when_the_server_is_back, initial_image, dropped_connection_takes_nothing].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

%% The cases that kill the HAL's server start on a HAL of their own: its supervisor
%% allows a few restarts a minute, and what earlier cases spent of them is not theirs
%% to count on.
init_per_testcase(Case, Config) when Case =:= server_crash_keeps_configuration;
                                     Case =:= io_while_the_server_restarts;
                                     Case =:= told_when_the_server_is_back ->
    ok = application:stop(cell_hal),
    ok = application:start(cell_hal),
    Config;
init_per_testcase(_Case, Config) ->
    Config.

end_per_testcase(_Case, _Config) ->
    %% A case that failed half-way may have left the HAL held.
    _ = [catch sys:resume(P) || P <- [cell_hal_sup, cell_hal_conn_sup]],
    [ok = cell_hal:remove_group(G) || G <- cell_hal:groups()],
    [begin ok = cell_hal:remove_connection(C), ok = cell_hal_sim_sup:stop_device(C) end
     || C <- cell_hal:connections()],
    ok.

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

%% A simulated PLC `Conn' with the test group `io' bound to it, up.
sim(Conn) -> sim(Conn, #{}).

sim(Conn, Opts) ->
    ok = cell_hal:add_connection(#{id => Conn, driver => cell_hal_sim,
                                   opts => maps:merge(#{poll_ms => 10, reconnect_ms => 50,
                                                        timeout_ms => 500}, Opts)}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => Conn}),
    {ok, _} = cell_hal:subscribe_connection(Conn),
    ok = await_status(Conn, up),
    %% The connection may have come up before the group was bound: wait for its first
    %% read (a fresh simulated PLC holds zeros).
    0 = await_value(int16_in, 0),
    ok.

await_status(Conn, Status) ->
    case cell_hal:status(Conn) of
        Status -> flush_conn(Conn), ok;
        _ -> receive {cell_hal_conn, Conn, Status} -> ok
             after ?WAIT -> ct:fail({not_reached, Conn, Status, cell_hal:info(Conn)})
             end
    end.

flush_conn(Conn) ->
    receive {cell_hal_conn, Conn, _} -> flush_conn(Conn) after 0 -> ok end.

%% Waits until a point reads a value (through a watch: no polling).
await_value(Point, V) ->
    {ok, Ref} = cell_hal:watch(io, Point, {eq, V}),
    receive {cell_hal_watch, Ref, Got} -> Got
    after ?WAIT -> ct:fail({never, Point, V, cell_hal:read(io, Point)})
    end.

await_msg(Match) ->
    receive Msg -> case Match(Msg) of true -> Msg; false -> await_msg(Match) end
    after ?WAIT -> ct:fail(no_message)
    end.

%%--------------------------------------------------------------------
%% Cases
%%--------------------------------------------------------------------

configuration_is_checked_at_the_door(_Config) ->
    Bad = fun(Spec) -> cell_hal:add_connection(Spec) end,
    ?assertEqual({error, {bad_option, driver}}, Bad(#{id => c})),
    ?assertEqual({error, {bad_option, id}}, Bad(#{id => "c", driver => cell_hal_sim})),
    ?assertEqual({error, {bad_option, driver}}, Bad(#{id => c, driver => no_such_module})),
    ?assertEqual({error, {bad_option, driver}}, Bad(#{id => c, driver => lists})),
    ?assertEqual({error, {bad_option, colour}}, Bad(#{id => c, driver => cell_hal_sim, colour => red})),
    ?assertEqual({error, {bad_option, poll_ms}},
                 Bad(#{id => c, driver => cell_hal_sim, opts => #{poll_ms => 0}})),
    ?assertEqual({error, {bad_option, max_reconnect_ms}},
                 Bad(#{id => c, driver => cell_hal_sim,
                       opts => #{reconnect_ms => 1000, max_reconnect_ms => 10}})),
    ?assertEqual({error, {bad_option, latency_ms}},
                 Bad(#{id => c, driver => cell_hal_sim, opts => #{latency_ms => -1}})),
    ?assertEqual({error, {bad_option, host}},
                 Bad(#{id => c, driver => cell_hal_modbus, opts => #{}})),
    ?assertEqual({error, {bad_option, spec}}, Bad(not_a_map)),
    ok = Bad(#{id => c, driver => cell_hal_sim}),
    ?assertEqual({error, {already_exists, c}}, Bad(#{id => c, driver => cell_hal_sim})),
    Group = fun(Spec) -> cell_hal:add_group(Spec) end,
    ?assertEqual({error, {bad_option, connection}},
                 Group(#{id => g, module => cell_hal_test_io, connection => nowhere})),
    ?assertEqual({error, {bad_option, module}},
                 Group(#{id => g, module => lists, connection => c})),
    ?assertEqual({error, {bad_option, opts}},
                 Group(#{id => g, module => cell_hal_test_io, connection => c, opts => []})),
    ?assertMatch({error, {bad_group, _}},
                 Group(#{id => g, module => cell_hal_test_io, connection => c,
                         opts => #{base => not_a_number}})),
    ok = cell_hal:add_connection(#{id => m, driver => cell_hal_modbus,
                                   opts => #{host => "127.0.0.1", port => 1}}),
    ?assertEqual({error, {bad_point, decimal_in, {field, address_out_of_range}}},
                 Group(#{id => g, module => cell_hal_test_io, connection => m,
                         opts => #{base => 65500}})),
    ok = Group(#{id => g, module => cell_hal_test_io, connection => c}),
    ?assertEqual({error, {already_exists, g}},
                 Group(#{id => g, module => cell_hal_test_io, connection => c})),
    ?assertEqual({error, {in_use, [g]}}, cell_hal:remove_connection(c)),
    ?assertEqual({ok, c}, cell_hal:connection_of(g)),
    ?assertEqual({error, unknown_group}, cell_hal:connection_of(nope)),
    ?assertEqual({error, unknown_connection}, cell_hal:remove_connection(nope)),
    ?assertEqual({error, unknown_group}, cell_hal:remove_group(nope)).

every_type_reads_and_writes(_Config) ->
    ok = sim(s1),
    lists:foreach(
      fun({T, _, _}) ->
              Name = atom_to_list(name(T)),
              In = list_to_atom(Name ++ "_in"),
              Out = list_to_atom(Name ++ "_out"),
              [begin
                   V = cell_hal_test_io:sample(T, N),
                   ok = cell_hal_sim:set({io, In}, V),
                   ?assertEqual(V, await_value(In, V)),
                   ?assertEqual({ok, V}, cell_hal:read(io, In)),
                   ok = cell_hal:write_sync(io, Out, V, ?WAIT),
                   ?assertEqual({ok, V}, cell_hal:read(io, Out)),
                   ?assertEqual({ok, V}, cell_hal_sim:get({io, Out}))
               end || N <- [1, 2]]
      end, cell_hal_test_io:types()),
    %% A REAL is stored as the PLC holds it: single precision.
    ok = cell_hal:write_sync(io, real_out, 0.1, ?WAIT),
    {ok, R} = cell_hal:read(io, real_out),
    ?assertEqual(<<R:32/float>>, <<0.1:32/float>>),
    ?assertEqual({error, {bad_value, 256}}, cell_hal:write(io, byte_out, 256)),
    ?assertEqual({error, {bad_value, <<"ABCDEFGHIJK">>}},
                 cell_hal:write(io, string10_out, <<"ABCDEFGHIJK">>)),
    ?assertEqual({error, not_an_output}, cell_hal:write(io, int16_in, 1)),
    ?assertEqual({error, unknown_point}, cell_hal:write(io, nope, 1)),
    ?assertEqual({error, unknown_point}, cell_hal:read(io, nope)),
    ?assertEqual({error, unknown_point}, cell_hal:read(nope, int16_in)).

name({string, N}) -> list_to_atom("string" ++ integer_to_list(N));
name(T) -> T.

reads_before_the_first_poll(_Config) ->
    %% A slow PLC: every answer takes 300 ms.
    ok = cell_hal:add_connection(#{id => s2, driver => cell_hal_sim,
                                   opts => #{latency_ms => 300, poll_ms => 10}}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => s2,
                              opts => #{only => [int16_in]}}),
    %% Until the first read of the group is answered its input has no value: the
    %% connection is down (its first read is on its way), or up from before the group
    %% was bound (nothing to read then) and the point not read yet.
    case cell_hal:read(io, int16_in) of
        {error, disconnected} -> ok;
        {error, not_yet_read} -> ok
    end,
    {ok, Ref} = cell_hal:watch(io, int16_in, {eq, 0}),
    receive {cell_hal_watch, Ref, 0} -> ok after ?WAIT -> ct:fail(never_read) end,
    ?assertEqual(up, cell_hal:status(s2)),
    ?assertEqual({ok, 0}, cell_hal:read(io, int16_in)),
    %% A group added while up is read before add_group returns, however slow the PLC.
    ok = cell_hal:add_group(#{id => io2, module => cell_hal_test_io, connection => s2,
                              opts => #{only => [int16_in]}}),
    ?assertEqual({ok, 0}, cell_hal:read(io2, int16_in)).

subscribers_see_every_change(_Config) ->
    ok = sim(s3),
    ok = cell_hal:subscribe(io, int16_in),
    ?assertEqual({error, unknown_point}, cell_hal:subscribe(io, nope)),
    [begin
         ok = cell_hal_sim:set({io, int16_in}, V),
         receive {cell_hal, {io, int16_in}, V} -> ok after ?WAIT -> ct:fail({missed, V}) end
     end || V <- [1, 2, 3, -4]],
    %% Setting the same value again is no change: nothing is published.
    ok = cell_hal_sim:set({io, int16_in}, -4),
    ok = cell_hal_sim:set({io, uint16_in}, 9),
    9 = await_value(uint16_in, 9),
    receive {cell_hal, {io, int16_in}, X} -> ct:fail({republished, X}) after 0 -> ok end,
    %% An output's subscribers see each commanded value.
    ok = cell_hal:subscribe(io, int16_out),
    ok = cell_hal:write(io, int16_out, 7),
    receive {cell_hal, {io, int16_out}, 7} -> ok after ?WAIT -> ct:fail(no_output_change) end,
    ok = cell_hal:unsubscribe(io, int16_in),
    ok = cell_hal_sim:set({io, int16_in}, 5),
    5 = await_value(int16_in, 5),
    receive {cell_hal, {io, int16_in}, _} = M -> ct:fail({after_unsubscribe, M}) after 0 -> ok end.

watches_fire_once(_Config) ->
    ok = sim(s4),
    %% Already true: fires at once.
    {ok, R1} = cell_hal:watch(io, int16_in, {eq, 0}),
    receive {cell_hal_watch, R1, 0} -> ok after ?WAIT -> ct:fail(not_at_once) end,
    %% Fires when the value gets there, once, even if it passes again.
    {ok, R2} = cell_hal:watch(io, int16_in, {gt, 10}),
    ok = cell_hal_sim:set({io, int16_in}, 5),
    5 = await_value(int16_in, 5),
    receive {cell_hal_watch, R2, _} -> ct:fail(too_early) after 0 -> ok end,
    ok = cell_hal_sim:set({io, int16_in}, 11),
    receive {cell_hal_watch, R2, 11} -> ok after ?WAIT -> ct:fail(never_fired) end,
    ok = cell_hal_sim:set({io, int16_in}, 12),
    12 = await_value(int16_in, 12),
    ok = cell_hal_sim:set({io, int16_in}, 13),
    13 = await_value(int16_in, 13),
    receive {cell_hal_watch, R2, _} -> ct:fail(fired_twice) after 0 -> ok end,
    %% A cancelled watch never fires; cancelling a fired one says so.
    {ok, R3} = cell_hal:watch(io, int16_in, {lt, 0}),
    ?assert(cell_hal:cancel_watch(R3)),
    ok = cell_hal_sim:set({io, int16_in}, -1),
    -1 = await_value(int16_in, -1),
    receive {cell_hal_watch, R3, _} -> ct:fail(cancelled_fired) after 0 -> ok end,
    ?assertNot(cell_hal:cancel_watch(R2)),
    %% Every operator.
    [begin
         {ok, R} = cell_hal:watch(io, int16_in, Cond),
         receive {cell_hal_watch, R, -1} -> ok after ?WAIT -> ct:fail({cond_missed, Cond}) end
     end || Cond <- [{eq, -1}, {ne, 0}, {lt, 0}, {le, -1}, {ge, -1}, {gt, -2}]],
    %% Many watchers on one point each get their message.
    Refs = [element(2, cell_hal:watch(io, int16_in, {eq, 100})) || _ <- lists:seq(1, 50)],
    ok = cell_hal_sim:set({io, int16_in}, 100),
    [receive {cell_hal_watch, R, 100} -> ok after ?WAIT -> ct:fail(lost_watcher) end || R <- Refs].

%% An input that never stops changing (a counter the simulated PLC counts up every
%% millisecond), many processes placing watches on it all the while: the worker
%% publishing and the server placing a watch race for each one, and every watch still
%% fires exactly once.
watches_fire_once_under_load(_Config) ->
    ok = sim(s23, #{poll_ms => 1}),
    ok = cell_hal_sim:on_change({io, int32_in}, fun(V) -> [{1, {io, int32_in}, V + 1}] end),
    ok = cell_hal_sim:set({io, int32_in}, 1),
    {ok, First} = cell_hal:watch(io, int32_in, {ge, 1}),
    receive {cell_hal_watch, First, _} -> ok after ?WAIT -> ct:fail(not_counting) end,
    Self = self(),
    Watchers = [spawn_link(fun() -> Self ! {done, self(), watch_many(100, [])} end)
                || _ <- lists:seq(1, 20)],
    Refs = lists:append([receive {done, W, Rs} -> Rs after ?WAIT * 6 -> ct:fail(stuck) end
                         || W <- Watchers]),
    ?assertEqual(2000, length(Refs)),
    ok = cell_hal_sim:clear_rules(s23),
    ?assertEqual(0, ets:info(cell_hal_watch_claims, size)).

%% Places watches for "more than now" one after the other, each waited for; then makes
%% sure none of them came twice.
watch_many(0, Refs) ->
    Dups = [R || R <- Refs, receive {cell_hal_watch, R, _} -> true after 0 -> false end],
    [] = Dups,
    Refs;
watch_many(N, Refs) ->
    {ok, Now} = cell_hal:read(io, int32_in),
    {ok, Ref} = cell_hal:watch(io, int32_in, {gt, Now}),
    receive {cell_hal_watch, Ref, V} when V > Now -> ok
    after ?WAIT -> exit({never_fired, Now, cell_hal:read(io, int32_in)})
    end,
    false = cell_hal:cancel_watch(Ref),
    watch_many(N - 1, [Ref | Refs]).

watch_conditions_are_checked(_Config) ->
    ok = sim(s5),
    ?assertEqual({error, {bad_condition, {gt, true}}}, cell_hal:watch(io, bool_in, {gt, true})),
    ?assertEqual({error, {bad_condition, {eq, 1}}}, cell_hal:watch(io, bool_in, {eq, 1})),
    ?assertEqual({error, {bad_condition, {eq, <<"too long a string">>}}},
                 cell_hal:watch(io, string10_in, {eq, <<"too long a string">>})),
    ?assertEqual({error, {bad_condition, {eq, 70000}}}, cell_hal:watch(io, int16_in, {eq, 70000})),
    ?assertEqual({error, {bad_condition, maybe}}, cell_hal:watch(io, int16_in, maybe)),
    ?assertEqual({error, unknown_point}, cell_hal:watch(io, nope, {eq, 1})),
    {ok, R} = cell_hal:watch(io, real_in, {lt, 2.5}),
    receive {cell_hal_watch, R, 0.0} -> ok after ?WAIT -> ct:fail(real_cond) end.

sensor_follows_output(_Config) ->
    ok = sim(s6),
    ok = cell_hal_sim:follow({io, bool_in}, {io, bool_out}, 150),
    ok = cell_hal_sim:follow({io, int16_in}, {io, int16_out}, 0, fun(V) -> -V end),
    {ok, Ref} = cell_hal:watch(io, bool_in, {eq, true}),
    T0 = erlang:monotonic_time(millisecond),
    ok = cell_hal:write(io, bool_out, true),
    receive {cell_hal_watch, Ref, true} -> ok after ?WAIT -> ct:fail(never_followed) end,
    Elapsed = erlang:monotonic_time(millisecond) - T0,
    ct:log("the sensor followed after ~b ms", [Elapsed]),
    ?assert(Elapsed >= 150),
    ok = cell_hal:write(io, int16_out, 42),
    -42 = await_value(int16_in, -42),
    %% A faulty rule is reported and the simulated PLC goes on.
    ok = cell_hal_sim:on_change({io, uint16_out}, fun(_) -> error(broken_rule) end),
    ok = cell_hal:write_sync(io, uint16_out, 3, ?WAIT),
    ok = cell_hal:write(io, int16_out, 43),
    -43 = await_value(int16_in, -43).

link_down_and_back(_Config) ->
    ok = sim(s7),
    ok = cell_hal_sim:set({io, int16_in}, 5),
    5 = await_value(int16_in, 5),
    ok = cell_hal_sim:link(s7, down),
    receive {cell_hal_conn, s7, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    ?assertEqual({error, disconnected}, cell_hal:read(io, int16_in)),
    ?assertEqual({error, disconnected}, cell_hal:write(io, int16_out, 1)),
    ?assertEqual({error, disconnected}, cell_hal:write_sync(io, int16_out, 1, 1000)),
    %% Outputs keep reading their commanded value.
    ?assertEqual({ok, 0}, cell_hal:read(io, int16_out)),
    ok = cell_hal_sim:link(s7, up),
    receive {cell_hal_conn, s7, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    ?assertEqual({ok, 5}, cell_hal:read(io, int16_in)),
    ok = cell_hal:write_sync(io, int16_out, 2, ?WAIT),
    %% A momentary drop: down, then up again by itself.
    ok = cell_hal_sim:drop(s7),
    receive {cell_hal_conn, s7, down} -> ok after ?WAIT -> ct:fail(no_down_on_drop) end,
    receive {cell_hal_conn, s7, up} -> ok after ?WAIT -> ct:fail(no_up_after_drop) end.

silent_device_goes_down(_Config) ->
    ok = sim(s8, #{timeout_ms => 200}),
    ok = cell_hal_sim:link(s8, silent),
    T0 = erlang:monotonic_time(millisecond),
    receive {cell_hal_conn, s8, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    Elapsed = erlang:monotonic_time(millisecond) - T0,
    ct:log("down after ~b ms", [Elapsed]),
    ?assert(Elapsed >= 150),
    {ok, #{reason := Reason}} = cell_hal:info(s8),
    ct:log("reason: ~s", [Reason]),
    ?assertNotEqual(nomatch, binary:match(Reason, <<"no answer within 200 ms">>)),
    %% While silent it stays down (the first read never completes).
    ?assertEqual({error, disconnected}, cell_hal:read(io, int16_in)),
    ok = cell_hal_sim:link(s8, up),
    receive {cell_hal_conn, s8, up} -> ok after ?WAIT -> ct:fail(no_up) end.

%% While the link is down the image changes; nothing of the old image is presented
%% after the link is back, and nothing at all while it is down.
stale_inputs_never_fresh(_Config) ->
    ok = sim(s9),
    ok = cell_hal_sim:set({io, int32_in}, 1),
    1 = await_value(int32_in, 1),
    ok = cell_hal:subscribe(io, int32_in),
    ok = cell_hal_sim:link(s9, down),
    receive {cell_hal_conn, s9, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    ok = cell_hal_sim:set({io, int32_in}, 2),
    ok = cell_hal_sim:link(s9, up),
    %% The new value is stored before the connection is up: whoever hears `up' reads it.
    receive {cell_hal_conn, s9, up} -> ?assertEqual({ok, 2}, cell_hal:read(io, int32_in))
    after ?WAIT -> ct:fail(no_up)
    end,
    receive {cell_hal, {io, int32_in}, V} -> ?assertEqual(2, V) after ?WAIT -> ct:fail(no_change) end.

watch_placed_while_down_fires_after_reconnect(_Config) ->
    ok = sim(s10),
    ok = cell_hal_sim:set({io, bool_in}, true),
    true = await_value(bool_in, true),
    ok = cell_hal_sim:link(s10, down),
    receive {cell_hal_conn, s10, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    %% The value does not change across the outage; the watch must still fire. It has
    %% not yet: the server would have sent its message before its reply.
    {ok, Ref} = cell_hal:watch(io, bool_in, {eq, true}),
    receive {cell_hal_watch, Ref, _} -> ct:fail(fired_while_down) after 0 -> ok end,
    ok = cell_hal_sim:link(s10, up),
    receive {cell_hal_watch, Ref, true} -> ok after ?WAIT -> ct:fail(never_fired) end.

outputs_read_back_after_reconnect(_Config) ->
    ok = sim(s11),
    ok = cell_hal:write_sync(io, int16_out, 10, ?WAIT),
    ok = cell_hal_sim:link(s11, down),
    receive {cell_hal_conn, s11, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    %% The PLC took its output to a safe value while the link was down.
    ok = cell_hal_sim:set({io, int16_out}, 0),
    ?assertEqual({ok, 10}, cell_hal:read(io, int16_out)),
    ok = cell_hal_sim:link(s11, up),
    receive {cell_hal_conn, s11, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    ?assertEqual({ok, 0}, cell_hal:read(io, int16_out)).

writes_keep_their_order(_Config) ->
    ok = sim(s12, #{latency_ms => 5}),
    ok = cell_hal_sim:on_change({io, int32_out},
                                fun(V) -> [{0, {io, int32_in}, V}] end),
    ok = cell_hal:subscribe(io, int32_in),
    [ok = cell_hal:write(io, int32_out, V) || V <- lists:seq(1, 200)],
    ?assertEqual({ok, 200}, cell_hal:read(io, int32_out)),
    200 = await_value(int32_in, 200),
    ?assertEqual({ok, 200}, cell_hal_sim:get({io, int32_out})),
    %% The polls saw the values rise, never fall.
    Seen = collect_changes(int32_in, []),
    ct:log("polls saw ~p", [Seen]),
    ?assertEqual(Seen, lists:usort(Seen)).

collect_changes(Point, Acc) ->
    receive {cell_hal, {io, Point}, V} -> collect_changes(Point, [V | Acc])
    after 0 -> lists:reverse(Acc)
    end.

write_sync_waits_for_the_device(_Config) ->
    ok = sim(s13, #{latency_ms => 200, timeout_ms => 2000}),
    T0 = erlang:monotonic_time(millisecond),
    ok = cell_hal:write_sync(io, int16_out, 3, ?WAIT),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 200),
    %% A caller's timeout is kept even when the device is slower.
    T1 = erlang:monotonic_time(millisecond),
    ?assertEqual({error, timeout}, cell_hal:write_sync(io, int16_out, 4, 50)),
    ?assert(erlang:monotonic_time(millisecond) - T1 < 190),
    %% write/3 never waits for the device.
    T2 = erlang:monotonic_time(millisecond),
    ok = cell_hal:write(io, int16_out, 5),
    ?assert(erlang:monotonic_time(millisecond) - T2 < 150),
    ?assertEqual({ok, 5}, cell_hal:read(io, int16_out)).

%% A simulated PLC started anew holds its `image' from the first read on (not the zeros
%% of its type), until the simulation sets a point; the PLC's memory keeps it, and a
%% value it was never given reads zero.
initial_image(_Config) ->
    ok = cell_hal:add_connection(#{id => s30, driver => cell_hal_sim,
                                   opts => #{poll_ms => 10, reconnect_ms => 50,
                                             image => #{{io, int16_in} => 42,
                                                        {io, bool_in} => true}}}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => s30}),
    {ok, _} = cell_hal:subscribe_connection(s30),
    ok = await_status(s30, up),
    42 = await_value(int16_in, 42),
    ?assertEqual({ok, true}, cell_hal:read(io, bool_in)),
    ?assertEqual({ok, 42}, cell_hal_sim:get({io, int16_in})),
    ?assertEqual({error, not_set}, cell_hal_sim:get({io, int32_in})),
    ok = cell_hal_sim:set({io, int16_in}, 7),
    {ok, R} = cell_hal:watch(io, int16_in, {eq, 7}),
    receive {cell_hal_watch, R, 7} -> ok after ?WAIT -> ct:fail(not_polled) end,
    ?assertMatch({error, {bad_option, image}},
                 cell_hal:add_connection(#{id => s31, driver => cell_hal_sim,
                                           opts => #{image => #{not_a_point => 1}}})).

group_added_while_up(_Config) ->
    ok = sim(s14),
    ok = cell_hal_sim:preset(s14, #{{io2, int16_out} => 77, {io2, int16_in} => 66,
                                   {io2, int32_in} => <<"not a DINT">>}),
    ok = cell_hal:add_group(#{id => io2, module => cell_hal_test_io, connection => s14,
                              opts => #{only => [int16_in, int16_out, int32_in]}}),
    {ok, R} = cell_hal:watch(io2, int16_in, {eq, 66}),
    receive {cell_hal_watch, R, 66} -> ok after ?WAIT -> ct:fail(not_polled) end,
    %% Its output shows what the PLC holds.
    {ok, R2} = cell_hal:watch(io2, int16_out, {eq, 77}),
    receive {cell_hal_watch, R2, 77} -> ok after ?WAIT -> ct:fail(not_read_back) end,
    %% A value of the wrong type in the PLC never reaches a task.
    ?assertEqual({ok, 0}, cell_hal:read(io2, int32_in)),
    ?assertEqual({ok, [int16_in, int16_out, int32_in]},
                 case cell_hal:points(io2) of
                     {ok, Ps} -> {ok, [maps:get(name, P) || P <- Ps]}
                 end),
    {ok, #{caption := <<"int16 input">>, address := <<"A1.IN.int16">>, dir := in,
           type := int16, connection := s14}} = cell_hal:describe(io2, int16_in).

%% Each group added while up has its outputs read back, even when the read of the one
%% before is still on its way (a slow PLC).
groups_added_back_to_back(_Config) ->
    ok = sim(s22, #{latency_ms => 100}),
    ok = cell_hal_sim:preset(s22, #{{a, int16_out} => 1, {b, int16_out} => 2, {c, int16_out} => 3}),
    [ok = cell_hal:add_group(#{id => G, module => cell_hal_test_io, connection => s22,
                               opts => #{only => [int16_out]}}) || G <- [a, b, c]],
    %% A write to one of them before its read back arrives wins over the read back.
    ok = cell_hal:write(c, int16_out, 30),
    [begin
         {ok, R} = cell_hal:watch(G, int16_out, {eq, V}),
         receive {cell_hal_watch, R, V} -> ok after ?WAIT -> ct:fail({not_read_back, G}) end
     end || {G, V} <- [{a, 1}, {b, 2}, {c, 30}]],
    ?assertEqual({ok, 30}, cell_hal_sim:get({c, int16_out})).

%% A group added while the first read after connecting is on its way (a PLC that takes
%% a second to answer) has its outputs read back once the connection is up.
group_added_during_the_first_read(_Config) ->
    ok = cell_hal:add_connection(#{id => s24, driver => cell_hal_sim,
                                   opts => #{latency_ms => 1000, timeout_ms => 3000,
                                             poll_ms => 10}}),
    ok = cell_hal_sim:preset(s24, #{{late, int16_out} => 24}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => s24,
                              opts => #{only => [int16_in]}}),
    ok = cell_hal:add_group(#{id => late, module => cell_hal_test_io, connection => s24,
                              opts => #{only => [int16_out]}}),
    {ok, R} = cell_hal:watch(late, int16_out, {eq, 24}),
    receive {cell_hal_watch, R, 24} -> ok after ?WAIT -> ct:fail(not_read_back) end.

%% A group added to a connection that is up (a PLC that takes 200 ms to answer) can be
%% read as soon as it is added: its inputs were read first, none is "not yet read".
inputs_read_once_a_group_is_added(_Config) ->
    ok = sim(s26, #{latency_ms => 200}),
    ok = cell_hal_sim:preset(s26, #{{io2, int16_in} => 66, {io2, bool_in} => true}),
    ok = cell_hal:add_group(#{id => io2, module => cell_hal_test_io, connection => s26,
                              opts => #{only => [int16_in, bool_in, int16_out]}}),
    ?assertEqual({ok, 66}, cell_hal:read(io2, int16_in)),
    ?assertEqual({ok, true}, cell_hal:read(io2, bool_in)).

%% A group added while the first read after connecting is on its way (a PLC that takes
%% a second to answer) is read before the connection comes up: a task that starts on
%% the news that it is up finds every input read. The test adds the group once the
%% PLC has been asked for the first read (seen by tracing its process).
inputs_of_a_group_added_during_the_first_read(_Config) ->
    Device = cell_hal_sim_sup:ensure_device(s27, #{latency_ms => 1000}),
    ok = gen_server:call(Device, {preset, #{{io, int16_in} => 1, {late, int16_in} => 27,
                                            {late, bool_in} => true}}),
    erlang:trace(Device, true, ['receive']),
    ok = cell_hal:add_connection(#{id => s27, driver => cell_hal_sim,
                                   opts => #{latency_ms => 1000, timeout_ms => 3000,
                                             poll_ms => 10}}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => s27,
                              opts => #{only => [int16_in]}}),
    receive {trace, Device, 'receive', {'$gen_cast', {read, _, _, _}}} -> ok
    after ?WAIT -> ct:fail(no_first_read)
    end,
    erlang:trace(Device, false, ['receive']),
    ok = cell_hal:add_group(#{id => late, module => cell_hal_test_io, connection => s27,
                              opts => #{only => [int16_in, bool_in]}}),
    {ok, Status} = cell_hal:subscribe_connection(s27),
    _ = Status =:= up orelse
        receive {cell_hal_conn, s27, up} -> ok after ?WAIT -> ct:fail(not_up) end,
    ?assertEqual({ok, 27}, cell_hal:read(late, int16_in)),
    ?assertEqual({ok, true}, cell_hal:read(late, bool_in)),
    ?assertEqual({ok, 1}, cell_hal:read(io, int16_in)).

remove_group_and_connection(_Config) ->
    ok = sim(s15),
    {ok, Ref} = cell_hal:watch(io, int16_in, {eq, 99}),
    ok = cell_hal:subscribe(io, int16_in),
    ok = cell_hal:remove_group(io),
    ?assertEqual({error, unknown_point}, cell_hal:read(io, int16_in)),
    ?assertEqual({error, unknown_group}, cell_hal:points(io)),
    ?assertNot(cell_hal:cancel_watch(Ref)),
    ok = cell_hal:remove_connection(s15),
    receive {cell_hal_conn, s15, down} -> ok after ?WAIT -> ct:fail(no_down_on_remove) end,
    ?assertEqual({error, unknown_connection}, cell_hal:status(s15)),
    ?assertEqual([], cell_hal:connections()),
    %% Its simulated PLC lost the connection.
    ?assertEqual(0, gen_server:call(cell_hal_sim_device:whereis(s15), clients)).

subscribers_are_cleaned_up(_Config) ->
    ok = sim(s16),
    Self = self(),
    {Pid, MRef} = spawn_monitor(
                    fun() ->
                            ok = cell_hal:subscribe(io, int16_in),
                            {ok, _} = cell_hal:watch(io, int16_in, {eq, 1234}),
                            {ok, _} = cell_hal:subscribe_connection(s16),
                            Self ! subscribed,
                            receive stop -> ok end
                    end),
    receive subscribed -> ok after ?WAIT -> ct:fail(no_subscriber) end,
    ?assert(lists:member(Pid, cell_hal_store:subscribers())),
    Pid ! stop,
    receive {'DOWN', MRef, process, Pid, _} -> ok end,
    %% The server handles the exit in order with our call.
    _ = cell_hal:subscribe_connection(s16),
    ?assertNot(lists:member(Pid, cell_hal_store:subscribers())),
    ?assertEqual(0, ets:info(cell_hal_watch_claims, size)).

%% The simulated PLC killed: its supervisor starts it again at once with its image and
%% its rules, as a PLC comes back from a reboot; the HAL's connection goes down, then
%% up by itself, and reads back the outputs as they were written. At its start the
%% device runs every rule again on the values it holds (a rule killed before it ran,
%% or a sensor due to follow its output, is not lost), and its rules act on what is
%% written after. Stopped, it forgets.
device_killed_comes_back_with_its_memory(_Config) ->
    ok = sim(s30),
    Self = self(),
    ok = cell_hal_sim:follow({io, int16_in}, {io, int16_out}, 0, fun(V) -> -V end),
    ok = cell_hal_sim:on_change({io, bool_out}, fun(V) -> Self ! {written, V}, [] end),
    ok = cell_hal_sim:set({io, uint16_in}, 7),
    7 = await_value(uint16_in, 7),
    ok = cell_hal:write(io, bool_out, true),
    receive {written, true} -> ok after ?WAIT -> ct:fail(not_written) end,
    Old = cell_hal_sim_device:whereis(s30),
    exit(Old, kill),
    receive {cell_hal_conn, s30, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    %% The rule runs again at the device's start, on the value the memory holds.
    receive {written, true} -> ok after ?WAIT -> ct:fail(rule_not_run_again) end,
    receive {cell_hal_conn, s30, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    New = cell_hal_sim_device:whereis(s30),
    ?assert(is_pid(New) andalso New =/= Old),
    ?assertEqual({ok, true}, cell_hal:read(io, bool_out)),
    ?assertEqual({ok, 7}, cell_hal:read(io, uint16_in)),
    ?assertEqual({ok, true}, cell_hal_sim:get({io, bool_out})),
    ok = cell_hal:write(io, int16_out, 42),
    -42 = await_value(int16_in, -42),
    ok = cell_hal_sim:stop_device(s30),
    ?assertEqual({error, not_set}, cell_hal_sim:get({io, bool_out})),
    ok = cell_hal_sim:set({io, int16_out}, 3),
    ?assertEqual({ok, 3}, cell_hal_sim:get({io, int16_out})),
    ?assertEqual({error, not_set}, cell_hal_sim:get({io, int16_in})).

%% A simulated PLC takes nothing on a connection it dropped (a momentary loss, a cable
%% pulled), however soon after the drop a request comes: a client of the test's own
%% speaks the driver's protocol to it, next to the HAL's worker.
dropped_connection_takes_nothing(_Config) ->
    ok = sim(s31),
    Dev = cell_hal_sim_device:whereis(s31),
    Out = {io, int16_out},
    R1 = connect_to(Dev),
    ok = write_to(Dev, R1, 1, 5),
    ok = cell_hal_sim:drop(s31),
    receive {cell_hal_sim, R1, closed} -> ok after ?WAIT -> ct:fail(not_dropped) end,
    gen_server:cast(Dev, {write, R1, 2, Out, 6}),
    %% Asked after the write, by the same process: the PLC has had it.
    ?assertEqual({ok, 5}, cell_hal_sim:get(Out)),
    R2 = connect_to(Dev),
    ok = cell_hal_sim:link(s31, down),
    receive {cell_hal_sim, R2, closed} -> ok after ?WAIT -> ct:fail(not_pulled) end,
    gen_server:cast(Dev, {write, R2, 3, Out, 7}),
    gen_server:cast(Dev, {read, R2, 4, [{Out, int16}]}),
    ?assertEqual({ok, 5}, cell_hal_sim:get(Out)),
    receive {cell_hal_sim, _, {reply, Tag, _}} when Tag > 1 -> ct:fail({answered, Tag})
    after 0 -> ok
    end,
    ok = cell_hal_sim:link(s31, up).

connect_to(Dev) ->
    Ref = make_ref(),
    gen_server:cast(Dev, {connect, self(), Ref}),
    receive {cell_hal_sim, Ref, connected} -> Ref after ?WAIT -> ct:fail(not_connected) end.

write_to(Dev, Ref, Tag, V) ->
    gen_server:cast(Dev, {write, Ref, Tag, {io, int16_out}, V}),
    receive {cell_hal_sim, Ref, {reply, Tag, Result}} -> Result
    after ?WAIT -> ct:fail({no_answer, Tag})
    end.

worker_crash_goes_down_and_recovers(_Config) ->
    ok = sim(s17),
    ok = cell_hal_sim:set({io, int16_in}, 8),
    8 = await_value(int16_in, 8),
    ok = cell_hal:subscribe(io, int16_in),
    [{s17, Worker, _, _}] = [C || {s17, _, _, _} = C <- supervisor:which_children(cell_hal_conn_sup)],
    exit(Worker, kill),
    receive {cell_hal_conn, s17, down} -> ok after ?WAIT -> ct:fail(no_down_after_crash) end,
    receive {cell_hal_conn, s17, up} -> ok after ?WAIT -> ct:fail(no_up_after_crash) end,
    %% Subscriptions survived the crash.
    ok = cell_hal_sim:set({io, int16_in}, 9),
    receive {cell_hal, {io, int16_in}, 9} -> ok after ?WAIT -> ct:fail(sub_lost) end.

server_crash_keeps_configuration(_Config) ->
    ok = sim(s18),
    {ok, Ref} = cell_hal:watch(io, int16_in, {eq, 31}),
    exit(whereis(cell_hal_server), kill),
    %% rest_for_one restarts the workers too: down, then up.
    receive {cell_hal_conn, s18, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    receive {cell_hal_conn, s18, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    ?assertEqual([io], cell_hal:groups()),
    ?assertEqual([s18], cell_hal:connections()),
    ok = cell_hal_sim:set({io, int16_in}, 31),
    receive {cell_hal_watch, Ref, 31} -> ok after ?WAIT -> ct:fail(watch_lost) end,
    %% The new server watches subscribers again.
    ?assertEqual({ok, up}, cell_hal:subscribe_connection(s18)).

%% The server killed, its supervisor held so that neither it nor the workers restarted
%% with it have come back: a watch or a subscription cannot be placed and says
%% `disconnected', as a lost connection does, never an exit; cancelling a watch and
%% unsubscribing need no server. Once the HAL is back, what was subscribed and
%% watched before works on, and what was cancelled stays cancelled.
io_while_the_server_restarts(_Config) ->
    ok = sim(s24),
    ok = cell_hal:subscribe(io, int16_in),
    ok = cell_hal:subscribe(io, uint16_in),
    {ok, Kept} = cell_hal:watch(io, int16_in, {eq, 41}),
    {ok, Cancelled} = cell_hal:watch(io, int16_in, {eq, 42}),
    Self = self(),
    Other = spawn_link(fun() ->
                               {ok, _} = cell_hal:subscribe_connection(s24),
                               Self ! {subscribed, self()},
                               receive unsubscribe -> ok end,
                               Self ! {self(), cell_hal:unsubscribe_connection(s24)},
                               receive stop -> ok end
                       end),
    receive {subscribed, Other} -> ok after ?WAIT -> ct:fail(no_subscriber) end,
    Server = whereis(cell_hal_server),
    ok = sys:suspend(cell_hal_sup),
    kill(Server),
    ?assertEqual({error, disconnected}, cell_hal:watch(io, int16_in, {eq, 1})),
    ?assertEqual({error, disconnected}, cell_hal:subscribe(io, int32_in)),
    ?assertEqual({error, disconnected}, cell_hal:subscribe_connection(s24)),
    ?assert(cell_hal:cancel_watch(Cancelled)),
    ?assertNot(cell_hal:cancel_watch(Cancelled)),
    ok = cell_hal:unsubscribe(io, uint16_in),
    Other ! unsubscribe,
    receive {Other, ok} -> ok after ?WAIT -> ct:fail(not_unsubscribed) end,
    ?assertNot(lists:member(Other, cell_hal_store:conn_subs(s24))),
    Other ! stop,
    ok = sys:resume(cell_hal_sup),
    ok = await_restart(s24),
    ok = cell_hal_sim:set({io, int16_in}, 41),
    receive {cell_hal_watch, Kept, 41} -> ok after ?WAIT -> ct:fail(watch_lost) end,
    receive {cell_hal, {io, int16_in}, 41} -> ok after ?WAIT -> ct:fail(sub_lost) end,
    ok = cell_hal_sim:set({io, int16_in}, 42),
    ok = cell_hal_sim:set({io, uint16_in}, 7),
    receive {cell_hal, {io, int16_in}, 42} -> ok after ?WAIT -> ct:fail(sub_lost) end,
    7 = await_value(uint16_in, 7),
    receive {cell_hal_watch, Cancelled, _} = M1 -> ct:fail({cancelled_fired, M1}) after 0 -> ok end,
    receive {cell_hal, {io, uint16_in}, _} = M2 -> ct:fail({unsubscribed, M2}) after 0 -> ok end.

%% A process that found the server away asks to be told when it is back: the server
%% that starts tells it, once; with a server running the message comes at once. A change of the configuration while the
%% server is away says `disconnected' too, and changes nothing.
told_when_the_server_is_back(_Config) ->
    ok = sim(s26),
    Now = cell_hal:notify_back(),
    receive {cell_hal_back, Now} -> ok after ?WAIT -> ct:fail(not_told_at_once) end,
    ok = sys:suspend(cell_hal_sup),
    kill(whereis(cell_hal_server)),
    ?assertEqual({error, disconnected},
                 cell_hal:add_group(#{id => io2, module => cell_hal_test_io, connection => s26})),
    ?assertEqual({error, disconnected}, cell_hal:remove_group(io)),
    Later = cell_hal:notify_back(),
    %% Nobody can tell it yet: the server is gone and its supervisor held.
    receive {cell_hal_back, Later} -> ct:fail(told_while_away) after 0 -> ok end,
    ok = sys:resume(cell_hal_sup),
    receive {cell_hal_back, Later} -> ok after ?WAIT -> ct:fail(not_told) end,
    ok = await_restart(s26),
    receive {cell_hal_back, _} = Again -> ct:fail({told_twice, Again}) after 0 -> ok end,
    ?assertEqual([io], cell_hal:groups()),
    ?assertEqual(ok, cell_hal:subscribe(io, int16_in)).

%% A worker killed, its supervisor held so that it has not come back: a write finds no
%% worker: `disconnected', as a lost connection does, never an exit; a raw request the
%% same. A worker that does not take a write in time (suspended) is the same to
%% `write/3'; `write_sync/4' says `timeout', the device's confirmation being what did
%% not come.
io_while_a_worker_restarts(_Config) ->
    ok = sim(s25),
    Worker = worker(s25),
    ok = sys:suspend(Worker),
    ?assertEqual({error, timeout}, cell_hal:write_sync(io, int16_out, 1, 100)),
    ?assertEqual({error, disconnected}, cell_hal:write(io, int16_out, 2)),
    ok = sys:resume(Worker),
    ok = sys:suspend(cell_hal_conn_sup),
    kill(Worker),
    ?assertEqual({error, disconnected}, cell_hal:write(io, int16_out, 3)),
    ?assertEqual({error, disconnected}, cell_hal:write_sync(io, int16_out, 3, 1000)),
    ?assertEqual({error, disconnected}, cell_hal:request(s25, {read_holding_registers, 0, 1}, 100)),
    ok = sys:resume(cell_hal_conn_sup),
    ok = await_restart(s25),
    ok = cell_hal:write_sync(io, int16_out, 4, ?WAIT).

%% A worker killed, its supervisor held so that no successor has started: nothing it
%% read is fresh any more though its connection's row still says up. The connection
%% reads as down (to `status/1', `info/1' and a new connection subscriber), its inputs
%% as `disconnected' and a watch placed meanwhile waits; an output reads what was last
%% commanded, as while down. Once the successor is up, every input reads fresh again
%% and the watch fires on the first read.
killed_worker_reads_down_until_replaced(_Config) ->
    ok = sim(s32),
    ok = cell_hal_sim:set({io, int16_in}, 8),
    8 = await_value(int16_in, 8),
    ok = cell_hal:write_sync(io, int16_out, 5, ?WAIT),
    Worker = worker(s32),
    ok = sys:suspend(cell_hal_conn_sup),
    kill(Worker),
    ?assertEqual(down, cell_hal:status(s32)),
    ?assertMatch({ok, #{status := down,
                        reason := <<"the connection's worker is gone; it is being started again">>}},
                 cell_hal:info(s32)),
    ?assertEqual({ok, down}, cell_hal:subscribe_connection(s32)),
    ?assertEqual({error, disconnected}, cell_hal:read(io, int16_in)),
    ?assertEqual({error, disconnected}, cell_hal_store:read({io, int16_in})),
    ?assertEqual({error, disconnected}, cell_hal:samples(io, int16_in, 0)),
    ?assertEqual({ok, 5}, cell_hal:read(io, int16_out)),
    {ok, Ref} = cell_hal:watch(io, int16_in, {eq, 8}),
    %% A watch that holds is fired while the server places it, before it answers.
    receive {cell_hal_watch, Ref, _} = Fired -> ct:fail({stale_fire, Fired}) after 0 -> ok end,
    ok = sys:resume(cell_hal_conn_sup),
    ok = await_restart(s32),
    receive {cell_hal_watch, Ref, 8} -> ok after ?WAIT -> ct:fail(watch_lost) end,
    ?assertEqual(up, cell_hal:status(s32)),
    ?assertEqual({ok, 8}, cell_hal:read(io, int16_in)),
    ?assertNotEqual(Worker, worker(s32)).

worker(Conn) ->
    [Worker] = [P || {Id, P, _, _} <- supervisor:which_children(cell_hal_conn_sup), Id =:= Conn],
    Worker.

kill(Pid) ->
    MRef = erlang:monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', MRef, process, Pid, _} -> ok after ?WAIT -> ct:fail({alive, Pid}) end.

%% A connection's worker started again: down, then up (the test subscribed to it).
await_restart(Conn) ->
    receive {cell_hal_conn, Conn, down} -> ok after ?WAIT -> ct:fail({no_down, Conn}) end,
    receive {cell_hal_conn, Conn, up} -> ok after ?WAIT -> ct:fail({no_up, Conn}) end,
    ok.

logs_speak_to_operators(_Config) ->
    ok = sim(s19),
    ok = cell_log:subscribe(),
    ok = cell_hal_sim:drop(s19),
    {cell_log, #{text := Lost, level := warning, source := <<"hal/s19">>}} =
        await_msg(fun({cell_log, #{text := T}}) -> binary:match(T, <<"lost">>) =/= nomatch;
                     (_) -> false end),
    ?assertEqual(<<"connection to s19 (simulated PLC s19) lost: the simulated PLC dropped "
                   "the connection; retrying in 50 ms">>, Lost),
    {cell_log, #{text := UpText, level := silent}} =
        await_msg(fun({cell_log, #{text := T}}) -> binary:match(T, <<" up: ">>) =/= nomatch;
                     (_) -> false end),
    Points = length(cell_hal_test_io:points(#{})),
    ?assertEqual(iolist_to_binary(["connection to s19 (simulated PLC s19) up: ",
                                   integer_to_list(Points), " points, 1 request a poll"]),
                 UpText),
    ok = cell_log:unsubscribe().

%% A device that accepts the connection and then fails is retried ever more slowly;
%% the wait goes back to the start once it works.
backoff_grows_then_resets(_Config) ->
    ok = sim(s20, #{reconnect_ms => 40, max_reconnect_ms => 160}),
    %% Repeated failures are logged at the verbose level.
    ok = cell_log:set_level(<<"hal/s20">>, verbose),
    ok = cell_log:subscribe(),
    ok = cell_hal_sim:link(s20, down),
    Waits = [retry_wait(<<"hal/s20">>) || _ <- lists:seq(1, 4)],
    ct:log("waits ~p", [Waits]),
    ?assertEqual([<<"40 ms">>, <<"80 ms">>, <<"160 ms">>, <<"160 ms">>], Waits),
    ok = cell_hal_sim:link(s20, up),
    ok = await_status(s20, up),
    ok = cell_hal_sim:drop(s20),
    ?assertEqual(<<"40 ms">>, retry_wait(<<"hal/s20">>)),
    ok = cell_log:unsubscribe().

retry_wait(Source) ->
    {cell_log, #{text := T}} =
        await_msg(fun({cell_log, #{source := S, text := T}}) when S =:= Source ->
                          binary:match(T, <<"retrying in">>) =/= nomatch;
                     (_) -> false end),
    [_, Wait] = binary:split(T, <<"retrying in ">>),
    Wait.

connection_info(_Config) ->
    ok = sim(s21),
    {ok, #{status := up, driver := cell_hal_sim, endpoint := <<"simulated PLC s21">>,
           reason := <<>>, groups := [io], since := Since}} = cell_hal:info(s21),
    ?assert(is_integer(Since)),
    ok = cell_hal_sim:link(s21, down),
    ok = await_status(s21, down),
    {ok, #{status := down, reason := Reason}} = cell_hal:info(s21),
    ?assertEqual(<<"the simulated PLC dropped the connection">>, Reason),
    ?assertEqual({error, unknown_connection}, cell_hal:info(nope)).
