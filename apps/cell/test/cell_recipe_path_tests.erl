%% The path a recipe drawing gives an interpolation channel (cell_recipe_path): cut
%% items in ExecOrder, in drawing coordinates; lines, arcs, circles and polylines with
%% bulges made lines and arcs whose ends and lengths are checked by hand.
-module(cell_recipe_path_tests).
-include_lib("eunit/include/eunit.hrl").

-define(D, cell_recipe_drawing).
-define(EPS, 1.0e-9).

cut(Order) ->
    #{<<"ItemType">> => <<"Cut">>, <<"ExecOrder">> => integer_to_binary(Order)}.

path(Drawing) ->
    {ok, Segs} = cell_recipe_path:from_drawing(Drawing, <<"Cut">>),
    {ok, Path} = cell_hal_path:new(Segs),
    Path.

near({X0, Y0, Z0}, {X1, Y1, Z1}) ->
    abs(X0 - X1) + abs(Y0 - Y1) + abs(Z0 - Z1) < 1.0e-6.

exec_order_and_transform_test() ->
    %% Two cuts given out of order, the second in a container moved by (100, 0).
    Drawing = ?D:new([?D:container(#{<<"Transform">> => ?D:matrix_to_text(?D:translation(100, 0, 0))},
                                   [?D:line({0, 0}, {10, 0}, cut(2))]),
                      ?D:line({0, 0}, {0, 10}, cut(1)),
                      ?D:line({5, 5}, {6, 6}, #{<<"ItemType">> => <<"Fiducial">>})]),
    Path = path(Drawing),
    ?assertEqual({0.0, 0.0, 0.0}, cell_hal_path:start(Path)),
    ?assertEqual({110.0, 0.0, 0.0}, cell_hal_path:finish(Path)),
    %% The first cut, the connecting line to the second (from (0,10) to (100,0)), the
    %% second.
    ?assertMatch([{line, path, 10.0}, {line, connecting, _}, {line, path, 10.0}],
                 cell_hal_path:segments(Path)).

arcs_and_circles_test() ->
    %% A half circle of radius 5 about (10, 0), 0° to 180°, then a full circle.
    Path = path(?D:new([?D:arc({10, 0}, 5, 0, 180, cut(1)), ?D:circle({10, 0}, 5, cut(2))])),
    ?assert(near({15.0, 0.0, 0.0}, cell_hal_path:start(Path))),
    ?assert(abs(cell_hal_path:length(Path) - (5 * math:pi() + 10 * math:pi() + 10)) < 1.0e-6),
    ?assert(near({5.0, 0.0, 0.0}, cell_hal_path:at(Path, 5 * math:pi()))).

polyline_bulges_test() ->
    %% No bulge: a line. A bulge of 1 is a half circle counter-clockwise, -1 clockwise:
    %% from (0,0) to (10,0) counter-clockwise about (5,0) it passes through (5,-5).
    Pl = ?D:polyline([{0, 0}, {10, 0}], false, cut(1)),
    ?assert(abs(cell_hal_path:length(path(?D:new([Pl]))) - 10) < ?EPS),
    Half = path(?D:new([Pl#{bulges := [1.0, 0.0]}])),
    ?assert(abs(cell_hal_path:length(Half) - 5 * math:pi()) < 1.0e-6),
    ?assert(near({5.0, -5.0, 0.0}, cell_hal_path:at(Half, 5 * math:pi() / 2))),
    Cw = path(?D:new([Pl#{bulges := [-1.0, 0.0]}])),
    ?assert(near({5.0, 5.0, 0.0}, cell_hal_path:at(Cw, 5 * math:pi() / 2))),
    ?assert(near({10.0, 0.0, 0.0}, cell_hal_path:finish(Cw))),
    %% A quarter bulge (tan 22.5°): a 90° arc, its chord √2·r.
    Q = path(?D:new([Pl#{bulges := [math:tan(math:pi() / 8), 0.0]}])),
    R = 10 / math:sqrt(2),
    ?assert(abs(cell_hal_path:length(Q) - R * math:pi() / 2) < 1.0e-6),
    ?assert(near({10.0, 0.0, 0.0}, cell_hal_path:finish(Q))).

closed_polyline_test() ->
    Path = path(?D:new([?D:polyline([{0, 0}, {4, 0}, {4, 3}], true, cut(1))])),
    ?assertEqual(12.0, cell_hal_path:length(Path)),
    ?assertEqual({0.0, 0.0, 0.0}, cell_hal_path:finish(Path)).

refused_test() ->
    ?assertEqual({error, no_items},
                 cell_recipe_path:from_drawing(?D:new([?D:line({0, 0}, {1, 0})]), <<"Cut">>)),
    ?assertMatch({error, {not_a_path, _}},
                 cell_recipe_path:from_drawing(
                   ?D:new([?D:polyface([{0, 0}, {1, 0}, {0, 1}], [[1, 2, 3]], cut(1))]),
                   <<"Cut">>)).

%% One item on its own (a cut followed by itself): a container's lines in tree order,
%% as the drawing places them; a mesh or an empty container is no path.
of_item_test() ->
    Drawing = ?D:new([?D:container(cut(1), [?D:line({0, 0}, {10, 0}),
                                            ?D:line({10, 0}, {10, 5})]),
                      ?D:line({0, 0}, {0, 10}, cut(2))]),
    [First, Second] = cell_recipe_drawing:items_by_type(Drawing, <<"Cut">>),
    ?assertEqual({ok, [{line, {0.0, 0.0, 0.0}, {10.0, 0.0, 0.0}},
                       {line, {10.0, 0.0, 0.0}, {10.0, 5.0, 0.0}}]},
                 cell_recipe_path:of_item(First)),
    ?assertEqual({ok, [{line, {0.0, 0.0, 0.0}, {0.0, 10.0, 0.0}}]},
                 cell_recipe_path:of_item(Second)),
    ?assertEqual({error, no_items}, cell_recipe_path:of_item(?D:container(cut(3), []))),
    ?assertMatch({error, {not_a_path, _}},
                 cell_recipe_path:of_item(?D:polyface([{0, 0}, {1, 0}, {0, 1}], [[1, 2, 3]]))).
