%% PropEr properties of the interpolation channel's path (cell_hal_path), from what a
%% path must be to a machine: its length is the sum of its lines' and arcs' lengths
%% (the connecting lines included); it starts at its first segment's start and ends at
%% its last one's end; walking it never jumps (two points of it are never further
%% apart than the distance along it between them); each arc's points lie on its
%% circle; and a segment's end is where the next begins.
-module(prop_cell_hal_path).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(P, cell_hal_path).
-define(EPS, 1.0e-6).

properties_test_() ->
    [{timeout, 120, ?_assert(proper:quickcheck(P, [{to_file, user}, {numtests, N}]))}
     || {P, N} <- [{prop_length_and_ends(), 500},
                   {prop_never_jumps(), 300},
                   {prop_arcs_on_their_circle(), 300}]].

%% Worked examples.
examples_test_() ->
    {ok, Square} = ?P:new([{line, {0, 0}, {10, 0}}, {line, {10, 0}, {10, 10}},
                           {line, {10, 10}, {0, 10}}, {line, {0, 10}, {0, 0}}]),
    %% A quarter circle of radius 10 about the origin, from 0° to 90°.
    {ok, Quarter} = ?P:new([{arc, {0, 0}, 10, 0, 90}]),
    %% Two cuts apart: a connecting line between them.
    {ok, Two} = ?P:new([{line, {0, 0}, {5, 0}}, {line, {5, 5}, {9, 5}}]),
    %% The same quarter clockwise: from 90° down to 0°.
    {ok, Cw} = ?P:new([{arc, {0, 0}, 10, 90, 0, cw}]),
    [?_assertEqual(40.0, ?P:length(Square)),
     ?_assertEqual({10.0, 5.0, 0.0}, ?P:at(Square, 15)),
     ?_assertEqual({2, 4, path}, ?P:segment_at(Square, 15)),
     ?_assertEqual({0.0, 0.0, 0.0}, ?P:at(Square, 40)),
     ?_assert(abs(?P:length(Quarter) - 5 * math:pi()) < ?EPS),
     ?_assert(near({0.0, 10.0, 0.0}, ?P:at(Quarter, ?P:length(Quarter)))),
     ?_assert(near({10 * math:cos(math:pi() / 4), 10 * math:sin(math:pi() / 4), 0.0},
                   ?P:at(Quarter, ?P:length(Quarter) / 2))),
     ?_assertEqual(14.0, ?P:length(Two)),
     ?_assertEqual([{line, path, 5.0}, {line, connecting, 5.0}, {line, path, 4.0}],
                   ?P:segments(Two)),
     %% As moves from the start: each to its end, arcs with centre and direction.
     ?_assertEqual([{line, {5.0, 0.0, 0.0}, path}, {line, {5.0, 5.0, 0.0}, connecting},
                    {line, {9.0, 5.0, 0.0}, path}], ?P:moves(Two)),
     ?_assertMatch([{arc, {X, Y, 0.0}, {0.0, 0.0, 0.0}, ccw, path}]
                       when abs(X) < ?EPS andalso abs(Y - 10) < ?EPS, ?P:moves(Quarter)),
     ?_assertMatch([{arc, {X, Y, 0.0}, {0.0, 0.0, 0.0}, cw, path}]
                       when abs(X - 10) < ?EPS andalso abs(Y) < ?EPS, ?P:moves(Cw)),
     ?_assertEqual({2, 3, connecting}, ?P:segment_at(Two, 7)),
     ?_assert(near({0.0, 10.0, 0.0}, ?P:at(Cw, 0))),
     ?_assert(near({10.0, 0.0, 0.0}, ?P:at(Cw, ?P:length(Cw)))),
     %% A full circle: start angle = end angle.
     ?_assert(abs(?P:length(element(2, ?P:new([{arc, {0, 0}, 1, 30, 30}]))) - 2 * math:pi())
              < ?EPS),
     %% Begun elsewhere: a connecting line to the start in front.
     ?_assertEqual(45.0, ?P:length(?P:from(Square, {0, -5, 0}))),
     ?_assertEqual({1, 5, connecting}, ?P:segment_at(?P:from(Square, {0, -5, 0}), 2)),
     ?_assertEqual({10.0, 0.0, 0.0}, ?P:at(?P:from(Square, {0, -5, 0}), 15)),
     ?_assertEqual(Square, ?P:from(Square, {0, 0, 0})),
     ?_assertEqual({error, empty_path}, ?P:new([])),
     ?_assertEqual({error, {bad_segment, 2, {arc, {0, 0}, 0, 0, 90}}},
                   ?P:new([{line, {0, 0}, {1, 0}}, {arc, {0, 0}, 0, 0, 90}]))].

