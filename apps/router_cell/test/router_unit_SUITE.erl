%% The fixture's clamps as a unit (seed 001) in the simulated router: panels flow with
%% the clamps closing on each panel and opening for its frame, ordered by the work
%% segment; a clamp jammed from the shell times out in the unit's sequence, which
%% stops on its fault, the error the operator answers (RESET) once the clamp is free;
%% then the clamps and the panels go on, nothing lost. A unit restarted in the middle
%% of a panel's routing recovers from its sensors and keeps the panel clamped.
%%
%% The machine is poked as the operator would (router_sim's functions); every wait is
%% for an event with a deadline.
-module(router_unit_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([panels_flow_with_the_clamps/1, jammed_clamp_fault_and_reset/1,
         unit_restart_keeps_the_panel_clamped/1, no_such_clamp/1]).

-define(DEADLINE_MS, 60000).
-define(EVENTS, [item_transfer_out, alarm_raised, alarm_cleared, task_state,
                 equipment_starved, equipment_unstarved, cell_state]).
-define(UNIT, clamps_front).

all() ->
    [panels_flow_with_the_clamps, jammed_clamp_fault_and_reset,
     unit_restart_keeps_the_panel_clamped, no_such_clamp].

init_per_testcase(Case, Config) ->
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    %% Clamps that stick are seen within half a second (their travel is 8 ms here).
    ok = router_test_settings:start_cell(
           Root, #{router_sim => #{time_scale => 0.02, arrival_ms => 0, jam_rate => 0.0,
                                   product_lost_rate => 0.0, no_read_rate => 0.0,
                                   magazine_low_s => 0},
                   router => #{hal_poll_ms => 5, transfer_timeout_ms => 3000,
                               motion_timeout_ms => 3000, clamp_timeout_ms => 500,
                               %% The inspection application is not started here.
                               inspection => false}},
           ?DEADLINE_MS),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:unset_env(cell, shutdown_wait_ms),
    cell_testkit:stop(router_cell, [router_plc]).

%% -------------------------------------------------------------------------------------

