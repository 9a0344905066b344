%% Device tasks and their IO (seed 000 §4): a task waits for an IO point by subscription
%% and writes outputs by name; a lost connection takes it DOWN with an error naming the
%% connection, and Retry takes it on once the connection is back; a point its device
%% cannot serve does the same naming the point; a group the HAL does not know stops it
%% at Start with a clear error. The HAL's processes killed or stuck under a task in the
%% middle of a step are a lost connection to it, never a crash: the same error, and
%% Retry takes it on with its product once the connection is back. What the task
%% commanded before the connection was lost and the device no longer holds is written
%% again at that Retry, before the task's wait is armed again.
-module(cell_task_io_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([waits_for_io/1, connection_lost_and_back/1, unknown_group/1,
         lost_while_paused/1, point_unavailable/1, worker_killed_mid_step/1,
         server_killed_mid_step/1, worker_stuck_mid_step/1, hal_restarts_while_waiting/1,
         outputs_set_again_after_reconnect/1, write_lost_in_flight_written_again/1,
         lost_in_a_step_that_stopped_the_belt/1, waited_point_unavailable/1]).

-define(TIMEOUT, 10000).

all() ->
    [waits_for_io, connection_lost_and_back, unknown_group, lost_while_paused,
     point_unavailable, worker_killed_mid_step, server_killed_mid_step,
     worker_stuck_mid_step, hal_restarts_while_waiting,
     outputs_set_again_after_reconnect, write_lost_in_flight_written_again,
     lost_in_a_step_that_stopped_the_belt, waited_point_unavailable].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Tab = ets:new(io_suite, [public]),
    _ = [application:load(A) || A <- [cell_base, cell_hal, cell]],
    ok = application:set_env(cell_base, root, Root),
    Group = case Case of unknown_group -> nowhere; _ -> conv end,
    Spec = #{tasks => [#{id => belt, module => cell_io_test_task, zone => <<"Belt">>,
                         lane => <<"1">>, io => [Group],
                         args => maps:merge(#{tab => Tab, notify => self()},
                                            case_args(Case, Tab))}]},
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_hal:add_connection(#{id => plc1, driver => cell_hal_sim,
                                   opts => #{poll_ms => 10}}),
    ok = cell_hal:add_group(#{id => conv, module => cell_io_test_group, connection => plc1}),
    ok = cell_hal_sim:set({conv, sensor}, false),
    ok = cell_hal_sim:set({conv, count}, 0),
    {ok, up} = await_conn(plc1, up),
    [{tab, Tab} | Config].

end_per_testcase(_Case, _Config) ->
    %% A case that failed half-way may have left the HAL held.
    _ = [catch sys:resume(P) || P <- [cell_hal_sup, cell_hal_conn_sup]],
    _ = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    %% The simulated PLC would outlive the case with its image and rules: the next
    %% case starts with a new one, its sensor not left on.
    _ = cell_hal_sim:stop_device(plc1),
    _ = cell_hal:remove_group(conv),
    _ = cell_hal:remove_connection(plc1),
    ok.

%% The task runs its belt, wakes when the sensor sees a panel (no polling by the task),
%% stops the belt, reads the counter, and waits for the panel to go.
waits_for_io(_Config) ->
    %% Outputs are written through without waiting for the PLC: the simulated PLC
    %% tells the test when the motor output reaches it.
    Self = self(),
    ok = cell_hal_sim:on_change({conv, motor}, fun(V) -> Self ! {motor, V}, [] end),
    ok = cell_controller:start(),
    await_woke(undefined),
    await_motor(true),
    ok = cell_hal_sim:set({conv, count}, 7),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    await_motor(false),
    ok = cell_hal_sim:set({conv, sensor}, false),
    await_woke({io, conv, sensor, false}),
    await_motor(true),
    ok = cell_controller:stop(),
    %% uninit leaves the belt off.
    await_motor(false).

%% The connection goes: DOWN, an error naming it. Retry while it is still gone: still
%% DOWN. Back and Retry: the task goes on where it was, its wait armed again.
connection_lost_and_back(_Config) ->
    ok = cell_controller:start(),
    await_woke(undefined),
    ok = cell_events:subscribe([task_state]),
    ok = cell_hal_sim:link(plc1, down),
    await_state(belt, down),
    [#{id := Id, caption := <<"IO connection lost">>, solutions := [retry],
       description := Text}] = cell_alarms:list(),
    ?assertNotEqual(nomatch, binary:match(Text, <<"plc1">>)),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_task_proc:state(belt)),
    [#{id := Id2, caption := <<"IO connection lost">>}] = cell_alarms:list(),
    ok = cell_hal_sim:link(plc1, up),
    {ok, up} = await_conn(plc1, up),
    ok = cell_alarms:answer(Id2, retry, <<"op">>),
    ok = cell_controller:sync(),
    ?assertEqual({ready, idle, starved}, cell_task_proc:state(belt)),
    %% The wait for the sensor is armed again.
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}).

