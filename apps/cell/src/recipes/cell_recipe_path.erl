%% @doc The path a recipe's drawing gives an interpolation channel (seed 000 §3.2.2 and
%% §2.3.7): the items of one `ItemType' (the router's "Cut") in `ExecOrder', in drawing
%% coordinates, as the lines and arcs of a {@link cell_hal_path}. Lines stay lines; an
%% arc stays an arc (counter-clockwise, as DXF has it); a circle is a full arc from 0°;
%% a polyline is its lines and, where a vertex has a bulge, the arc the bulge describes
%% (DXF's: the tangent of a quarter of the included angle, positive counter-clockwise),
%% closed back to its first point if it is closed; a container's primitives come in
%% tree order. A mesh (polyface) is not a path: refused, naming it.
-module(cell_recipe_path).

-export([from_drawing/2, of_item/1]).

%% @doc The segments for `cell_hal_path:new/1' of the drawing's items of `Type';
%% `{error, no_items}' when it has none.
-spec from_drawing(cell_recipe_drawing:drawing(), binary()) ->
          {ok, [cell_hal_path:segment(), ...]} | {error, no_items | {not_a_path, term()}}.
from_drawing(Drawing, Type) ->
    path_of(lists:append([prims(Item) || Item <- cell_recipe_drawing:items_by_type(Drawing, Type)])).

%% @doc The segments of one item of a drawing (a cut line of a recipe), a container's
%% primitives in tree order; a mesh (polyface) or an item without primitives is refused.
-spec of_item(cell_recipe_drawing:item()) ->
          {ok, [cell_hal_path:segment(), ...]} | {error, no_items | {not_a_path, term()}}.
of_item(Item) ->
    path_of(prims(Item)).

path_of([]) ->
    {error, no_items};
path_of(Prims) ->
    case [P || #{kind := polyface} = P <- Prims] of
        [] -> {ok, lists:append([segments(P) || P <- Prims])};
        [P | _] -> {error, {not_a_path, maps:get(attrs, P)}}
    end.

prims(#{kind := container, children := Children}) ->
    lists:append([prims(C) || C <- Children]);
prims(Prim) ->
    [Prim].

segments(#{kind := line, from := A, to := B}) ->
    [{line, A, B}];
segments(#{kind := arc, center := C, radius := R, start_angle := A0, end_angle := A1}) ->
    [{arc, C, R, A0, A1}];
segments(#{kind := circle, center := C, radius := R}) ->
    [{arc, C, R, 0.0, 0.0}];
segments(#{kind := polyline, points := Points, bulges := Bulges, closed := Closed}) ->
    Ends = case Closed of
               true -> tl(Points) ++ [hd(Points)];
               false -> tl(Points)
           end,
    Pairs = lists:zip3(lists:sublist(Points, length(Ends)), Ends,
                       lists:sublist(Bulges ++ lists:duplicate(length(Ends), 0.0),
                                     length(Ends))),
    [edge(P1, P2, B) || {P1, P2, B} <- Pairs].

%% A polyline's edge: a line, or the arc its bulge describes.
edge(P1, P2, B) when B == 0 ->
    {line, P1, P2};
edge({X1, Y1, Z1} = P1, {X2, Y2, _} = P2, B) ->
    Dx = X2 - X1,
    Dy = Y2 - Y1,
    C = math:sqrt(Dx * Dx + Dy * Dy),
    case C == 0 of
        true ->
            {line, P1, P2};
        false ->
            Theta = 4 * math:atan(abs(B)),
            R = C / (2 * math:sin(Theta / 2)),
            %% From the chord's middle to the centre: on its left for a
            %% counter-clockwise arc, on its right for a clockwise one (past a half
            %% circle, the distance turns negative and the centre crosses over).
            D = C / (2 * math:tan(Theta / 2)),
            Side = case B > 0 of true -> 1; false -> -1 end,
            {Nx, Ny} = {-Dy / C, Dx / C},
            Cx = (X1 + X2) / 2 + Side * D * Nx,
            Cy = (Y1 + Y2) / 2 + Side * D * Ny,
            Dir = case B > 0 of true -> ccw; false -> cw end,
            {arc, {Cx, Cy, Z1}, R, deg(math:atan2(Y1 - Cy, X1 - Cx)),
             deg(math:atan2(Y2 - Cy, X2 - Cx)), Dir}
    end.

deg(Rad) -> Rad * 180 / math:pi().
