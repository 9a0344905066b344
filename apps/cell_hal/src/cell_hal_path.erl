%% The path an interpolation channel follows (seed 000 §2.3.7: multi-axis
%% interpolation, TwinCAT NC's NcChannel): lines and arcs, measured and sampled by
%% their length along the path. Pure.
%%
%% Segments:
%% <ul>
%% <li>`{line, From, To}' — a straight line, points `{X, Y, Z}';</li>
%% <li>`{arc, Center, Radius, StartAngle, EndAngle}' — an arc in the XY plane at the
%%   centre's Z, counter-clockwise from the start angle to the end angle in degrees, as
%%   DXF and the recipe drawing give it (an end below the start goes round through
%%   360; equal angles are a full circle); `{arc, Center, Radius, Start, End, cw}' runs
%%   the other way, from Start clockwise to End.</li>
%% </ul>
%% Where a segment does not start where the previous one ended (the next cut of a
%% drawing elsewhere on the panel), a straight connecting line is put in between; it
%% is marked as such, so a tool can be lifted over it.
%%
%% A point of the path is asked for by its distance from the start (`at/2'), found by
%% a binary search over the segments' cumulative lengths, so a path of ten thousand
%% segments costs a few comparisons per sample.
-module(cell_hal_path).

-export([new/1, from/2, length/1, at/2, segment_at/2, segments/1, moves/1, start/1,
         finish/1]).
-compile({no_auto_import, [length/1]}).

-export_type([path/0, segment/0, point/0, move/0]).

-type point() :: {number(), number(), number()}.
%% A segment as an NC program says it, from where the one before ended: a line to a
%% point, or an arc to a point round a centre, clockwise or counter-clockwise.
-type move() :: {line, To :: point(), path | connecting}
              | {arc, To :: point(), Center :: point(), cw | ccw, path | connecting}.
-type segment() :: {line, point(), point()}
                 | {arc, point(), number(), number(), number()}
                 | {arc, point(), number(), number(), number(), cw | ccw}.

%% Per segment: {StartS, Length, Kind, connecting | path}; Kind is
%% {line, P0, P1} or {arc, {Cx, Cy, Z}, R, Theta0 (rad), Sweep (rad, signed)}.
-record(path, {segs :: tuple(), length :: float(), start :: point(), finish :: point()}).
-opaque path() :: #path{}.

%% @doc A path from its segments, connecting lines put in where one does not start at
%% the previous one's end; refused: an empty list, a malformed segment, a radius not
%% positive (naming the segment by its position, 1-based).
-spec new([segment()]) -> {ok, path()} | {error, term()}.
new([]) ->
    {error, empty_path};
new(Segments) when is_list(Segments) ->
    case parse(Segments, 1, []) of
        {ok, Parsed} -> {ok, build(Parsed)};
        {error, _} = Error -> Error
    end;
new(_) ->
    {error, not_a_list}.

%% @doc The path begun at `Point' (where the axes stand): a connecting line to its
%% start put in front when it starts elsewhere.
-spec from(path(), point()) -> path().
from(#path{segs = Segs}, Point) ->
    {ok, P} = pt(Point),
    build(P, [Kind || {_, _, Kind, path} <- tuple_to_list(Segs)]).

%% @doc The path's length.
-spec length(path()) -> float().
length(#path{length = L}) -> L.

%% @doc Where the path begins.
-spec start(path()) -> {float(), float(), float()}.
start(#path{start = P}) -> P.

%% @doc Where the path ends.
-spec finish(path()) -> {float(), float(), float()}.
finish(#path{finish = P}) -> P.

%% @doc The point `S' along the path (clamped to the path: its start before 0, its end
%% past its length).
-spec at(path(), number()) -> {float(), float(), float()}.
at(#path{start = P}, S) when S =< 0 -> P;
at(#path{length = L, finish = P}, S) when S >= L -> P;
at(#path{segs = Segs} = Path, S) ->
    I = find(Segs, float(S), 1, tuple_size(Segs)),
    {S0, _Len, Kind, _} = element(I, Segs),
    point(Kind, S - S0, Path).

%% @doc Which segment `S' lies on, 1-based, of how many, and whether it is a
%% connecting line: the progress a channel reports.
-spec segment_at(path(), number()) -> {pos_integer(), pos_integer(), path | connecting}.
segment_at(#path{segs = Segs}, S) ->
    N = tuple_size(Segs),
    I = if S =< 0 -> 1;
           true -> find(Segs, float(S), 1, N)
        end,
    {I, N, element(4, element(I, Segs))}.

%% @doc The segments as the path has them, connecting lines included.
-spec segments(path()) -> [{line | arc, path | connecting, float()}].
segments(#path{segs = Segs}) ->
    [{element(1, Kind), Role, Len} || {_, Len, Kind, Role} <- tuple_to_list(Segs)].

%% @doc The segments as moves from the path's start ({@link start/1}), in order,
%% connecting lines included: what an NC's part program is written from.
-spec moves(path()) -> [move()].
moves(#path{segs = Segs}) ->
    [move(Kind, Role) || {_, _, Kind, Role} <- tuple_to_list(Segs)].

move({line, _, B}, Role) ->
    {line, B, Role};
move({arc, Center, _, _, Sweep} = Arc, Role) ->
    Dir = case Sweep < 0 of true -> cw; false -> ccw end,
    {arc, last(Arc), Center, Dir, Role}.

%%--------------------------------------------------------------------

parse([], _I, Acc) ->
    {ok, lists:reverse(Acc)};
parse([Seg | Rest], I, Acc) ->
    case segment(Seg) of
        {ok, Kind} -> parse(Rest, I + 1, [Kind | Acc]);
        error -> {error, {bad_segment, I, Seg}}
    end.

segment({line, From, To}) ->
    case {pt(From), pt(To)} of
        {{ok, A}, {ok, B}} -> {ok, {line, A, B}};
        _ -> error
    end;
segment({arc, C, R, A0, A1}) ->
    segment({arc, C, R, A0, A1, ccw});
segment({arc, C, R, A0, A1, Dir}) when is_number(R), R > 0, is_number(A0), is_number(A1),
                                       (Dir =:= cw orelse Dir =:= ccw) ->
    case pt(C) of
        {ok, Center} ->
            Sweep0 = case Dir of
                         ccw -> norm360(A1 - A0);
                         cw -> -norm360(A0 - A1)
                     end,
            {ok, {arc, Center, float(R), rad(A0), rad(Sweep0)}};
        error ->
            error
    end;
segment(_) ->
    error.

%% A sweep of 0 is the full circle.
norm360(D) ->
    case D - 360 * math:floor(D / 360) of
        Z when Z == 0 -> 360.0;
        Z -> float(Z)
    end.

rad(Deg) -> Deg * math:pi() / 180.

pt({X, Y, Z}) when is_number(X), is_number(Y), is_number(Z) -> {ok, {float(X), float(Y), float(Z)}};
pt({X, Y}) when is_number(X), is_number(Y) -> {ok, {float(X), float(Y), 0.0}};
pt(_) -> error.

build(Kinds) ->
    build(first(hd(Kinds)), Kinds).

%% Laid from Start: a connecting line put in wherever the next segment begins
%% elsewhere, the first included.
build(Start, Kinds) ->
    {Segs, Length, Finish} = lay(Kinds, Start, 0.0, []),
    #path{segs = list_to_tuple(Segs), length = Length, start = Start, finish = Finish}.

lay([], At, S, Acc) ->
    {lists:reverse(Acc), S, At};
lay([Kind | Rest], At, S, Acc) ->
    From = first(Kind),
    case dist(At, From) > 1.0e-9 of
        true ->
            Gap = dist(At, From),
            lay([Kind | Rest], From, S + Gap, [{S, Gap, {line, At, From}, connecting} | Acc]);
        false ->
            Len = len(Kind),
            lay(Rest, last(Kind), S + Len, [{S, Len, Kind, path} | Acc])
    end.

first({line, A, _}) -> A;
first({arc, _, _, _, _} = Arc) -> arc_point(Arc, 0.0).

last({line, _, B}) -> B;
last({arc, _, _, _, Sweep} = Arc) -> arc_point(Arc, Sweep).

len({line, A, B}) -> dist(A, B);
len({arc, _, R, _, Sweep}) -> R * abs(Sweep).

arc_point({arc, {Cx, Cy, Z}, R, Theta0, _}, Angle) ->
    T = Theta0 + Angle,
    {Cx + R * math:cos(T), Cy + R * math:sin(T), Z}.

%% The point D into a segment.
point({line, {X0, Y0, Z0} = A, B}, D, _Path) ->
    case dist(A, B) of
        L when L == 0.0 -> A;
        L ->
            {X1, Y1, Z1} = B,
            F = min(max(D / L, 0.0), 1.0),
            {X0 + F * (X1 - X0), Y0 + F * (Y1 - Y0), Z0 + F * (Z1 - Z0)}
    end;
point({arc, _, R, _, Sweep} = Arc, D, _Path) ->
    Sign = case Sweep < 0 of true -> -1; false -> 1 end,
    arc_point(Arc, Sign * min(max(D / R, 0.0), abs(Sweep))).

%% The last segment starting at or before S (binary search over start lengths).
find(_Segs, _S, Lo, Lo) ->
    Lo;
find(Segs, S, Lo, Hi) ->
    Mid = (Lo + Hi + 1) div 2,
    case element(1, element(Mid, Segs)) =< S of
        true -> find(Segs, S, Mid, Hi);
        false -> find(Segs, S, Lo, Mid - 1)
    end.

dist({X0, Y0, Z0}, {X1, Y1, Z1}) ->
    math:sqrt((X1 - X0) * (X1 - X0) + (Y1 - Y0) * (Y1 - Y0) + (Z1 - Z0) * (Z1 - Z0)).
