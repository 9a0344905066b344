%% @doc The default cell's throughput: panels per hour the simulated inline router
%% passes with a panel always waiting upstream and no faults,
%% <ul>
%% <li>with every physical delay set to zero: the runtime's own ceiling (device tasks,
%%     handshakes, the HAL polling the simulated PLC every 20 ms, product files,
%%     statistics), beside the line's theoretical maximum;</li>
%% <li>with the real machine's delays (run at a quarter of their length and counted
%%     back to machine time): the line's throughput as a share of its theoretical
%%     maximum.</li>
%% </ul>
%% for one lane (the cell `make run' starts) and for two.
%%
%% The theoretical maximum is that of the bottleneck station when it never waits:
%% each station's busy time per panel is the sum of the physical delays it cannot
%% overlap (settings `router_sim', the demo recipes' cut lines at their feed), see
%% {@link busy/3}. No schedule can pass more. Run at a quarter of the delays, the
%% runtime's fixed latencies (a poll period per sensor change, about thirty changes
%% per panel on the bottleneck) weigh four times what they would at full length: the
%% share measured is a lower bound of the real machine's.
-module(router_bench).

-export([run/0, busy/3]).

-define(WARMUP, 4).
-define(ZERO_PANELS, 60).
-define(REAL_PANELS, 12).
-define(REAL_SCALE, 0.25).
-define(TIMEOUT_MS, 120000).

-spec run() -> [cell_bench:result()].
run() ->
    lists:append([lane(Dual) || Dual <- [false, true]]).

lane(Dual) ->
    Lanes = case Dual of true -> "two lanes"; false -> "one lane" end,
    Sim = cell_settings_schema:defaults(router_sim_settings),
    Router = cell_settings_schema:defaults(router_settings),
    {Theory, Bottleneck} = theoretical(Dual, Router, Sim),
    Zero = measure(Dual, 0.0, ?ZERO_PANELS),
    Real = measure(Dual, ?REAL_SCALE, ?REAL_PANELS) * ?REAL_SCALE,
    Peer = io_lib:format("theoretical maximum (bottleneck: ~s)", [Bottleneck]),
    [#{title => ["Panels per hour, ", Lanes, ", physical delays zero (the runtime's ceiling)"],
       unit => "panels/h", ours => Zero, peer => Theory, peer_name => Peer,
       better => higher, goal => "ratio > 10: the runtime is never the bottleneck"},
     #{title => ["Panels per hour, ", Lanes, ", real delays (", fmt(?REAL_SCALE),
                 " time scale, machine time)"],
       unit => "panels/h", ours => Real, peer => Theory, peer_name => Peer,
       better => higher, goal => "ratio > 0.8 of the theoretical maximum",
       note => io_lib:format(
                 "Router, ~s: at zero delay the bottleneck takes ~.2f s a panel, the "
                 "runtime's own time (mostly one HAL poll, 20 ms, per sensor change it "
                 "waits for). Run at ~s of the machine's delays that time weighs ~b "
                 "times what it does on the machine: at full length the line would pass "
                 "about ~b% of its theoretical maximum. Both robots move on axes "
                 "(paths and lines of their interpolation channels, with the profiles' "
                 "accelerations, which the theoretical maximum counts too) at a speed "
                 "override of 100 %. The inspection at the unloading exit is switched "
                 "off: the cell runs without the application that answers the lanes' "
                 "inspection blocks (cell_inspect_bench measures the block), and an "
                 "unanswered block holds each panel for the inspection's timeout.",
                 [Lanes, 3600 / Zero, fmt(?REAL_SCALE), round(1 / ?REAL_SCALE),
                  round(100 * (3600000 / Theory) / (3600000 / Theory + 3600000 / Zero))])}].

