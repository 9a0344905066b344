%% Units end to end: the picker of seed 001 (cell_picker_*) on the simulated HAL, its
%% cylinders' sensors following their valves after believable delays, under the real
%% controller. Its automatic sequence runs step for step as the seed's; faults,
%% Halt, the emergency stop, lost IO, actions and crashes do what the lifecycle
%% says; a unit and a task run side by side in one cell.
-module(cell_unit_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([picker_runs_as_the_seed_says/1, one_step_per_cycle_runs_the_same_steps/1,
         no_step_after_the_emergency_stop/1, a_cylinder_that_does_not_arrive_is_a_fault/1,
         lost_io_is_a_fault/1, pause_holds_at_once_where_the_picker_waits/1,
         pause_during_a_move_holds_at_the_next_step/1, service_mode_halts/1,
         an_action_from_fault_returns_there/1, a_crashed_unit_waits_for_the_operator/1,
         units_and_tasks_side_by_side/1, specs_name_what_is_wrong/1,
         ready_events_outside_ready_are_a_fault/1, hal_server_away_is_lost_io/1,
         a_watched_point_unavailable_is_a_fault/1, unexpected_message_crashes_a_unit/1]).

-define(WAIT, 10000).
-define(U, picker).
-define(G, picker_io).
-define(STARVED, {ready, idle, starved}).

%% One cycle of the automatic sequence, from the part's arrival to waiting for the
%% next: the seed's order.
-define(CYCLE, [move_right, switch_magnet_on, fetch_vertical_up, move_left,
                switch_magnet_off, release_vertical_up, automatic_end, automatic_begin,
                begin_vertical_up, wait_part_at_end]).

all() ->
    [picker_runs_as_the_seed_says, one_step_per_cycle_runs_the_same_steps,
     no_step_after_the_emergency_stop, a_cylinder_that_does_not_arrive_is_a_fault,
     lost_io_is_a_fault, pause_holds_at_once_where_the_picker_waits,
     pause_during_a_move_holds_at_the_next_step, service_mode_halts,
     an_action_from_fault_returns_there, a_crashed_unit_waits_for_the_operator,
     units_and_tasks_side_by_side, specs_name_what_is_wrong,
     ready_events_outside_ready_are_a_fault, hal_server_away_is_lost_io,
     a_watched_point_unavailable_is_a_fault, unexpected_message_crashes_a_unit].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, crash_log, false),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_testcase(_Case, Config) ->
    Config.

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    _ = cell_log:unsubscribe(),
    [ok = cell_hal:remove_group(G) || G <- cell_hal:groups()],
    [begin ok = cell_hal:remove_connection(C), ok = cell_hal_sim_sup:stop_device(C) end
     || C <- cell_hal:connections()],
    flush(),
    ok.

%% -------------------------------------------------------------------------------------
%% The picker on the simulated PLC
%% -------------------------------------------------------------------------------------

