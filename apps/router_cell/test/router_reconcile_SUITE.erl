%% Restart reconciliation of the router's tasks against the simulated machine: each
%% task is killed in each phase of its table while the line runs, restarts, and is
%% answered as an operator standing at the machine would (the simulated world says
%% where each panel physically is); the line must go on, and once stopped every serial
%% a task holds is one the machine physically has, and the other way round.
%%
%% A phase is reached by tracing the task's calls of cell_handover:phase/2 (a message
%% per phase entered): no waiting on time anywhere, every wait has a deadline.
-module(router_reconcile_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([loading_killed_in_every_phase/1, work_killed_in_every_phase/1,
         lower_killed_in_every_phase/1, upper_killed_in_every_phase/1,
         unloading_killed_in_every_phase/1, every_task_killed_at_once/1,
         task_tree_restarted/1, unloading_killed_while_the_upper_puts_down/1,
         panel_forgotten_in_the_fixture/1, plc_killed_during_a_routing_move/1,
         plc_killed_during_a_clamp_move/1, held_twice_answered_at_the_machine/1,
         held_twice_answered_wrong_the_loading_offer_taken_in/1,
         upper_lost_its_modules_the_next_panel_in_the_nest/1,
         physics_stopped_before_the_hal_keeps_its_world/1]).

-define(DEADLINE_MS, 60000).
%% How long the line may take to go on after its PLC was killed: a restart of the PLC,
%% a reconnect, one Retry, a panel routed and two products out.
-define(PLC_BACK_MS, 30000).
-define(EVENTS, [item_transfer_out, alarm_raised, cell_state, task_crashed, product_saved]).

all() ->
    [unloading_killed_in_every_phase, upper_killed_in_every_phase,
     loading_killed_in_every_phase, work_killed_in_every_phase,
     lower_killed_in_every_phase, every_task_killed_at_once, task_tree_restarted,
     unloading_killed_while_the_upper_puts_down, panel_forgotten_in_the_fixture,
     plc_killed_during_a_routing_move, plc_killed_during_a_clamp_move,
     held_twice_answered_at_the_machine, held_twice_answered_wrong_the_loading_offer_taken_in,
     upper_lost_its_modules_the_next_panel_in_the_nest,
     physics_stopped_before_the_hal_keeps_its_world].

init_per_testcase(Case, Config) ->
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = router_test_settings:write(
           Root, #{machine => #{dual_lane => false},
                   router_sim => maps:merge(#{time_scale => 0.02, arrival_ms => 0,
                                              product_lost_rate => 0.0, jam_rate => 0.0, no_read_rate => 0.0,
                                              magazine_low_s => 0}, sim_faults(Case)),
                   %% The inspection: router_inspect_SUITE's.
                   router => #{hal_poll_ms => 5, transfer_timeout_ms => 3000,
                               motion_timeout_ms => 3000, inspection => false}}),
    _ = [application:load(A) || A <- [cell_base, cell_hal, cell, router_cell]],
    ok = application:set_env(cell_base, root, Root),
    ok = application:unset_env(cell, cell_spec),
    ok = application:set_env(cell, cell_module, router_cell),
    {ok, _} = application:ensure_all_started(router_cell),
    {ok, up} = await_connection(),
    ok = router_sim:ready(?DEADLINE_MS),
    {module, cell_handover} = code:ensure_loaded(cell_handover),
    1 = erlang:trace_pattern({cell_handover, phase, 2}, true, [local]),
    Config.

end_per_testcase(_Case, _Config) ->
    _ = erlang:trace_pattern({cell_handover, phase, 2}, false, [local]),
    _ = application:unset_env(cell, shutdown_wait_ms),
    _ = application:stop(router_cell),
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok = cell_hal_sim_sup:stop_device(router_plc),
    ok.