%% Panels per hour of wall-clock time at a time scale, after a warm-up.
measure(Dual, Scale, Panels) ->
    router_bench_cell:panels_per_hour(
      #{settings => router_bench_cell:settings(#{scale => Scale, dual_lane => Dual})},
      #{warmup => ?WARMUP, panels => Panels, timeout => ?TIMEOUT_MS}).

%% The bottleneck's panels per hour, and its name.
theoretical(Dual, Router, Sim) ->
    Busy = busy(Dual, Router, Sim),
    {Station, Ms} = hd(lists:reverse(lists:keysort(2, Busy))),
    {3600000 / Ms, Station}.

%% @doc Each station's busy time per panel passed by the line, in ms of machine time,
%% when it never waits for another: a lane's stations serve every other panel with two
%% lanes, the robots every panel. The work segment holds a panel from its transfer in
%% until the frame is out: transfer, clamp, routing, the upper robot reaching the nest
%% and gripping, unclamp, eject. The routing robot routes, then waits for the upper
%% robot to grip (it takes over the modules from the routing robot's nest then). The
%% upper robot moves to the nest (of the other lane, with two lanes), grips, moves to
%% the unloading segment, lets go.
-spec busy(boolean(), map(), map()) -> [{string(), float()}].
busy(Dual, Router, Sim) ->
    D = fun(K) -> maps:get(K, Sim) * 1.0 end,
    Routing = routing(Dual, Router, Sim),
    Share = case Dual of true -> 0.5; false -> 1.0 end,
    {ToNest, ToUnloading} = upper(Dual, Router),
    Pick = ToNest + D(gripper_ms),
    [{"loading segment", Share * (D(intake_ms) + D(transfer_ms))},
     {"work segment", Share * (D(transfer_ms) + D(clamp_ms) + Routing + Pick + D(clamp_ms)
                               + D(eject_ms))},
     {"routing robot", Routing + Pick},
     {"upper robot", ToNest + ToUnloading + 2 * D(gripper_ms)},
     {"unloading segment", Share * (D(unload_ms) + D(handout_ms))}].

%% The routing robot's time for one panel, the lanes' panels routed in turn: the
%% spindle up to speed, then per cut a rapid move from where the last one ended (the
%% rear fixture lies further back), the bit down, the cut at its feed, the bit up; each
%% move the trapezoidal profile the robot's channel plans for it.
routing(Dual, Router, Sim) ->
    Demo = router_recipes:demo(),
    Cuts = fun(Recipe, Offset) ->
                   #{drawing := Drawing} = proplists:get_value(maps:get(Recipe, Router), Demo),
                   [C#{from := {X1, Y1 + Offset}, to := {X2, Y2 + Offset}}
                    || #{from := {X1, Y1}, to := {X2, Y2}} = C
                           <- router_recipes:cuts(Drawing, maps:get(feed_rate, Router))]
           end,
    Panels = [Cuts(recipe_front, 0.0)]
        ++ [Cuts(recipe_rear, maps:get(rear_lane_offset, Router)) || Dual],
    #{to := Start} = lists:last(lists:last(Panels)),
    Rapid = maps:get(rapid_speed, Router),
    Plunge = maps:get(plunge_ms, Sim),
    {Ms, _} = lists:foldl(
                fun(#{from := {X, Y}, to := To, length := L, feed := F}, {Acc, {Px, Py}}) ->
                        Move = move_s(rapid, math:sqrt((X - Px) * (X - Px) + (Y - Py) * (Y - Py)),
                                      Rapid),
                        {Acc + 1000 * (Move + move_s(feed, L, F)) + 2 * Plunge, To}
                end, {0.0, Start}, lists:append(Panels)),
    Ms / length(Panels) + maps:get(spindle_ramp_ms, Sim).

%% The upper robot's moves for one panel, in ms: from the unloading segment it last
%% served to the next panel's nest (across to the other lane with two lanes), and on to
%% the unloading segment; each the trapezoidal profile its channel plans for the line.
upper(Dual, Router) ->
    Dx = maps:get(upper_unloading_x, Router) - maps:get(upper_nest_x, Router),
    Dy = case Dual of
             true -> maps:get(rear_lane_offset, Router);
             false -> 0.0
         end,
    Params = router_upper_task:path_params(maps:get(upper_speed, Router)),
    Ms = fun(L) ->
                 1000 * cell_hal_axis_profile:duration(
                          cell_hal_axis_profile:move({0.0, 0.0}, L, Params))
         end,
    {Ms(math:sqrt(Dx * Dx + Dy * Dy)), Ms(abs(Dx))}.

%% The seconds a path of `L' mm takes from rest to rest.
move_s(Kind, L, Speed) ->
    Profile = cell_hal_axis_profile:move({0.0, 0.0}, L, router_lower_task:path_params(Kind, Speed)),
    cell_hal_axis_profile:duration(Profile).

fmt(X) -> float_to_list(X, [{decimals, 2}]).
