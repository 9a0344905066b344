%% @doc The lower routing robot (seed 000 §2.3): takes charge of a panel clamped in a
%% work segment's fixture (either lane), routes it along the cut lines of its recipe in
%% ExecOrder, and offers the routed modules to the upper robot.
%%
%% <pre>
%%  phase     waits for                                      then
%%  idle      a work segment's offer (STARVED)               commit (phase 2) → taking
%%  taking    the segment's Available off (phase 3)          complete (phase 4, ItemTransferIn);
%%                                                           the recipe from the buffer → routing
%%  routing   the bit lifted, the axes ready, the spindle     after each cut the count of cuts
%%            at speed; per cut (EXECUTING): a rapid move     done is saved with the product, so
%%            to the cut's start, the bit plunged, the cut    a restart goes on at the next cut;
%%            followed, the bit lifted; each with a           all done: spindle off,
%%            watchdog                                        ItemWorkComplete → routed
%%  routed    -                                              offer to the upper robot (phase 1,
%%                                                           BLOCKED) → offered
%%  offered   the upper robot's NotBusy                      release at once: the modules lie in
%%                                                           the nest for it to lift → released
%%  released  the upper robot's NotBusy off                  ItemTransferOut → idle
%% </pre>
%%
%% The robot's X and Y are NC axes (seed 000 §2.1: `LowerRobotTask.Axes'), and its moves
%% are paths of their interpolation channel (§2.3.7): the rapid move a line from where
%% the axes stand to the cut's start, the cut its recipe's own lines and arcs
%% (cell_recipe_path) at its feed, shifted across to the rear lane's fixture for a panel
%% there. Each move is started in a step and its end waited for as a reply. Before the
%% first cut the axes are made ready, one command at a time: a path the channel still
%% follows (a predecessor's, or one cut short by a watchdog) halted, an axis in error
%% reset, its drive powered, the axis homed. An axis's fault (a following error) is the
%% task's error naming the axis and the NC's code; RETRY makes the axes ready again and
%% does the stage again.
%%
%% Restarted (reconcile), the product says how far routing got: all cuts done, routed
%% (spindle off); otherwise routing goes on at the next cut after the bit is lifted,
%% whatever the robot's outputs were; no product, spindle and bit off, idle.
-module(router_lower_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).
-export([path_params/2]).

%% Path accelerations, mm/s²: between cuts, and along a cut.
-define(RAPID_ACC, 2000.0).
-define(FEED_ACC, 1000.0).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T0) ->
    {_, T} = cell_handover:reset_chosen(T0),
    %% The cut list is made again from the recipe: a stage cut short is done again.
    {ok, cell_task:put(cell_task:put(T, cuts, undefined), resume, undefined)}.

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

%% The spindle stops, the bit is lifted and the axes halt; the panel stays clamped.
-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    ok = router_axes:halt(channel(T)),
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
    %% A path still under way is given up: the stage starts again on Retry.
    ok = router_axes:halt(channel(T)),
    {error, cell_task:error_spec(
              <<"motion">>, "Routing robot fault",
              io_lib:format("The routing robot did not finish \"~ts\" in time (panel ~ts).~n"
                            "Check the robot and the spindle, then select RETRY to do it "
                            "again.", [cell_task:get(T, stage), serial(T)]),
              [retry]),
     T};
step(routing, {reply, _, Failed}, T) when Failed =/= done ->
    axis_fault(Failed, T);
step(routing, Woken, T) ->
    case {cell_task:get(T, cuts, undefined), Woken} of
        {undefined, {answer, ignore}} -> unrouted(T);
        {undefined, _} -> load_recipe(T);
        %% After a fault: the axes made ready again, then the stage from its start.
        {_, {answer, retry}} -> stage(axes, cell_task:put(T, resume, cell_task:get(T, stage)));
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
next_stage(retract_first, T) -> stage(axes, T);
%% One command to the axes done: what else do they need?
next_stage(axes, T) -> stage(axes, T);
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
stage(axes, T) ->
    case router_axes:prepare(channel(T), axes(T)) of
        ready ->
            case cell_task:get(T, resume) of
                undefined -> stage(spindle, T);
                Stage -> stage(Stage, cell_task:put(T, resume, undefined))
            end;
        Started ->
            motion(T, axes, Started)
    end;
