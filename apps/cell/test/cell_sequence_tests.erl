%% The step-sequence runner as pure functions: no process, no HAL. IO reads come from
%% a table the test sets; the effects the runner returns are what is checked.
-module(cell_sequence_tests).
-include_lib("eunit/include/eunit.hrl").

-define(SEQ, cell_test_fun_seq).
-define(IN(P), {io, P, {eq, true}}).

%% -------------------------------------------------------------------------------------
%% Helpers
%% -------------------------------------------------------------------------------------

%% A runner for unit `u' with IO group `g', reading the table `Tab'.
runner(Tab) -> runner(Tab, #{}).

runner(Tab, Acts) ->
    runner(Tab, Acts, fun() -> false end).

runner(Tab, Acts, Estop) ->
    {ok, Seq} = cell_sequence_runner:new(
                  #{unit => u, io => [g], actuators => Acts, estop => Estop,
                    read => fun(G, P) ->
                                    case ets:lookup(Tab, {G, P}) of
                                        [{_, V}] -> {ok, V};
                                        [] -> {error, disconnected}
                                    end
                            end}),
    Seq.

io() ->
    ets:new(io, [public]).

set(Tab, P, V) -> true = ets:insert(Tab, {{g, P}, V}).

start(Seq, Steps, First) -> start(Seq, Steps, First, #{}).

start(Seq, Steps, First, Opts) ->
    Args = maps:merge(#{first => First, steps => Steps}, maps:with([mode], Opts)),
    cell_sequence_runner:start(Seq, ?SEQ, Args,
                               maps:merge(#{now => 0}, maps:without([mode], Opts))).

steps(Effects) -> [S || {step, _, _, S} <- Effects].

count(Seq, Key) -> cell_sequence:put(Seq, Key, cell_sequence:get(Seq, Key, 0) + 1).

lift() ->
    {cell_cylinder, #{up => #{out => lift_up, sensor => is_up},
                      down => #{out => lift_down, sensor => is_down},
                      timeout_ms => 500}}.

%% -------------------------------------------------------------------------------------
%% Several steps in one go, or one per cycle
%% -------------------------------------------------------------------------------------

several_steps_run_in_one_go_test() ->
    Steps = #{a => fun(S) -> cell_sequence:next(S, b) end,
              b => fun(S) -> cell_sequence:next(S, c) end,
              c => fun(S) -> cell_sequence:done(S) end},
    {Outcome, _, Effects} = start(runner(io()), Steps, a),
    ?assertEqual(done, Outcome),
    ?assertEqual([a, b, c], steps(Effects)).

one_step_per_cycle_test() ->
    Steps = #{a => fun(S) -> cell_sequence:next(S, b) end,
              b => fun(S) -> cell_sequence:next(S, c) end,
              c => fun(S) -> cell_sequence:done(S) end},
    {continue, S1, E1} = start(runner(io()), Steps, a, #{mode => one}),
    ?assertEqual([a, b], steps(E1)),            %% a ran at the state's entry; b is due
    {continue, S2, E2} = cell_sequence_runner:cycle(S1, 1),
    ?assertEqual([c], steps(E2)),
    ?assertMatch({done, _, _}, cell_sequence_runner:cycle(S2, 2)).

a_step_coming_round_again_waits_for_the_next_cycle_test() ->
    %% The seed's IsNotRepeatable: a loop a → b → a stops at the second a.
    Steps = #{a => fun(S) -> cell_sequence:next(count(S, n), b) end,
              b => fun(S) -> cell_sequence:next(S, a) end},
    {continue, S1, E1} = start(runner(io()), Steps, a),
    ?assertEqual([a, b, a], steps(E1)),
    {continue, _S2, E2} = cell_sequence_runner:cycle(S1, 1),
    ?assertEqual([b, a], steps(E2)).

on_entry_is_true_once_per_entry_test() ->
    Tab = io(),
    set(Tab, part, false),
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> count(S0, entries);
                                   false -> count(S0, reruns)
                               end,
                           cell_sequence:await(S, ?IN(part), b)
                   end,
              b => fun(S) -> cell_sequence:abort(S, {counts, cell_sequence:get(S, entries),
                                                     cell_sequence:get(S, reruns, 0)}) end},
    {wait, S1, _} = start(runner(Tab), Steps, a),
    {Aborted, _, _} = cell_sequence_runner:event(S1, {watch, {io, g, part, {eq, true}}, true}, 5),
    ?assertMatch({aborted, _, {counts, 1, 1}}, Aborted).

