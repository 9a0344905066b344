%% @doc The recipe drawing (seed 000 §3.2.2): a tree of containers and primitives,
%% each with string attributes.
%%
%% A container groups primitives and other containers; the drawing itself is the root
%% container. Primitives: `line' (from, to), `circle' (center, radius), `arc' (center,
%% radius, start and end angle in degrees, counter-clockwise as in DXF), `polyline'
%% (points, a bulge per point as in DXF, closed or not) and `polyface' (a mesh:
%% vertices and faces listing 1-based vertex positions). Points are `{X, Y, Z}' floats.
%%
%% Attributes are binaries to binaries. Three have a meaning here:
%% <ul>
%% <li>`ItemType' — what the item is for: "PanelDrawing", "Cut", "Fiducial" ...</li>
%% <li>`ExecOrder' — an integer: the order items of one type are worked in.</li>
%% <li>`Transform' — on a container, a 4×4 affine matrix applied to everything inside
%%   it: 16 numbers, row by row, separated by spaces or commas. A point is a column
%%   vector, so `p′ = M·[x y z 1]ᵀ' and the translation is the last column. Inner
%%   transforms apply first. Circles and arcs keep their shape only under rotation,
%%   translation, uniform scaling and mirroring in the XY plane.</li>
%% </ul>
%%
%% The JSON form (a recipe's `drawing.json') puts one primitive on each line, so a
%% drawing diffs line by line. Input is checked in full by {@link validate/1}: every
%% error names the item by its path, e.g. `[children, 3, children, 1, radius]'.
-module(cell_recipe_drawing).

-export([new/0, new/1, container/2, line/2, line/3, circle/2, circle/3, arc/4, arc/5,
         polyline/2, polyline/3, polyface/2, polyface/3]).
-export([attr/2, attr/3, set_attr/3, item_type/1, exec_order/1, transform/1]).
-export([items_by_type/2, primitives/1, count/1, apply_transform/2]).
-export([identity/0, translation/3, rotation_z/1, scaling/3, multiply/2,
         transform_point/2, matrix_to_text/1, parse_matrix/1, parse_number/1]).
-export([validate/1, to_json/1, from_json/1, format_error/1]).

-export_type([drawing/0, item/0, container/0, primitive/0, point/0, attrs/0, matrix/0]).

-type point() :: {float(), float(), float()}.
-type attrs() :: #{binary() => binary()}.
-type container() :: #{kind := container, attrs := attrs(), children := [item()]}.
-type primitive() :: #{kind := line, attrs := attrs(), from := point(), to := point()}
                   | #{kind := circle, attrs := attrs(), center := point(), radius := float()}
                   | #{kind := arc, attrs := attrs(), center := point(), radius := float(),
                       start_angle := float(), end_angle := float()}
                   | #{kind := polyline, attrs := attrs(), points := [point()],
                       bulges := [float()], closed := boolean()}
                   | #{kind := polyface, attrs := attrs(), vertices := [point()],
                       faces := [[pos_integer()]]}.
-type item() :: container() | primitive().
-type drawing() :: container().
-type matrix() :: {float(), float(), float(), float(), float(), float(), float(), float(),
                   float(), float(), float(), float(), float(), float(), float(), float()}.
-type in_point() :: {number(), number()} | {number(), number(), number()}.

-define(MAX_DEPTH, 64).
-define(KINDS, [container, line, circle, arc, polyline, polyface]).

%%====================================================================
%% Building
%%====================================================================

%% @doc An empty drawing.
-spec new() -> drawing().
new() -> new([]).

%% @doc A drawing holding `Items'.
-spec new([item()]) -> drawing().
new(Items) -> container(#{}, Items).

%% @doc A container with attributes and children.
-spec container(attrs(), [item()]) -> container().
container(Attrs, Children) ->
    #{kind => container, attrs => Attrs, children => Children}.

%% @doc A line.
-spec line(in_point(), in_point()) -> primitive().
line(From, To) -> line(From, To, #{}).

%% @doc A line with attributes.
-spec line(in_point(), in_point(), attrs()) -> primitive().
line(From, To, Attrs) ->
    #{kind => line, attrs => Attrs, from => point(From), to => point(To)}.

%% @doc A circle.
-spec circle(in_point(), number()) -> primitive().
circle(Center, R) -> circle(Center, R, #{}).

%% @doc A circle with attributes.
-spec circle(in_point(), number(), attrs()) -> primitive().
circle(Center, R, Attrs) ->
    #{kind => circle, attrs => Attrs, center => point(Center), radius => float(R)}.

%% @doc An arc, counter-clockwise from `Start' to `End' degrees.
-spec arc(in_point(), number(), number(), number()) -> primitive().
arc(Center, R, Start, End) -> arc(Center, R, Start, End, #{}).

%% @doc An arc with attributes.
-spec arc(in_point(), number(), number(), number(), attrs()) -> primitive().
arc(Center, R, Start, End, Attrs) ->
    #{kind => arc, attrs => Attrs, center => point(Center), radius => float(R),
      start_angle => float(Start), end_angle => float(End)}.

%% @doc A polyline of straight segments.
-spec polyline([in_point()], boolean()) -> primitive().
polyline(Points, Closed) -> polyline(Points, Closed, #{}).

%% @doc A polyline with attributes.
-spec polyline([in_point()], boolean(), attrs()) -> primitive().
polyline(Points, Closed, Attrs) ->
    #{kind => polyline, attrs => Attrs, points => [point(P) || P <- Points],
      bulges => [0.0 || _ <- Points], closed => Closed}.

%% @doc A polyface mesh: faces list 1-based positions in `Vertices'.
-spec polyface([in_point()], [[pos_integer()]]) -> primitive().
polyface(Vertices, Faces) -> polyface(Vertices, Faces, #{}).

%% @doc A polyface mesh with attributes.
-spec polyface([in_point()], [[pos_integer()]], attrs()) -> primitive().
polyface(Vertices, Faces, Attrs) ->
    #{kind => polyface, attrs => Attrs, vertices => [point(V) || V <- Vertices],
      faces => Faces}.

point({X, Y}) -> {float(X), float(Y), 0.0};
point({X, Y, Z}) -> {float(X), float(Y), float(Z)}.

%%====================================================================
%% Attributes
%%====================================================================

%% @doc An attribute, or `undefined'.
-spec attr(item(), binary()) -> binary() | undefined.
attr(Item, Key) -> attr(Item, Key, undefined).

%% @doc An attribute, or `Default'.
-spec attr(item(), binary(), Default) -> binary() | Default.
attr(#{attrs := A}, Key, Default) -> maps:get(Key, A, Default).

%% @doc Sets an attribute.
-spec set_attr(Item, binary(), binary()) -> Item when Item :: item().
set_attr(#{attrs := A} = Item, Key, Value) when is_binary(Key), is_binary(Value) ->
    Item#{attrs := A#{Key => Value}}.

%% @doc The `ItemType' attribute, or `undefined'.
-spec item_type(item()) -> binary() | undefined.
item_type(Item) -> attr(Item, <<"ItemType">>).

%% @doc The `ExecOrder' attribute as an integer, or `undefined'. A drawing that passed
%% {@link validate/1} has only integers there.
-spec exec_order(item()) -> integer() | undefined.
exec_order(Item) ->
    case attr(Item, <<"ExecOrder">>) of
        undefined -> undefined;
        Text -> {ok, N} = int_text(Text), N
    end.

int_text(Text) ->
    try {ok, binary_to_integer(string:trim(Text))}
    catch error:badarg -> error
    end.

%% @doc The `Transform' attribute as a matrix (identity when there is none).
-spec transform(item()) -> matrix().
transform(Item) ->
    case attr(Item, <<"Transform">>) of
        undefined -> identity();
        Text -> {ok, M} = parse_matrix(Text), M
    end.

%%====================================================================
%% Queries
%%====================================================================

%% @doc Every item whose `ItemType' is `Type', anywhere in the tree, in `ExecOrder'
%% (items without one last, ties in tree order), in drawing coordinates: the
%% transforms of the containers around an item, and of the item itself when it is a
%% container, are applied, and a returned container holds its contents transformed,
%% with no `Transform' attributes left.
-spec items_by_type(drawing(), binary()) -> [item()].
items_by_type(Drawing, Type) when is_binary(Type) ->
    Found = collect(Drawing, Type, identity(), []),
    Keyed = lists:zip(lists:seq(1, length(Found)), lists:reverse(Found)),
    Sorted = lists:sort(fun({I, A}, {J, B}) -> order_key(I, A) =< order_key(J, B) end, Keyed),
    [Item || {_, Item} <- Sorted].

order_key(I, Item) ->
    case exec_order(Item) of
        undefined -> {1, 0, I};
        N -> {0, N, I}
    end.

collect(#{kind := container, children := Children} = C, Type, M0, Acc) ->
    M = multiply(M0, transform(C)),
    Acc1 = case item_type(C) of
               Type -> [flatten(C, M0) | Acc];
               _ -> Acc
           end,
    lists:foldl(fun(Child, A) -> collect(Child, Type, M, A) end, Acc1, Children);
collect(Prim, Type, M, Acc) ->
    case item_type(Prim) of
        Type -> [apply_transform(M, Prim) | Acc];
        _ -> Acc
    end.

%% A container in drawing coordinates: its own and inner transforms applied.
flatten(#{kind := container, attrs := A, children := Children} = C, M0) ->
    M = multiply(M0, transform(C)),
    C#{attrs := maps:remove(<<"Transform">>, A),
       children := [case Child of
                        #{kind := container} -> flatten(Child, M);
                        _ -> apply_transform(M, Child)
                    end || Child <- Children]}.

%% @doc Every primitive of the drawing in drawing coordinates, in tree order.
-spec primitives(drawing()) -> [primitive()].
primitives(Drawing) ->
    lists:reverse(prims(Drawing, identity(), [])).

prims(#{kind := container, children := Children} = C, M0, Acc) ->
    M = multiply(M0, transform(C)),
    lists:foldl(fun(Child, A) -> prims(Child, M, A) end, Acc, Children);
prims(Prim, M, Acc) ->
    [apply_transform(M, Prim) | Acc].

%% @doc The number of primitives in the tree.
-spec count(drawing()) -> non_neg_integer().
count(#{kind := container, children := Children}) ->
    lists:sum([count(C) || C <- Children]);
count(_) ->
    1.

%%====================================================================
%% Transforms
%%====================================================================

%% @doc The identity matrix.
-spec identity() -> matrix().
identity() ->
    {1.0, 0.0, 0.0, 0.0,
     0.0, 1.0, 0.0, 0.0,
     0.0, 0.0, 1.0, 0.0,
     0.0, 0.0, 0.0, 1.0}.

%% @doc A translation.
-spec translation(number(), number(), number()) -> matrix().
translation(X, Y, Z) ->
    {1.0, 0.0, 0.0, float(X),
     0.0, 1.0, 0.0, float(Y),
     0.0, 0.0, 1.0, float(Z),
     0.0, 0.0, 0.0, 1.0}.

%% @doc A rotation about the Z axis, counter-clockwise, in degrees.
-spec rotation_z(number()) -> matrix().
rotation_z(Deg) ->
    R = Deg * math:pi() / 180,
    C = math:cos(R),
    S = math:sin(R),
    {C, -S, 0.0, 0.0,
     S, C, 0.0, 0.0,
     0.0, 0.0, 1.0, 0.0,
     0.0, 0.0, 0.0, 1.0}.

%% @doc A scaling (a negative factor mirrors).
-spec scaling(number(), number(), number()) -> matrix().
scaling(X, Y, Z) ->
    {float(X), 0.0, 0.0, 0.0,
     0.0, float(Y), 0.0, 0.0,
     0.0, 0.0, float(Z), 0.0,
     0.0, 0.0, 0.0, 1.0}.

%% @doc `A·B': applies `B' first, then `A'.
-spec multiply(matrix(), matrix()) -> matrix().
multiply(A, B) ->
    list_to_tuple([lists:sum([element(R * 4 + K + 1, A) * element(K * 4 + C + 1, B)
                              || K <- [0, 1, 2, 3]])
                   || R <- [0, 1, 2, 3], C <- [0, 1, 2, 3]]).

%% @doc A point through an affine matrix.
-spec transform_point(matrix(), point()) -> point().
transform_point({A, B, C, D, E, F, G, H, I, J, K, L, _, _, _, _}, {X, Y, Z}) ->
    {A * X + B * Y + C * Z + D, E * X + F * Y + G * Z + H, I * X + J * Y + K * Z + L}.

%% @doc One item in the coordinates `M' maps it to (a container's own transform and
%% those inside it are applied too, see {@link items_by_type/2}).
-spec apply_transform(matrix(), Item) -> Item when Item :: item().
apply_transform(M, #{kind := container} = C) ->
    flatten(C, M);
apply_transform(M, #{kind := line, from := F, to := T} = L) ->
    L#{from := transform_point(M, F), to := transform_point(M, T)};
apply_transform(M, #{kind := circle, center := C, radius := R} = Circle) ->
    Circle#{center := transform_point(M, C), radius := R * scale(M)};
apply_transform(M, #{kind := arc, center := {Cx, Cy, Cz} = C, radius := R,
                     start_angle := A0, end_angle := A1} = Arc) ->
    At = fun(Deg) -> Rad = Deg * math:pi() / 180,
                     {Cx + R * math:cos(Rad), Cy + R * math:sin(Rad), Cz}
         end,
    Ct = transform_point(M, C),
    Sweep = sweep(A0, A1),
    %% A mirror turns counter-clockwise into clockwise: the arc starts at the image
    %% of its end point.
    From = case mirrors(M) of
               false -> At(A0);
               true -> At(A1)
           end,
    Start = angle_of(Ct, transform_point(M, From)),
    Arc#{center := Ct, radius := R * scale(M), start_angle := Start,
         end_angle := normalise(Start + Sweep)};
apply_transform(M, #{kind := polyline, points := Ps, bulges := Bs} = P) ->
    Sign = case mirrors(M) of true -> -1.0; false -> 1.0 end,
    P#{points := [transform_point(M, X) || X <- Ps], bulges := [Sign * B || B <- Bs]};
apply_transform(M, #{kind := polyface, vertices := Vs} = P) ->
    P#{vertices := [transform_point(M, V) || V <- Vs]}.

scale({A, B, _, _, E, F, _, _, _, _, _, _, _, _, _, _}) ->
    math:sqrt(abs(A * F - B * E)).

mirrors({A, B, _, _, E, F, _, _, _, _, _, _, _, _, _, _}) ->
    A * F - B * E < 0.

sweep(A0, A1) ->
    case normalise(A1 - A0) of
        S when S == 0, A1 =/= A0 -> 360.0;
        S -> S
    end.

angle_of({Cx, Cy, _}, {X, Y, _}) ->
    normalise(math:atan2(Y - Cy, X - Cx) * 180 / math:pi()).

normalise(Deg) ->
    D = math:fmod(Deg, 360.0),
    case D < 0 of
        true -> D + 360.0;
        false -> D
    end.

%% @doc A matrix as the `Transform' attribute holds it.
-spec matrix_to_text(matrix()) -> binary().
matrix_to_text(M) ->
    iolist_to_binary(lists:join(" ", [float_to_binary(X, [short]) || X <- tuple_to_list(M)])).

%% @doc Reads a `Transform' attribute: 16 numbers, row by row, the last row `0 0 0 1'.
-spec parse_matrix(binary()) -> {ok, matrix()} | {error, term()}.
parse_matrix(Text) ->
    Parts = [P || P <- re:split(Text, "[\\s,;]+", [unicode]), P =/= <<>>],
    case length(Parts) of
        16 ->
            case [parse_number(P) || P <- Parts] of
                [_, _, _, _, _, _, _, _, _, _, _, _, W1, W2, W3, W4] = Nums
                  when W1 == 0, W2 == 0, W3 == 0, W4 == 1 ->
                    {ok, list_to_tuple(Nums)};
                Nums ->
                    case lists:member(error, Nums) of
                        true -> {error, {not_a_matrix, Text}};
                        false -> {error, {not_affine, Text}}
                    end
            end;
        _ ->
            {error, {not_a_matrix, Text}}
    end.

%% @doc A number as people and CAD programs write it: 1, -2.5, .5, 1e3, 1.5E-3.
-spec parse_number(binary()) -> float() | error.
parse_number(Bin) ->
    case re:run(Bin, "^([+-]?)([0-9]*)(?:\\.([0-9]*))?(?:[eE]([+-]?[0-9]+))?$",
                [{capture, all_but_first, binary}]) of
        {match, Groups} ->
            %% Groups left unmatched at the end are not returned at all.
            [Sign, Int, Frac, Exp] = Groups ++ lists:duplicate(4 - length(Groups), <<>>),
            case Int =:= <<>> andalso Frac =:= <<>> of
                true -> error;
                false -> to_float(Sign, Int, Frac, Exp)
            end;
        nomatch ->
            error
    end.

to_float(Sign, Int, Frac, Exp) ->
    Digits = fun(<<>>) -> <<"0">>; (D) -> D end,
    try binary_to_float(<<Sign/binary, (Digits(Int))/binary, ".", (Digits(Frac))/binary,
                          "e", (Digits(Exp))/binary>>)
    catch error:badarg -> error  %% beyond the range of a float
    end.

%%====================================================================
%% Validation
%%====================================================================

%% @doc Checks a drawing in full and returns it with every number as a float: the
%% root is a container, items are known kinds with their fields of the right types,
%% radii positive, polylines of two points or more with one bulge each, faces of three
%% vertices or more that exist, attributes binaries, `ExecOrder' an integer,
%% `Transform' an affine matrix, containers nested at most 64 deep.
-spec validate(term()) -> {ok, drawing()} | {error, {invalid, list(), term()}}.
validate(#{kind := container} = D) ->
    %% Paths are built reversed while walking (cheap), and turned round on error.
    try {ok, item(D, [], 0)}
    catch throw:{invalid, RevPath, Why} -> {error, {invalid, lists:reverse(RevPath), Why}}
    end;
validate(Other) ->
    {error, {invalid, [], {not_a_container, kind_of(Other)}}}.

kind_of(#{kind := K}) -> K;
kind_of(_) -> not_an_item.

item(_, Path, Depth) when Depth > ?MAX_DEPTH ->
    bad(Path, too_deep);
item(#{kind := container} = C, Path, Depth) ->
    keys(C, [attrs, children], Path),
    Children = case maps:get(children, C) of
                   L when is_list(L) -> L;
                   X -> bad([children | Path], {not_a_list, X})
               end,
    Attrs = attrs(maps:get(attrs, C), Path),
    {Items, _} = lists:mapfoldl(fun(Child, I) ->
                                        {item(Child, [I, children | Path], Depth + 1), I + 1}
                                end, 1, Children),
    #{kind => container, attrs => Attrs, children => Items};
item(#{kind := line} = L, Path, _) ->
    keys(L, [attrs, from, to], Path),
    L#{attrs := attrs(maps:get(attrs, L), Path),
       from := pt(maps:get(from, L), [from | Path]),
       to := pt(maps:get(to, L), [to | Path])};
item(#{kind := circle} = C, Path, _) ->
    keys(C, [attrs, center, radius], Path),
    C#{attrs := attrs(maps:get(attrs, C), Path),
       center := pt(maps:get(center, C), [center | Path]),
       radius := radius(maps:get(radius, C), [radius | Path])};
item(#{kind := arc} = A, Path, _) ->
    keys(A, [attrs, center, radius, start_angle, end_angle], Path),
    A#{attrs := attrs(maps:get(attrs, A), Path),
       center := pt(maps:get(center, A), [center | Path]),
       radius := radius(maps:get(radius, A), [radius | Path]),
       start_angle := num(maps:get(start_angle, A), [start_angle | Path]),
       end_angle := num(maps:get(end_angle, A), [end_angle | Path])};
item(#{kind := polyline} = P, Path, _) ->
    keys(P, [attrs, points, bulges, closed], Path),
    Points = pts(maps:get(points, P), [points | Path]),
    length(Points) >= 2 orelse bad([points | Path], fewer_than_two_points),
    Bulges = case maps:get(bulges, P) of
                 Bs when is_list(Bs), length(Bs) =:= length(Points) ->
                     indexed(fun(B, Pa) -> num(B, Pa) end, Bs, [bulges | Path]);
                 Bs ->
                     bad([bulges | Path], {not_one_per_point, Bs})
             end,
    Closed = case maps:get(closed, P) of
                 B when is_boolean(B) -> B;
                 B -> bad([closed | Path], {not_a_boolean, B})
             end,
    P#{attrs := attrs(maps:get(attrs, P), Path), points := Points, bulges := Bulges,
       closed := Closed};
item(#{kind := polyface} = P, Path, _) ->
    keys(P, [attrs, vertices, faces], Path),
    Vs = pts(maps:get(vertices, P), [vertices | Path]),
    N = length(Vs),
    Faces = case maps:get(faces, P) of
                Fs when is_list(Fs) ->
                    indexed(fun(F, Pa) -> face(F, N, Pa) end, Fs, [faces | Path]);
                Fs ->
                    bad([faces | Path], {not_a_list, Fs})
            end,
    P#{attrs := attrs(maps:get(attrs, P), Path), vertices := Vs, faces := Faces};
item(#{kind := K}, Path, _) ->
    bad([kind | Path], {unknown_kind, K});
item(Other, Path, _) ->
    bad(Path, {not_an_item, Other}).

keys(Item, Required, Path) ->
    case [K || K <- Required, not is_map_key(K, Item)] of
        [] -> ok;
        [Missing | _] -> bad([Missing | Path], missing)
    end,
    %% Every required key is there: one more than kind and those means an unknown one.
    case map_size(Item) =:= length(Required) + 1 of
        true ->
            ok;
        false ->
            [Unknown | _] = maps:keys(Item) -- [kind | Required],
            bad([Unknown | Path], unknown_field)
    end.

attrs(A, _Path) when map_size(A) =:= 0 ->
    A;
attrs(A, Path) when is_map(A) ->
    maps:foreach(fun(K, V) ->
                         (is_binary(K) andalso utf8(K)) orelse bad([attrs | Path], {bad_name, K}),
                         (is_binary(V) andalso utf8(V)) orelse bad([K, attrs | Path], {not_text, V})
                 end, A),
    case A of
        #{<<"ExecOrder">> := Order} ->
            case int_text(Order) of
                {ok, _} -> ok;
                error -> bad([<<"ExecOrder">>, attrs | Path], {not_an_integer, Order})
            end;
        _ ->
            ok
    end,
    case A of
        #{<<"Transform">> := T} ->
            case parse_matrix(T) of
                {ok, _} -> ok;
                {error, Why} -> bad([<<"Transform">>, attrs | Path], Why)
            end;
        _ ->
            ok
    end,
    A;
attrs(A, Path) ->
    bad([attrs | Path], {not_a_map, A}).

utf8(B) -> is_binary(unicode:characters_to_binary(B)).

pts(L, Path) when is_list(L) -> indexed(fun pt/2, L, Path);
pts(L, Path) -> bad(Path, {not_a_list, L}).

pt({X, Y, Z}, Path) -> {num(X, [x | Path]), num(Y, [y | Path]), num(Z, [z | Path])};
pt(P, Path) -> bad(Path, {not_a_point, P}).

num(N, _Path) when is_number(N) -> float(N);
num(N, Path) -> bad(Path, {not_a_number, N}).

radius(R, _Path) when is_number(R), R > 0 -> float(R);
radius(R, Path) -> bad(Path, {not_positive, R}).

face(F, N, Path) when is_list(F), length(F) >= 3 ->
    indexed(fun(I, _) when is_integer(I), I >= 1, I =< N -> I;
               (I, P) -> bad(P, {no_such_vertex, I})
            end, F, Path);
face(F, _N, Path) ->
    bad(Path, {not_a_face, F}).

indexed(Fun, List, Path) ->
    {Out, _} = lists:mapfoldl(fun(E, I) -> {Fun(E, [I | Path]), I + 1} end, 1, List),
    Out.

-spec bad(list(), term()) -> no_return().
bad(Path, Why) -> throw({invalid, Path, Why}).

%%====================================================================
%% JSON
%%====================================================================

%% @doc The drawing as JSON text, one primitive a line.
-spec to_json(drawing()) -> iodata().
to_json(Drawing) ->
    [encode(Drawing, 0), $\n].

encode(#{kind := container, attrs := A, children := []}, _Ind) ->
    jsx:encode([{<<"kind">>, <<"container">>}, {<<"attributes">>, attrs_json(A)},
                {<<"children">>, []}]);
encode(#{kind := container, attrs := A, children := Children}, Ind) ->
    Pad = lists:duplicate(2 * (Ind + 1), $\s),
    [<<"{\"kind\":\"container\",\"attributes\":">>, jsx:encode(attrs_json(A)),
     <<",\"children\":[\n">>,
     lists:join(",\n", [[Pad, encode(C, Ind + 1)] || C <- Children]),
     $\n, lists:duplicate(2 * Ind, $\s), <<"]}">>];
encode(Prim, _Ind) ->
    jsx:encode(prim_json(Prim)).

prim_json(#{kind := line, attrs := A, from := F, to := T}) ->
    [{<<"kind">>, <<"line">>}, {<<"attributes">>, attrs_json(A)},
     {<<"from">>, pt_json(F)}, {<<"to">>, pt_json(T)}];
prim_json(#{kind := circle, attrs := A, center := C, radius := R}) ->
    [{<<"kind">>, <<"circle">>}, {<<"attributes">>, attrs_json(A)},
     {<<"center">>, pt_json(C)}, {<<"radius">>, R}];
prim_json(#{kind := arc, attrs := A, center := C, radius := R, start_angle := S,
            end_angle := E}) ->
    [{<<"kind">>, <<"arc">>}, {<<"attributes">>, attrs_json(A)},
     {<<"center">>, pt_json(C)}, {<<"radius">>, R}, {<<"start_angle">>, S},
     {<<"end_angle">>, E}];
prim_json(#{kind := polyline, attrs := A, points := Ps, bulges := Bs, closed := Cl}) ->
    [{<<"kind">>, <<"polyline">>}, {<<"attributes">>, attrs_json(A)},
     {<<"points">>, [pt_json(P) || P <- Ps]}, {<<"bulges">>, Bs}, {<<"closed">>, Cl}];
prim_json(#{kind := polyface, attrs := A, vertices := Vs, faces := Fs}) ->
    [{<<"kind">>, <<"polyface">>}, {<<"attributes">>, attrs_json(A)},
     {<<"vertices">>, [pt_json(V) || V <- Vs]}, {<<"faces">>, Fs}].

attrs_json(A) when map_size(A) =:= 0 -> [{}];
attrs_json(A) -> lists:sort(maps:to_list(A)).

pt_json({X, Y, Z}) -> [X, Y, Z].

%% @doc Reads a drawing's JSON text and validates it (see {@link validate/1}).
-spec from_json(binary()) -> {ok, drawing()} | {error, not_json | {invalid, list(), term()}}.
from_json(Bin) ->
    %% jsx's object lists go straight into the Erlang form: a drawing is read on every
    %% recipe load, and a map of every object first would double the work.
    try jsx:decode(Bin, [{return_maps, false}]) of
        Term ->
            try validate(from_term(Term, [], 0))
            catch throw:{invalid, RevPath, Why} -> {error, {invalid, lists:reverse(RevPath), Why}}
            end
    catch
        error:_ -> {error, not_json}
    end.

%% JSON objects (jsx's `[{Key, Value}]', `[{}]' when empty) onto the Erlang form: the
%% field names and kinds are a fixed list, so no atom is ever made from the text.
from_term(_Term, Path, Depth) when Depth > ?MAX_DEPTH ->
    bad(Path, too_deep);
from_term([{K, _} | _] = Pairs, Path, Depth) when is_binary(K) ->
    no_duplicates(Pairs, Path),
    case lists:keyfind(<<"kind">>, 1, Pairs) of
        {_, Name} ->
            Kind = case [A || A <- ?KINDS, atom_to_binary(A, utf8) =:= Name] of
                       [A] -> A;
                       [] -> bad([kind | Path], {unknown_kind, Name})
                   end,
            lists:foldl(fun({<<"kind">>, _}, Acc) -> Acc;
                           ({Key, V}, Acc) -> field(Kind, Key, V, Path, Depth, Acc)
                        end, #{kind => Kind}, Pairs);
        false ->
            bad([kind | Path], missing)
    end;
from_term(Other, Path, _Depth) ->
    bad(Path, {not_an_item, Other}).

no_duplicates(Pairs, Path) ->
    Keys = lists:sort([K || {K, _} <- Pairs]),
    case [K || {K, K} <- lists:zip(lists:droplast(Keys), tl(Keys))] of
        [] -> ok;
        [Dup | _] -> bad([Dup | Path], duplicate_field)
    end.

field(container, <<"children">>, L, Path, Depth, Acc) when is_list(L) ->
    {Children, _} = lists:mapfoldl(fun(C, I) ->
                                           {from_term(C, [I, children | Path], Depth + 1), I + 1}
                                   end, 1, L),
    Acc#{children => Children};
field(_, <<"attributes">>, [{}], _Path, _Depth, Acc) ->
    Acc#{attrs => #{}};
field(_, <<"attributes">>, [{K, _} | _] = Pairs, Path, _Depth, Acc) when is_binary(K) ->
    no_duplicates(Pairs, [attrs | Path]),
    Acc#{attrs => maps:from_list(Pairs)};
field(_, <<"attributes">>, A, _Path, _Depth, Acc) ->
    Acc#{attrs => A};
field(_, Key, V, Path, _Depth, Acc) ->
    Fields = [children, from, to, center, radius, start_angle, end_angle, points, bulges,
              closed, vertices, faces],
    case [F || F <- Fields, atom_to_binary(F, utf8) =:= Key] of
        [F] when F =:= from; F =:= to; F =:= center -> Acc#{F => tuple_pt(V)};
        [F] when (F =:= points orelse F =:= vertices), is_list(V) ->
            Acc#{F => [tuple_pt(P) || P <- V]};
        [F] -> Acc#{F => V};
        [] -> bad([Key | Path], unknown_field)
    end.

tuple_pt([X, Y, Z]) -> {X, Y, Z};
tuple_pt(Other) -> Other.

%% @doc A drawing error in words.
-spec format_error(term()) -> binary().
format_error({invalid, Path, Why}) ->
    iolist_to_binary(io_lib:format("drawing item ~ts: ~0tp",
                                   [cell_settings_schema:format_path(Path), Why]));
format_error(not_json) ->
    <<"the drawing is not valid JSON">>;
format_error(Other) ->
    iolist_to_binary(io_lib:format("~0tp", [Other])).