%% The simulated picker: at rest down and left, sensors following their valves.
sim() ->
    ok = cell_hal:add_connection(#{id => plc, driver => cell_hal_sim,
                                   opts => #{poll_ms => 10, reconnect_ms => 50,
                                             timeout_ms => 500}}),
    ok = cell_hal_sim:preset(plc, #{{?G, lift_is_down} => true, {?G, is_left} => true}),
    ok = cell_hal:add_group(#{id => ?G, module => cell_picker_io, connection => plc}),
    {ok, _} = cell_hal:subscribe_connection(plc),
    ok = await_conn(plc, up),
    true = await_value(lift_is_down, true),
    rules([lift_up, lift_down, move_left, move_right, magnet]).

%% The valves move the cylinders (a lift stroke 120 ms, the slide 250 ms); the magnet
%% takes the part off the conveyor.
rules(Valves) ->
    Rule = fun(lift_up) -> {lift_up, [{20, lift_is_down, false}, {120, lift_is_up, true}]};
              (lift_down) -> {lift_down, [{20, lift_is_up, false}, {120, lift_is_down, true}]};
              (move_right) -> {move_right, [{30, is_left, false}, {250, is_right, true}]};
              (move_left) -> {move_left, [{30, is_right, false}, {250, is_left, true}]};
              (magnet) -> {magnet, [{30, part_is_at_end, false}]}
           end,
    lists:foreach(fun(V) ->
                          {Valve, Changes} = Rule(V),
                          ok = cell_hal_sim:on_change(
                                 {?G, Valve},
                                 fun(true) -> [{D, {?G, P}, X} || {D, P, X} <- Changes];
                                    (false) -> []
                                 end)
                  end, Valves).

%% A cell of the picker (and other tasks), watched: every event, the picker's log.
start_cell(Args) ->
    start_cell(Args, []).

start_cell(Args, Others) ->
    sim(),
    Picker = #{id => ?U, module => cell_picker_unit, zone => <<"Picker">>,
               lane => <<"Main">>, io => [?G], args => Args},
    ok = application:set_env(cell, cell_spec, #{tasks => [Picker | Others]}),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe(),
    ok = cell_log:set_level(?U, verbose),
    ok = cell_log:subscribe(),
    await_state(init).

%% Starts the cell and waits until the picker waits for a part; what it said on the
%% way there is dropped.
run() ->
    ok = cell_controller:start(),
    await_state(automatic),
    await_ipc(?STARVED),
    ok = cell_unit:settle(?U),
    drop_events(?U).

part() ->
    ok = cell_hal_sim:set({?G, part_is_at_end}, true).

%% -------------------------------------------------------------------------------------
%% Waiting for the unit, never polling
%% -------------------------------------------------------------------------------------

%% The unit reaches a state: events from before are dropped, then its state now (every
%% event it published before answering is in the mailbox, later ones follow), or the
%% first event announcing it.
await_state(State) ->
    await_state(?U, State).

await_state(Unit, State) ->
    drop_events(Unit),
    case cell_unit:state(Unit) of
        State -> ok;
        _ -> await_event(fun(#{type := task_state, task := T, unit_state := S}) ->
                                 T =:= Unit andalso S =:= State;
                            (_) -> false
                         end)
    end.

await_ipc(Ipc) ->
    drop_events(?U),
    case cell_task_proc:state(?U) of
        Ipc -> ok;
        _ -> await_event(fun(#{type := task_state, task := T, state := S}) ->
                                 T =:= ?U andalso S =:= Ipc;
                            (_) -> false
                         end)
    end.

await_event(Match) ->
    await_event(Match, []).

await_event(Match, Seen) ->
    receive
        {cell_event, E} ->
            case Match(E) of
                true -> E;
                false -> await_event(Match, [maps:with([type, task, unit_state, state], E) | Seen])
            end
    after ?WAIT ->
        ct:fail({no_event, cell_unit:info(?U), lists:reverse(Seen)})
    end.

drop_events(Unit) ->
    receive {cell_event, #{task := Unit}} -> drop_events(Unit)
    after 0 -> ok
    end.

%% The picker's steps logged so far (the log lines of its sequences), oldest first.
steps() ->
    receive
        {cell_log, #{source := <<"picker">>, text := Text}} ->
            case re:run(Text, "step ([a-z_0-9]+)$", [{capture, all_but_first, binary}]) of
                {match, [S]} -> [binary_to_atom(S, utf8) | steps()];
                nomatch -> steps()
            end
    after 0 ->
        []
    end.

await_step(Step) ->
    receive
        {cell_log, #{source := <<"picker">>, text := Text}} ->
            case binary:match(Text, <<"step ", (atom_to_binary(Step, utf8))/binary>>) of
                nomatch -> await_step(Step);
                _ -> ok
            end
    after ?WAIT ->
        ct:fail({no_step, Step, cell_unit:info(?U)})
    end.

await_log(Text) ->
    receive
        {cell_log, #{source := <<"picker">>, text := Text}} -> ok
    after ?WAIT ->
        ct:fail({no_log, Text, cell_unit:info(?U)})
    end.

await_value(Point, V) ->
    {ok, Ref} = cell_hal:watch(?G, Point, {eq, V}),
    receive {cell_hal_watch, Ref, Got} -> Got =:= V
    after ?WAIT -> ct:fail({never, Point, V})
    end.

%% The connection's status: news of it before now are dropped first, so an old
%% message cannot pass for a new one.
await_conn(Conn, Status) ->
    flush_conn(Conn),
    case cell_hal:status(Conn) of
        Status -> ok;
        _ -> receive {cell_hal_conn, Conn, Status} -> ok
             after ?WAIT -> ct:fail({conn, Conn, Status})
             end
    end.

flush_conn(Conn) ->
    receive {cell_hal_conn, Conn, _} -> flush_conn(Conn) after 0 -> ok end.

%% What the HAL wrote to an output (never written: off).
sim_get(Point) ->
    case cell_hal_sim:get({?G, Point}) of
        {ok, V} -> V;
        {error, not_set} -> false
    end.

error_of(Unit) ->
    [A] = [A || #{task := T, kind := error} = A <- cell_alarms:list(), T =:= Unit],
    A.

flush() ->
    receive _ -> flush() after 0 -> ok end.

%% -------------------------------------------------------------------------------------
%% Cases
%% -------------------------------------------------------------------------------------

%% The seed's delays (0.5 s to pick, 0.2 s to set down); two parts.
picker_runs_as_the_seed_says(_Config) ->
    start_cell(#{}),
    ?assertEqual(off, cell_task_proc:state(?U)),              %% Init: not referenced
    run(),
    %% GoHome lifted the picker and left it on the left; Automatic lifted (already up)
    %% and waits for a part: STARVED.
    ?assert(sim_get(lift_up)),
    ?assertNot(sim_get(magnet)),
    _ = steps(),
    part(),
    %% STARVED → ACTIVE (a part) → EXECUTING (picked) → ACTIVE (set down) → STARVED,
    %% each with the seed's event.
    ?assertEqual([equipment_unstarved, {ready, processing, active},
                  item_work_start, {ready, processing, executing},
                  item_work_complete, {ready, processing, active},
                  equipment_starved, ?STARVED], cycle_events([])),
    ?assertEqual(?CYCLE, steps()),
    ?assertNot(sim_get(magnet)),
    ?assert(await_value(part_is_at_end, false)),
    %% A second part, and the cell stops: Stop lifts the picker, then it is Stopped.
    part(),
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= item_work_complete;
                       (_) -> false
                    end),
    await_ipc(?STARVED),
    ?assertEqual(?CYCLE, steps()),
    ok = cell_controller:stop(),
    await_state(stopped),
    ?assertEqual(off, cell_task_proc:state(?U)),
    %% The controller works the cell's state out from the task's event: it follows.
    await_cell_state(off),
    ?assertEqual([stop_lift_up, stop_done], steps()).

await_cell_state(State) ->
    case cell_controller:state() of
        State -> ok;
        _ -> _ = await_event(fun(#{type := cell_state, state := S}) -> S =:= State;
                                (_) -> false
                             end),
             ok
    end.

%% The picker's IPC-2541 states and events until it is STARVED again.
cycle_events(Acc) ->
    receive
        {cell_event, #{type := task_state, task := ?U, state := S, from := F}} when S =/= F ->
            case S of
                ?STARVED -> lists:reverse([S | Acc]);
                _ -> cycle_events([S | Acc])
            end;
        {cell_event, #{type := task_state}} ->
            cycle_events(Acc);
        {cell_event, #{type := T, task := ?U}} when T =/= product_saved ->
            cycle_events([T | Acc]);
        {cell_event, _} ->
            cycle_events(Acc)
    after ?WAIT ->
        ct:fail({not_starved_again, lists:reverse(Acc)})
    end.

one_step_per_cycle_runs_the_same_steps(_Config) ->
    start_cell(#{mode => one, pick_delay_ms => 50, release_delay_ms => 50}),
    run(),
    _ = steps(),
    part(),
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= item_work_complete;
                       (_) -> false
                    end),
    await_ipc(?STARVED),
    ?assertEqual(?CYCLE, steps()),
    ?assertMatch(#{sequence := #{sequences := [#{mode := one}]}}, cell_unit:info(?U)).

%% The emergency stop in the middle of a move: everything stops at once, the slide's
%% valves are switched off, not one step more; Start afterwards references again.
no_step_after_the_emergency_stop(_Config) ->
    %% Here the lift's valve is closed too when the emergency stop comes.
    start_cell(#{pick_delay_ms => 100, release_delay_ms => 50,
                 safe_outputs => [{lift_up, false}, {{?G, lift_down}, false}]}),
    run(),
    part(),
    await_step(move_right),
    ok = cell_controller:estop(true),
    await_state(stopped),
    ?assertEqual(off, cell_task_proc:state(?U)),
    ?assertNot(sim_get(move_right)),
    ?assertNot(sim_get(move_left)),
    ?assertNot(sim_get(lift_up)),
    ?assertNot(sim_get(lift_down)),
    %% The slide's sensor arrives after all: nothing follows from it.
    true = await_value(is_right, true),
    ok = cell_unit:settle(?U),
    ?assertEqual([], steps()),
    ?assertEqual({error, estop_active}, cell_unit:go_home(?U)),
    %% The part is taken away by hand; the operator releases and starts.
    ok = cell_hal_sim:set({?G, part_is_at_end}, false),
    true = await_value(part_is_at_end, false),
    ok = cell_controller:estop(false),
    ?assertEqual(off, cell_task_proc:state(?U)),
    run(),
    ?assertEqual([home_lift_up, home_move_left, home_done, automatic_begin, begin_vertical_up,
                  wait_part_at_end], steps()).

%% A lift whose sensor never comes: the GoHome sequence is aborted into FaultReaction
%% with an error that says what and where; Reset references the unit again.
a_cylinder_that_does_not_arrive_is_a_fault(_Config) ->
    start_cell(#{lift_timeout_ms => 300}),
    ok = cell_hal_sim:clear_rules(plc),
    rules([lift_down, move_left, move_right, magnet]),          %% lift_is_up never comes
    ok = cell_controller:start(),
    await_state(fault),
    ?assertEqual(down, cell_task_proc:state(?U)),
    #{caption := Caption, description := Text, solutions := Solutions, id := Id} = error_of(?U),
    ?assertEqual(<<"vertical_lift did not reach up within 300 ms (sensor picker_io.lift_is_up "
                   "stayed off)">>, Caption),
    ?assertMatch({match, _}, re:run(Text, "sequence cell_picker_sequences, step home_lift_up")),
    ?assertEqual([reset], Solutions),
    ?assertMatch(#{unit_state := fault, down := {error, Id, fault}}, cell_unit:info(?U)),
    %% FaultReaction stopped the slide without waiting for anything.
    ?assertNot(sim_get(move_left)),
    ?assertNot(sim_get(move_right)),
    %% The sensor is fixed; the operator resets: GoHome, Idle, Automatic.
    ok = cell_hal_sim:set({?G, lift_is_up}, true),
    true = await_value(lift_is_up, true),
    ok = cell_alarms:answer(Id, reset, <<"ct">>),
    await_state(automatic),
    await_ipc(?STARVED),
    ?assertEqual([], [A || #{task := ?U} = A <- cell_alarms:list()]).

%% The PLC's link drops while the picker works: a fault (its outputs cannot be made
%% safe either, so FaultReaction ends early in Fault).
lost_io_is_a_fault(_Config) ->
    start_cell(#{}),
    run(),
    ok = cell_hal_sim:link(plc, down),
    await_state(fault),
    #{caption := Caption, id := Id} = error_of(?U),
    ?assertEqual(<<"the connection plc to the unit's IO was lost">>, Caption),
    ok = cell_hal_sim:link(plc, up),
    ok = await_conn(plc, up),
    ok = cell_alarms:answer(Id, reset, <<"ct">>),
    await_state(automatic),
    await_ipc(?STARVED).

%% The input the picker waits for becomes unreadable (a Modbus PLC refusing its
%% address): the wait ends in a fault naming the point and why, never waits for ever;
%% once the point reads again, Reset takes the picker back to work.
a_watched_point_unavailable_is_a_fault(_Config) ->
    start_cell(#{}),
    run(),
    Why = <<"the PLC refuses this address (illegal data address, Modbus exception 2)">>,
    true = cell_hal_store:set_fault({?G, part_is_at_end}, Why),
    await_state(fault),
    #{caption := Caption, id := Id} = error_of(?U),
    ?assertEqual(<<"IO point picker_io.part_is_at_end cannot be read: ", Why/binary>>, Caption),
    true = cell_hal_store:set_fault({?G, part_is_at_end}, undefined),
    ok = cell_alarms:answer(Id, reset, <<"ct">>),
    await_state(automatic),
    await_ipc(?STARVED).

%% Waiting for a part only watches an input: Pause holds there at once (DOWN), Start
%% goes on waiting.
pause_holds_at_once_where_the_picker_waits(_Config) ->
    start_cell(#{pick_delay_ms => 50, release_delay_ms => 50}),
    run(),
    ok = cell_controller:pause(),
    await_ipc(down),
    ?assertMatch(#{unit_state := automatic, halt := true, down := {paused, pause},
                   sequence := #{held := true, sequences := [#{step := wait_part_at_end}]}},
                 cell_unit:info(?U)),
    %% The panel's view of it (`/api/tasks/picker').
    ?assertMatch(#{<<"state">> := <<"automatic">>, <<"halt">> := true, <<"fault">> := null,
                   <<"step">> := #{<<"sequence">> := <<"cell_picker_automatic">>,
                                   <<"step">> := <<"wait_part_at_end">>},
                   <<"sequences">> := [#{<<"step">> := <<"wait_part_at_end">>}]},
                 cell_web_json:unit(cell_unit:info(?U))),
    %% A part comes while paused: nothing moves.
    part(),
    true = await_value(part_is_at_end, true),
    ok = cell_unit:settle(?U),
    ?assertNot(sim_get(move_right)),
    ok = cell_controller:start(),
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= item_work_complete;
                       (_) -> false
                    end),
    await_ipc(?STARVED).

%% Paused while the cylinders move: the move finishes, the sequence holds before its
%% next step (the magnet is not switched on), and goes on at Start.
pause_during_a_move_holds_at_the_next_step(_Config) ->
    start_cell(#{pick_delay_ms => 50, release_delay_ms => 50}),
    run(),
    _ = steps(),
    part(),
    await_step(move_right),
    ok = cell_controller:pause(),
    await_ipc(down),
    ?assertMatch(#{sequence := #{held := true, sequences := [#{step := switch_magnet_on}]}},
                 cell_unit:info(?U)),
    ?assert(sim_get(move_right)),
    ?assertNot(sim_get(magnet)),
    ok = cell_controller:start(),
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= item_work_complete;
                       (_) -> false
                    end),
    await_ipc(?STARVED),
    ?assertEqual(?CYCLE -- [move_right], steps()).

service_mode_halts(_Config) ->
    start_cell(#{pick_delay_ms => 50, release_delay_ms => 50}),
    run(),
    ok = cell_controller:service_mode(true),
    await_ipc(down),
    ?assertMatch(#{service_mode := true, down := {paused, service}}, cell_unit:info(?U)),
    ok = cell_controller:start(),
    await_ipc(?STARVED),
    ?assertMatch(#{service_mode := true, halt := false}, cell_unit:info(?U)).

%% A fault with the part on the magnet; the service action releases it and the unit is
%% back in Fault, its error still waiting for the operator.
an_action_from_fault_returns_there(_Config) ->
    start_cell(#{pick_delay_ms => 2000}),
    run(),
    part(),
    await_step(switch_magnet_on),
    ?assert(await_value(magnet, true)),
    ok = cell_unit:abort(?U, <<"light curtain interrupted">>),
    await_state(fault),
    #{caption := <<"light curtain interrupted">>} = error_of(?U),
    ?assert(sim_get(magnet)),
    ?assertEqual({error, {not_allowed, start, fault}}, cell_unit:start(?U)),
    drop_events(?U),
    ok = cell_unit:action(?U, release_part),
    E = await_event(fun(#{type := task_state, task := ?U, unit_from := F, unit_state := S}) ->
                            F =/= S;
                       (_) -> false
                    end),
    ?assertMatch(#{unit_from := fault, unit_state := {action, release_part, fault},
                   state := setup}, E),
    await_state(fault),
    ?assertNot(sim_get(magnet)),
    #{caption := <<"light curtain interrupted">>} = error_of(?U).

%% The unit's process dies: it comes back, its outputs made safe, in Init with an
%% error naming the crash; Reset references it and it goes back to work.
a_crashed_unit_waits_for_the_operator(_Config) ->
    start_cell(#{pick_delay_ms => 2000}),
    run(),
    part(),
    await_step(move_right),
    Old = cell_unit:whereis(?U),
    exit(Old, kill),
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= task_crashed; (_) -> false end),
    await_state(init),
    ?assertNotEqual(Old, cell_unit:whereis(?U)),
    ?assertNot(sim_get(move_right)),                       %% the slide's safe position
    #{local_id := <<"crashed">>, solutions := [reset], id := Id} = error_of(?U),
    ok = cell_unit:settle(?U),
    ?assertEqual(init, cell_unit:state(?U)),                %% nothing moves by itself
    ok = cell_alarms:answer(Id, reset, <<"ct">>),
    await_state(automatic).

%% A message the unit's engine does not know crashes it: it comes back in Init with the
%% crash, in words, for the operator. A reply no sequence waits for is dropped.
unexpected_message_crashes_a_unit(_Config) ->
    start_cell(#{}),
    run(),
    Old = cell_unit:whereis(?U),
    Old ! {make_ref(), late},
    ok = cell_unit:settle(?U),
    ?assertEqual(Old, cell_unit:whereis(?U)),
    Old ! {no_such_message, 1},
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= task_crashed; (_) -> false end),
    await_state(init),
    ?assertNotEqual(Old, cell_unit:whereis(?U)),
    #{local_id := <<"crashed">>, description := Text} = error_of(?U),
    ?assertNotEqual(nomatch, binary:match(Text, <<"does not expect">>)).

%% The HAL's server is away (it restarts) as the unit starts again after a crash: the
%% unit does not crash again; its connection, which it could not subscribe to, is lost
%% IO for it, so Reset stops it on that fault; woken by the HAL when its server is back,
%% it follows the connection again, and Reset then takes it back to work.
hal_server_away_is_lost_io(_Config) ->
    start_cell(#{}),
    run(),
    ok = supervisor:terminate_child(cell_hal_sup, cell_hal_server),
    Old = cell_unit:whereis(?U),
    exit(Old, kill),
    _ = await_event(fun(#{type := T, task := ?U}) -> T =:= task_crashed; (_) -> false end),
    await_state(init),
    New = cell_unit:whereis(?U),
    ?assertNotEqual(Old, New),
    #{local_id := <<"crashed">>, id := Crashed} = error_of(?U),
    ok = cell_alarms:answer(Crashed, reset, <<"ct">>),
    await_state(fault),
    #{caption := Caption, id := Lost} = error_of(?U),
    ?assertEqual(<<"the connection plc to the unit's IO was lost">>, Caption),
    {ok, _} = supervisor:restart_child(cell_hal_sup, cell_hal_server),
    await_log(<<"the HAL is back: connection plc followed again (up)">>),
    ok = cell_alarms:answer(Lost, reset, <<"ct">>),
    await_state(automatic),
    await_ipc(?STARVED),
    %% Followed indeed: the connection lost now is a fault again.
    ok = cell_hal_sim:link(plc, down),
    await_state(fault),
    #{id := Fault} = error_of(?U),
    ok = cell_hal_sim:link(plc, up),
    ok = await_conn(plc, up),
    ok = cell_alarms:answer(Fault, reset, <<"ct">>),
    await_state(automatic),
    await_ipc(?STARVED),
    %% The HAL's server killed while the unit works: its workers restart with it, the
    %% connection goes down and up; the unit stops on the fault, and Reset takes it
    %% back to work. The same unit all along.
    {ok, _} = cell_hal:subscribe_connection(plc),
    exit(whereis(cell_hal_server), kill),
    await_state(fault),
    #{caption := Caption, id := Restarted} = error_of(?U),
    ok = await_conn(plc, up),
    ok = cell_alarms:answer(Restarted, reset, <<"ct">>),
    await_state(automatic),
    await_ipc(?STARVED),
    ?assertEqual(New, cell_unit:whereis(?U)).

%% A unit and a device task in one cell: the controller starts, pauses and stops both;
%% the cell state is the higher of theirs; the panel's calls answer for both.
units_and_tasks_side_by_side(_Config) ->
    Tab = ets:new(tasks, [public]),
    Task = cell_test_task:spec(t1, Tab, self()),
    start_cell(#{}, [Task]),
    ?assertMatch([#{id := picker, kind := unit}, #{id := t1}], cell_controller:tasks()),
    ok = cell_controller:start(),
    await_state(automatic),
    ok = cell_controller:sync(),
    ?assertEqual(?STARVED, cell_task_proc:state(t1)),
    ?assertEqual(?STARVED, cell_task_proc:state(?U)),
    ?assertEqual(?STARVED, cell_controller:state()),
    #{state := ?STARVED, request := start, down := undefined, product := undefined} =
        cell_task_proc:info(?U),
    ok = cell_controller:pause(),
    await_ipc(down),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_controller:state()),
    ok = cell_controller:stop(),
    await_state(stopped),
    ok = cell_controller:sync(),
    ?assertEqual(off, cell_task_proc:state(t1)),
    ?assertEqual(off, cell_controller:state()).

%% The cell spec takes units beside tasks and checks a unit's declaration at the door.
specs_name_what_is_wrong(_Config) ->
    Unit = fun(Decl) -> #{id => u, module => cell_test_decl_unit, zone => <<"Z">>,
                          lane => <<"L">>, args => #{decl => Decl}} end,
    Check = fun(Decl) -> cell_spec:validate(#{tasks => [Unit(Decl)]}) end,
    Seq = {cell_test_seq, #{}},
    ?assertMatch({ok, #{tasks := [#{id := u, io := [], args := #{decl := #{}}}]}}, Check(#{})),
    ?assertEqual({error, {bad_task, u, {bad_unit, colour, unknown_key}}}, Check(#{colour => red})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {sequence, init}, _}}},
                 Check(#{sequences => #{init => Seq}})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {sequence, {user, x}}, _}}},
                 Check(#{user_states => [x]})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {sequence, {action, y}}, _}}},
                 Check(#{sequences => #{{action, y} => Seq}})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {sequence, automatic}, _}}},
                 Check(#{sequences => #{automatic => lists}})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {sequence, automatic}, {mode, fast}}}},
                 Check(#{sequences => #{automatic => {cell_test_seq, #{mode => fast}}}})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {actuator, c}, _}}},
                 Check(#{actuators => #{c => {cell_cylinder, #{up => #{sensor => a}}}}})),
    ?assertMatch({error, {bad_task, u, {bad_unit, {actuator, c}, _}}},
                 Check(#{actuators => #{c => {lists, #{}}}})),
    ?assertEqual({error, {bad_task, u, {bad_unit, idle, busy}}}, Check(#{idle => busy})),
    ?assertMatch({error, {bad_task, u, {bad_unit, user_states, _}}},
                 Check(#{user_states => [x, x]})),
    ?assertEqual({error, {bad_link, l, {unit, u}}},
                 cell_spec:validate(#{tasks => [Unit(#{}), #{id => t, module => cell_test_task,
                                                             zone => <<"T">>, lane => <<"L">>}],
                                      links => [#{id => l, from => t, to => u}]})).

%% A user state reports the READY sub-state its sequence says; the same report from
%% GoHome, which is not READY, is a fault that says so.
ready_events_outside_ready_are_a_fault(_Config) ->
    Ref = make_ref(),
    Wait = fun(S) -> cell_sequence:await(S, {reply, Ref}, done) end,
    Decl = #{user_states => [calibrate],
             sequences =>
                 #{go_home => {cell_test_fun_seq,
                               #{first => a, steps => #{a => fun(S) -> cell_sequence:done(S) end}}},
                   {user, calibrate} =>
                       {cell_test_fun_seq,
                        #{first => a,
                          steps => #{a => fun(S) -> Wait(cell_sequence:work_start(S)) end,
                                     done => fun(S) -> cell_sequence:done(S) end}}}}},
    Unit = #{id => v, module => cell_test_decl_unit, zone => <<"V">>, lane => <<"L">>,
             args => #{decl => Decl}},
    ok = application:set_env(cell, cell_spec, #{tasks => [Unit]}),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe(),
    ok = cell_controller:start(),
    await_state(v, idle),
    ok = cell_unit:user_state(v, calibrate),
    ok = cell_unit:settle(v),
    ?assertEqual({ready, processing, executing}, cell_task_proc:state(v)),
    cell_unit:whereis(v) ! {Ref, ok},
    await_state(v, idle),
    %% GoHome reporting EXECUTING.
    ok = application:stop(cell),
    Bad = Decl#{sequences => #{go_home => {cell_test_fun_seq,
                                           #{first => a,
                                             steps => #{a => fun(S) -> cell_sequence:done(
                                                                         cell_sequence:work_start(S))
                                                             end}}}}},
    ok = application:set_env(cell, cell_spec,
                             #{tasks => [Unit#{args => #{decl => Bad#{user_states => []}}}]}),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe(),
    ok = cell_controller:start(),
    await_state(v, fault),
    #{caption := Caption} = error_of(v),
    ?assertEqual(<<"the sequence reported item_work_start in go_home; only Automatic and "
                   "user states can">>, Caption).
