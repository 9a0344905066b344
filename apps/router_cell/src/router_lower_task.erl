%% @doc The lower routing robot (seed 000 §2.3): takes charge of a panel clamped in a
%% work segment's fixture (either lane), routes it along the cut lines of its recipe in
%% ExecOrder, and offers the routed modules to the upper robot.
%%
%% <pre>
%%  phase     waits for                                      then
%%  idle      a work segment's offer (STARVED)               commit (phase 2) → taking
%%  taking    the segment's Available off (phase 3)          complete (phase 4, ItemTransferIn);
%%                                                           the recipe from the buffer → routing
%%  routing   per cut (EXECUTING): the spindle at speed,     after each cut the count of cuts
%%            a rapid move to the cut's start, the bit        done is saved with the product, so
%%            plunged, the feed along the cut, the bit        a restart goes on at the next cut;
%%            lifted; each with a watchdog                    all done: spindle off,
%%                                                           ItemWorkComplete → routed
%%  routed    -                                              offer to the upper robot (phase 1,
%%                                                           BLOCKED) → offered
%%  offered   the upper robot's NotBusy                      release at once: the modules lie in
%%                                                           the nest for it to lift → released
%%  released  the upper robot's NotBusy off                  ItemTransferOut → idle
%% </pre>
%%
%% A move takes the time its path needs at its feed (the robot's controller
%% interpolates); the task writes the target, the path length and the feed, then a new
%% command number, and waits for the controller to report that number done.
%%
%% Restarted (reconcile), the product says how far routing got: all cuts done, routed
%% (spindle off); otherwise routing goes on at the next cut after the bit is lifted,
%% whatever the robot's outputs were; no product, spindle and bit off, idle.
-module(router_lower_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T0) ->
    {_, T} = cell_handover:reset_chosen(T0),
    %% Go on counting commands from the controller's last answer.
    %% The cut list is made again from the recipe: a stage cut short is done again.
    {ok, cell_task:put(cell_task:put(T, command, cell_task:in(T, done)), cuts, undefined)}.

%% How far routing got is saved with the product (cuts done); the robot's own state
%% (bit down, spindle running) is not trusted: routing goes on by lifting the bit first.
-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    case cell_task:product(T) of
        undefined ->
            {ok, phase(cell_task:out(cell_task:out(T, spindle_run, false), plunge, false), idle)};
        #{cuts_total := N, cuts_done := N} ->
            {ok, phase(cell_task:out(T, spindle_run, false), routed)};
        _ ->
            %% Routing was cut short: lift the bit, then on from the next cut.
            {ok, phase(cell_handshake:confirm_here(T), routing)}
    end.

%% The spindle stops and the bit is lifted; the panel stays clamped.
-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    cell_task:out(cell_task:out(T, spindle_run, false), plunge, false).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

%% -- empty: take a clamped panel from either lane ---------------------------------------
step(idle, _Woken, T) ->
    case [L || L <- prevs(T), cell_handshake:available(T, L)] of
        [Link | _] ->
            case cell_handshake:commit(T, Link) of
                {ok, T1} ->
                    {wait, {handshake, Link, available, false},
                     phase(cell_task:put(T1, from, Link), taking)};
                {not_available, T1} ->
                    {wait, [{handshake, L, available, true} || L <- prevs(T1)], T1}
            end;
        [] ->
            {wait, [{handshake, L, available, true} || L <- prevs(T)], T}
    end;
step(taking, {handshake, _Link, interrupted}, T) ->
    cell_handover:interrupted(T, routing, idle);
step(taking, {handshake, Link, available, false}, T) ->
    T1 = cell_handshake:complete(T, Link),
    {continue, phase(T1, routing)};
step(taking, _Woken, T) ->
    {wait, {handshake, cell_task:get(T, from), available, false}, T};
%% -- routing ------------------------------------------------------------------------------
step(routing, {timer, _}, T) ->
    {error, cell_task:error_spec(
              <<"motion">>, "Routing robot fault",
              io_lib:format("The routing robot did not finish \"~ts\" in time (panel ~ts).~n"
                            "Check the robot and the spindle, then select RETRY to do it "
                            "again.", [cell_task:get(T, stage), serial(T)]),
              [retry]),
     T};
step(routing, Woken, T) ->
    case {cell_task:get(T, cuts, undefined), Woken} of
        {undefined, {answer, ignore}} -> unrouted(T);
        {undefined, _} -> load_recipe(T);
        %% After a fault: the stage again, from its start.
        {_, {answer, retry}} -> stage(cell_task:get(T, stage), T);
        {_, _} -> next_stage(cell_task:get(T, stage), T)
    end;
step(routed, _Woken, T) ->
    T1 = cell_handshake:offer(cell_task:put(T, cuts, undefined), next(T)),
    {wait, {handshake, next(T), not_busy, true}, phase(T1, offered)};
step(offered, {handshake, Next, not_busy, true}, T) ->
    T1 = cell_handshake:release(T, Next),
    {wait, {handshake, Next, not_busy, false}, phase(T1, released)};
step(offered, _Woken, T) ->
    cell_handover:offered(T, next(T), routed);
step(released, {handshake, _Next, interrupted}, T) ->
    cell_handover:interrupted(T, routed, idle);
step(released, _Woken, T) ->
    cell_handover:finish(T, next(T), idle, routed);
