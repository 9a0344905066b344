%% PropEr properties of the axis's trapezoidal profiles, from what a move must be on a
%% machine: it ends exactly at its target and at rest, its position and velocity are
%% continuous (no jump a drive could not follow), it never exceeds the move's velocity
%% unless it began faster (and then only slows), its acceleration stays within the
%% move's acceleration and deceleration, and it takes no longer than the slowest sane
%% plan. A stop comes to rest with its deceleration.
-module(prop_cell_hal_axis_profile).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(P, cell_hal_axis_profile).
%% Samples per profile, to check continuity and bounds between them.
-define(SAMPLES, 400).
-define(EPS, 1.0e-6).

properties_test_() ->
    [{timeout, 120, ?_assert(proper:quickcheck(P, [{to_file, user}, {numtests, N}]))}
     || {P, N} <- [{prop_move_ends_at_target_at_rest(), 1000},
                   {prop_move_is_continuous_and_bounded(), 500},
                   {prop_stop_comes_to_rest(), 500}]].

%% Worked examples a reader can check by hand.
examples_test_() ->
    Params = #{velocity => 100, acceleration => 1000, deceleration => 500},
    %% 0 -> 100 in 0.1 s over 5 mm; 100 -> 0 in 0.2 s over 10 mm; 85 mm cruise.
    Long = ?P:move({0, 0}, 100, Params),
    %% Too short to reach 100: a triangle.
    Short = ?P:move({0, 0}, 3, Params),
    [?_assertEqual(1.15, round_to(?P:duration(Long), 6)),
     ?_assertEqual({5.0, 100.0}, rounded(?P:at(Long, 0.1))),
     ?_assertEqual({100.0, 0.0}, ?P:at(Long, 2.0)),
     ?_assert(lists:max([abs(element(2, ?P:at(Short, T / 100))) || T <- lists:seq(0, 30)])
              < 100),
     %% Moving at 100 towards -10 from 0: stops first (10 mm), then comes back.
     ?_assertEqual(-10.0, ?P:target(?P:move({0, 100}, -10, Params))),
     ?_assertEqual({10.0, 0.0}, rounded(?P:at(?P:move({0, 100}, -10, Params), 0.2))),
     ?_assertEqual(10.0, ?P:target(?P:stop({0, 100}, 500))),
     ?_assertEqual(0.0, ?P:duration(?P:move({5, 0}, 5, Params)))].

%%--------------------------------------------------------------------

start() ->
    {range(-1000, 1000), oneof([0, range(-300, 300)])}.

params() ->
    ?LET({V, A, D}, {range(1, 500), range(1, 5000), range(1, 5000)},
         #{velocity => V, acceleration => A, deceleration => D}).

prop_move_ends_at_target_at_rest() ->
    ?FORALL({From, Target, Params}, {start(), range(-1000, 1000), params()},
            begin
                Profile = ?P:move(From, Target, Params),
                Duration = ?P:duration(Profile),
                {X, V} = ?P:at(Profile, Duration),
                {XLast, VLast} = ?P:at(Profile, Duration * (1 - 1.0e-9)),
                ?WHENFAIL(io:format("~p~n", [{Duration, {X, V}, {XLast, VLast}}]),
                          X == float(Target) andalso V == 0.0
                          andalso abs(XLast - Target) < 1.0e-3
                          andalso abs(VLast) < 1.0e-3 * max(1, maps:get(deceleration, Params)))
            end).

prop_move_is_continuous_and_bounded() ->
    ?FORALL({{X0, V0} = From, Target, Params}, {start(), range(-1000, 1000), params()},
            begin
                #{velocity := Vmax, acceleration := Acc, deceleration := Dec} = Params,
                Profile = ?P:move(From, Target, Params),
                Duration = ?P:duration(Profile),
                Dt = Duration / ?SAMPLES,
                Samples = [?P:at(Profile, I * Dt) || I <- lists:seq(0, ?SAMPLES)],
                Pairs = lists:zip(lists:droplast(Samples), tl(Samples)),
                %% Between samples the velocity changes by at most the larger of the
                %% two accelerations times the step, the position by the speed.
                AMax = max(Acc, Dec),
                VBound = max(Vmax, abs(V0)),
                Starts = hd(Samples) =:= {float(X0), float(V0)} orelse Duration == 0.0,
                Jumps = [P || {{Xa, Va}, {Xb, Vb}} = P <- Pairs,
                              abs(Vb - Va) > AMax * Dt * (1 + ?EPS) + ?EPS
                              orelse abs(Xb - Xa) > VBound * Dt * (1 + ?EPS) + ?EPS],
                TooFast = [V || {_, V} <- Samples, abs(V) > VBound * (1 + ?EPS)],
                %% Starting faster than the move's velocity, it only ever slows to it.
                Speeding = [V || abs(V0) =< Vmax, {_, V} <- Samples,
                                 abs(V) > Vmax * (1 + ?EPS)],
                ?WHENFAIL(io:format("~p~n", [{Duration, Starts, lists:sublist(Jumps, 3),
                                              lists:sublist(TooFast, 3), Speeding}]),
                          Starts andalso Jumps =:= [] andalso TooFast =:= []
                          andalso Speeding =:= [])
            end).

prop_stop_comes_to_rest() ->
    ?FORALL({{X0, V0}, Dec}, {start(), range(1, 5000)},
            begin
                Profile = ?P:stop({X0, V0}, Dec),
                Duration = ?P:duration(Profile),
                Expected = X0 + V0 * abs(V0) / (2 * Dec),
                {X, V} = ?P:at(Profile, Duration),
                %% A stop takes |V0| / Dec, and its velocity falls all the way.
                abs(Duration - abs(V0) / Dec) < ?EPS andalso V == 0.0
                    andalso abs(X - Expected) < ?EPS
                    andalso lists:all(fun(I) ->
                                              {_, Vi} = ?P:at(Profile, Duration * I / 10),
                                              abs(Vi) =< abs(V0) + ?EPS
                                      end, lists:seq(0, 10))
            end).

round_to(X, N) ->
    F = math:pow(10, N),
    round(X * F) / F.

rounded({X, V}) ->
    {round_to(X, 6), round_to(V, 6)}.