%% The unit is in the spec with its IO; Start references it (GoHome: the clamps open)
%% and runs it in Automatic. Each panel is clamped (the unit unstarved: both clamps
%% closed) before the robot routes it and unclamped before its frame leaves (starved:
%% both open): three panels out, three closings and openings at least, no error.
panels_flow_with_the_clamps(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ?assertEqual(init, cell_unit:state(?UNIT)),
    ok = cell_controller:start(<<"suite">>),
    await(fun(#{type := task_state, task := ?UNIT, unit_state := automatic}) -> true;
             (_) -> false
          end),
    %% The clamps' IPC events, as the unit reported them while the panels passed.
    #{closed := Closed, opened := Opened} = flow(3),
    ?assert(Closed >= 3),
    ?assert(Opened >= 3),
    ?assertEqual(automatic, cell_unit:state(?UNIT)),
    %% The order the work segment gave, and the clamps where it put them, as the unit
    %% shows them.
    #{sequence := #{orders := #{clamp := Clamp}, actuators := #{clamp_a := A}}} =
        cell_unit:info(?UNIT),
    ?assert(is_boolean(Clamp)),
    ?assertMatch(#{type := cylinder}, A),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS),
    %% Stopped with the cell; its sequences kept the order they were last given.
    ?assertEqual(stopped, cell_unit:state(?UNIT)),
    #{counters := #{scrapped := 0, removed := 0}, ledger := Ledger} = router_sim:world(),
    assert_once(Ledger).

%% A clamp jams: the unit's move times out, the unit goes through FaultReaction (the
%% coils off) to Fault and raises its error; the work segment raises none, it waits.
%% The clamp freed and the error answered (RESET), the unit references itself and goes
%% on in Automatic; panels flow again, none lost or counted twice.
jammed_clamp_fault_and_reset(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(1, fun never_answer/1),
    ok = router_sim:jam_clamp(front),
    Self = self(),
    %% The unit's fault, answered once the clamp is free.
    Answer = fun(#{kind := error, task := ?UNIT, id := Id}) -> Self ! {fault, Id}, ok;
                (A) -> never_answer(A)
             end,
    Id = receive_fault(Answer),
    ?assertEqual(fault, cell_unit:state(?UNIT)),
    #{fault := Why} = cell_unit:info(?UNIT),
    ct:log("the unit's fault: ~ts", [Why]),
    ?assertNotEqual(nomatch, binary:match(Why, <<"clamp_a">>)),
    %% The coils of every valve off: the valves hold.
    [?assertEqual({ok, false}, cell_hal:read(clamps_front_io, P))
     || P <- [a_close, a_open, b_close, b_open]],
    %% Only the unit's error waits for the operator.
    ?assertEqual([Id], [I || #{kind := error, id := I} <- cell_alarms:list()]),
    ok = router_sim:free_clamp(front),
    ok = cell_alarms:answer(Id, reset, <<"suite">>),
    await(fun(#{type := alarm_cleared, alarm := #{id := I}}) -> I =:= Id; (_) -> false end),
    await(fun(#{type := task_state, task := ?UNIT, unit_state := automatic}) -> true;
             (_) -> false
          end),
    _ = collect_out(2, fun never_answer/1),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS),
    #{counters := #{scrapped := 0, removed := 0}, ledger := Ledger} = router_sim:world(),
    assert_once(Ledger).

%% The unit's process is killed while the robot routes a panel in the fixture: it
%% restarts, its outputs left as they were (the valves hold: the clamps stay closed),
%% and asks the operator (RESET); GoHome then finds a panel with the clamps closed on
%% it and keeps them closed; the work segment's order, given again, is followed, and
%% the panel goes on.
unit_restart_keeps_the_panel_clamped(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    %% The lower robot has taken charge of a clamped panel.
    await(fun(#{type := task_state, task := work_front, state := {ready, idle, blocked}}) ->
                  true;
             (_) ->
                  false
          end),
    {ok, true} = cell_hal:read(clamps_front_io, a_is_closed),
    Pid = cell_unit:whereis(?UNIT),
    Ref = monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', Ref, process, Pid, _} -> ok after ?DEADLINE_MS -> ct:fail(not_killed) end,
    Self = self(),
    Answer = fun(#{kind := error, task := ?UNIT, id := Id}) -> Self ! {fault, Id}, ok;
                (A) -> never_answer(A)
             end,
    Id = receive_fault(Answer),
    %% Never opened meanwhile.
    ?assertEqual({ok, true}, cell_hal:read(clamps_front_io, a_is_closed)),
    ?assertEqual({ok, true}, cell_hal:read(clamps_front_io, b_is_closed)),
    ok = cell_alarms:answer(Id, reset, <<"suite">>),
    _ = collect_out(2, fun never_answer/1),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS),
    #{counters := #{scrapped := 0, removed := 0}, ledger := Ledger} = router_sim:world(),
    assert_once(Ledger).

%% A machine with one lane has no rear clamps to jam.
no_such_clamp(_Config) ->
    ?assertEqual({error, no_such_clamp}, router_sim:jam_clamp(rear)),
    ?assertEqual({error, no_such_clamp}, router_sim:free_clamp({rear, b})),
    ?assertEqual(ok, router_sim:jam_clamp({front, b})),
    ?assertEqual(ok, router_sim:free_clamp({front, b})).

%% -------------------------------------------------------------------------------------

collect_out(N, Answer) ->
    cell_testkit:collect(N, fun(#{type := item_transfer_out, task := unloading_front,
                                  item := S}) -> {true, S};
                               (_) -> false
                            end, Answer, ?DEADLINE_MS).

%% The unit's error, raised as the collect of panels goes on (none may pass while the
%% fixture's clamps are stuck: at most the panels already past it).
receive_fault(Answer) ->
    Deadline = erlang:monotonic_time(millisecond) + ?DEADLINE_MS,
    receive_fault(Answer, Deadline).

receive_fault(Answer, Deadline) ->
    receive
        {fault, Id} ->
            Id;
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = Answer(A),
            receive_fault(Answer, Deadline);
        {cell_event, _} ->
            receive_fault(Answer, Deadline)
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail({no_fault, cell_unit:info(?UNIT), cell_alarms:list()})
    end.

%% Waits for N panels out, counting the closings (unstarved) and openings (starved)
%% the unit reports meanwhile; any error fails the case.
flow(N) ->
    flow(N, #{closed => 0, opened => 0},
         erlang:monotonic_time(millisecond) + ?DEADLINE_MS).

flow(0, Acc, _Deadline) ->
    Acc;
flow(N, #{closed := C, opened := O} = Acc, Deadline) ->
    receive
        {cell_event, #{type := item_transfer_out, task := unloading_front}} ->
            flow(N - 1, Acc, Deadline);
        {cell_event, #{type := equipment_unstarved, task := ?UNIT}} ->
            flow(N, Acc#{closed := C + 1}, Deadline);
        {cell_event, #{type := equipment_starved, task := ?UNIT}} ->
            flow(N, Acc#{opened := O + 1}, Deadline);
        {cell_event, #{type := alarm_raised, alarm := A}} ->
            ok = never_answer(A),
            flow(N, Acc, Deadline);
        {cell_event, _} ->
            flow(N, Acc, Deadline)
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail({only, Acc, N, cell_controller:tasks(), cell_alarms:list()})
    end.

%% Every serial the machine let go of, once.
assert_once(Ledger) ->
    Serials = [S || {S, _} <- Ledger],
    ?assertEqual(length(Serials), length(lists:usort(Serials))).

never_answer(#{kind := error} = A) -> ct:fail({unexpected_error, A});
never_answer(_) -> ok.

await(Match) ->
    cell_testkit:await_event(Match, ?DEADLINE_MS).