%%--------------------------------------------------------------------

coord() -> range(-500, 500).

pt() -> {coord(), coord(), range(-50, 50)}.

segment() ->
    oneof([{line, pt(), pt()},
           {arc, pt(), range(1, 300), range(0, 359), range(0, 359)},
           {arc, pt(), range(1, 300), range(0, 359), range(0, 359), cw}]).

path_segments() ->
    non_empty(list(segment())).

%% Each given segment's own length.
own_length({line, A, B}) -> dist(fl(A), fl(B));
own_length({arc, C, R, A0, A1}) -> own_length({arc, C, R, A0, A1, ccw});
own_length({arc, _, R, A0, A1, Dir}) ->
    D = case Dir of ccw -> A1 - A0; cw -> A0 - A1 end,
    Sweep = case D rem 360 of 0 -> 360; X when X < 0 -> X + 360; X -> X end,
    R * Sweep * math:pi() / 180.

prop_length_and_ends() ->
    ?FORALL(Segs, path_segments(),
            begin
                {ok, Path} = ?P:new(Segs),
                Listed = ?P:segments(Path),
                Own = lists:sum([own_length(S) || S <- Segs]),
                Gaps = lists:sum([L || {_, connecting, L} <- Listed]),
                L = ?P:length(Path),
                abs(L - (Own + Gaps)) < ?EPS * max(1, L)
                    andalso ?P:at(Path, 0) =:= ?P:start(Path)
                    andalso ?P:at(Path, L) =:= ?P:finish(Path)
                    andalso length([x || {_, path, _} <- Listed]) =:= length(Segs)
            end).

prop_never_jumps() ->
    ?FORALL(Segs, path_segments(),
            begin
                {ok, Path} = ?P:new(Segs),
                L = ?P:length(Path),
                N = 500,
                Ss = [L * I / N || I <- lists:seq(0, N)],
                Pts = [?P:at(Path, S) || S <- Ss],
                Steps = lists:zip(lists:droplast(Pts), tl(Pts)),
                Jumps = [{A, B} || {A, B} <- Steps, dist(A, B) > L / N + ?EPS * max(1, L)],
                ?WHENFAIL(io:format("~p~n", [lists:sublist(Jumps, 3)]), Jumps =:= [])
            end).

prop_arcs_on_their_circle() ->
    ?FORALL({C, R, A0, A1, Dir}, {pt(), range(1, 300), range(0, 359), range(0, 359),
                                  oneof([cw, ccw])},
            begin
                {ok, Path} = ?P:new([{arc, C, R, A0, A1, Dir}]),
                L = ?P:length(Path),
                {Cx, Cy, Cz} = fl(C),
                lists:all(fun(I) ->
                                  {X, Y, Z} = ?P:at(Path, L * I / 50),
                                  abs(math:sqrt((X - Cx) * (X - Cx) + (Y - Cy) * (Y - Cy)) - R)
                                      < ?EPS * R andalso Z == Cz
                          end, lists:seq(0, 50))
            end).

fl({X, Y, Z}) -> {float(X), float(Y), float(Z)}.

dist({X0, Y0, Z0}, {X1, Y1, Z1}) ->
    math:sqrt((X1 - X0) * (X1 - X0) + (Y1 - Y0) * (Y1 - Y0) + (Z1 - Z0) * (Z1 - Z0)).

near(A, B) -> dist(A, B) < ?EPS.
