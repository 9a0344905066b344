%% PropEr generators for recipe drawings of random shape: primitives of every kind,
%% containers nested at random, attributes with ItemType, ExecOrder and Transform.
-module(cell_recipe_gen).

-include_lib("proper/include/proper.hrl").

-export([drawing/0, flat_drawing/0, primitive/0, point/0, matrix/0, item_type/0,
         text/0, layer/0]).

-define(D, cell_recipe_drawing).

coord() -> float(-1.0e4, 1.0e4).

point() -> {coord(), coord(), coord()}.

item_type() -> elements([<<"Cut">>, <<"Fiducial">>, <<"PanelDrawing">>, <<"Glue">>]).

text() -> proper_unicode:utf8(12).

%% Similarity transforms: rotations, translations, uniform scale, mirror.
matrix() ->
    ?LET({Deg, {X, Y, Z}, S, Mirror}, {float(-360.0, 360.0), point(), float(0.1, 10.0), boolean()},
         ?D:multiply(?D:translation(X, Y, Z),
                     ?D:multiply(?D:rotation_z(Deg),
                                 ?D:scaling(case Mirror of true -> -S; false -> S end, S, S)))).

attrs(Container) ->
    ?LET({Type, Order, Transform, Extra},
         {oneof([none, item_type()]), oneof([none, integer(-5, 20)]),
          case Container of true -> oneof([none, matrix()]); false -> none end,
          ?LET(N, range(0, 2), vector(N, {text(), text()}))},
         maps:from_list(
           Extra
           ++ [{<<"ItemType">>, Type} || Type =/= none]
           ++ [{<<"ExecOrder">>, integer_to_binary(Order)} || Order =/= none]
           ++ [{<<"Transform">>, ?D:matrix_to_text(Transform)} || Transform =/= none])).

primitive() ->
    ?LET(A, attrs(false),
         oneof([?LET({F, T}, {point(), point()}, ?D:line(F, T, A)),
                ?LET({C, R}, {point(), float(0.001, 1.0e3)}, ?D:circle(C, R, A)),
                ?LET({C, R, S, E}, {point(), float(0.001, 1.0e3), float(0.0, 360.0),
                                    float(0.0, 360.0)},
                     ?D:arc(C, R, S, E, A)),
                ?LET({Ps, Bs, Closed}, {?LET(N, range(1, 8), vector(N, point())),
                                        list(float(-2.0, 2.0)), boolean()},
                     begin
                         Points = [hd(Ps) | Ps],
                         Bulges = lists:sublist(Bs ++ [0.0 || _ <- Points], length(Points)),
                         (?D:polyline(Points, Closed, A))#{bulges := Bulges}
                     end),
                ?LET({Vs, N}, {vector(4, point()), range(1, 3)},
                     ?D:polyface(Vs, lists:sublist([[1, 2, 3], [1, 3, 4], [4, 3, 2, 1]], N), A))])).

item(0) -> primitive();
item(Size) ->
    frequency([{4, primitive()},
               {1, ?LAZY(?LET({A, Children},
                              {attrs(true), ?LET(N, range(0, 4), vector(N, item(Size div 2)))},
                              ?D:container(A, Children)))}]).

%% A drawing: a tree of any shape, up to a few hundred items.
drawing() ->
    ?SIZED(Size, ?LET(Children, ?LET(N, range(0, 10), vector(N, item(min(Size, 32)))),
                      ?D:new(Children))).

layer() -> elements([<<"0">>, <<"Cut">>, <<"Board outline">>, <<"Fräsbahn"/utf8>>]).

%% A drawing DXF can hold: lines, circles, arcs and flat polylines on named layers,
%% no containers.
flat_drawing() ->
    ?LET(Prims, list(?LET({P, Layer}, {primitive(), layer()},
                          flat(P#{attrs := #{<<"Layer">> => Layer}}))),
         ?D:new([P || P <- Prims, maps:get(kind, P) =/= polyface])).

flat(#{kind := polyline, points := [{_, _, Z} | _] = Ps} = P) ->
    P#{points := [{X, Y, Z} || {X, Y, _} <- Ps]};
flat(P) ->
    P.
