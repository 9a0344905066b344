%% Trapezoidal motion profiles of one axis: accelerate, cruise, decelerate, each
%% segment at a constant acceleration, as an NC plans a point-to-point move. Pure.
%%
%% A move may start with the axis already moving (a newer move that aborts the one
%% running): if it cannot stop at the target from its speed, or moves away from it, it
%% first decelerates to a stop and then moves back. A speed above the new move's
%% velocity is brought down with its deceleration. The profile ends exactly at the
%% target, at rest.
%%
%% The speed override is a time base, as in an NC: a profile is sampled at its own time
%% `Tau', which the axis advances at `override' times the real time (at 0 the axis holds
%% its place; velocities are scaled by the override, accelerations by its square), so
%% changing the override never needs a new profile.
-module(cell_hal_axis_profile).

-export([move/3, stop/2, at/2, duration/1, target/1]).

-export_type([profile/0]).

%% Segments of constant acceleration: {Duration, X0, V0, A}.
-type segment() :: {float(), float(), float(), float()}.
-opaque profile() :: #{segments := [segment()], target := float(), duration := float()}.

%% @doc A move from position X0 at velocity V0 to `Target' with the move's velocity,
%% acceleration and deceleration (all positive).
-spec move({number(), number()}, number(), #{velocity := number(), acceleration := number(),
                                             deceleration := number()}) -> profile().
move({X0, V0}, Target, #{velocity := Vmax, acceleration := Acc, deceleration := Dec}) ->
    Segments = plan(float(X0), float(V0), float(Target), float(Vmax), float(Acc), float(Dec)),
    profile(Segments, float(Target)).

%% @doc Decelerates from X0 at V0 to a stop with `Dec' (halt, stop, a fault's stop).
-spec stop({number(), number()}, number()) -> profile().
stop({X0, V0}, Dec) ->
    {Segments, X1} = brake(float(X0), float(V0), float(Dec)),
    profile(Segments, X1).

%% @doc Position and velocity `Tau' seconds into the profile (at its target, at rest,
%% after its end).
-spec at(profile(), number()) -> {float(), float()}.
at(#{target := Target, duration := D}, Tau) when Tau >= D ->
    {Target, 0.0};
at(#{segments := Segments, target := Target}, Tau) ->
    sample(Segments, float(Tau), Target).

-spec duration(profile()) -> float().
duration(#{duration := D}) -> D.

%% @doc Where the profile ends.
-spec target(profile()) -> float().
target(#{target := T}) -> T.

%%--------------------------------------------------------------------

profile(Segments, Target) ->
    Kept = [S || {D, _, _, _} = S <- Segments, D > 0.0],
    #{segments => Kept, target => Target,
      duration => lists:foldl(fun({D, _, _, _}, Acc) -> Acc + D end, 0.0, Kept)}.

plan(X0, V0, Target, Vmax, Acc, Dec) ->
    Dist = Target - X0,
    Dir = sign(Dist),
    if
        V0 /= 0.0, (Dir * V0 < 0.0 orelse V0 * V0 / (2 * Dec) > abs(Dist)) ->
            %% Moving away, or too fast to stop at the target: stop first.
            {Brake, X1} = brake(X0, V0, Dec),
            Brake ++ plan(X1, 0.0, Target, Vmax, Acc, Dec);
        Dist == 0.0 ->
            [];
        true ->
            towards(X0, abs(V0), Dir, abs(Dist), Vmax, Acc, Dec)
    end.

%% From X0 at speed U (towards the target, able to stop there) over distance D.
towards(X0, U, Dir, D, Vmax, Acc, Dec) ->
    Peak = math:sqrt((D + U * U / (2 * Acc)) / (1 / (2 * Acc) + 1 / (2 * Dec))),
    if
        U > Vmax ->
            %% Faster than this move allows: down to its velocity, cruise, stop.
            D1 = (U * U - Vmax * Vmax) / (2 * Dec),
            Cruise = D - D1 - Vmax * Vmax / (2 * Dec),
            chain(X0, Dir, [{(U - Vmax) / Dec, U, -Dec}, {max(Cruise, 0.0) / Vmax, Vmax, 0.0},
                            {Vmax / Dec, Vmax, -Dec}]);
        Peak =< Vmax ->
            %% A triangle: the move is too short to reach its velocity.
            chain(X0, Dir, [{(Peak - U) / Acc, U, Acc}, {Peak / Dec, Peak, -Dec}]);
        true ->
            D1 = (Vmax * Vmax - U * U) / (2 * Acc),
            Cruise = D - D1 - Vmax * Vmax / (2 * Dec),
            chain(X0, Dir, [{(Vmax - U) / Acc, U, Acc}, {max(Cruise, 0.0) / Vmax, Vmax, 0.0},
                            {Vmax / Dec, Vmax, -Dec}])
    end.

%% Segments given as {Duration, speed at start, acceleration along Dir}, placed one
%% after the other from X0.
chain(_X, _Dir, []) ->
    [];
chain(X, Dir, [{T, U, A} | Rest]) ->
    [{T, X, Dir * U, Dir * A} | chain(X + Dir * (U * T + A * T * T / 2), Dir, Rest)].

brake(X0, V0, _Dec) when V0 == 0.0 ->
    {[], X0};
brake(X0, V0, Dec) ->
    T = abs(V0) / Dec,
    {[{T, X0, V0, -sign(V0) * Dec}], X0 + V0 * abs(V0) / (2 * Dec)}.

sample([], _Tau, Target) ->
    {Target, 0.0};
sample([{D, X0, V0, A} | _], Tau, _Target) when Tau < D ->
    T = max(Tau, 0.0),
    {X0 + V0 * T + A * T * T / 2, V0 + A * T};
sample([{D, _, _, _} | Rest], Tau, Target) ->
    sample(Rest, Tau - D, Target).

sign(X) when X > 0 -> 1.0;
sign(X) when X < 0 -> -1.0;
sign(_) -> 0.0.