unhandled_step_aborts_test() ->
    {Outcome, _, _} = start(runner(io()), #{a => fun(S) -> cell_sequence:next(S, zz) end}, a),
    ?assertMatch({aborted, #{step := zz, depth := 1}, {unhandled_step, zz}}, Outcome),
    {aborted, _, Why} = Outcome,
    ?assertEqual(<<"sequence contains unhandled step zz">>, cell_sequence:format_reason(Why)).

a_bad_step_result_is_a_bug_test() ->
    ?assertError({bad_step_result, a, oops}, start(runner(io()), #{a => fun(_) -> oops end}, a)).

%% -------------------------------------------------------------------------------------
%% Await
%% -------------------------------------------------------------------------------------

await_io_watches_and_wakes_test() ->
    Tab = io(),
    set(Tab, part, false),
    Steps = #{a => fun(S) -> cell_sequence:await(S, ?IN(part), b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    Key = {io, g, part, {eq, true}},
    {wait, S1, E1} = start(runner(Tab), Steps, a),
    ?assertEqual([{step, 1, ?SEQ, a}, {watch, Key, {g, part}, {eq, true}}], E1),
    %% The watch fired: the value may have gone again, the condition was seen.
    set(Tab, part, false),
    {done, _, E2} = cell_sequence_runner:event(S1, {watch, Key, true}, 3),
    ?assertEqual([b], steps(E2)),
    ?assertEqual([], [E || {cancel_watch, _} = E <- E2]).

await_io_that_holds_goes_straight_on_test() ->
    Tab = io(),
    set(Tab, part, true),
    Steps = #{a => fun(S) -> cell_sequence:await(S, ?IN(part), b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    {done, _, E} = start(runner(Tab), Steps, a),
    ?assertEqual([], [W || {watch, _, _, _} = W <- E]).

await_timeout_aborts_naming_the_step_test() ->
    Tab = io(),
    set(Tab, part, false),
    Steps = #{a => fun(S) -> cell_sequence:await(S, ?IN(part), b, 100) end},
    {wait, S1, E1} = start(runner(Tab), Steps, a, #{now => 1000}),
    ?assert(lists:member({timer, deadline, 100}, E1)),
    %% Another look before the deadline re-arms nothing.
    {wait, S2, E2} = cell_sequence_runner:cycle(S1, 1050),
    ?assertEqual([], [X || X <- E2, element(1, X) =/= step]),
    {{aborted, Where, Why}, _, E3} = cell_sequence_runner:event(S2, {timer, deadline}, 1100),
    ?assertEqual(#{module => ?SEQ, step => a, depth => 1}, Where),
    ?assert(lists:member({cancel_watch, {io, g, part, {eq, true}}}, E3)),
    ?assertEqual(<<"step a waited more than 100 ms for g.part = true">>,
                 cell_sequence:format_reason(Why)).

await_reply_test() ->
    Ref = make_ref(),
    Steps = #{a => fun(S) -> cell_sequence:await(S, {reply, Ref}, b) end,
              b => fun(S) -> cell_sequence:abort(S, {got, cell_sequence:reply(S, Ref)}) end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    ?assert(cell_sequence_runner:expects(S1, Ref)),
    {wait, _, []} = cell_sequence_runner:event(S1, {reply, make_ref(), other}, 1),
    ?assertMatch({{aborted, _, {got, 42}}, _, _},
                 cell_sequence_runner:event(S1, {reply, Ref, 42}, 1)).

%% A standing order (cell_unit:order/3): read with a default, awaited as a condition;
%% the waiting step runs again when it changes, and not when it is given again as it
%% was. Orders outlive the sequence that read them.
await_order_test() ->
    Steps = #{a => fun(S) -> cell_sequence:await(S, {order, clamp, {ne, undefined}}, b) end,
              b => fun(S) -> cell_sequence:await(S, {order, clamp, {eq, false}}, c) end,
              c => fun(S) ->
                           case cell_sequence:order(S, clamp, undefined) of
                               false -> cell_sequence:done(S);
                               Other -> cell_sequence:abort(S, {got, Other})
                           end
                   end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    {wait, S2, E2} = cell_sequence_runner:set_order(S1, clamp, true, 1),
    ?assertEqual([b], steps(E2)),
    ?assertMatch({wait, _, []}, cell_sequence_runner:set_order(S2, clamp, true, 2)),
    {done, S3, E3} = cell_sequence_runner:set_order(S2, clamp, false, 3),
    ?assertEqual([c], steps(E3)),
    ?assertEqual(false, cell_sequence:order(element(2, start(S3, Steps, c)), clamp, none)),
    %% Given while no sequence runs: kept for the next.
    {idle, S4, []} = cell_sequence_runner:set_order(S3, other, 1, 4),
    {done, _, _} = start(S4, #{a => fun(S) -> cell_sequence:await(S, {order, other, {eq, 1}}, c) end,
                               c => fun(S) -> cell_sequence:done(S) end}, a).

%% Halt holds a step that waits only for an order (nothing of the unit's moves).
halt_holds_where_only_an_order_is_awaited_test() ->
    Steps = #{a => fun(S) -> cell_sequence:await(S, {order, go, {eq, true}}, b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    {wait, S2, _} = cell_sequence_runner:set_halt(S1, true, 10),
    ?assert(cell_sequence_runner:held(S2)),
    %% Held: the order is kept, the step does not run until Halt is released.
    {wait, S3, []} = cell_sequence_runner:set_order(S2, go, true, 11),
    ?assertMatch({done, _, _}, cell_sequence_runner:set_halt(S3, false, 12)).

an_answer_can_come_before_it_is_awaited_test() ->
    Ref = make_ref(),
    Steps = #{a => fun(S0) ->
                           S = cell_sequence:on_entry(
                                 S0, fun(S1) -> cell_seq_timer:run_async(
                                                  cell_sequence:expect_reply(S1, Ref), t, 10)
                                     end),
                           cell_sequence:await(S, t, b)
                   end,
              b => fun(S) -> cell_sequence:await(S, {reply, Ref}, c) end,
              c => fun(S) -> cell_sequence:abort(S, {got, cell_sequence:reply(S, Ref)}) end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    %% The answer comes while the sequence still waits for its timer: kept for b.
    {wait, S2, E2} = cell_sequence_runner:event(S1, {reply, Ref, 7}, 5),
    ?assertEqual([], steps(E2)),
    ?assertMatch({{aborted, _, {got, 7}}, _, _},
                 cell_sequence_runner:event(S2, {timer, {act, t, elapsed}}, 10)).

reading_a_lost_input_aborts_naming_it_test() ->
    Steps = #{a => fun(S) -> cell_sequence:in(S, gone), cell_sequence:done(S) end},
    {{aborted, _, Why}, _, _} = start(runner(io()), Steps, a),
    ?assertEqual({io, {g, gone}, disconnected}, Why),
    ?assertEqual(<<"IO point g.gone cannot be reached: its connection is down">>,
                 cell_sequence:format_reason(Why)).

outputs_and_ipc_events_are_effects_in_order_test() ->
    Steps = #{a => fun(S) ->
                           S1 = cell_sequence:out(S, magnet, true),
                           S2 = cell_sequence:work_start(cell_sequence:starved(S1)),
                           cell_sequence:done(cell_sequence:out(S2, {other, lamp}, false))
                   end},
    {done, _, E} = start(runner(io()), Steps, a),
    ?assertEqual([{write, {g, magnet}, true}, {ipc, equipment_starved}, {ipc, item_work_start},
                  {write, {other, lamp}, false}],
                 [X || X <- E, element(1, X) =/= step]).

%% -------------------------------------------------------------------------------------
%% Actuators
%% -------------------------------------------------------------------------------------

cylinder_move_done_when_the_sensor_confirms_test() ->
    Tab = io(),
    set(Tab, is_up, false),
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_cylinder:move_up(S0, lift);
                                   false -> S0
                               end,
                           cell_sequence:await(S, lift, b)
                   end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, E1} = start(runner(Tab, #{lift => lift()}), Steps, a),
    ?assertEqual([{write, {g, lift_down}, false}, {write, {g, lift_up}, true},
                  {watch, {act, lift, arrived}, {g, is_up}, {eq, true}},
                  {timer, {act, lift, timeout}, 500}],
                 [X || X <- E1, element(1, X) =/= step]),
    {done, S2, E2} = cell_sequence_runner:event(S1, {watch, {act, lift, arrived}, true}, 100),
    ?assert(lists:member({cancel_timer, {act, lift, timeout}}, E2)),
    ?assertMatch(#{actuators := #{lift := #{position := up, status := idle}}},
                 cell_sequence_runner:describe(S2)).

cylinder_already_there_is_done_at_once_test() ->
    Tab = io(),
    set(Tab, is_up, true),
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_cylinder:move_up(S0, lift);
                                   false -> S0
                               end,
                           cell_sequence:await(S, lift, b)
                   end,
              b => fun(S) -> cell_sequence:done(S) end},
    {done, _, E} = start(runner(Tab, #{lift => lift()}), Steps, a),
    ?assertEqual([a, b], steps(E)),
    ?assertEqual([], [W || {watch, _, _, _} = W <- E]).

cylinder_timeout_aborts_in_words_test() ->
    Tab = io(),
    set(Tab, is_down, false),
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_cylinder:move_down(S0, lift);
                                   false -> S0
                               end,
                           cell_sequence:await(S, lift, b)
                   end},
    {wait, S1, _} = start(runner(Tab, #{lift => lift()}), Steps, a),
    {{aborted, _, Why}, _, E} = cell_sequence_runner:event(S1, {timer, {act, lift, timeout}}, 500),
    ?assert(lists:member({cancel_watch, {act, lift, arrived}}, E)),
    ?assertEqual(<<"lift did not reach down within 500 ms (sensor g.is_down stayed off)">>,
                 cell_sequence:format_reason(Why)).

a_failing_actuator_aborts_even_if_not_awaited_test() ->
    Tab = io(),
    set(Tab, part, false),
    set(Tab, is_up, false),
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_cylinder:move_up(S0, lift);
                                   false -> S0
                               end,
                           cell_sequence:await(S, ?IN(part), b)
                   end},
    {wait, S1, _} = start(runner(Tab, #{lift => lift()}), Steps, a),
    ?assertMatch({{aborted, #{step := a}, {actuator, lift, cell_cylinder, {timeout, up, 500, _}}}, _, _},
                 cell_sequence_runner:event(S1, {timer, {act, lift, timeout}}, 500)).

await2_waits_for_both_test() ->
    Tab = io(),
    [set(Tab, P, false) || P <- [is_up, is_down, is_left, is_right]],
    Side = {cell_cylinder, #{left => #{out => go_left, sensor => is_left},
                             right => #{out => go_right, sensor => is_right}}},
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_cylinder:move(cell_cylinder:move_down(S0, lift),
                                                              side, right);
                                   false -> S0
                               end,
                           cell_sequence:await2(S, side, lift, b)
                   end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, _} = start(runner(Tab, #{lift => lift(), side => Side}), Steps, a),
    {wait, S2, E2} = cell_sequence_runner:event(S1, {watch, {act, side, arrived}, true}, 10),
    ?assertEqual([], steps(E2)),
    ?assertMatch({done, _, _}, cell_sequence_runner:event(S2, {watch, {act, lift, arrived}, true}, 20)).

timer_runs_and_goes_with_its_sequence_test() ->
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_seq_timer:run_async(S0, delay, 200);
                                   false -> S0
                               end,
                           cell_sequence:await(S, delay, b)
                   end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, E1} = start(runner(io()), Steps, a),
    ?assert(lists:member({timer, {act, delay, elapsed}, 200}, E1)),
    {done, S2, _} = cell_sequence_runner:event(S1, {timer, {act, delay, elapsed}}, 200),
    ?assertEqual(#{}, maps:get(actuators, cell_sequence_runner:describe(S2))).

unknown_actuator_aborts_test() ->
    {Outcome, _, _} = start(runner(io()), #{a => fun(S) -> cell_sequence:await(S, nope, b) end}, a),
    ?assertMatch({aborted, _, {unknown_actuator, nope}}, Outcome).

cylinder_options_are_checked_test_() ->
    New = fun(Opts) -> cell_cylinder:new(c, Opts, fun(P) -> {ok, {g, P}} end) end,
    Ends = #{up => #{sensor => a}, down => #{sensor => b, out => v}},
    [?_assertMatch({ok, _}, New(Ends)),
     ?_assertMatch({error, _}, New(#{up => #{sensor => a}})),
     ?_assertEqual({error, {bad_option, {up, sensor}}}, New(Ends#{up => #{out => x}})),
     ?_assertEqual({error, {bad_option, {up, colour}}}, New(Ends#{up => #{sensor => a, colour => red}})),
     ?_assertEqual({error, {bad_option, timeout_ms}}, New(Ends#{timeout_ms => 0})),
     ?_assertEqual({error, {bad_option, safe}}, New(Ends#{safe => sideways})),
     ?_assertMatch({ok, _}, New(Ends#{safe => down})),
     ?_assertMatch({ok, _}, New(Ends#{safe => off}))].

cylinder_safe_positions_test_() ->
    Secure = fun(Safe) ->
                     {ok, C} = cell_cylinder:new(c, #{up => #{sensor => a, out => u},
                                                      down => #{sensor => b, out => d},
                                                      safe => Safe},
                                                 fun(P) -> {ok, {g, P}} end),
                     cell_cylinder:secure(C)
             end,
    [?_assertEqual([], Secure(keep)),
     ?_assertEqual([{write, {g, d}, false}, {write, {g, u}, false}], Secure(off)),
     ?_assertEqual([{write, {g, d}, true}, {write, {g, u}, false}], Secure(down))].

%% -------------------------------------------------------------------------------------
%% Halt
%% -------------------------------------------------------------------------------------

halt_holds_before_the_next_step_test() ->
    Ref = make_ref(),
    Steps = #{a => fun(S) -> cell_sequence:await(S, {reply, Ref}, b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    %% Waiting for an answer is an operation under way: Halt does not hold there...
    {wait, S2, []} = cell_sequence_runner:set_halt(S1, true, 1),
    ?assertNot(cell_sequence_runner:held(S2)),
    %% ... but before the next step.
    {wait, S3, E3} = cell_sequence_runner:event(S2, {reply, Ref, ok}, 2),
    ?assertEqual([b], steps(E3)),
    ?assert(cell_sequence_runner:held(S3)),
    ?assertMatch({done, _, _}, cell_sequence_runner:set_halt(S3, false, 3)).

halt_at_start_holds_before_the_first_step_test() ->
    Steps = #{a => fun(S) -> cell_sequence:done(count(S, ran)) end},
    {wait, S1, _} = start(runner(io()), Steps, a, #{halt => true}),
    ?assert(cell_sequence_runner:held(S1)),
    ?assertMatch({done, _, _}, cell_sequence_runner:set_halt(S1, false, 1)).

halt_holds_at_once_where_only_io_is_awaited_test() ->
    Tab = io(),
    set(Tab, part, false),
    Key = {io, g, part, {eq, true}},
    Steps = #{a => fun(S) -> cell_sequence:await(S, ?IN(part), b, 1000) end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, _} = start(runner(Tab), Steps, a),
    {wait, S2, E2} = cell_sequence_runner:set_halt(S1, true, 10),
    ?assert(cell_sequence_runner:held(S2)),
    ?assertEqual(lists:sort([{cancel_watch, Key}, {cancel_timer, deadline}]), lists:sort(E2)),
    %% Resumed a long while later: the watch is placed again, the timeout counted afresh.
    {wait, S3, E3} = cell_sequence_runner:set_halt(S2, false, 5000),
    ?assertEqual([{watch, Key, {g, part}, {eq, true}}, {timer, deadline, 1000}], E3),
    ?assertNot(cell_sequence_runner:held(S3)).

halt_does_not_hold_before_a_step_that_is_not_resumable_test() ->
    Ref = make_ref(),
    Steps = #{a => fun(S) -> cell_sequence:await(S, {reply, Ref}, busy_b) end,
              busy_b => fun(S) -> cell_sequence:next(S, c) end,
              c => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    {wait, S2, _} = cell_sequence_runner:set_halt(S1, true, 1),
    %% busy_b is entered and runs without holding; c is a resumable point.
    {wait, S3, E3} = cell_sequence_runner:event(S2, {reply, Ref, ok}, 2),
    ?assertEqual([busy_b, c], steps(E3)),
    ?assert(cell_sequence_runner:held(S3)),
    ?assertMatch({done, _, _}, cell_sequence_runner:set_halt(S3, false, 3)).

halt_leaves_stop_and_fault_reaction_alone_test() ->
    Steps = #{a => fun(S) -> cell_sequence:done(S) end},
    ?assertMatch({done, _, _}, start(runner(io()), Steps, a, #{halt => true, haltable => false})).

%% -------------------------------------------------------------------------------------
%% Sub-sequences
%% -------------------------------------------------------------------------------------

sub_sequence_returns_to_its_caller_test() ->
    Sub = #{first => x, steps => #{x => fun(S) -> cell_sequence:next(S, y) end,
                                   y => fun(S) -> cell_sequence:done(S) end}},
    Steps = #{a => fun(S) -> cell_sequence:call(S, ?SEQ, Sub, b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    {done, _, E} = start(runner(io()), Steps, a),
    ?assertEqual([{1, a}, {2, x}, {2, y}, {1, b}], [{D, S} || {step, D, _, S} <- E]).

halt_reaches_the_sub_sequence_test() ->
    Ref = make_ref(),
    Sub = #{first => x, steps => #{x => fun(S) -> cell_sequence:await(S, {reply, Ref}, y) end,
                                   y => fun(S) -> cell_sequence:done(S) end}},
    Steps = #{a => fun(S) -> cell_sequence:call(S, ?SEQ, Sub, b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    {wait, S1, _} = start(runner(io()), Steps, a),
    {wait, S2, _} = cell_sequence_runner:set_halt(S1, true, 1),
    {wait, S3, E3} = cell_sequence_runner:event(S2, {reply, Ref, ok}, 2),
    ?assertEqual([y], steps(E3)),
    ?assert(cell_sequence_runner:held(S3)),
    ?assertMatch(#{sequences := [#{step := a}, #{step := y}]}, cell_sequence_runner:describe(S3)),
    {done, _, E4} = cell_sequence_runner:set_halt(S3, false, 3),
    ?assertEqual([b], steps(E4)).

an_abort_in_a_sub_sequence_aborts_its_caller_test() ->
    Sub = #{first => x, steps => #{x => fun(S) -> cell_sequence:abort(S, <<"jammed">>) end}},
    Steps = #{a => fun(S) -> cell_sequence:call(S, ?SEQ, Sub, b) end},
    {Outcome, S, _} = start(runner(io()), Steps, a),
    ?assertEqual({aborted, #{module => ?SEQ, step => x, depth => 2}, <<"jammed">>}, Outcome),
    ?assertNot(cell_sequence_runner:running(S)).

%% -------------------------------------------------------------------------------------
%% Stop, faults, the emergency stop
%% -------------------------------------------------------------------------------------

interrupt_cancels_everything_test() ->
    Tab = io(),
    set(Tab, part, false),
    set(Tab, is_up, false),
    Steps = #{a => fun(S0) ->
                           S = case cell_sequence:on_entry(S0) of
                                   true -> cell_seq_timer:run_async(cell_cylinder:move_up(S0, lift),
                                                                    t, 50);
                                   false -> S0
                               end,
                           cell_sequence:await(S, ?IN(part), b, 900)
                   end},
    {wait, S1, _} = start(runner(Tab, #{lift => lift()}), Steps, a),
    {S2, E} = cell_sequence_runner:interrupt(S1),
    ?assertEqual(lists:sort([{cancel_watch, {io, g, part, {eq, true}}}, {cancel_timer, deadline},
                             {cancel_timer, {act, t, elapsed}}, {cancel_watch, {act, lift, arrived}},
                             {cancel_timer, {act, lift, timeout}}]),
                 lists:sort(E)),
    ?assertNot(cell_sequence_runner:running(S2)),
    %% Messages still on their way change nothing.
    ?assertMatch({idle, _, []}, cell_sequence_runner:event(S2, {watch, {act, lift, arrived}, true}, 9)),
    ?assertMatch({idle, _, []}, cell_sequence_runner:event(S2, {timer, deadline}, 9)).

no_step_starts_during_the_emergency_stop_test() ->
    Tab = io(),
    Flag = atomics:new(1, []),
    Estop = fun() -> atomics:get(Flag, 1) =:= 1 end,
    Steps = #{a => fun(S) -> cell_sequence:next(count(S, ran), b) end,
              b => fun(S) -> cell_sequence:done(S) end},
    ok = atomics:put(Flag, 1, 1),
    {estop, S1, E1} = start(runner(Tab, #{}, Estop), Steps, a),
    ?assertEqual([], E1),                     %% the sequence did not begin
    ?assertNot(cell_sequence_runner:running(S1)),
    %% Raised between two steps: the next one does not run.
    ok = atomics:put(Flag, 1, 0),
    {continue, S2, E2} = start(runner(Tab, #{}, Estop), Steps, a, #{mode => one}),
    ?assertEqual([a, b], steps(E2)),
    ok = atomics:put(Flag, 1, 1),
    ?assertMatch({estop, _, []}, cell_sequence_runner:cycle(S2, 1)),
    ok = atomics:put(Flag, 1, 0),
    ?assertMatch({done, _, _}, cell_sequence_runner:cycle(S2, 2)).