%% The point a task waits for becomes one its device cannot serve (a PLC refusing its
%% address): the task is told, not left waiting for ever: DOWN with an error naming
%% the point and why. Retry while the fault stands: DOWN again; once it is gone the
%% wait is armed again and wakes the task.
waited_point_unavailable(_Config) ->
    ok = cell_controller:start(),
    await_woke(undefined),
    ok = cell_events:subscribe([task_state]),
    Why = <<"the PLC refuses this address (illegal data address, Modbus exception 2)">>,
    true = cell_hal_store:set_fault({conv, sensor}, Why),
    await_state(belt, down),
    [#{id := Id, caption := <<"IO point unavailable">>, solutions := [retry],
       description := Text}] = cell_alarms:list(),
    ?assertNotEqual(nomatch, binary:match(Text, <<"sensor">>)),
    ?assertNotEqual(nomatch, binary:match(Text, Why)),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    await_state(belt, down),
    [#{id := Id2, caption := <<"IO point unavailable">>}] = cell_alarms:list(),
    true = cell_hal_store:set_fault({conv, sensor}, undefined),
    ok = cell_hal_sim:set({conv, sensor}, true),
    ok = cell_alarms:answer(Id2, retry, <<"op">>),
    await_woke({io, conv, sensor, true}),
    ok = cell_controller:sync(),
    ?assertEqual([], cell_alarms:list()).

%% The device reports a point it cannot serve (a PLC variable renamed, say): the step
%% that reads it takes the task DOWN with an error naming the point and why, not a
%% crash. Retry while the fault stands: still DOWN; once it is gone the step runs
%% again, as it was woken.
point_unavailable(_Config) ->
    ok = cell_controller:start(),
    await_woke(undefined),
    true = cell_hal_store:set_fault({conv, count}, <<"symbol MAIN.nCount not found">>),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_task_proc:state(belt)),
    [#{id := Id, caption := <<"IO point unavailable">>, solutions := [retry],
       description := Text}] = cell_alarms:list(),
    ?assertNotEqual(nomatch, binary:match(Text, <<"count">>)),
    ?assertNotEqual(nomatch, binary:match(Text, <<"MAIN.nCount not found">>)),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    await_woke({io, conv, sensor, true}),
    ok = cell_controller:sync(),
    [#{id := Id2, caption := <<"IO point unavailable">>}] = cell_alarms:list(),
    true = cell_hal_store:set_fault({conv, count}, undefined),
    ok = cell_hal_sim:set({conv, count}, 3),
    ok = cell_alarms:answer(Id2, retry, <<"op">>),
    await_woke({io, conv, sensor, true}),
    ok = cell_controller:sync(),
    ?assertEqual({ready, idle, starved}, cell_task_proc:state(belt)),
    ?assertEqual([], cell_alarms:list()).

%% A group the HAL does not know: the task cannot start, and says so.
unknown_group(_Config) ->
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_task_proc:state(belt)),
    [#{caption := <<"IO group not configured">>, description := Text}] = cell_alarms:list(),
    ?assertNotEqual(nomatch, binary:match(Text, <<"nowhere">>)).

%% Paused when the connection goes: Start does not resume a task without its IO.
lost_while_paused(_Config) ->
    ok = cell_controller:start(),
    await_woke(undefined),
    ok = cell_controller:pause(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([alarm_raised]),
    ok = cell_hal_sim:link(plc1, down),
    {ok, down} = await_conn(plc1, down),
    ok = cell_controller:sync(),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_task_proc:state(belt)),
    [#{id := Id, caption := <<"IO connection lost">>}] = cell_alarms:list(),
    ok = cell_hal_sim:link(plc1, up),
    {ok, up} = await_conn(plc1, up),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    ok = cell_controller:sync(),
    ?assertEqual({ready, idle, starved}, cell_task_proc:state(belt)).

%% The connection's worker killed while the task is in the middle of a step (its
%% supervisor held, so it is not started again yet): the step's write finds no worker.
%% The task goes DOWN with "IO connection lost", not a crash; Retry once the worker is
%% back runs the step again as it was woken, and the task goes on with its product.
worker_killed_mid_step(_Config) ->
    Task = started(),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    Id = await_io_error(),
    ok = sys:resume(cell_hal_conn_sup),
    await_conn_restart(plc1),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    await_woke({io, conv, sensor, true}),
    ok = cell_hal_sim:set({conv, sensor}, false),
    await_woke({io, conv, sensor, false}),
    still_holding(Task).

%% The HAL's server killed in the middle of a step (its supervisor held, so neither it
%% nor the workers it restarts with have come back yet): the wait the step returns
%% cannot be placed. The same error, not a crash; Retry once the HAL is back places the
%% wait with the new server, and the task goes on with its product.
server_killed_mid_step(_Config) ->
    Task = started(),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    Id = await_io_error(),
    ok = sys:resume(cell_hal_sup),
    await_conn_restart(plc1),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    ok = cell_hal_sim:set({conv, sensor}, false),
    await_woke({io, conv, sensor, false}),
    still_holding(Task).