step(in_transit, _Woken, T) ->
    {continue, phase(cell_handshake:confirm_here(T), routing)}.

%% The recipe comes from the buffer (seed §3.2.3): read from its file once per Start.
load_recipe(T) ->
    #{recipe := Name} = cell_task:product(T),
    case cell_recipe_buffer:get(Name) of
        {ok, #{drawing := Drawing}} ->
            Cuts = router_recipes:cuts(Drawing, cell_task:setting(T, feed_rate, 25.0)),
            P = cell_task:product(T),
            T1 = cell_task:set_product(T, P#{cuts_total => length(Cuts),
                                             cuts_done => maps:get(cuts_done, P, 0),
                                             modules => router_recipes:modules(Drawing)}),
            T2 = cell_task:work_start(cell_task:put(T1, cuts, Cuts)),
            cell_task:log(T2, verbose, "routing ~ts: ~b cuts", [serial(T2), length(Cuts)]),
            %% The bit up first: after a restart it may be down.
            stage(retract_first, T2);
        {error, Why} ->
            {error, cell_task:error_spec(
                      <<"recipe">>, "Recipe not available",
                      io_lib:format("The recipe ~ts of panel ~ts cannot be loaded: ~ts.~n"
                                    "Select RETRY once the recipe is in place, or IGNORE to "
                                    "pass the panel on unrouted, marked failed.",
                                    [Name, serial(T), cell_recipe:format_error(Why)]),
                      [retry, ignore]),
             T}
    end.

unrouted(T) ->
    P = cell_task:product(T),
    T1 = cell_task:set_product(T, P#{failed => true, cuts_total => 0, cuts_done => 0,
                                     note => <<"not routed: its recipe was not available">>}),
    {continue, phase(cell_task:work_abort(T1, <<"recipe not available">>), routed)}.

%% What follows a stage that is done.
next_stage(retract_first, T) -> stage(spindle, T);
next_stage(spindle, T) -> next_cut(T);
next_stage(rapid, T) -> stage(plunge, T);
next_stage(plunge, T) -> stage(feed, T);
next_stage(feed, T) -> stage(retract, T);
next_stage(retract, T) ->
    P = cell_task:product(T),
    next_cut(cell_task:set_product(T, P#{cuts_done => maps:get(cuts_done, P) + 1})).

next_cut(T) ->
    #{cuts_done := Done, cuts_total := Total} = cell_task:product(T),
    case Done < Total of
        true ->
            stage(rapid, T);
        false ->
            T1 = cell_task:work_complete(cell_task:out(T, spindle_run, false)),
            cell_task:log(T1, brief, "panel ~ts routed", [serial(T1)]),
            {continue, phase(cell_task:put(T1, cuts, undefined), routed)}
    end.

%% Commands one stage and waits for it.
stage(retract_first, T) ->
    wait_io(cell_task:out(T, plunge, false), retract_first, plunged, false);
stage(spindle, T) ->
    wait_io(cell_task:out(T, spindle_run, true), spindle, spindle_at_speed, true);
stage(rapid, T) ->
    #{from := Start} = cut(T),
    Here = {cell_task:in(T, pos_x), cell_task:in(T, pos_y)},
    Target = machine(T, Start),
    move(T, rapid, Target, dist(Here, Target), cell_task:setting(T, rapid_speed, 400.0));
stage(plunge, T) ->
    wait_io(cell_task:out(T, plunge, true), plunge, plunged, true);
stage(feed, T) ->
    #{to := End, length := Length, feed := Feed} = cut(T),
    move(T, feed, machine(T, End), Length, Feed);
stage(retract, T) ->
    wait_io(cell_task:out(T, plunge, false), retract, plunged, false).

move(T, Stage, {X, Y}, Path, Feed) ->
    Command = cell_task:get(T, command) + 1,
    T1 = lists:foldl(fun({Point, V}, Acc) -> cell_task:out(Acc, Point, V) end, T,
                     [{target_x, X}, {target_y, Y}, {path_mm, float(Path)},
                      {feed, float(Feed)}, {command, Command}]),
    {wait, [{io, done, {eq, Command}}, router_task:watchdog(T, motion_timeout_ms, 30000)],
     cell_task:put(cell_task:put(T1, command, Command), stage, Stage)}.

wait_io(T, Stage, Point, Value) ->
    {wait, [{io, Point, {eq, Value}}, router_task:watchdog(T, motion_timeout_ms, 30000)],
     cell_task:put(T, stage, Stage)}.

cut(T) ->
    #{cuts_done := Done} = cell_task:product(T),
    lists:nth(Done + 1, cell_task:get(T, cuts)).

%% A point of the panel in the robot's coordinates: the rear fixture lies further back.
machine(T, {X, Y}) ->
    case cell_task:product(T) of
        #{lane := rear} -> {X, Y + cell_task:setting(T, rear_lane_offset, 350.0)};
        _ -> {X, Y}
    end.

dist({X1, Y1}, {X2, Y2}) ->
    math:sqrt((X2 - X1) * (X2 - X1) + (Y2 - Y1) * (Y2 - Y1)).

serial(T) ->
    case cell_task:product(T) of
        #{serial := S} -> S;
        undefined -> <<"-">>
    end.

prevs(T) -> cell_task:arg(T, prevs, []).
next(T) -> cell_task:arg(T, next, undefined).

phase(T, Phase) -> cell_handover:phase(T, Phase).