%% The modules slip in the gripper on every move and are not seated again while a
%% case runs (an hour of the machine's time).
sim_faults(upper_lost_its_modules_the_next_panel_in_the_nest) ->
    #{product_lost_rate => 1.0, reseat_ms => 3600000};
sim_faults(_Case) ->
    #{}.

%% -------------------------------------------------------------------------------------

loading_killed_in_every_phase(_Config) ->
    killed_in_phases(loading_front, [idle, intake, reading, full, offered, leaving, released]).

work_killed_in_every_phase(_Config) ->
    killed_in_phases(work_front, [idle, take, moving_in, arriving, clamping, offered,
                                  released, emptying, unclamping, ejecting]).

lower_killed_in_every_phase(_Config) ->
    killed_in_phases(lower, [idle, taking, routing, routed, offered, released]).

upper_killed_in_every_phase(_Config) ->
    killed_in_phases(upper, [idle, taking, to_nest, gripping, carrying, full, offered,
                             placing, released]).

unloading_killed_in_every_phase(_Config) ->
    killed_in_phases(unloading_front, [idle, receiving, landing, conveying, waiting, leaving]).

%% The unloading segment killed while the upper robot opens its gripper over it: the
%% modules land on the conveyor with no transfer to take them in. The robot's gripper
%% sensors say where they are (let go of over the conveyor): they are offered again as
%% they lie, the restarted segment takes them from its entry, and nobody is asked
%% where they are. The physics waits (suspended) from the robot's offer until the
%% segment has restarted, so the gripper opens only then, whatever the machine's load.
unloading_killed_while_the_upper_puts_down(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(1),
    Upper = cell_task_proc:whereis(upper),
    1 = erlang:trace(Upper, true, [call, {tracer, self()}]),
    ok = await_phase(Upper, offered, deadline()),
    ok = sys:suspend(router_sim),
    ok = await_phase(Upper, placing, deadline()),
    Serial = serial(upper),
    Unloading = cell_task_proc:whereis(unloading_front),
    exit(Unloading, kill),
    ct:log("unloading killed while the upper robot puts ~ts down", [Serial]),
    ok = await_restart([unloading_front], deadline()),
    ok = sys:resume(router_sim),
    1 = erlang:trace(Upper, false, [call]),
    flush_trace(Upper),
    %% Asked nothing but the restart itself; the modules left, not marked failed.
    {Asked, Out} = collect(3, [], [], deadline()),
    ?assertEqual([], [A || A <- Asked, A =/= <<"crashed">>]),
    ?assert(lists:member(Serial, Out)),
    ok = stop_cell(),
    ok = cell_stats:flush(),
    {ok, #{status := out, failed := false}} = cell_stats:product(Serial),
    assert_books_agree().

%% The upper robot's modules slip in its gripper on the way to the unloading conveyor
%% (its sensor loses them; they are still in it), "Product lost"; meanwhile the frame
%% leaves the fixture and the next panel comes in and is routed. The robot is killed;
%% restarted, it finds its gripper sensor empty and asks where the modules are; the
%% operator, who sees them in the gripper, answers Retry. The robot must not put them
%% down over the unloading conveyor nor grip the next panel's modules in the nest as
%% its own: the next panel's record is the routing robot's, so the Retry is refused
%% with the reason, and the gripper still holds the robot's own product.
upper_lost_its_modules_the_next_panel_in_the_nest(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    Lower = cell_task_proc:whereis(lower),
    1 = erlang:trace(Lower, true, [call, {tracer, self()}]),
    ok = cell_controller:start(<<"suite">>),
    #{local_id := <<"lost">>} = await_alarm([<<"lost">>], upper, deadline()),
    Mine = serial(upper),
    %% The next panel routed and offered to the upper robot, which does not take it.
    Next = await_offered_other(Lower, Mine, deadline()),
    1 = erlang:trace(Lower, false, [call]),
    flush_trace(Lower),
    ct:log("~ts lost in the gripper, ~ts routed in the fixture; the machine: ~tp",
           [Mine, Next, router_sim:world()]),
    ?assertMatch(#{gripper := Mine}, router_sim:world()),
    exit(cell_task_proc:whereis(upper), kill),
    ok = await_restart([upper], deadline()),
    #{id := Id} = await_alarm([<<"where">>], upper, deadline()),
    ok = cell_alarms:answer(Id, retry, <<"suite">>),
    %% Asked again, saying why; nothing moved.
    #{local_id := Local, description := Text} =
        await_alarm([<<"where">>, <<"lost">>, <<"not_gripped">>], upper, deadline()),
    World = router_sim:world(),
    ct:log("after Retry: ~ts ~ts; the machine: ~tp", [Local, Text, World]),
    ?assertEqual(<<"where">>, Local),
    ?assertMatch({match, _}, re:run(Text, <<"RETRY was refused">>)),
    ?assertMatch(#{gripper := Mine}, World),
    ?assertEqual(empty, slot(World, unloading, Mine)),
    ?assertEqual({Next, full}, slot(World, work, Next)),
    ?assertEqual(Mine, serial(upper)),
    ?assertEqual(Next, serial(lower)).

%% The serial of the product the task offers when it enters phase `offered' with a
%% product other than `Not'.
await_offered_other(Pid, Not, Deadline) ->
    receive
        {trace, Pid, call, {cell_handover, phase, [T, offered]}} ->
            case cell_task:product(T) of
                #{serial := S} when S =/= Not -> S;
                _ -> await_offered_other(Pid, Not, Deadline)
            end;
        {trace, Pid, call, _} ->
            await_offered_other(Pid, Not, Deadline);
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            await_offered_other(Pid, Not, Deadline);
        {cell_event, _} ->
            await_offered_other(Pid, Not, Deadline)
    after left(Deadline) ->
        ct:fail({never_offered, Not, cell_controller:tasks(), cell_alarms:list()})
    end.

%% The work segment killed once the panel lies clamped in its fixture: its record and
%% its fixture's sensor agree, so it goes on by itself, asked nothing. Then an operator
%% who did not look at the machine says the panel is not there (the Reset a double
%% holding's error offers): the record of the panel is gone, the panel is not. The
%% segment does not wait for ever for a nest nobody empties: it asks for the panel to
%% be taken out of the machine; the operator's hand takes it out, Retry, and the line
%% goes on. The machine's ledger has the panel as removed by the operator.
panel_forgotten_in_the_fixture(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(1),
    Work = cell_task_proc:whereis(work_front),
    1 = erlang:trace(Work, true, [call, {tracer, self()}]),
    ok = await_phase(Work, clamping, deadline()),
    Serial = serial(work_front),
    exit(Work, kill),
    ct:log("work_front killed with ~ts in its fixture; the machine: ~tp",
           [Serial, router_sim:world()]),
    flush_trace(Work),
    ok = await_restart([work_front], deadline()),
    ok = cell_task_proc:sync(work_front),
    %% What the task raised as it booted (sent before the sync's answer) is listed.
    ok = cell_alarms:sync(),
    ?assertEqual([], [A || #{task := work_front, kind := error} = A <- cell_alarms:list()]),
    ?assertMatch({ok, #{kind := warning}}, cell_alarms:get(<<"work_front:crash_resumed">>)),
    cell_task_proc:whereis(work_front) ! {cell_registry, forget, Serial, <<"suite">>},
    #{id := Id, description := Text} = await_alarm([<<"unheld">>], work_front, deadline()),
    ?assertMatch({match, _}, re:run(Text, "work fixture of lane front and no record holds it")),
    ?assertMatch({Serial, full}, maps:get(front, maps:get(work, router_sim:world()))),
    ?assertEqual({ok, Serial}, router_sim:take_out(work, front)),
    %% The operator selects Retry once the fixture's sensor (as the HAL reads it) shows
    %% the fixture empty: asked nothing more about the fixture after that.
    {ok, Ref} = cell_hal:watch(router_cell:group(work, front), panel_in_position, {eq, false}),
    receive {cell_hal_watch, Ref, false} -> ok
    after ?DEADLINE_MS -> ct:fail(fixture_still_seen_full)
    end,
    ok = cell_alarms:answer(Id, retry, <<"suite">>),
    {Asked, _Out} = collect(2, [], [], deadline()),
    ?assertEqual([], [A || A <- Asked, A =:= <<"unheld">>]),
    ok = stop_cell(),
    W = router_sim:world(),
    ?assertEqual([removed], [How || {S, How} <- maps:get(ledger, W), S =:= Serial]),
    ?assertEqual(1, maps:get(removed, maps:get(counters, W))),
    assert_books_agree().

%% The simulated PLC killed the moment the routing robot's bit is commanded down into
%% the panel, between two paths of its axes:
%% the PLC comes back at once with its memory and the machine's physics still attached,
%% every task is told its IO connection was lost (one Retry each, given once the
%% connection is back, as an operator who sees the PLC up again; the cell's own error
%% for the lost connection the same), the robot finishes
%% the panel's routing and the line goes on; nothing else is asked (no "did not finish
%% in time").
plc_killed_during_a_routing_move(_Config) ->
    plc_killed_during({lower_io, plunge}, fun(V) -> V =:= true end, lower, routed).

%% The same the moment the fixture's clamps are commanded closed on a panel (their
%% unit, ordered by the work segment, drives the valve of clamp A): the unit stops on
%% its lost IO too, answered Retry as the tasks' are, and closes the clamps again.
plc_killed_during_a_clamp_move(_Config) ->
    plc_killed_during({router_cell:group(clamps, front), a_close}, fun(V) -> V =:= true end,
                      work_front, offered).

%% Kills the simulated PLC from within (a rule of its own, after the physics' rule on
%% the same output) the first time `Key' is written a value `Moving' holds for, so the
%% kill falls between the command and the sensors' answer; then waits (at most
%% ?PLC_BACK_MS) for `Task' to enter `Done' and for two more products to leave.
plc_killed_during(Key, Moving, Task, Done) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(1),
    {ok, up} = await_connection(),
    Self = self(),
    Once = atomics:new(1, []),
    ok = cell_hal_sim:on_change(
           Key, fun(V) ->
                        case Moving(V) andalso atomics:compare_exchange(Once, 1, 0, 1) =:= ok of
                            true -> Self ! {plc_killed, self(), V}, exit(self(), kill);
                            false -> ok
                        end,
                        []
                end),
    Pid = cell_task_proc:whereis(Task),
    Old = receive {plc_killed, P, V} -> ct:log("the PLC killed as ~p took ~p", [Key, V]), P
          after ?DEADLINE_MS -> ct:fail({never_written, Key})
          end,
    1 = erlang:trace(Pid, true, [call, {tracer, self()}]),
    Deadline = erlang:monotonic_time(millisecond) + ?PLC_BACK_MS,
    Asked = after_plc_kill(Pid, Done, #{conn => up, done => false, asked => [], due => [],
                                        out => 0}, Deadline),
    1 = erlang:trace(Pid, false, [call]),
    flush_trace(Pid),
    New = cell_hal_sim_device:whereis(router_plc),
    ?assert(is_pid(New) andalso New =/= Old),
    %% One Retry at most per task, for the lost connection only.
    ct:log("asked after the kill: ~tp", [Asked]),
    ?assertEqual([], [A || {_, L} = A <- Asked, L =/= <<"io">>,
                           L =/= <<"connection.router_plc">>]),
    Tasks = [T || {T, _} <- Asked],
    ?assertEqual(lists:usort(Tasks), lists:sort(Tasks)),
    ok = stop_cell(),
    assert_books_agree().

%% Until the task entered `Done' after the kill and two products left: the connection
%% seen down and up again, each error noted (a task's lost IO and the cell's lost
%% connection answered Retry once the connection is back; any other question fails
%% the test at the end, answered as an operator would meanwhile).
after_plc_kill(_Pid, _Done, #{conn := up, done := true, out := Out, due := [],
                               asked := Asked}, _Deadline) when Out >= 2 ->
    lists:reverse(Asked);
after_plc_kill(Pid, Done, #{asked := Asked, due := Due} = S, Deadline) ->
    receive
        {cell_hal_conn, router_plc, down} ->
            after_plc_kill(Pid, Done, S#{conn := down}, Deadline);
        {cell_hal_conn, router_plc, up} ->
            %% Those the cell withdrew by itself meanwhile are no longer there to answer.
            _ = [cell_alarms:answer(Id, retry, <<"suite">>) || Id <- Due],
            after_plc_kill(Pid, Done, S#{conn := up, due := []}, Deadline);
        {trace, Pid, call, {cell_handover, phase, [_, Done]}} ->
            after_plc_kill(Pid, Done, S#{done := true}, Deadline);
        {trace, Pid, call, _} ->
            after_plc_kill(Pid, Done, S, Deadline);
        {cell_event, #{type := item_transfer_out, task := unloading_front}} ->
            after_plc_kill(Pid, Done, S#{out := maps:get(out, S) + 1}, Deadline);
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, id := Id,
                                                         local_id := L, task := T}}}
          when L =:= <<"io">>; L =:= <<"connection.router_plc">> ->
            S1 = S#{asked := [{T, L} | Asked]},
            case S of
                #{conn := up} ->
                    _ = cell_alarms:answer(Id, retry, <<"suite">>),
                    after_plc_kill(Pid, Done, S1, Deadline);
                #{conn := down} ->
                    after_plc_kill(Pid, Done, S1#{due := [Id | Due]}, Deadline)
            end;
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, local_id := L,
                                                         task := T} = A}} ->
            ok = answer(A),
            after_plc_kill(Pid, Done, S#{asked := [{T, L} | Asked]}, Deadline);
        {cell_event, _} ->
            after_plc_kill(Pid, Done, S, Deadline)
    after left(Deadline) ->
        ct:fail({no_recovery_in_time, S, cell_controller:tasks(), cell_alarms:list(),
                 router_sim:world()})
    end.

%% The wedge of a chaos run: a node kill left the panel in the work fixture held by the
%% work segment and by the loading segment at once (a copy in the loading segment's
%% file as new as the work segment's record). The cell's guard raises its error on
%% both. The operator at the machine finds the panel in the work fixture: Reset on the
%% loading segment's error, none on the work segment's (it goes with the other). The
%% loading segment forgets it, the work segment goes on with it, and it leaves the
%% cell.
held_twice_answered_at_the_machine(_Config) ->
    Serial = held_in_the_fixture_and_at_loading(),
    {Asked, Refused} = settle_held_twice(Serial, loading_front, #{}),
    ct:log("asked ~tp; refused ~tp", [Asked, Refused]),
    ?assertEqual([], [A || A <- Asked, lists:member(A, [<<"unheld">>, <<"fixture_unsettled">>])]),
    ok = stop_cell(),
    ?assertEqual([delivered], [How || {S, How} <- maps:get(ledger, router_sim:world()),
                                      S =:= Serial]),
    assert_books_agree().

%% The same double holding answered as the chaos run's operator did, who did not look:
%% Reset on the work segment's error, though the panel lies in its fixture. The work
%% segment holds nothing, a whole panel lies in position, and the loading segment
%% holds that serial with its stopper empty. The work segment neither waits for its
%% nest to empty nor asks for the panel to be taken out: it says the loading segment's
%% record is still being settled; the loading segment's question ("Panel not at the
%% stopper") answered IGNORE (it is past the stopper: handed over as it lies), the
%% loading segment offers it, and the work segment, at RETRY, takes it in through the
%% hand-over as it lies. The line moves again and the panel leaves the cell.
held_twice_answered_wrong_the_loading_offer_taken_in(_Config) ->
    Serial = held_in_the_fixture_and_at_loading(),
    {Asked, Refused} = settle_held_twice(Serial, work_front, #{<<"where">> => ignore}),
    ct:log("asked ~tp; refused ~tp", [Asked, Refused]),
    ?assertEqual([], [A || A <- Asked, A =:= <<"unheld">>]),
    ok = stop_cell(),
    ?assertEqual([delivered], [How || {S, How} <- maps:get(ledger, router_sim:world()),
                                      S =:= Serial]),
    assert_books_agree().

%% The line runs, then no panel arrives any more; the last panel is caught clamped in
%% the work fixture while the loading segment is empty (the physics held still). The
%% loading segment is killed while its supervisor waits, and comes back from a file
%% holding that panel in a record as new as the work segment's, as a node kill can
%% leave it; the physics goes on. Returns the serial.
held_in_the_fixture_and_at_loading() ->
    ok = cell_events:subscribe(?EVENTS ++ [alarm_cleared]),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(1),
    ok = cell_settings:put(router_sim, #{arrival_ms => 3600000}, <<"suite">>),
    Work = cell_task_proc:whereis(work_front),
    1 = erlang:trace(Work, true, [call, {tracer, self()}]),
    Serial = last_clamping(Work, deadline()),
    1 = erlang:trace(Work, false, [call]),
    flush_trace(Work),
    [{work_front, Gen}] = cell_registry:holders(Serial),
    #{product := Product} = cell_task_proc:info(work_front),
    ok = sys:suspend(cell_task_sup),
    Loading = cell_task_proc:whereis(loading_front),
    Ref = erlang:monitor(process, Loading),
    exit(Loading, kill),
    receive {'DOWN', Ref, process, Loading, _} -> ok
    after ?DEADLINE_MS -> ct:fail(loading_not_killed)
    end,
    ok = cell_product:save(cell_product:path(<<"Loading">>, <<"Front">>),
                           cell_product:stored(Product, Gen, undefined)),
    ok = sys:resume(cell_task_sup),
    ok = sys:resume(router_sim),
    ct:log("~ts in the work fixture, held by the work segment and copied to the loading "
           "segment (generation ~b)", [Serial, Gen]),
    Serial.

%% The work segment enters clamping with a panel while none waits upstream and the
%% loading segment is empty: the physics is held there (the clamps do not close) and
%% the panel's serial returned. A panel caught otherwise lets the physics go on.
last_clamping(Work, Deadline) ->
    ok = await_phase(Work, clamping, Deadline),
    W = router_sim:world(),
    Empty = maps:get(front, maps:get(upstream, W)) =:= []
        andalso maps:get(front, maps:get(loading, W)) =:= empty,
    ok = sys:suspend(router_sim),
    case {Empty, cell_task_proc:info(work_front), serial(loading_front)} of
        {true, #{phase := clamping, product := #{serial := S}}, undefined} ->
            S;
        _ ->
            ok = sys:resume(router_sim),
            last_clamping(Work, Deadline)
    end.

%% Answers until the panel leaves the cell: the guard's error on `Reset' with Reset,
%% on the other holder none (it goes with the first); the local ids in `Answers' so,
%% the others as the suite's operator does. An answer refused (the double holding not
%% settled yet) is given again once a record changed or an error went. Returns the
%% local ids asked and those refused.
settle_held_twice(Serial, Reset, Answers) ->
    settle_held_twice(Serial, Reset, Answers, [], [], [], deadline()).

settle_held_twice(Serial, Reset, Answers, Asked, Refused, Parked, Deadline) ->
    receive
        {cell_event, #{type := item_transfer_out, task := unloading_front, item := Serial}} ->
            {lists:reverse(Asked), lists:reverse(Refused)};
        {cell_event, #{type := alarm_raised, alarm := #{kind := error} = A}} ->
            #{local_id := L} = A,
            case held_twice_answer(A, Reset, Answers) of
                refused ->
                    settle_held_twice(Serial, Reset, Answers, [L | Asked], [L | Refused],
                                      [A | Parked], Deadline);
                ok ->
                    settle_held_twice(Serial, Reset, Answers, [L | Asked], Refused, Parked,
                                      Deadline)
            end;
        {cell_event, #{type := Type}} when Type =:= product_saved; Type =:= alarm_cleared ->
            Listed = [Id || #{id := Id} <- cell_alarms:list()],
            Again = [A || #{id := Id} = A <- lists:reverse(Parked), lists:member(Id, Listed)],
            Still = [A || A <- Again, held_twice_answer(A, Reset, Answers) =:= refused],
            settle_held_twice(Serial, Reset, Answers, Asked, Refused, lists:reverse(Still),
                              Deadline);
        {cell_event, _} ->
            settle_held_twice(Serial, Reset, Answers, Asked, Refused, Parked, Deadline)
    after left(Deadline) ->
        ct:fail({line_stuck, Serial, lists:reverse(Asked), cell_controller:tasks(),
                 cell_alarms:list(), router_sim:world()})
    end.

held_twice_answer(#{local_id := <<"held_twice">>, task := Task, id := Id}, Reset, _Answers) ->
    case Task of
        Reset -> refused_or_ok(cell_alarms:answer(Id, reset, <<"suite">>));
        _ -> ok
    end;
held_twice_answer(#{local_id := L, id := Id} = A, _Reset, Answers) ->
    case maps:find(L, Answers) of
        {ok, Solution} -> refused_or_ok(cell_alarms:answer(Id, Solution, <<"suite">>));
        error -> refused_or_ok(cell_alarms:answer(Id, solution(L, maps:get(task, A), A),
                                                  <<"suite">>))
    end.

refused_or_ok(ok) -> ok;
refused_or_ok({error, not_found}) -> ok;
refused_or_ok({error, {double_holding, _, _}}) -> refused.

%% An error of one of these local ids raised by the task, the others answered meanwhile.
await_alarm(Locals, Task, Deadline) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, local_id := L,
                                                         task := Task} = A}} ->
            case lists:member(L, Locals) of
                true -> A;
                false -> ok = answer(A), await_alarm(Locals, Task, Deadline)
            end;
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            await_alarm(Locals, Task, Deadline);
        {cell_event, _} ->
            await_alarm(Locals, Task, Deadline)
    after left(Deadline) ->
        ct:fail({no_error, Locals, cell_controller:tasks(), cell_alarms:list()})
    end.

%% The local ids of the errors asked (and answered) until N products left, and what left.
collect(0, Asked, Out, _Deadline) ->
    {lists:reverse(Asked), lists:reverse(Out)};
collect(N, Asked, Out, Deadline) ->
    receive
        {cell_event, #{type := item_transfer_out, task := unloading_front, item := S}} ->
            collect(N - 1, Asked, [S | Out], Deadline);
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, local_id := L} = A}} ->
            ok = answer(A),
            collect(N, [L | Asked], Out, Deadline);
        {cell_event, _} ->
            collect(N, Asked, Out, Deadline)
    after left(Deadline) ->
        ct:fail({line_stuck, cell_controller:tasks(), cell_alarms:list(), router_sim:world()})
    end.

%% Every task of the line killed in the same instant, at moments that differ from round
%% to round (after a number of the cell's events): each restarts and reconciles with
%% the others mid-transfer; answered, the line goes on and the books agree with the
%% machine.
every_task_killed_at_once(_Config) ->
    Tasks = [loading_front, work_front, lower, upper, unloading_front],
    ok = cell_events:subscribe(?EVENTS ++ [task_state]),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(1),
    lists:foldl(fun(Round, R0) ->
                        {Skip, R1} = rand:uniform_s(60, R0),
                        ok = skip_events(Skip, deadline()),
                        Pids = [cell_task_proc:whereis(T) || T <- Tasks],
                        ct:log("round ~b: every task killed after ~b events; the machine: ~tp",
                               [Round, Skip, router_sim:world()]),
                        _ = [exit(P, kill) || P <- Pids],
                        ok = await_restart(Tasks, deadline()),
                        ok = line_goes_on(2),
                        R1
                %% Three rounds: fifteen restarts, within the task supervisor's
                %% intensity (beyond it the whole task tree restarts, and the cell
                %% waits for Start, by design).
                end, rand:seed_s(exsss, {3, 5, 7}), lists:seq(1, 3)),
    ok = stop_cell(),
    assert_books_agree().

%% The supervisor of the tasks killed while panels move: the tasks, the HAL and the
%% controller restart, and the cell waits for Start (by design: an internal fault is
%% the operator's to see). Start pressed, every task reconciles from its product file
%% against the machine, and the line goes on.
task_tree_restarted(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_log:subscribe(),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(2),
    ok = skip_events(17, deadline()),
    ct:log("the task tree killed; the machine: ~tp", [router_sim:world()]),
    exit(whereis(cell_task_sup), kill),
    ok = await_log(<<"the cell's tasks were restarted">>, deadline()),
    ok = cell_log:unsubscribe(),
    %% Its supervisor answers once it has restarted everything after it.
    _ = supervisor:which_children(cell_controller_sup),
    %% The cell stopped by itself and says so, until Start.
    ?assertMatch({ok, #{kind := alarm, caption := <<"Cell stopped after an internal fault">>}},
                 cell_alarms:get(<<"cell:stopped">>)),
    {ok, up} = await_connection(),
    ok = router_sim:ready(?DEADLINE_MS),
    ok = cell_controller:start(<<"suite">>),
    ?assertEqual({error, not_found}, cell_alarms:get(<<"cell:stopped">>)),
    ok = line_goes_on(3),
    ok = stop_cell(),
    assert_books_agree().

await_log(Prefix, Deadline) ->
    receive
        {cell_log, #{text := <<Prefix:(byte_size(Prefix))/binary, _/binary>>}} -> ok;
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            await_log(Prefix, Deadline)
    after left(Deadline) ->
        ct:fail({no_log_line, Prefix})
    end.

skip_events(0, _Deadline) ->
    ok;
skip_events(N, Deadline) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            skip_events(N - 1, Deadline);
        {cell_event, _} ->
            skip_events(N - 1, Deadline)
    after left(Deadline) ->
        ct:fail({no_event, cell_controller:tasks()})
    end.

%% -------------------------------------------------------------------------------------

killed_in_phases(Task, Phases) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = line_goes_on(1),
    lists:foreach(fun(Phase) -> kill_in(Task, Phase) end, Phases),
    ok = stop_cell(),
    assert_books_agree().

%% Waits for the task to enter the phase, kills it there, and waits for the line to go
%% on (two more products out), answering what the cell asks.
kill_in(Task, Phase) ->
    Pid = cell_task_proc:whereis(Task),
    1 = erlang:trace(Pid, true, [call, {tracer, self()}]),
    ok = await_phase(Pid, Phase, deadline()),
    exit(Pid, kill),
    ct:log("~ts killed in ~ts; the machine: ~tp", [Task, Phase, router_sim:world()]),
    ok = await_restart([Task], deadline()),
    flush_trace(Pid),
    ok = line_goes_on(2).

await_phase(Pid, Phase, Deadline) ->
    receive
        {trace, Pid, call, {cell_handover, phase, [_, Phase]}} -> ok;
        {trace, Pid, call, _} -> await_phase(Pid, Phase, Deadline);
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            await_phase(Pid, Phase, Deadline);
        {cell_event, _} -> await_phase(Pid, Phase, Deadline)
    after left(Deadline) ->
        ct:fail({phase_never_entered, Phase, cell_controller:tasks(), cell_alarms:list()})
    end.

%% Every task of the list restarted.
await_restart([], _Deadline) ->
    ok;
await_restart(Tasks, Deadline) ->
    receive
        {cell_event, #{type := task_crashed, task := Task}} ->
            await_restart(Tasks -- [Task], Deadline);
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            await_restart(Tasks, Deadline);
        {cell_event, _} -> await_restart(Tasks, Deadline)
    after left(Deadline) ->
        ct:fail({no_restart, Tasks})
    end.

flush_trace(Pid) ->
    receive {trace, Pid, _, _} -> flush_trace(Pid)
    after 0 -> ok
    end.

%% N products handed to the next machine, the cell's questions answered meanwhile.
line_goes_on(N) ->
    line_goes_on(N, deadline()).

line_goes_on(0, _Deadline) ->
    ok;
line_goes_on(N, Deadline) ->
    receive
        {cell_event, #{type := item_transfer_out, task := unloading_front}} ->
            line_goes_on(N - 1, Deadline);
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            line_goes_on(N, Deadline);
        {cell_event, _} ->
            line_goes_on(N, Deadline)
    after left(Deadline) ->
        ct:fail({line_stuck, cell_controller:tasks(), cell_alarms:list(), router_sim:world(),
                 [catch cell_task_proc:info(T) || T <- [loading_front, work_front, lower,
                                                        upper, unloading_front]]})
    end.

%% The operator at the machine: looks where the record says the panel is and answers.
answer(#{kind := Kind}) when Kind =/= error ->
    %% A warning (a task went on by itself after a crash) is read, an alarm (the cell
    %% stopped by itself) is settled by Start: nothing to answer.
    ok;
answer(#{id := Id, local_id := Local, task := Task} = A) ->
    Solution = solution(Local, Task, A),
    ct:log("~ts: ~ts -> ~ts", [Id, maps:get(description, A), Solution]),
    case cell_alarms:answer(Id, Solution, <<"suite">>) of
        {error, {double_holding, S, Others}} ->
            %% Refused: a restarted task read its copy of the serial before the task it
            %% went to took it on in a newer record, and drops that copy only now. The
            %% operator answers again once a record has changed (a task saved or dropped
            %% a product); a double holding that stays fails at the deadline.
            ct:log("refused: ~ts held by ~tp too; answered again once a record changes",
                   [S, Others]),
            ok = await_record(deadline()),
            case [O || #{id := I} = O <- cell_alarms:list(), I =:= Id] of
                [Again] -> answer(Again);
                %% Withdrawn meanwhile (the task asks anew, an event of its own).
                [] -> ok
            end;
        Answered ->
            Answered
    end.

await_record(Deadline) ->
    receive
        {cell_event, #{type := product_saved}} -> ok
    after left(Deadline) ->
        ct:fail({held_twice_for_good, cell_controller:tasks(), cell_alarms:list()})
    end.

solution(<<"crashed">>, Task, _A) ->
    %% A unit restarted after a crash references itself again on Reset; a task goes on
    %% on Retry.
    case cell_registry:task(Task) of
        {ok, #{kind := unit}} -> reset;
        _ -> retry
    end;
solution(Where, upper, _A) when Where =:= <<"where">>; Where =:= <<"lost">> ->
    S = serial(upper),
    W = router_sim:world(),
    case {maps:get(gripper, W), slot(W, work, S), slot(W, unloading, S)} of
        {S, _, _} -> retry;               %% in the gripper after all: look again
        {_, {S, full}, _} when Where =:= <<"where">> -> retry;  %% back in the module nest
        {_, _, {S, _}} -> ignore;         %% on the unloading conveyor
        _ -> reset                        %% not in the machine
    end;
solution(<<"where">>, Task, _A) ->
    S = serial(Task),
    case slot(router_sim:world(), loading, S) of
        {S, _} -> ignore;                 %% between the stopper and the fixture
        _ -> reset
    end;
solution(Transit, Task, _A) when Transit =:= <<"in_transit">>; Transit =:= <<"transfer">> ->
    %% Confirmed here when the machine has it; forgotten when it does not.
    case lists:member(serial(Task), in_machine(router_sim:world())) of
        true -> ignore;
        false -> reset
    end;
solution(_Other, _Task, #{solutions := Solutions}) ->
    case lists:member(retry, Solutions) of
        true -> retry;
        false -> hd(Solutions)
    end.

serial(Task) ->
    case cell_task_proc:info(Task) of
        #{product := #{serial := S}} -> S;
        _ -> undefined
    end.

slot(W, Where, S) ->
    case [Slot || {S1, _} = Slot <- maps:values(maps:get(Where, W)), S1 =:= S] of
        [Slot | _] -> Slot;
        [] -> empty
    end.

%% Every serial the simulated machine physically has on a station (not the frames
%% left after the modules were lifted, nor a panel still entering from the previous
%% machine: no task has read its code yet).
in_machine(W) ->
    [S || Where <- [loading, work, unloading], {S, At} <- maps:values(maps:get(Where, W)),
          At =/= frame, At =/= entering]
        ++ [G || G <- [maps:get(gripper, W)], G =/= empty].

%% Stopped: what the tasks hold is what the machine has, each serial once. Nothing is
%% left to answer or settle: the warnings of tasks that went on by themselves after a
%% crash are read and closed, and then nothing else is listed.
assert_books_agree() ->
    Held = [S || #{serial := S} <- cell_controller:tasks(), is_binary(S)],
    World = router_sim:world(),
    ?assertEqual(length(Held), length(lists:usort(Held))),
    %% A panel the previous machine pushed to the loading stopper as the cell stopped,
    %% before the loading segment read its code, has not entered the cell yet.
    Unread = [S || {S, stop} <- maps:values(maps:get(loading, World)),
                   not lists:member(S, Held), cell_stats:product(S) =:= {error, not_found}],
    ?assertEqual({held, lists:sort(in_machine(World) -- Unread)}, {held, lists:sort(Held)}),
    _ = [ok = cell_alarms:close(Id, <<"suite">>)
         || #{id := Id, kind := warning, local_id := <<"crash_resumed">>} <- cell_alarms:list()],
    ?assertEqual([], cell_alarms:list()).

stop_cell() ->
    ok = cell_controller:stop(<<"suite">>),
    ok = cell_controller:sync(),
    case cell_controller:state() of
        off -> ok;
        _ -> await_off(deadline())
    end.

await_off(Deadline) ->
    receive
        {cell_event, #{type := cell_state, state := off}} -> ok;
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = answer(A),
            await_off(Deadline);
        {cell_event, _} -> await_off(Deadline)
    after left(Deadline) ->
        ct:fail({not_off, cell_controller:tasks(), cell_alarms:list()})
    end.

await_connection() ->
    case cell_hal:subscribe_connection(router_plc) of
        {ok, up} -> {ok, up};
        {ok, down} ->
            receive {cell_hal_conn, router_plc, up} -> {ok, up}
            after ?DEADLINE_MS -> ct:fail(router_plc_not_up)
            end
    end.

deadline() ->
    erlang:monotonic_time(millisecond) + ?DEADLINE_MS.

left(Deadline) ->
    max(0, Deadline - erlang:monotonic_time(millisecond)).

%% The physics started while the cell's HAL is not there (the cell stopped), then
%% stopped before the HAL came: it shows the world it saved and leaves it as it was,
%% never an empty machine in its place (which would make the panels in it vanish and
%% their serials be made again).
physics_stopped_before_the_hal_keeps_its_world(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    receive
        {cell_event, #{type := item_transfer_out, task := unloading_front}} -> ok
    after ?DEADLINE_MS -> ct:fail(nothing_out)
    end,
    ok = application:stop(router_cell),
    ok = application:stop(cell),
    Path = filename:join(cell_config:dir(data), "router_sim.world"),
    {ok, Saved} = cell_file:read_term(Path),
    ?assertMatch(#{counters := #{delivered := D}} when D >= 1, Saved),
    process_flag(trap_exit, true),
    {ok, Pid} = router_sim:start_link(#{lanes => [front]}),
    ?assertEqual(maps:get(counters, Saved), maps:get(counters, router_sim:world())),
    ok = gen_server:stop(Pid),
    ?assertEqual({ok, Saved}, cell_file:read_term(Path)).