%% The worker stuck (suspended) in the middle of a step: the write is not taken in
%% time. The same error; the connection itself never went down, so no `up' will come:
%% Retry once the worker answers again finds the connection up and goes on.
worker_stuck_mid_step(_Config) ->
    Task = started(),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    Id = await_io_error(),
    ok = sys:resume(worker(plc1)),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    await_woke({io, conv, sensor, true}),
    ok = cell_hal_sim:set({conv, sensor}, false),
    await_woke({io, conv, sensor, false}),
    still_holding(Task).

%% The HAL's server killed while the task waits for its sensor (the workers restart
%% with it): the connection goes down, the task DOWN with the error. Once it is back,
%% Retry places the wait again with the new server and the sensor wakes the task.
hal_restarts_while_waiting(_Config) ->
    Task = started(),
    kill(whereis(cell_hal_server)),
    Id = await_io_error(),
    await_conn_restart(plc1),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    still_holding(Task).

%% The task runs its belt and waits for the panel the belt brings. The link drops, and
%% while it is down the PLC takes its outputs to safe values (the belt stops), as a
%% write lost with the connection would leave it. Once the link is back, one Retry:
%% the belt is commanded on again before the task waits again, the panel comes, and
%% the task goes on with no second error.
outputs_set_again_after_reconnect(Config) ->
    Tab = ?config(tab, Config),
    Self = self(),
    %% The belt brings a panel only once it runs again after the loss.
    ok = cell_hal_sim:on_change(
           {conv, motor},
           fun(V) ->
                   Self ! {motor, V},
                   case V andalso not ets:insert_new(Tab, {belt_ran}) of
                       true -> [{0, {conv, sensor}, true}];
                       false -> []
                   end
           end),
    Task = started(),
    await_motor(true),
    ok = cell_hal_sim:link(plc1, down),
    Id = await_io_error(),
    ok = cell_hal_sim:set({conv, motor}, false),
    ok = cell_hal_sim:link(plc1, up),
    {ok, up} = await_conn(plc1, up),
    ?assertEqual({ok, false}, cell_hal:read(conv, motor)),
    belt_on_again_after_retry(Id, Task).

%% The PLC stops answering just as the task commands its belt on: the write is taken
%% by the connection but never reaches the PLC, and the connection counts as lost. Once
%% the PLC answers again the HAL reads the belt back off; one Retry commands it on
%% again before the task waits again, the panel comes, and the task goes on with no
%% second error.
write_lost_in_flight_written_again(_Config) ->
    Self = self(),
    %% The belt brings a panel whenever it runs.
    ok = cell_hal_sim:on_change({conv, motor},
                                fun(V) ->
                                        Self ! {motor, V},
                                        [{0, {conv, sensor}, true} || V]
                                end),
    Task = started(),
    Id = await_io_error(),
    ok = cell_hal_sim:link(plc1, up),
    {ok, up} = await_conn(plc1, up),
    ?assertNotEqual({ok, true}, cell_hal:read(conv, motor)),
    belt_on_again_after_retry(Id, Task).

%% The step that sees a panel stops the belt (the PLC has it stopped), then finds its
%% connection's worker gone and is dropped. At the Retry the belt is not started
%% again on the way: what the step commanded before the loss counts, and the step runs
%% again as it was woken.
lost_in_a_step_that_stopped_the_belt(_Config) ->
    Self = self(),
    ok = cell_hal_sim:on_change({conv, motor}, fun(V) -> Self ! {motor, V}, [] end),
    Task = started(),
    await_motor(true),
    flush_motor(),
    ok = cell_hal_sim:set({conv, sensor}, true),
    await_woke({io, conv, sensor, true}),
    Id = await_io_error(),
    await_motor(false),
    ok = sys:resume(cell_hal_conn_sup),
    await_conn_restart(plc1),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    await_woke({io, conv, sensor, true}),
    ok = cell_controller:sync(),
    %% Written after whatever the task wrote: once the PLC confirmed it, every change
    %% of the belt before it has been reported.
    ok = cell_hal:write_sync(conv, motor, false, ?TIMEOUT),
    receive
        {motor, true} -> ct:fail(belt_started_again_at_retry)
    after 0 ->
        ok
    end,
    still_holding(Task).

%% -------------------------------------------------------------------------------------

%% What a case gives its task: a product to hold, and what happens to the HAL in the
%% middle of the step that sees a panel (the first time only; Retry runs it again).
case_args(worker_killed_mid_step, Tab) ->
    #{serial => <<"P1">>,
      mid_step => once(Tab, fun() ->
                                    Worker = worker(plc1),
                                    ok = sys:suspend(cell_hal_conn_sup),
                                    kill(Worker)
                            end)};
case_args(server_killed_mid_step, Tab) ->
    #{serial => <<"P1">>,
      mid_step => once(Tab, fun() ->
                                    Server = whereis(cell_hal_server),
                                    ok = sys:suspend(cell_hal_sup),
                                    kill(Server)
                            end)};
case_args(worker_stuck_mid_step, Tab) ->
    #{serial => <<"P1">>,
      mid_step => once(Tab, fun() -> ok = sys:suspend(worker(plc1)) end)};
case_args(hal_restarts_while_waiting, _Tab) ->
    #{serial => <<"P1">>};
case_args(outputs_set_again_after_reconnect, _Tab) ->
    #{serial => <<"P1">>};
case_args(lost_in_a_step_that_stopped_the_belt, Tab) ->
    %% The belt's stop confirmed by the PLC before the worker goes.
    #{serial => <<"P1">>, stop_first => true,
      mid_step => once(Tab, fun() ->
                                    ok = cell_hal:write_sync(conv, motor, false, ?TIMEOUT),
                                    Worker = worker(plc1),
                                    ok = sys:suspend(cell_hal_conn_sup),
                                    kill(Worker)
                            end)};
case_args(write_lost_in_flight_written_again, Tab) ->
    #{serial => <<"P1">>,
      before_run => once(Tab, fun() -> ok = cell_hal_sim:link(plc1, silent) end)};
case_args(_Case, _Tab) ->
    #{}.

once(Tab, Fun) ->
    fun() ->
            case ets:insert_new(Tab, {mid_step_done}) of
                true -> Fun();
                false -> ok
            end
    end.

worker(Conn) ->
    [Worker] = [P || {Id, P, _, _} <- supervisor:which_children(cell_hal_conn_sup), Id =:= Conn],
    Worker.

kill(Pid) ->
    MRef = erlang:monitor(process, Pid),
    exit(Pid, kill),
    receive
        {'DOWN', MRef, process, Pid, _} -> ok
    after ?TIMEOUT ->
        erlang:error({still_alive, Pid})
    end.

%% Started, the task running and holding its product; its pid.
started() ->
    ok = cell_controller:start(),
    await_woke(undefined),
    [#{id := belt, pid := Task, serial := <<"P1">>}] = cell_controller:tasks(),
    ok = cell_events:subscribe([task_state]),
    flush_conn(plc1),
    Task.

%% DOWN with the lost connection's error, offering Retry.
await_io_error() ->
    await_state(belt, down),
    [#{id := Id, caption := <<"IO connection lost">>, solutions := [retry],
       description := Text}] = cell_alarms:list(),
    ?assertNotEqual(nomatch, binary:match(Text, <<"plc1">>)),
    Id.

%% The same process (no crash), holding its product.
still_holding(Task) ->
    ?assertMatch([#{id := belt, pid := Task, serial := <<"P1">>}], cell_controller:tasks()),
    ?assertEqual([], cell_alarms:list()).

%% A restarted worker: the connection down, then up again.
await_conn_restart(Conn) ->
    [receive
         {cell_hal_conn, Conn, Status} -> ok
     after ?TIMEOUT ->
         ct:fail({connection_not, Status})
     end || Status <- [down, up]],
    ok.

flush_motor() ->
    receive {motor, _} -> flush_motor() after 0 -> ok end.

flush_conn(Conn) ->
    receive {cell_hal_conn, Conn, _} -> flush_conn(Conn) after 0 -> ok end.

await_motor(V) ->
    receive
        {motor, V} -> ok
    after ?TIMEOUT ->
        ct:fail({motor_not, V})
    end.

await_woke(Woken) ->
    receive
        {woke, belt, Woken} -> ok
    after ?TIMEOUT ->
        ct:fail({not_woken, Woken})
    end.

await_state(Task, State) ->
    receive
        {cell_event, #{type := task_state, task := Task, state := State}} -> ok
    after ?TIMEOUT ->
        ct:fail({state_not_reached, Task, State})
    end.

%% Subscribing answers the current status, then every change comes as a message. A
%% change while the HAL takes a subscription is both in its answer and in a message, so
%% an earlier subscription (every case's set-up has one) may have left an `up' in the
%% mailbox that is old news: the connection's messages before this subscription are
%% dropped, its answer says where the connection is now.
await_conn(Conn, Want) ->
    flush_conn(Conn),
    case cell_hal:subscribe_connection(Conn) of
        {ok, Want} ->
            {ok, Want};
        {ok, _} ->
            receive
                {cell_hal_conn, Conn, Want} -> {ok, Want}
            after ?TIMEOUT ->
                ct:fail({connection_not, Want})
            end
    end.

%% One Retry: the belt is commanded on again, the panel it brings wakes the task, and
%% the task goes on holding its product with no second error.
belt_on_again_after_retry(Id, Task) ->
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    await_motor(true),
    await_woke({io, conv, sensor, true}),
    ok = cell_controller:sync(),
    ?assertEqual({ready, processing, active}, cell_task_proc:state(belt)),
    still_holding(Task).
