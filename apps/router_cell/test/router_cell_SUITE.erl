%% The simulated router, run in this node: panels pass the whole line; the operator's
%% answers to the injected faults do what the seed says; nothing is lost or counted
%% twice, across a restart too; statistics add up; every serial has its history.
%%
%% The physics runs fast (`time_scale') so a case sees dozens of panels in seconds;
%% every wait is for an event with a deadline.
-module(router_cell_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([panels_pass_the_line/1, routes_along_the_cut_lines/1, axis_killed_while_routing/1,
         upper_moves_on_its_axes/1, upper_axis_fault_retried/1,
         product_lost_answers/1, reset_scrap_survives_a_stop/1,
         reset_clears_the_nest/1,
         jams_and_magazine_warning/1,
         dual_lane/1, restart_keeps_every_panel/1, stop_and_start_while_running/1,
         stop_at_any_moment/1, frame_leaves_after_a_stop_with_the_clamps_open/1,
         physics_waits_for_the_hal/1, node_stop_secures_outputs/1,
         histories_kept_within_their_limit/1, real_mode_spec/1, diagnostics/1]).

-define(DEADLINE_MS, 60000).
%% What the cases listen to (subscribing again replaces a subscription: one list).
-define(EVENTS, [item_transfer_out, item_transfer_in, alarm_raised, alarm_cleared, cell_state]).

all() ->
    [panels_pass_the_line, routes_along_the_cut_lines, axis_killed_while_routing,
     upper_moves_on_its_axes, upper_axis_fault_retried,
     product_lost_answers, reset_scrap_survives_a_stop,
     reset_clears_the_nest,
     jams_and_magazine_warning, dual_lane,
     restart_keeps_every_panel, stop_and_start_while_running, stop_at_any_moment,
     frame_leaves_after_a_stop_with_the_clamps_open,
     physics_waits_for_the_hal,
     node_stop_secures_outputs, histories_kept_within_their_limit, real_mode_spec,
     diagnostics].

init_per_testcase(Case, Config) ->
    %% The cell stops its tasks before it goes down, as the release has it.
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Sim = maps:merge(#{time_scale => 0.02, arrival_ms => 0, product_lost_rate => 0.0,
                       jam_rate => 0.0, magazine_low_s => 0, no_read_rate => 0.0},
                     sim_settings(Case)),
    Machine = #{dual_lane => lists:member(Case, [dual_lane, upper_moves_on_its_axes])},
    ok = router_test_settings:write(Root, #{machine => Machine, router_sim => Sim,
                                            %% The inspection: router_inspect_SUITE's.
                                            router => #{hal_poll_ms => 5,
                                                        transfer_timeout_ms => 3000,
                                                        motion_timeout_ms => 3000,
                                                        inspection => false},
                                            statistics => stats_settings(Case)}),
    ok = start(Root),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:unset_env(cell, shutdown_wait_ms),
    stop(),
    ok.

sim_settings(product_lost_answers) ->
    %% Seated again after 2 s (at the time scale): a Retry at once finds them missing.
    #{product_lost_rate => 1.0, reseat_ms => 100000};
sim_settings(reset_scrap_survives_a_stop) ->
    %% Every carry slips; moves long enough for a Stop to fall inside the one to the
    %% scrap bin.
    #{product_lost_rate => 1.0, reseat_ms => 100000, time_scale => 0.1};
sim_settings(reset_clears_the_nest) ->
    %% The first lift leaves the modules stuck in the nest (the case lowers the rate
    %% once it has happened).
    #{nest_stick_rate => 1.0};
sim_settings(jams_and_magazine_warning) ->
    %% The tasks' watchdogs are not scaled (3 s here), the physics is (0.02): a jam of
    %% 200 s of machine time is 4 s, enough for the watchdog to see it.
    #{jam_rate => 0.5, jam_ms => 200000, magazine_low_s => 20, magazine_refill_s => 10};
sim_settings(stop_at_any_moment) ->
    %% Moves long enough for a Stop to fall inside them.
    #{time_scale => 0.1};
sim_settings(node_stop_secures_outputs) ->
    %% Routing a panel takes a few seconds: the spindle runs when the node stops.
    #{time_scale => 0.2};
sim_settings(histories_kept_within_their_limit) ->
    %% A thousand history records take dozens of panels: with the machine's physics
    %% taking no time, a busy machine makes them within the wait too.
    #{time_scale => 0.0};
sim_settings(_) ->
    #{}.

stats_settings(histories_kept_within_their_limit) ->
    #{trace_max_records => 1000};
stats_settings(_) ->
    #{}.

%% -------------------------------------------------------------------------------------

%% The lower robot routes a panel along its recipe's cut lines with its axes: for each
%% cut in ExecOrder, a path of its interpolation channel to the cut's start at the
%% rapid speed (none where the last cut ended there), then the cut itself, from its
%% start to its end at the cut's feed, as long as the cut.
routes_along_the_cut_lines(_Config) ->
    {_, #{drawing := Drawing}} = lists:keyfind(<<"demo-2x2">>, 1, router_recipes:demo()),
    Cuts = router_recipes:cuts(Drawing, 25.0),
    Lower = trace_follows(),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    try
        _ = collect_out(1, fun never_answer/1)
    after
        untrace_follows(Lower)
    end,
    ok = stop_cell(),
    Follows = follows(Lower, []),
    ct:log("~b cuts, ~b paths followed", [length(Cuts), length(Follows)]),
    %% The first panel's cuts, in order; what follows is the next panel's, if it began.
    _ = lists:foldl(fun followed_cut/2, Follows, Cuts),
    ok.

%% An axis's process killed as the robot starts a cut (its drive and NC gone and back,
%% not powered, not homed): either the cut never ends and the robot's watchdog says so,
%% or, the cut done first, the next path is refused by the axis ("Routing robot axis
%% fault"). Either way one question, and the operator's Retry makes the axes ready
%% again (the new axis powered and homed) and the robot cuts on; the panels leave, and
%% nothing else is asked.
axis_killed_while_routing(_Config) ->
    Lower = trace_follows(),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    %% The first cut under way (the rapid move to it went first).
    receive {trace, Lower, call, {cell_hal_channel, follow, [_, _, #{velocity := 400.0}]}} -> ok
    after ?DEADLINE_MS -> ct:fail(no_rapid_move)
    end,
    receive {trace, Lower, call, {cell_hal_channel, follow, _}} -> ok
    after ?DEADLINE_MS -> ct:fail(no_cut)
    end,
    untrace_follows(Lower),
    {ok, Axis} = cell_hal_hw:watch(lower_x),
    exit(Axis, kill),
    Self = self(),
    Answer = fun(#{id := Id}) when Id =:= <<"lower:motion">>; Id =:= <<"lower:axis">> ->
                     Self ! {answered, Id},
                     ok = cell_alarms:answer(Id, retry, <<"suite">>);
                (#{kind := error} = A) ->
                     ct:fail({unexpected_error, A});
                (_) ->
                     ok
             end,
    [_, _] = collect_out(2, Answer),
    receive {answered, _} -> ok after 0 -> ct:fail(no_question) end,
    receive {answered, Again} -> ct:fail({asked_again, Again}) after 0 -> ok end,
    ?assertMatch({ok, #{homed := true, powered := true}}, cell_hal_axis:status(lower_x)),
    ok = stop_cell().

%% The upper robot's moves are lines of its axes' channel between its taught positions
%% (the router settings'), on both lanes: from home to the module nest of the first
%% panel's lane, on to that lane's unloading segment, where it offers the modules to
%% the segment, then to the nest of the next panel's lane, and so on, each line from
%% where the last one ended, at the robot's speed.
upper_moves_on_its_axes(_Config) ->
    {module, _} = code:ensure_loaded(cell_hal_channel),
    {module, _} = code:ensure_loaded(cell_handshake),
    Upper = cell_task_proc:whereis(upper),
    1 = erlang:trace_pattern({cell_hal_channel, follow, 3}, true, []),
    1 = erlang:trace_pattern({cell_handshake, offer, 2}, true, []),
    1 = erlang:trace(Upper, true, [call, {tracer, self()}]),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    try
        _ = collect_out(8, fun never_answer/1)
    after
        _ = erlang:trace(Upper, false, [call]),
        _ = erlang:trace_pattern({cell_hal_channel, follow, 3}, false, []),
        _ = erlang:trace_pattern({cell_handshake, offer, 2}, false, [])
    end,
    ok = stop_cell(),
    Moves = upper_moves(Upper, []),
    ct:log("the upper robot's moves and offers: ~p", [Moves]),
    Router = cell_settings:get(router),
    Lanes = carried({0.0, 0.0}, Moves, Router),
    ?assert(length(Lanes) >= 8, Lanes),
    ?assert(lists:member(front, Lanes) andalso lists:member(rear, Lanes), Lanes).

%% The upper task's lines and offers, in the order it made them.
upper_moves(Upper, Acc) ->
    receive
        {trace, Upper, call, {cell_hal_channel, follow, [upper_xy, Path, #{velocity := V}]}} ->
            {X0, Y0, _} = cell_hal_path:start(Path),
            {X1, Y1, _} = cell_hal_path:finish(Path),
            upper_moves(Upper, [{line, {X0, Y0}, {X1, Y1}, V} | Acc]);
        {trace, Upper, call, {cell_handshake, offer, [_, Link]}} ->
            upper_moves(Upper, [{offer, Link} | Acc])
    after 0 ->
        lists:reverse(Acc)
    end.

%% Each carry: a line from where the robot stood to the nest of the lane it then offers
%% to, a line on to that lane's unloading segment, the offer. Returns the lanes carried
%% to, in order; what follows the last offer is a carry cut short by the Stop.
carried(Here, [{line, From, Nest, V}, {line, Nest, Unloading, V}, {offer, Link} | Rest],
        Router) ->
    Lane = case Link of
               pick_unload_front -> front;
               pick_unload_rear -> rear
           end,
    assert_at(Here, From),
    assert_at(taught(nest, Lane, Router), Nest),
    assert_at(taught(unloading, Lane, Router), Unloading),
    ?assertEqual(maps:get(upper_speed, Router), V),
    [Lane | carried(Unloading, Rest, Router)];
carried(_Here, Rest, _Router) ->
    ?assert(length(Rest) < 3 andalso not lists:keymember(offer, 1, Rest), Rest),
    [].

taught(Where, Lane, Router) ->
    #{upper_front_y := Front, rear_lane_offset := Rear} = Router,
    X = maps:get(case Where of nest -> upper_nest_x; unloading -> upper_unloading_x end,
                 Router),
    {X, case Lane of front -> Front; rear -> Front + Rear end}.

assert_at({X, Y}, {A, B}) ->
    ?assert(abs(X - A) + abs(Y - B) < 1.0e-6, {{X, Y}, {A, B}}).

%% An axis of the upper robot faults (a following error) halfway through a move: the
%% error "Upper robot axis fault" names the axis; the operator's Retry resets it and the
%% robot goes on from where it stopped; the panels leave, and nothing else is asked.
upper_axis_fault_retried(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(1, fun never_answer/1),
    ok = cell_hal_axis_sim:fault_next(upper_x),
    Self = self(),
    Answer = fun(#{id := <<"upper:axis">> = Id, description := Text}) ->
                     Self ! {answered, Text},
                     ok = cell_alarms:answer(Id, retry, <<"suite">>);
                (#{kind := error} = A) ->
                     ct:fail({unexpected_error, A});
                (_) ->
                     ok
             end,
    _ = collect_out(3, Answer),
    Text = receive {answered, T} -> T after 0 -> ct:fail(no_question) end,
    ?assertMatch({match, _}, re:run(Text, <<"Axis upper_x of the upper robot">>)),
    receive {answered, Again} -> ct:fail({asked_again, Again}) after 0 -> ok end,
    ?assertMatch({ok, #{state := standstill, homed := true}}, cell_hal_axis:status(upper_x)),
    ok = stop_cell().

%% The lower task's calls to start a channel path, traced to this process; returns the
%% task's process.
trace_follows() ->
    {module, _} = code:ensure_loaded(cell_hal_channel),
    Lower = cell_task_proc:whereis(lower),
    1 = erlang:trace_pattern({cell_hal_channel, follow, 3}, true, []),
    1 = erlang:trace(Lower, true, [call, {tracer, self()}]),
    Lower.

untrace_follows(Lower) ->
    _ = erlang:trace(Lower, false, [call]),
    erlang:trace_pattern({cell_hal_channel, follow, 3}, false, []).

%% The channel's paths as the lower task started them: start, finish, length, velocity.
follows(Lower, Acc) ->
    receive
        {trace, Lower, call, {cell_hal_channel, follow, [lower_xy, Path, #{velocity := V}]}} ->
            follows(Lower, [{cell_hal_path:start(Path), cell_hal_path:finish(Path),
                             cell_hal_path:length(Path), V} | Acc])
    after 0 ->
        lists:reverse(Acc)
    end.

%% One cut routed: a rapid path to its start (unless the axes stood there), then the cut.
followed_cut(#{from := {X0, Y0}, to := {X1, Y1}, length := L, feed := Feed} = Cut, Follows) ->
    Rest = case Follows of
               [{_, To, _, 400.0} | More] -> assert_near({X0, Y0, 0.0}, To, Cut), More;
               _ -> Follows
           end,
    [{From, End, Length, V} | Rest1] = Rest,
    assert_near({X0, Y0, 0.0}, From, Cut),
    assert_near({X1, Y1, 0.0}, End, Cut),
    ?assert(abs(Length - L) < 1.0e-6, {Cut, Length}),
    ?assertEqual(Feed, V),
    Rest1.

assert_near({X, Y, Z}, {A, B, C}, Cut) ->
    ?assert(abs(X - A) + abs(Y - B) + abs(Z - C) < 1.0e-6, {Cut, {X, Y, Z}, {A, B, C}}).

%% Twenty panels enter, pass every station and leave; the counts agree with the
%% physics, each serial's history runs from its entry to its exit, and the time of
%% every task in its states adds up to the time it was watched.
panels_pass_the_line(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    T0 = os:system_time(millisecond),
    ok = cell_controller:start(<<"suite">>),
    Out = collect_out(20, fun never_answer/1),
    ok = stop_cell(),
    Stats = settle(),
    Watched = os:system_time(millisecond) - T0,
    #{counters := #{delivered := Delivered, scrapped := 0}} = router_sim:world(),
    #{cell := #{in := In, out := OutN, good := Good, scrapped := 0}, in_cell := InCell} = Stats,
    ?assertEqual(Delivered, OutN),
    ?assertEqual(OutN, Good),
    ?assertEqual(In, OutN + InCell),
    ?assertEqual(InCell, length(held())),
    [assert_left(S, good) || S <- Out],
    %% The cell's states: every stretch of time counted once.
    assert_time_adds_up(),
    #{tasks := #{lower := #{completed := Routed, work_ms := #{n := Routed}}}} = Stats,
    ?assert(Routed >= 20),
    %% Cycle time between two panels out, lead time of each in the cell, throughput
    %% over the time the statistics cover.
    #{from := From, to := To,
      cell := #{cycle_ms := #{n := NCycles, mean := Cycle, min := CycleMin, max := CycleMax},
                lead_ms := #{n := NLeads, min := LeadMin, max := LeadMax},
                throughput_per_hour := PerHour}} = Stats,
    ?assertEqual(OutN - 1, NCycles),
    ?assert(0 < CycleMin andalso CycleMin =< Cycle andalso Cycle =< CycleMax),
    ?assert(Cycle * NCycles =< Watched),
    ?assertEqual(OutN, NLeads),
    ?assert(0 < LeadMin andalso LeadMax =< Watched),
    ?assert(To - From >= Watched div 2),
    %% The summary's span is in whole milliseconds, the rate from microseconds.
    Expected = OutN * 3600000 / (To - From),
    ?assert(abs(PerHour - Expected) =< 0.002 * Expected + 0.1).

%% Every carry loses the modules: the seed's "Product lost" error, answered in turn.
%% Retry before they are seated again finds them missing (the error again); Retry
%% after, goes on; Ignore goes on with the product marked failed; Reset forgets it,
%% and its modules go to the scrap bin. Nothing is lost from the books either way.
product_lost_answers(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    %% Answers by turn: an immediate Retry (still lost), Ignore, an immediate Retry,
    %% Reset, and so on; a Retry that comes late finds the modules seated again.
    Policy = fun(N) -> lists:nth(N rem 4 + 1, [retry, ignore, retry, reset]) end,
    {Answers0, Out0} = answer_lost(Policy, 8),
    %% The modules hold from now on; two more products out, so the last Reset's
    %% modules have gone to the scrap bin (the robot empties its gripper first).
    ok = cell_settings:put(router_sim, #{product_lost_rate => 0.0}, <<"suite">>),
    {Answers1, Out1} = answer_lost(fun(_) -> ignore end, infinity, 2),
    Answers = Answers0 ++ Answers1,
    Out = Out0 ++ Out1,
    ok = stop_cell(),
    Stats = settle(),
    #{counters := #{delivered := Delivered, scrapped := Scrapped}} = router_sim:world(),
    #{cell := #{in := In, out := OutN, good := Good, failed := Failed, scrapped := ScrappedN},
      in_cell := InCell} = Stats,
    Resets = length([R || {reset, R} <- Answers]),
    ?assert(Resets >= 1),
    ?assertEqual({Resets, [R || {reset, R} <- Answers]}, {ScrappedN, scrapped()}),
    ?assertEqual(Scrapped, ScrappedN),
    ?assertEqual(Delivered, OutN),
    ?assertEqual(In, OutN + ScrappedN + InCell),
    ?assertEqual(OutN, Good + Failed),
    ?assert(Failed >= 1),
    %% Each Reset's product: its history says what happened, and it never left.
    [begin
         {ok, #{status := scrapped, events := Events}} = cell_stats:product(S),
         Kinds = [maps:get(event, E) || E <- Events],
         ?assert(lists:member(item_work_abort, Kinds)),
         ?assert(lists:member(alarm_raised, Kinds)),
         ?assert(lists:member(scrapped, Kinds)),
         ?assertNot(lists:member(S, Out))
     end || {reset, S} <- Answers],
    %% Each Ignore's product left marked failed.
    [assert_left(S, failed) || {ignore, S} <- Answers, lists:member(S, Out)].

%% Reset on "Product lost" sends the modules to the scrap bin: the product is the upper
%% robot's until they are in it. A Stop on the way leaves them in the gripper and the
%% product with the robot (the books still agree with the machine); the next Start
%% takes them to the bin, and only then is the product counted scrapped.
reset_scrap_survives_a_stop(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = await_event(fun(#{type := alarm_raised, alarm := #{id := <<"upper:lost">>}}) -> true;
                        (_) -> false
                     end),
    Serial = upper_serial(),
    ok = cell_alarms:answer(<<"upper:lost">>, reset, <<"suite">>),
    ok = stop_cell(),
    %% Stopped on the way: the modules in the gripper, the product the robot's.
    #{gripper := Serial, counters := #{scrapped := 0}} = router_sim:world(),
    ?assertMatch({ok, #{serial := Serial}}, cell_registry:task(upper)),
    #{cell := #{scrapped := 0, in := In0, out := Out0}, in_cell := InCell0} = settle(),
    ?assertEqual(In0, Out0 + InCell0),
    ?assert(lists:member(Serial, held())),
    %% Started again (the modules hold from now on): to the scrap bin first.
    ok = cell_settings:put(router_sim, #{product_lost_rate => 0.0}, <<"suite">>),
    ok = cell_events:subscribe(?EVENTS ++ [item_work_abort]),
    ok = cell_controller:start(<<"suite">>),
    ok = await_event(fun(#{type := item_work_abort, task := upper, item := S}) -> S =:= Serial;
                        (_) -> false
                     end),
    ok = stop_cell(),
    #{counters := #{scrapped := 1, delivered := Delivered}} = router_sim:world(),
    #{cell := #{scrapped := 1, in := In, out := Out}, in_cell := InCell} = settle(),
    ?assertEqual(Delivered, Out),
    ?assertEqual(In, Out + 1 + InCell),
    ?assertNot(lists:member(Serial, held())),
    ?assertEqual([Serial], scrapped()).

%% "Product lost" with the modules still in the module nest (they stuck there as the
%% robot lifted: its gripper came away empty). Reset deletes the product's data and the
%% robot goes on with an empty gripper, the nest cleared: it takes the modules out of
%% the nest to the scrap bin, so the fixture is free for the next panel and nothing the
%% books do not know of stays in the machine.
reset_clears_the_nest(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    ok = await_event(fun(#{type := alarm_raised, alarm := #{id := <<"upper:lost">>}}) -> true;
                        (#{type := alarm_raised, alarm := #{kind := error} = A}) ->
                             ct:fail({unexpected_error, A});
                        (_) -> false
                     end),
    Serial = upper_serial(),
    %% The machine as the operator finds it: the gripper empty, the modules in the nest.
    #{gripper := empty, work := #{front := {Serial, full}}} = router_sim:world(),
    #{description := Text} = hd([A || #{id := <<"upper:lost">>} = A <- cell_alarms:list()]),
    ok = cell_settings:put(router_sim, #{nest_stick_rate => 0.0}, <<"suite">>),
    ok = cell_alarms:answer(<<"upper:lost">>, reset, <<"suite">>),
    %% The line goes on: the next panels pass the fixture the modules were stuck in.
    Out = collect_out(2, fun never_answer/1),
    ok = stop_cell(),
    ?assertNot(lists:member(Serial, Out)),
    #{counters := #{scrapped := 1, delivered := Delivered}} = W = router_sim:world(),
    ?assertNotEqual({Serial, full}, maps:get(front, maps:get(work, W))),
    #{cell := #{scrapped := 1, out := Delivered}} = settle(),
    ?assertNot(lists:member(Serial, held())),
    ?assertEqual([Serial], scrapped()),
    %% The error said what Reset would do with modules left in the nest.
    ?assertNotEqual(nomatch, string:find(Text, <<"module nest">>)).

%% Conveyor jams stop a belt until the operator answers Retry (after freeing the
%% panel: here, once the simulation has it free); the magazine warning comes and goes
%% by itself, set and reset by the loading segment's code.
jams_and_magazine_warning(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Self = self(),
    %% A stuck panel moves on when its belt runs again after Retry.
    Answer = fun(#{id := Id}) -> Self ! {retry, Id}, ok end,
    {Jams, Warnings} = jam_loop(Answer, 6, {0, #{}}),
    %% A panel may stick while the cell stops: Retry lets it finish its move.
    ok = stop_cell(fun(#{id := Id, kind := error}) -> cell_alarms:answer(Id, retry, <<"suite">>);
                      (_) -> ok
                   end),
    ?assert(Jams >= 1),
    ?assertMatch(#{raised := R, cleared := C} when R >= 1 andalso C >= 1, Warnings),
    Stats = settle(),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = Stats,
    ?assertEqual(In, OutN + InCell).

%% Two lanes: both loading segments feed, the shared robots serve both, and each
%% product leaves on the unloading segment of its own lane.
dual_lane(_Config) ->
    Tasks = [Id || #{id := Id} <- cell_controller:tasks()],
    ?assertEqual(lists:sort([loading_front, loading_rear, work_front, work_rear,
                             unloading_front, unloading_rear, lower, upper,
                             clamps_front, clamps_rear]),
                 lists:sort(Tasks)),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Lanes = lanes_out(#{}, 12),
    ok = stop_cell(),
    ?assertMatch(#{front := F, rear := R} when F >= 3 andalso R >= 3, Lanes),
    #{cell := #{in := In, out := OutN}, in_cell := InCell} = settle(),
    ?assertEqual(In, OutN + InCell).

%% Stopped with panels in the machine, the node's applications stopped and started
%% again: the panels are where they were (product files, and the simulated machine's
%% world), the line goes on, no serial is lost or doubled, and the statistics still
%% add up (the time the runtime was down counts as OFF).
restart_keeps_every_panel(Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    First = collect_out(6, fun never_answer/1),
    ok = stop_cell(),
    ok = cell_stats:flush(),
    Held = held(),
    ?assert(length(Held) >= 1),
    stop(),
    ok = start(?config(root, Config)),
    ?assertEqual(lists:sort(Held), lists:sort(held())),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Second = collect_out(6, fun never_answer/1),
    ok = stop_cell(),
    Stats = settle(),
    Out = First ++ Second,
    ?assertEqual(length(Out), length(lists:usort(Out))),
    %% The panels held at the restart left after it.
    [?assert(lists:member(S, Second)) || S <- Held, not lists:member(S, held())],
    #{counters := #{delivered := Delivered}} = router_sim:world(),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = Stats,
    ?assertEqual(Delivered, OutN),
    ?assertEqual(length(Out), OutN),
    ?assertEqual(In, OutN + InCell),
    [assert_left(S, good) || S <- Out],
    assert_time_adds_up().

%% Stop while panels move, Start again at once, a few times: every transfer either
%% finishes or is taken up again; nothing is lost.
stop_and_start_while_running(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(2, fun never_answer/1),
    lists:foreach(fun(_) ->
                          ok = stop_cell(),
                          ok = cell_controller:start(<<"suite">>),
                          _ = collect_out(1, fun never_answer/1)
                  end, lists:seq(1, 4)),
    ok = stop_cell(),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = settle(),
    ?assertEqual(In, OutN + InCell),
    ?assertEqual([], cell_alarms:list()).

%% Stop at many different moments of the line's work (after a varying number of the
%% cell's events, so inside transfers, motions and waits alike): every Stop ends in
%% OFF with no error for the operator, since a move under way finishes first; and
%% after the last, every panel that entered has left or is still in the cell.
stop_at_any_moment(_Config) ->
    Rand = rand:seed_s(exsss, {7, 11, 13}),
    lists:foldl(fun(Round, R0) ->
                        {Skip, R1} = rand:uniform_s(150, R0),
                        ok = cell_events:subscribe(),
                        ok = cell_controller:start(<<"suite">>),
                        ok = skip_events(Skip),
                        ct:log("round ~b: Stop after ~b events", [Round, Skip]),
                        ok = stop_cell(),
                        R1
                end, Rand, lists:seq(1, 25)),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = settle(),
    ?assert(In > 0),
    ?assertEqual(In, OutN + InCell),
    ?assertEqual([], cell_alarms:list()).

%% Stopped with the frame in the fixture, its clamps open (the modules out) and the
%% belt not run yet: started again, the work segment runs the frame out, the clamps
%% staying open, and nobody is asked. Clamp A jams closed while the panel is routed, so
%% the Stop falls while the segment waits for it to open, whatever the machine's load;
%% it is freed once the cell is off.
frame_leaves_after_a_stop_with_the_clamps_open(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    {module, cell_handover} = code:ensure_loaded(cell_handover),
    1 = erlang:trace_pattern({cell_handover, phase, 2}, true, [local]),
    Work = cell_task_proc:whereis(work_front),
    1 = erlang:trace(Work, true, [call, {tracer, self()}]),
    ok = cell_controller:start(<<"suite">>),
    ok = await_phase(Work, offered),
    ok = router_sim:jam_clamp({front, a}),
    ok = await_phase(Work, unclamping),
    Clamps = router_cell:group(clamps, front),
    ok = await_io(Clamps, b_is_open, true),
    ok = stop_cell(),
    1 = erlang:trace(Work, false, [call]),
    _ = erlang:trace_pattern({cell_handover, phase, 2}, false, [local]),
    flush_trace(Work),
    ok = router_sim:free_clamp({front, a}),
    ok = await_io(Clamps, a_is_open, true),
    #{work := #{front := {_, frame}}} = World = router_sim:world(),
    ct:log("stopped with the frame in the fixture, the clamps open: ~tp", [World]),
    %% The frame out of the fixture before either clamp leaves its open end.
    {ok, Out} = cell_hal:watch(router_cell:group(work, front), panel_in_position, {eq, false}),
    {ok, A} = cell_hal:watch(Clamps, a_is_open, {eq, false}),
    {ok, B} = cell_hal:watch(Clamps, b_is_open, {eq, false}),
    ok = cell_controller:start(<<"suite">>),
    receive
        {cell_hal_watch, Out, false} -> ok;
        {cell_hal_watch, Ref, false} when Ref =:= A; Ref =:= B ->
            ct:fail({clamps_closed_on_the_frame, router_sim:world()})
    after ?DEADLINE_MS ->
        ct:fail({frame_never_left, router_sim:world(), cell_alarms:list()})
    end,
    _ = [cell_hal:cancel_watch(Ref) || Ref <- [A, B]],
    %% The line goes on, nobody asked.
    _ = collect_out(2, fun never_answer/1),
    ok = stop_cell(),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = settle(),
    ?assertEqual(In, OutN + InCell),
    ?assertEqual([], cell_alarms:list()).

%% The cell's monitor takes the HAL down under the physics (the cell stops) and the
%% physics restarts meanwhile: it waits for the HAL, and once the cell is back it
%% goes on from the world it saved; the line runs again.
physics_waits_for_the_hal(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(2, fun never_answer/1),
    ok = stop_cell(),
    ok = application:stop(cell),
    ?assertEqual([], cell_hal:groups()),
    Old = whereis(router_sim),
    Ref = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', Ref, process, Old, _} -> ok end,
    %% Restarted by its supervisor (which answers once it has), it waits: the
    %% simulated PLC has no points.
    [{router_sim, New, _, _}] = supervisor:which_children(router_cell_sup),
    ?assert(is_pid(New) andalso New =/= Old),
    {ok, _} = application:ensure_all_started(cell),
    await_hal(),
    %% What the tasks said as their IO went away with the old cell is history.
    drain_events(),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(3, fun never_answer/1),
    ?assertEqual(New, whereis(router_sim)),
    ok = stop_cell(),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = settle(),
    ?assertEqual(In, OutN + InCell).

%% The node stops while the line runs: every task stops as at a Stop, through its
%% uninit, while the HAL is still connected, so the spindle, the bit, the belts and
%% the SMEMA signals are off in the PLC when the monitor disconnects it.
node_stop_secures_outputs(_Config) ->
    ok = cell_controller:start(<<"suite">>),
    {ok, Ref} = cell_hal:watch(lower_io, spindle_at_speed, {eq, true}),
    receive {cell_hal_watch, Ref, _} -> ok
    after ?DEADLINE_MS -> ct:fail(spindle_never_on)
    end,
    ok = application:stop(cell),
    %% The simulated PLC's image holds what the HAL wrote before it disconnected: the
    %% PLC took each write before it acknowledged it. (Not the physics' record of the
    %% outputs: a timer of the physics may fire once the HAL is gone, and the physics
    %% then starts afresh, its record empty, while it waits for the HAL.)
    Plc = cell_hal_sim_device:whereis(router_plc),
    Safe = [{loading_front_io, belt_run}, {loading_front_io, upstream_ready},
            {work_front_io, belt_run}, {lower_io, spindle_run}, {lower_io, plunge},
            {unloading_front_io, belt_run}, {unloading_front_io, board_available}],
    ?assertEqual([{K, {ok, false}} || K <- Safe],
                 [{K, gen_server:call(Plc, {get, K})} || K <- Safe]).

%% A cell that makes products faster than its histories may grow: past the limit the
%% histories of the products that left longest ago go, and the log says so; the
%% newest and those in the cell keep theirs, and the counts are untouched.
histories_kept_within_their_limit(_Config) ->
    ok = cell_log:subscribe(),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    await_log(<<"statistics: the product histories reached 1000 records">>),
    %% The next two out (not those that left before).
    drain_events(),
    Out = collect_out(2, fun never_answer/1),
    ok = stop_cell(),
    #{cell := #{in := In, out := OutN, scrapped := 0}, in_cell := InCell} = settle(),
    ?assertEqual(In, OutN + InCell),
    ?assert(mnesia:table_info(cell_trace_event, size) =< 1000),
    ?assert(mnesia:table_info(cell_trace_product, size) < In),
    [{ok, #{events := [_ | _]}} = cell_stats:product(S) || S <- Out ++ held()].

%% With simulation off the same tasks are bound to the router's PLC over Modbus TCP,
%% each lane's groups at their own addresses; the groups pass the driver's checks.
real_mode_spec(_Config) ->
    Machine = (cell_settings_schema:defaults(cell_machine_settings))#{simulation_mode => false,
                                                                       dual_lane => true},
    Router = cell_settings_schema:defaults(router_settings),
    #{hal := #{connections := [Conn], groups := Groups}, tasks := Tasks} =
        router_cell:cell_spec(Machine, Router),
    ?assertMatch(#{driver := cell_hal_modbus, opts := #{host := "192.168.0.10", port := 502}},
                 Conn),
    %% Per lane three tasks and the clamps' unit, and the two robots.
    ?assertEqual(10, length(Tasks)),
    {ok, _} = cell_spec:validate(router_cell:cell_spec(Machine, Router)),
    %% No PLC answers at this address; the configuration is checked all the same.
    Real = Conn#{id => router_plc_real, opts => (maps:get(opts, Conn))#{host => "127.0.0.1",
                                                                        port => 1}},
    %% The running cell's own groups, besides those added here.
    Before = length(cell_hal:groups()),
    ok = cell_hal:add_connection(Real),
    try
        [ok = cell_hal:add_group(G#{id => list_to_atom(atom_to_list(Id) ++ "_real"),
                                    connection => router_plc_real})
         || #{id := Id} = G <- Groups],
        ?assertEqual(length(Groups), length(cell_hal:groups()) - Before)
    after
        [cell_hal:remove_group(list_to_atom(atom_to_list(Id) ++ "_real")) || #{id := Id} <- Groups],
        cell_hal:remove_connection(router_plc_real)
    end.

%% The shell's one-call answers say what is going on.
diagnostics(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    [Serial | _] = collect_out(2, fun never_answer/1),
    ok = cell_stats:flush(),
    Status = captured(fun cell_diag:status/0),
    ?assertNotEqual(nomatch, string:find(Status, "HAL router_plc: up")),
    ?assertNotEqual(nomatch, string:find(Status, "request start")),
    ?assertNotEqual(nomatch, string:find(Status, "Node restarts: 0 after an unexpected stop")),
    Tasks = captured(fun cell_diag:tasks/0),
    [?assertNotEqual(nomatch, string:find(Tasks, atom_to_list(T)))
     || T <- [loading_front, work_front, lower, upper, unloading_front]],
    Io = captured(fun() -> cell_diag:io(upper_io) end),
    ?assertNotEqual(nomatch, string:find(Io, "product_present")),
    ?assertNotEqual(nomatch, string:find(Io, "A4.01.02")),
    ?assertEqual({error, unknown_group}, cell_diag:io(no_such_group)),
    Product = captured(fun() -> cell_diag:product(Serial) end),
    ?assertNotEqual(nomatch, string:find(Product, "item_transfer_out")),
    ?assertNotEqual(nomatch, string:find(Product, "entered")),
    ?assertEqual({error, not_found}, cell_diag:product(<<"no such panel">>)),
    Stats = captured(fun cell_diag:stats/0),
    ?assertNotEqual(nomatch, string:find(Stats, "lower")),
    %% Tracing lasts as long as asked (the last ask counts), then the task logs as
    %% before.
    Before = cell_log:level(work_front),
    ?assertNotEqual(verbose, Before),
    ok = cell_diag:trace(work_front, 60000),
    ok = cell_diag:trace(work_front, 300),
    ?assertEqual(verbose, cell_log:level(work_front)),
    receive after 400 -> ok end,
    _ = sys:get_state(cell_log_server),
    ?assertEqual(Before, cell_log:level(work_front)),
    ?assertNotEqual(nomatch, string:find(captured(fun cell_diag:alarms/0), "No active")),
    ?assertNotEqual(nomatch, string:find(captured(fun cell_diag:top/0), "QUEUE")),
    ok = stop_cell().

%% -------------------------------------------------------------------------------------

start(Root) ->
    ok = cell_testkit:start(Root, router_cell, router_cell),
    await_hal().

%% The router's PLC connected, and its inputs read as the physics set them up: a task
%% reading them at its first Start finds the machine as it is.
await_hal() ->
    await_up(router_plc),
    ok = router_sim:ready(?DEADLINE_MS).

%% As the node stops: the physics, the cell (its monitor takes the HAL down), the
%% database; and the simulated PLC, which a new node has anew (the world it simulates
%% is on disc).
stop() ->
    cell_testkit:stop(router_cell, [router_plc]).

await_up(Conn) ->
    cell_testkit:await_connection(Conn, ?DEADLINE_MS).

%% Stop, and wait until every task is OFF; errors raised meanwhile are answered by
%% `Answer' (none is expected unless one is given).
stop_cell() ->
    stop_cell(fun never_answer/1).

stop_cell(Answer) ->
    ok = cell_events:subscribe(?EVENTS),
    cell_testkit:stop_cell(Answer, ?DEADLINE_MS).

await_event(Match) ->
    cell_testkit:await_event(Match, ?DEADLINE_MS).

%% Products the unloading segments hand out, until N have left; errors are answered
%% by `Answer'.
collect_out(N, Answer) ->
    cell_testkit:collect(N, fun(#{type := item_transfer_out, task := T, item := S}) ->
                                    is_unloading(T) andalso {true, S};
                               (_) ->
                                    false
                            end, Answer, ?DEADLINE_MS).

%% Waits for a task log line that begins with `Prefix' (the case subscribed).
await_log(Prefix) ->
    receive
        {cell_log, #{text := <<Prefix:(byte_size(Prefix))/binary, _/binary>>}} -> ok
    after ?DEADLINE_MS ->
        ct:fail({no_log_line, Prefix})
    end.

%% Waits for the traced task to enter the phase (cell_handover:phase/2 traced); an
%% error meanwhile fails the case.
await_phase(Pid, Phase) ->
    receive
        {trace, Pid, call, {cell_handover, phase, [_, Phase]}} -> ok;
        {trace, Pid, call, _} -> await_phase(Pid, Phase);
        {cell_event, #{type := alarm_raised, alarm := #{kind := error} = A}} ->
            ct:fail({unexpected_error, A});
        {cell_event, _} -> await_phase(Pid, Phase)
    after ?DEADLINE_MS ->
        ct:fail({phase_never_entered, Phase, cell_controller:tasks(), cell_alarms:list()})
    end.

flush_trace(Pid) ->
    receive {trace, Pid, _, _} -> flush_trace(Pid)
    after 0 -> ok
    end.

%% Waits for an IO point, as the HAL reads it, to have the value.
await_io(Group, Point, Value) ->
    {ok, Ref} = cell_hal:watch(Group, Point, {eq, Value}),
    receive {cell_hal_watch, Ref, Value} -> ok
    after ?DEADLINE_MS -> ct:fail({io_never, Group, Point, Value, router_sim:world()})
    end.

%% Lets N events of the cell pass; an error among them fails the case.
skip_events(0) ->
    ok;
skip_events(N) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := #{kind := error} = A}} ->
            ct:fail({unexpected_error, A});
        {cell_event, _} ->
            skip_events(N - 1)
    after ?DEADLINE_MS ->
        ct:fail({no_event, cell_controller:tasks()})
    end.

drain_events() ->
    receive {cell_event, _} -> drain_events()
    after 0 -> ok
    end.

never_answer(#{kind := error} = A) -> ct:fail({unexpected_error, A});
never_answer(_) -> ok.

is_unloading(T) -> lists:member(T, [unloading_front, unloading_rear]).

%% Answers "Product lost" by the policy until N have been answered (or, the other
%% way, until M products have left); returns the answers with the serial each was
%% about, and what left.
answer_lost(Policy, N) ->
    answer_lost(Policy, N, infinity).

answer_lost(Policy, N, M) ->
    answer_lost(Policy, {N, M}, 0, [], [], erlang:monotonic_time(millisecond) + ?DEADLINE_MS * 2).

answer_lost(_Policy, {N, _}, N, Answers, Out, _Deadline) ->
    {lists:reverse(Answers), lists:reverse(Out)};
answer_lost(_Policy, {_, M}, _Done, Answers, Out, _Deadline) when length(Out) =:= M ->
    {lists:reverse(Answers), lists:reverse(Out)};
answer_lost(Policy, N, Done, Answers, Out, Deadline) ->
    receive
        {cell_event, #{type := alarm_raised,
                       alarm := #{id := <<"upper:lost">> = Id, kind := error}}} ->
            Serial = upper_serial(),
            Solution = Policy(Done),
            ok = cell_alarms:answer(Id, Solution, <<"suite">>),
            answer_lost(Policy, N, Done + 1, [{Solution, Serial} | Answers], Out, Deadline);
        {cell_event, #{type := alarm_raised, alarm := #{kind := error} = A}} ->
            ct:fail({unexpected_error, A});
        {cell_event, #{type := item_transfer_out, task := T, item := S}} ->
            case is_unloading(T) of
                true -> answer_lost(Policy, N, Done, Answers, [S | Out], Deadline);
                false -> answer_lost(Policy, N, Done, Answers, Out, Deadline)
            end;
        {cell_event, _} ->
            answer_lost(Policy, N, Done, Answers, Out, Deadline)
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail({only_answered, Done, cell_controller:tasks(), cell_alarms:list(),
                 [cell_task_proc:info(T) || T <- [upper, lower]]})
    end.

upper_serial() ->
    {ok, #{serial := S}} = cell_registry:task(upper),
    S.

%% Retries every jam once its panel is free; counts jams and the warning's comings
%% and goings until N products left.
jam_loop(_Answer, 0, {Jams, Warnings}) ->
    {Jams, Warnings};
jam_loop(Answer, N, {Jams, W} = Acc) ->
    receive
        {retry, Id} ->
            ok = cell_alarms:answer(Id, retry, <<"suite">>),
            jam_loop(Answer, N, Acc);
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, caption := C} = A}} ->
            lists:member(C, [<<"Conveyor jam">>, <<"Work segment fault">>])
                orelse ct:fail({unexpected_error, A}),
            ok = Answer(A),
            jam_loop(Answer, N, {Jams + 1, W});
        {cell_event, #{type := alarm_raised, alarm := #{kind := warning,
                                                        caption := <<"Panel magazine low">>}}} ->
            jam_loop(Answer, N, {Jams, maps:update_with(raised, fun(X) -> X + 1 end, 1, W)});
        {cell_event, #{type := alarm_cleared, alarm := #{kind := warning, cleared := cleared}}} ->
            jam_loop(Answer, N, {Jams, maps:update_with(cleared, fun(X) -> X + 1 end, 1, W)});
        {cell_event, #{type := item_transfer_out, task := T}} ->
            case is_unloading(T) of
                true -> jam_loop(Answer, N - 1, Acc);
                false -> jam_loop(Answer, N, Acc)
            end;
        {cell_event, _} ->
            jam_loop(Answer, N, Acc)
    after ?DEADLINE_MS ->
        ct:fail({stuck, Acc, cell_controller:tasks(), cell_alarms:list()})
    end.

lanes_out(Lanes, 0) ->
    Lanes;
lanes_out(Lanes, N) ->
    receive
        {cell_event, #{type := item_transfer_out, task := T, item := S}} ->
            case T of
                unloading_front -> check_lane(S, front), lanes_out(inc(front, Lanes), N - 1);
                unloading_rear -> check_lane(S, rear), lanes_out(inc(rear, Lanes), N - 1);
                _ -> lanes_out(Lanes, N)
            end;
        {cell_event, _} ->
            lanes_out(Lanes, N)
    after ?DEADLINE_MS ->
        ct:fail({only, Lanes, cell_controller:tasks(), cell_alarms:list()})
    end.

%% A product leaves on its own lane: it entered on the loading segment of that lane.
check_lane(Serial, Lane) ->
    {ok, #{entry_task := Entry}} = cell_stats:product(Serial),
    ?assertEqual(Entry, case Lane of front -> loading_front; rear -> loading_rear end).

inc(K, M) -> maps:update_with(K, fun(X) -> X + 1 end, 1, M).

%% The statistics once every product the tasks dropped has been found scrapped (two
%% writes without a holder) and written.
settle() ->
    ok = cell_stats:flush(),
    ok = cell_stats:flush(),
    ok = cell_stats:flush(),
    cell_stats:summary(total).

scrapped() ->
    lists:sort(mnesia:dirty_select(cell_trace_product,
                                   [{{cell_trace_product, '$1', #{status => scrapped}}, [], ['$1']}])).

held() ->
    [S || #{serial := S} <- cell_controller:tasks(), is_binary(S)].

assert_left(Serial, Quality) ->
    {ok, #{status := out, events := Events} = Info} = cell_stats:product(Serial),
    ?assertEqual(Quality =:= failed, maps:get(failed, Info)),
    Kinds = [maps:get(event, E) || E <- Events],
    ?assertEqual(entered, hd(Kinds)),
    ?assertEqual(left, lists:last(Kinds)),
    %% It passed every station.
    Tasks = lists:usort([T || #{event := item_transfer_in, task := T} <- Events]),
    ?assertEqual(5, length(Tasks)).

%% For every task, the time in each state adds up to the time since it was first seen
%% to the last write, to the microsecond.
assert_time_adds_up() ->
    [?assertEqual({T, Span}, {T, Sum}) || {T, Sum, Span} <- router_release_probe:time_check()].

captured(Fun) ->
    ct:capture_start(),
    _ = Fun(),
    ct:capture_stop(),
    lists:flatten(ct:capture_get()).
