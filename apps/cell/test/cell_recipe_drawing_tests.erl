%% The recipe drawing: building, validation of every field, JSON round trips of
%% drawings of random shape, items by type in ExecOrder, transforms (checked against
%% the geometry, not the code).
-module(cell_recipe_drawing_tests).

-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(D, cell_recipe_drawing).
-define(EPS, 1.0e-6).

%%====================================================================
%% Examples
%%====================================================================

build_test() ->
    L = ?D:line({0, 0}, {10, 5}),
    ?assertEqual(#{kind => line, attrs => #{}, from => {0.0, 0.0, 0.0}, to => {10.0, 5.0, 0.0}}, L),
    D = ?D:new([L, ?D:container(#{<<"ItemType">> => <<"Fiducial">>}, [?D:circle({1, 1}, 2)])]),
    ?assertEqual({ok, D}, ?D:validate(D)),
    ?assertEqual(2, ?D:count(D)),
    ?assertEqual(<<"Fiducial">>, ?D:item_type(lists:last(maps:get(children, D)))),
    ?assertEqual(undefined, ?D:exec_order(L)),
    ?assertEqual(7, ?D:exec_order(?D:set_attr(L, <<"ExecOrder">>, <<" 7 ">>))),
    %% integers in hand-built input become floats
    {ok, #{children := [#{radius := R}]}} =
        ?D:validate(#{kind => container, attrs => #{}, children => [#{kind => circle, attrs => #{},
                                                                       center => {1, 2, 3}, radius => 4}]}),
    ?assertEqual(4.0, R).

validation_test_() ->
    C = fun(Children) -> #{kind => container, attrs => #{}, children => Children} end,
    Line = ?D:line({0, 0}, {1, 1}),
    V = fun(D) -> ?D:validate(D) end,
    Err = fun(Path, Why) -> {error, {invalid, Path, Why}} end,
    Deep = lists:foldl(fun(_, Acc) -> C([Acc]) end, Line, lists:seq(1, 65)),
    [?_assertEqual(Err([], {not_a_container, line}), V(Line)),
     ?_assertEqual(Err([], {not_a_container, not_an_item}), V(42)),
     ?_assertEqual(Err([children, 1, kind], {unknown_kind, spline}),
                   V(C([#{kind => spline, attrs => #{}}]))),
     ?_assertEqual(Err([children, 1, to], missing),
                   V(C([maps:remove(to, Line)]))),
     ?_assertEqual(Err([children, 1, colour], unknown_field), V(C([Line#{colour => red}]))),
     ?_assertEqual(Err([children, 1, from, y], {not_a_number, <<"1">>}),
                   V(C([Line#{from := {0, <<"1">>, 0}}]))),
     ?_assertEqual(Err([children, 1, from], {not_a_point, {0, 0}}), V(C([Line#{from := {0, 0}}]))),
     ?_assertEqual(Err([children, 1, radius], {not_positive, 0.0}),
                   V(C([(?D:circle({0, 0}, 1))#{radius := 0.0}]))),
     ?_assertEqual(Err([children, 1, points], fewer_than_two_points),
                   V(C([?D:polyline([{0, 0}], false)]))),
     ?_assertEqual(Err([children, 1, bulges], {not_one_per_point, [0.0]}),
                   V(C([(?D:polyline([{0, 0}, {1, 1}], false))#{bulges := [0.0]}]))),
     ?_assertEqual(Err([children, 1, closed], {not_a_boolean, yes}),
                   V(C([(?D:polyline([{0, 0}, {1, 1}], false))#{closed := yes}]))),
     ?_assertEqual(Err([children, 1, faces, 2, 3], {no_such_vertex, 4}),
                   V(C([?D:polyface([{0, 0}, {1, 0}, {0, 1}], [[1, 2, 3], [3, 2, 4]])]))),
     ?_assertEqual(Err([children, 1, faces, 1], {not_a_face, [1, 2]}),
                   V(C([?D:polyface([{0, 0}, {1, 0}, {0, 1}], [[1, 2]])]))),
     ?_assertEqual(Err([children, 1, attrs, <<"ExecOrder">>], {not_an_integer, <<"first">>}),
                   V(C([?D:line({0, 0}, {1, 1}, #{<<"ExecOrder">> => <<"first">>})]))),
     ?_assertEqual(Err([children, 1, attrs, <<"Note">>], {not_text, 5}),
                   V(C([?D:line({0, 0}, {1, 1}, #{<<"Note">> => 5})]))),
     ?_assertEqual(Err([attrs, <<"Transform">>], {not_a_matrix, <<"1 0 0">>}),
                   V(#{kind => container, attrs => #{<<"Transform">> => <<"1 0 0">>}, children => []})),
     ?_assertEqual(Err([attrs, <<"Transform">>],
                       {not_affine, <<"1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1">>}),
                   V(#{kind => container, attrs => #{<<"Transform">> => <<"1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1">>},
                       children => []})),
     ?_assertEqual(Err([children, 1, children], {not_a_list, x}),
                   V(C([#{kind => container, attrs => #{}, children => x}]))),
     ?_assertMatch({error, {invalid, _, too_deep}}, V(Deep))].

matrix_text_test_() ->
    [?_assertEqual({ok, ?D:translation(5, -2.5, 0.5)},
                   ?D:parse_matrix(<<"1,0,0,5; 0 1 0 -2.5\n0 0 1 .5  0 0 0 1">>)),
     ?_assertEqual({ok, ?D:scaling(1.0e3, 1.5e-3, 1)},
                   ?D:parse_matrix(<<"1e3 0 0 0 0 1.5E-3 0 0 0 0 1 0 0 0 0 1">>)),
     ?_assertEqual({error, {not_a_matrix, <<"1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 one">>}},
                   ?D:parse_matrix(<<"1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 one">>)),
     ?_assertEqual({ok, ?D:rotation_z(30)}, ?D:parse_matrix(?D:matrix_to_text(?D:rotation_z(30)))),
     ?_assertEqual(error, ?D:parse_number(<<".">>)),
     ?_assertEqual(error, ?D:parse_number(<<"1e999">>)),
     ?_assertEqual(-0.5, ?D:parse_number(<<"-.5">>))].

json_layout_test() ->
    D = ?D:new([?D:line({0, 0}, {1, 1}),
                ?D:container(#{<<"ItemType">> => <<"Fiducial">>},
                             [?D:circle({1, 1}, 2), ?D:arc({0, 0}, 1, 0, 90)])]),
    Text = iolist_to_binary(?D:to_json(D)),
    Lines = binary:split(Text, <<"\n">>, [global, trim]),
    %% one primitive a line
    ?assertEqual(7, length(Lines)),
    ?assertMatch({match, _}, re:run(lists:nth(4, Lines), "^    \\{\"kind\":\"circle\"")),
    ?assertEqual({ok, D}, ?D:from_json(Text)),
    ?assertEqual({error, not_json}, ?D:from_json(<<"{\"kind\":">>)),
    ?assertEqual({error, {invalid, [children, 1, <<"colour">>], unknown_field}},
                 ?D:from_json(<<"{\"kind\":\"container\",\"attributes\":{},\"children\":[",
                                "{\"kind\":\"line\",\"colour\":1}]}">>)),
    ?assertEqual({error, {invalid, [kind], {unknown_kind, <<"blob">>}}},
                 ?D:from_json(<<"{\"kind\":\"blob\"}">>)),
    ?assertEqual({error, {invalid, [], {not_an_item, [1]}}}, ?D:from_json(<<"[1]">>)),
    ?assertEqual({error, {invalid, [<<"kind">>], duplicate_field}},
                 ?D:from_json(<<"{\"kind\":\"line\",\"kind\":\"circle\"}">>)),
    ?assertEqual({error, {invalid, [kind], missing}}, ?D:from_json(<<"{\"attributes\":{}}">>)),
    ?assertEqual({error, {invalid, [attrs, <<"A">>], duplicate_field}},
                 ?D:from_json(<<"{\"kind\":\"container\",\"children\":[],",
                                "\"attributes\":{\"A\":\"1\",\"A\":\"2\"}}">>)),
    %% nesting without end is refused while reading, before it is walked
    Deep = lists:foldl(fun(_, Inner) ->
                               <<"{\"kind\":\"container\",\"attributes\":{},\"children\":[",
                                 Inner/binary, "]}">>
                       end, <<"{\"kind\":\"container\",\"attributes\":{},\"children\":[]}">>,
                       lists:seq(1, 5000)),
    ?assertMatch({error, {invalid, _, too_deep}}, ?D:from_json(Deep)).

items_by_type_test() ->
    Cut = fun(Order, From, To) ->
                  A = case Order of none -> #{}; _ -> #{<<"ExecOrder">> => Order} end,
                  ?D:line(From, To, A#{<<"ItemType">> => <<"Cut">>})
          end,
    %% The panel is moved by (100, 0); the module inside it is turned 90° about its
    %% own origin first, then moved with the panel.
    Module = ?D:container(#{<<"Transform">> => ?D:matrix_to_text(?D:rotation_z(90)),
                            <<"ItemType">> => <<"Module">>},
                          [Cut(<<"1">>, {1, 0}, {2, 0})]),
    Panel = ?D:container(#{<<"Transform">> => ?D:matrix_to_text(?D:translation(100, 0, 0))},
                         [Cut(<<"3">>, {0, 0}, {0, 5}), Module, Cut(none, {9, 9}, {9, 8})]),
    D = ?D:new([Cut(<<"2">>, {0, 0}, {1, 0}), Panel]),
    Cuts = ?D:items_by_type(D, <<"Cut">>),
    ?assertEqual([<<"1">>, <<"2">>, <<"3">>, undefined],
                 [?D:attr(C, <<"ExecOrder">>) || C <- Cuts]),
    [First, Second, Third, Last] = Cuts,
    assert_point({100.0, 1.0, 0.0}, maps:get(from, First)),
    assert_point({100.0, 2.0, 0.0}, maps:get(to, First)),
    ?assertEqual({0.0, 0.0, 0.0}, maps:get(from, Second)),
    ?assertEqual({100.0, 5.0, 0.0}, maps:get(to, Third)),
    ?assertEqual({109.0, 9.0, 0.0}, maps:get(from, Last)),
    %% a container comes back in drawing coordinates, its Transform applied and gone
    [M] = ?D:items_by_type(D, <<"Module">>),
    ?assertEqual(error, maps:find(<<"Transform">>, maps:get(attrs, M))),
    [Inner] = maps:get(children, M),
    assert_point({100.0, 1.0, 0.0}, maps:get(from, Inner)),
    ?assertEqual([], ?D:items_by_type(D, <<"Glue">>)),
    ?assertEqual(4, length(?D:primitives(D))).

arc_mirror_test() ->
    %% a quarter arc from 0° to 90° mirrored in X runs from 90° to 180°
    Arc = ?D:arc({0, 0}, 2, 0, 90),
    #{start_angle := S, end_angle := E, radius := R} =
        ?D:apply_transform(?D:scaling(-1, 1, 1), Arc),
    ?assert(abs(S - 90.0) < ?EPS),
    ?assert(abs(E - 180.0) < ?EPS),
    ?assertEqual(2.0, R),
    #{bulges := [B, _]} = ?D:apply_transform(?D:scaling(-1, 1, 1),
                                              (?D:polyline([{0, 0}, {1, 0}], false))#{bulges := [0.5, 0.0]}),
    ?assertEqual(-0.5, B).

assert_point({X, Y, Z}, {A, B, C}) ->
    ?assert(abs(X - A) < ?EPS andalso abs(Y - B) < ?EPS andalso abs(Z - C) < ?EPS).

%%====================================================================
%% Properties
%%====================================================================

json_roundtrip_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_json_roundtrip(),
                                              [{to_file, user}, {numtests, 200}]))}.

by_type_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_items_by_type(),
                                              [{to_file, user}, {numtests, 200}]))}.

transform_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_transform_geometry(),
                                              [{to_file, user}, {numtests, 500}]))}.

%% A drawing of any shape is valid as built and survives its JSON text exactly.
prop_json_roundtrip() ->
    ?FORALL(D, cell_recipe_gen:drawing(),
            ?D:validate(D) =:= {ok, D} andalso
                ?D:from_json(iolist_to_binary(?D:to_json(D))) =:= {ok, D}).

%% items_by_type finds every item of the type, wherever it is, ordered by ExecOrder
%% with the unordered last.
prop_items_by_type() ->
    ?FORALL({D, Type}, {cell_recipe_gen:drawing(), cell_recipe_gen:item_type()},
            begin
                Items = ?D:items_by_type(D, Type),
                Orders = [?D:exec_order(I) || I <- Items],
                {Ordered, Unordered} = lists:splitwith(fun(O) -> O =/= undefined end, Orders),
                length(Items) =:= count_type(D, Type)
                    andalso lists:all(fun(I) -> ?D:item_type(I) =:= Type end, Items)
                    andalso Ordered =:= lists:sort(Ordered)
                    andalso lists:all(fun(O) -> O =:= undefined end, Unordered)
            end).

count_type(#{attrs := A} = Item, Type) ->
    Own = case A of #{<<"ItemType">> := Type} -> 1; _ -> 0 end,
    Own + lists:sum([count_type(C, Type) || C <- maps:get(children, Item, [])]).

%% A primitive inside a container with a Transform comes out with its geometry moved
%% by the matrix: end points, centres, radii, arc end points (swapped by a mirror).
prop_transform_geometry() ->
    ?FORALL({M, P}, {cell_recipe_gen:matrix(), cell_recipe_gen:primitive()},
            begin
                P1 = P#{attrs := #{<<"ItemType">> => <<"Cut">>}},
                D = ?D:new([?D:container(#{<<"Transform">> => ?D:matrix_to_text(M)}, [P1])]),
                [Out] = ?D:items_by_type(D, <<"Cut">>),
                {ok, M1} = ?D:parse_matrix(?D:matrix_to_text(M)),
                geometry_moved(M1, P1, Out)
            end).

geometry_moved(M, #{kind := line, from := F, to := T}, #{from := F1, to := T1}) ->
    close(mul(M, F), F1) andalso close(mul(M, T), T1);
geometry_moved(M, #{kind := circle, center := C, radius := R}, #{center := C1, radius := R1}) ->
    close(mul(M, C), C1) andalso near(R * det_scale(M), R1);
geometry_moved(M, #{kind := arc} = A, #{center := C1} = A1) ->
    {S, E} = arc_ends(A),
    {S1, E1} = arc_ends(A1),
    Mirror = det2(M) < 0,
    close(mul(M, maps:get(center, A)), C1)
        andalso case Mirror of
                    false -> close(mul(M, S), S1) andalso close(mul(M, E), E1);
                    true -> close(mul(M, E), S1) andalso close(mul(M, S), E1)
                end;
geometry_moved(M, #{kind := polyline, points := Ps, bulges := Bs},
               #{points := Ps1, bulges := Bs1}) ->
    Sign = case det2(M) < 0 of true -> -1; false -> 1 end,
    lists:all(fun({P, P1}) -> close(mul(M, P), P1) end, lists:zip(Ps, Ps1))
        andalso [Sign * B || B <- Bs] == Bs1;
geometry_moved(M, #{kind := polyface, vertices := Vs, faces := Fs},
               #{vertices := Vs1, faces := Fs1}) ->
    Fs =:= Fs1 andalso lists:all(fun({V, V1}) -> close(mul(M, V), V1) end, lists:zip(Vs, Vs1)).

%% The matrix written out by hand: row r of M times the column (x, y, z, 1).
mul(M, {X, Y, Z}) ->
    Row = fun(R) -> element(R * 4 + 1, M) * X + element(R * 4 + 2, M) * Y
                        + element(R * 4 + 3, M) * Z + element(R * 4 + 4, M)
          end,
    {Row(0), Row(1), Row(2)}.

det2(M) -> element(1, M) * element(6, M) - element(2, M) * element(5, M).

det_scale(M) -> math:sqrt(abs(det2(M))).

arc_ends(#{center := {X, Y, Z}, radius := R, start_angle := S, end_angle := E}) ->
    At = fun(D) -> {X + R * math:cos(D * math:pi() / 180), Y + R * math:sin(D * math:pi() / 180), Z} end,
    {At(S), At(E)}.

close({A, B, C}, {X, Y, Z}) -> near(A, X) andalso near(B, Y) andalso near(C, Z).

near(A, B) -> abs(A - B) =< 1.0e-6 * max(1.0, max(abs(A), abs(B))).