stage(rapid, T) ->
    #{from := Start} = cut(T),
    case router_axes:position(axes(T)) of
        {ok, Here} ->
            To = machine(T, Start),
            case router_axes:there(Here, To) of
                true ->
                    next_stage(rapid, T);
                false ->
                    Speed = cell_task:setting(T, rapid_speed, 400.0),
                    motion(T, rapid, router_axes:line(channel(T), Here, To,
                                                      path_params(rapid, Speed)))
            end;
        Failed ->
            axis_fault(Failed, T)
    end;
stage(plunge, T) ->
    wait_io(cell_task:out(T, plunge, true), plunge, plunged, true);
stage(feed, T) ->
    #{segments := Segments, feed := Feed} = cut(T),
    {ok, Path} = cell_hal_path:new([shift(T, Segment) || Segment <- Segments]),
    follow(T, feed, Path, Feed);
stage(retract, T) ->
    wait_io(cell_task:out(T, plunge, false), retract, plunged, false).

%% @doc The path velocity, acceleration and deceleration of a rapid move between cuts or
%% of a cut, at `Speed' (mm/s).
-spec path_params(rapid | feed, float()) -> cell_hal_axis_fsm:params().
path_params(rapid, Speed) -> #{velocity => Speed, acceleration => ?RAPID_ACC, deceleration => ?RAPID_ACC};
path_params(feed, Speed) -> #{velocity => Speed, acceleration => ?FEED_ACC, deceleration => ?FEED_ACC}.

%% The channel follows `Path'; the stage waits for its end.
follow(T, Stage, Path, Speed) ->
    Params = path_params(Stage, Speed),
    motion(T, Stage, cell_hal_channel:follow(channel(T), Path, Params)).

motion(T, Stage, {ok, Ref}) ->
    {wait, [{reply, Ref}, router_task:watchdog(T, motion_timeout_ms, 30000)],
     cell_task:put(T, stage, Stage)};
motion(T, Stage, Refused) ->
    axis_fault(Refused, cell_task:put(T, stage, Stage)).

%% A move refused, failed or aborted: the task's error, naming the axis.
axis_fault(Failed, T) ->
    {Axis, What} = router_axes:failed(Failed, channel(T), axes(T)),
    {error, cell_task:error_spec(
              <<"axis">>, "Routing robot axis fault",
              io_lib:format("Axis ~ts of the routing robot stopped \"~ts\" (panel ~ts): "
                            "~ts.~nCheck the robot, then select RETRY: the axes are made "
                            "ready again and the move is made again.",
                            [Axis, cell_task:get(T, stage), serial(T), What]),
              [retry]),
     T}.

wait_io(T, Stage, Point, Value) ->
    {wait, [{io, Point, {eq, Value}}, router_task:watchdog(T, motion_timeout_ms, 30000)],
     cell_task:put(T, stage, Stage)}.

cut(T) ->
    #{cuts_done := Done} = cell_task:product(T),
    lists:nth(Done + 1, cell_task:get(T, cuts)).

%% A point of the panel in the robot's coordinates: the rear fixture lies further back.
machine(T, {X, Y}) ->
    {X, Y + offset(T)}.

%% A cut's segment in the robot's coordinates, on the tool's plane (Z 0).
shift(T, {line, {X1, Y1, _}, {X2, Y2, _}}) ->
    {line, {X1, Y1 + offset(T), 0.0}, {X2, Y2 + offset(T), 0.0}};
shift(T, Arc) when element(1, Arc) =:= arc ->
    {Cx, Cy, _} = element(2, Arc),
    setelement(2, Arc, {Cx, Cy + offset(T), 0.0}).

offset(T) ->
    case cell_task:product(T) of
        #{lane := rear} -> cell_task:setting(T, rear_lane_offset, 350.0);
        _ -> 0.0
    end.

serial(T) ->
    case cell_task:product(T) of
        #{serial := S} -> S;
        undefined -> <<"-">>
    end.

prevs(T) -> cell_task:arg(T, prevs, []).
axes(T) -> cell_task:arg(T, axes, [lower_x, lower_y]).
channel(T) -> cell_task:arg(T, channel, lower_xy).
next(T) -> cell_task:arg(T, next, undefined).

phase(T, Phase) -> cell_handover:phase(T, Phase).
