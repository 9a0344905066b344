%% @doc AutoCAD DXF (ASCII) into a recipe drawing and simple drawings back out (seed
%% 000 §3.2.2, CAD teaching).
%%
%% Import reads the ENTITIES section: LINE, CIRCLE, ARC and LWPOLYLINE become
%% primitives carrying their layer as the `Layer' attribute, inside one container
%% whose `ItemType' is "PanelDrawing". Circles, arcs and polylines drawn with the
%% extrusion direction (0, 0, -1) (mirrored in CAD) are brought into world
%% coordinates. Other entities (TEXT, INSERT, SPLINE ...) and those out of the XY plane
%% are not imported and are counted in the report, so the operator sees what was left
%% out. A file from outside is untrusted: its size and entity count are bounded, and
%% every error names the line of the file.
%%
%% Export writes every primitive in drawing coordinates (transforms applied): LINE,
%% CIRCLE, ARC, LWPOLYLINE (flat polylines only) and a 3DFACE for each polyface face.
%% The layer is the `Layer' attribute, else the `ItemType', else "0". Numbers are
%% written in their shortest exact form, so an exported drawing imports back equal.
-module(cell_recipe_dxf).

-export([import/1, import/2, export/1, format_error/1]).

-export_type([report/0, options/0]).

-type report() :: #{imported := non_neg_integer(),
                    skipped := #{binary() => pos_integer()}}.
-type options() :: #{max_bytes => pos_integer(),     %% default 64 MiB
                     max_entities => pos_integer(),  %% default 1,000,000
                     item_type => binary()}.         %% default <<"PanelDrawing">>
-type error() :: {dxf, non_neg_integer(), term()}.

-define(MAX_BYTES, 64 * 1024 * 1024).
-define(MAX_ENTITIES, 1000000).
-define(TINY, 1.0e-9).

%%====================================================================
%% Import
%%====================================================================

%% @doc Imports with the default limits.
-spec import(binary()) -> {ok, cell_recipe_drawing:container(), report()} | {error, error()}.
import(Bin) ->
    import(Bin, #{}).

%% @doc Imports a DXF text into a container of primitives.
-spec import(binary(), options()) ->
          {ok, cell_recipe_drawing:container(), report()} | {error, error() | {bad_option, term()}}.
import(Bin, Opts) when is_binary(Bin) ->
    case check_options(Opts) of
        ok -> import1(Bin, Opts);
        {error, _} = E -> E
    end.

check_options(Opts) when is_map(Opts) ->
    Ok = fun(max_bytes, V) -> is_integer(V) andalso V > 0;
            (max_entities, V) -> is_integer(V) andalso V > 0;
            (item_type, V) -> is_binary(V);
            (_, _) -> false
         end,
    case [K || {K, V} <- maps:to_list(Opts), not Ok(K, V)] of
        [] -> ok;
        [K | _] -> {error, {bad_option, K}}
    end;
check_options(_) ->
    {error, {bad_option, options}}.

import1(Bin, Opts) ->
    MaxBytes = maps:get(max_bytes, Opts, ?MAX_BYTES),
    case Bin of
        _ when byte_size(Bin) > MaxBytes ->
            {error, {dxf, 0, {too_big, byte_size(Bin), MaxBytes}}};
        <<"AutoCAD Binary DXF", _/binary>> ->
            {error, {dxf, 0, binary_dxf}};
        _ ->
            try convert(parse(Bin, maps:get(max_entities, Opts, ?MAX_ENTITIES))) of
                {Prims, Skipped} ->
                    Type = maps:get(item_type, Opts, <<"PanelDrawing">>),
                    {ok, cell_recipe_drawing:container(#{<<"ItemType">> => Type}, Prims),
                     #{imported => length(Prims), skipped => Skipped}}
            catch
                throw:{dxf, _, _} = E -> {error, E}
            end
    end.

%% The entities of the ENTITIES section as {Line, Type, [{Code, Value, Line}]}. The
%% text is read pair by pair from the binary, never split into a list of lines.
parse(Bin, MaxEntities) ->
    top({Bin, 0, 1}, MaxEntities).

%% The next group code / value pair, {Code, Value, LineNo}, and the rest of the text.
next({Bin, Pos, N}) ->
    case line(Bin, Pos) of
        eof ->
            eof;
        {CodeText, Pos1} ->
            case line(Bin, Pos1) of
                eof ->
                    case string:trim(CodeText) of
                        <<>> -> eof;
                        _ -> bad(N, group_without_value)
                    end;
                {Value, Pos2} ->
                    {{code(CodeText, N), Value, N}, {Bin, Pos2, N + 2}}
            end
    end.

line(Bin, Pos) when Pos >= byte_size(Bin) ->
    eof;
line(Bin, Pos) ->
    {Line, Next} = case binary:match(Bin, <<"\n">>, [{scope, {Pos, byte_size(Bin) - Pos}}]) of
                       {At, 1} -> {binary:part(Bin, Pos, At - Pos), At + 1};
                       nomatch -> {binary:part(Bin, Pos, byte_size(Bin) - Pos), byte_size(Bin)}
                   end,
    {string:trim(Line, trailing, "\r"), Next}.

code(Text, N) ->
    try binary_to_integer(string:trim(Text))
    catch error:badarg -> bad(N, {bad_group_code, printable(Text)})
    end.

top(Text, Max) ->
    case next(Text) of
        eof -> [];
        {{0, <<"EOF">>, _}, _} -> [];
        {{0, <<"SECTION">>, _}, Rest} ->
            case next(Rest) of
                {{2, <<"ENTITIES">>, _}, Rest1} ->
                    {Entities, Rest2} = entities(Rest1, Max, 0, []),
                    Entities ++ top(Rest2, Max);
                {{2, _Name, _}, Rest1} ->
                    top(skip_section(Rest1), Max);
                {{_, _, N}, _} ->
                    bad(N, section_without_name);
                eof ->
                    bad(0, ends_inside_a_section)
            end;
        {{999, _, _}, Rest} ->
            top(Rest, Max);
        {{Code, Value, N}, _} ->
            bad(N, {unexpected, Code, printable(Value)})
    end.

skip_section(Text) ->
    case next(Text) of
        {{0, <<"ENDSEC">>, _}, Rest} -> Rest;
        {_, Rest} -> skip_section(Rest);
        eof -> bad(0, ends_inside_a_section)
    end.

entities(Text, Max, Count, Acc) ->
    case next(Text) of
        {{0, <<"ENDSEC">>, _}, Rest} ->
            {lists:reverse(Acc), Rest};
        {{0, Type, N}, Rest} ->
            Count < Max orelse bad(N, {too_many_entities, Max}),
            {Groups, Rest1} = groups(Rest, []),
            entities(Rest1, Max, Count + 1, [{N, Type, Groups} | Acc]);
        {{999, _, _}, Rest} ->
            entities(Rest, Max, Count, Acc);
        {{Code, _, N}, _} ->
            bad(N, {expected_entity, Code});
        eof ->
            bad(0, ends_inside_the_entities)
    end.

%% The groups of one entity: everything up to the next code 0.
groups(Text, Acc) ->
    case next(Text) of
        {{0, _, _}, _} -> {lists:reverse(Acc), Text};
        {G, Rest} -> groups(Rest, [G | Acc]);
        eof -> bad(0, ends_inside_the_entities)
    end.

convert(Entities) ->
    {Prims, Skipped} =
        lists:foldl(fun({N, Type, Groups}, {Ps, Sk}) ->
                            case entity(Type, Groups, N) of
                                {ok, P} -> {[P | Ps], Sk};
                                {skip, Why} ->
                                    {Ps, maps:update_with(Why, fun(C) -> C + 1 end, 1, Sk)}
                            end
                    end, {[], #{}}, Entities),
    {lists:reverse(Prims), Skipped}.

entity(<<"LINE">>, G, N) ->
    From = {num(G, 10, N), num(G, 20, N), num(G, 30, 0.0, N)},
    To = {num(G, 11, N), num(G, 21, N), num(G, 31, 0.0, N)},
    {ok, cell_recipe_drawing:line(From, To, layer(G))};
entity(<<"CIRCLE">>, G, N) ->
    R = num(G, 40, N),
    planar(<<"CIRCLE">>, G, N,
           fun() when R > 0 ->
                   cell_recipe_drawing:circle(centre(G, N), R, layer(G));
              () -> {skip, <<"CIRCLE with no radius">>}
           end);
entity(<<"ARC">>, G, N) ->
    R = num(G, 40, N),
    A0 = num(G, 50, N),
    A1 = num(G, 51, N),
    planar(<<"ARC">>, G, N,
           fun() when R > 0 ->
                   cell_recipe_drawing:arc(centre(G, N), R, A0, A1, layer(G));
              () -> {skip, <<"ARC with no radius">>}
           end);
entity(<<"LWPOLYLINE">>, G, N) ->
    Z = num(G, 38, 0.0, N),
    Vertices = vertices(G, Z, []),
    case lists:keyfind(90, 1, G) of
        {90, Count, L} ->
            case int(Count, L) =:= length(Vertices) of
                true -> ok;
                false -> bad(L, {vertex_count, int(Count, L), length(Vertices)})
            end;
        false ->
            ok
    end,
    Flags = case lists:keyfind(70, 1, G) of
                {70, F, L70} -> int(F, L70);
                false -> 0
            end,
    planar(<<"LWPOLYLINE">>, G, N,
           fun() when length(Vertices) >= 2 ->
                   P = cell_recipe_drawing:polyline([P || {P, _} <- Vertices], Flags band 1 =:= 1,
                                                    layer(G)),
                   P#{bulges := [B || {_, B} <- Vertices]};
              () -> {skip, <<"LWPOLYLINE with fewer than two vertices">>}
           end);
entity(Type, _G, _N) ->
    {skip, printable(Type)}.

%% Circles, arcs and polylines lie in the plane their extrusion direction sets: the
%% XY plane, seen from above (0, 0, 1) or below (0, 0, -1). Below is a mirror in X.
planar(Type, G, N, Build) ->
    Normal = {num(G, 210, 0.0, N), num(G, 220, 0.0, N), num(G, 230, 1.0, N)},
    case Normal of
        {X, Y, Z} when abs(X) < ?TINY, abs(Y) < ?TINY, Z > 0 ->
            wrap(Build());
        {X, Y, Z} when abs(X) < ?TINY, abs(Y) < ?TINY, Z < 0 ->
            case Build() of
                {skip, _} = S -> S;
                P -> {ok, cell_recipe_drawing:apply_transform(
                            cell_recipe_drawing:scaling(-1, 1, -1), P)}
            end;
        _ ->
            {skip, <<Type/binary, " out of the XY plane">>}
    end.

wrap({skip, _} = S) -> S;
wrap(P) -> {ok, P}.

centre(G, N) ->
    {num(G, 10, N), num(G, 20, N), num(G, 30, 0.0, N)}.

vertices([{10, X, L} | Rest], Z, Acc) ->
    {Y, Bulge, Rest1} = vertex(Rest, undefined, 0.0, L),
    vertices(Rest1, Z, [{{number(X, L), Y, Z}, Bulge} | Acc]);
vertices([_ | Rest], Z, Acc) ->
    vertices(Rest, Z, Acc);
vertices([], _Z, Acc) ->
    lists:reverse(Acc).

vertex([{20, Y, L} | Rest], _, B, L0) -> vertex(Rest, number(Y, L), B, L0);
vertex([{42, B, L} | Rest], Y, _, L0) -> vertex(Rest, Y, number(B, L), L0);
vertex([{C, _, _} | Rest], Y, B, L0) when C =/= 10 -> vertex(Rest, Y, B, L0);
vertex(_Rest, undefined, _, L0) -> bad(L0, {missing, 20});
vertex(Rest, Y, B, _L0) -> {Y, B, Rest}.

layer(G) ->
    case lists:keyfind(8, 1, G) of
        {8, Name, _} when Name =/= <<>> -> #{<<"Layer">> => text(Name)};
        _ -> #{}
    end.

num(G, Code, N) ->
    case lists:keyfind(Code, 1, G) of
        {Code, V, L} -> number(V, L);
        false -> bad(N, {missing, Code})
    end.

num(G, Code, Default, _N) ->
    case lists:keyfind(Code, 1, G) of
        {Code, V, L} -> number(V, L);
        false -> Default
    end.

number(Text, L) ->
    case cell_recipe_drawing:parse_number(string:trim(Text)) of
        error -> bad(L + 1, {not_a_number, printable(Text)});
        F -> F
    end.

int(Text, L) ->
    try binary_to_integer(string:trim(Text))
    catch error:badarg -> bad(L + 1, {not_an_integer, printable(Text)})
    end.

%% DXF text is UTF-8 from AutoCAD 2007 on and a code page before; `\U+XXXX' escapes
%% stand for characters either way.
text(Bin) ->
    Utf8 = case unicode:characters_to_binary(Bin) of
               B when is_binary(B) -> B;
               _ -> unicode:characters_to_binary(Bin, latin1)
           end,
    unescape(Utf8, <<>>).

unescape(<<"\\U+", H:4/binary, Rest/binary>>, Acc) ->
    try binary_to_integer(H, 16) of
        C when C < 16#D800; C > 16#DFFF -> unescape(Rest, <<Acc/binary, C/utf8>>);
        _ -> unescape(<<H/binary, Rest/binary>>, <<Acc/binary, "\\U+">>)
    catch error:badarg -> unescape(<<H/binary, Rest/binary>>, <<Acc/binary, "\\U+">>)
    end;
unescape(<<C/utf8, Rest/binary>>, Acc) -> unescape(Rest, <<Acc/binary, C/utf8>>);
unescape(<<>>, Acc) -> Acc.

printable(Bin) ->
    Short = binary:part(Bin, 0, min(byte_size(Bin), 40)),
    case unicode:characters_to_binary(Short) of
        B when is_binary(B) -> B;
        _ -> unicode:characters_to_binary(Short, latin1)
    end.

-spec bad(non_neg_integer(), term()) -> no_return().
bad(Line, Why) -> throw({dxf, Line, Why}).

%%====================================================================
%% Export
%%====================================================================

%% @doc The drawing as DXF text (see the module doc); refused when a polyline is not
%% flat, naming its position among the primitives.
-spec export(cell_recipe_drawing:drawing()) ->
          {ok, iodata()} | {error, {not_exportable, pos_integer(), term()}}.
export(Drawing) ->
    Prims = lists:reverse(walk(Drawing, cell_recipe_drawing:identity(), <<"0">>, [])),
    try lists:zipwith(fun(I, {Layer, P}) -> [out(I, P, g(8, escape(Layer)))] end,
                      lists:seq(1, length(Prims)), Prims) of
        Body ->
            %% LWPOLYLINE came with AutoCAD 2000 (AC1015): say so, or readers take the
            %% file for R12 and drop what R12 did not have.
            {ok, [g(0, <<"SECTION">>), g(2, <<"HEADER">>), g(9, <<"$ACADVER">>),
                  g(1, <<"AC1015">>), g(0, <<"ENDSEC">>),
                  g(0, <<"SECTION">>), g(2, <<"ENTITIES">>), Body,
                  g(0, <<"ENDSEC">>), g(0, <<"EOF">>)]}
    catch
        throw:{not_exportable, _, _} = E -> {error, E}
    end.

%% The primitives in drawing coordinates, each with its layer: its own `Layer' or
%% `ItemType', else that of the nearest container around it that has one.
walk(#{kind := container, children := Children} = C, M0, Layer0, Acc) ->
    M = cell_recipe_drawing:multiply(M0, cell_recipe_drawing:transform(C)),
    Layer = layer_of(C, Layer0),
    lists:foldl(fun(Child, A) -> walk(Child, M, Layer, A) end, Acc, Children);
walk(Prim, M, Layer, Acc) ->
    [{layer_of(Prim, Layer), cell_recipe_drawing:apply_transform(M, Prim)} | Acc].

layer_of(Item, Inherited) ->
    Own = case cell_recipe_drawing:attr(Item, <<"Layer">>) of
              undefined -> cell_recipe_drawing:item_type(Item);
              L -> L
          end,
    case Own =/= undefined andalso layer_name_ok(Own) of
        true -> Own;
        false -> Inherited
    end.

%% Subclass markers (group 100) are written as AutoCAD 2000 and later expect them.
out(_I, #{kind := line, from := F, to := T}, Lay) ->
    [head(<<"LINE">>, Lay, <<"AcDbLine">>), xyz(10, F), xyz(11, T)];
out(_I, #{kind := circle, center := C, radius := R}, Lay) ->
    [head(<<"CIRCLE">>, Lay, <<"AcDbCircle">>), xyz(10, C), g(40, R)];
out(_I, #{kind := arc, center := C, radius := R, start_angle := A0, end_angle := A1}, Lay) ->
    [head(<<"ARC">>, Lay, <<"AcDbCircle">>), xyz(10, C), g(40, R),
     g(100, <<"AcDbArc">>), g(50, A0), g(51, A1)];
out(I, #{kind := polyline, points := Ps, bulges := Bs, closed := Closed}, Lay) ->
    Z = case lists:usort([Z || {_, _, Z} <- Ps]) of
            [Z0] -> Z0;
            _ -> throw({not_exportable, I, polyline_not_flat})
        end,
    [head(<<"LWPOLYLINE">>, Lay, <<"AcDbPolyline">>), g(90, length(Ps)),
     g(70, case Closed of true -> 1; false -> 0 end),
     [g(38, Z) || Z /= 0],
     [[g(10, X), g(20, Y), [g(42, B) || B /= 0]] || {{X, Y, _}, B} <- lists:zip(Ps, Bs)]];
out(_I, #{kind := polyface, vertices := Vs, faces := Faces}, Lay) ->
    [[head(<<"3DFACE">>, Lay, <<"AcDbFace">>),
      xyz(10, lists:nth(A, Vs)), xyz(11, lists:nth(B, Vs)),
      xyz(12, lists:nth(C, Vs)), xyz(13, lists:nth(D, Vs))]
     || Face <- Faces, [A, B, C, D] <- quads(Face)].

head(Type, Lay, Subclass) ->
    [g(0, Type), g(100, <<"AcDbEntity">>), Lay, g(100, Subclass)].

%% A 3DFACE has three or four corners (a triangle repeats its third): larger faces
%% are split into a fan of triangles.
quads([A, B, C]) -> [[A, B, C, C]];
quads([A, B, C, D]) -> [[A, B, C, D]];
quads([A, B, C | Rest]) -> [[A, B, C, C] | quads([A, C | Rest])].

%% What AutoCAD accepts as a layer name (and what `\U+XXXX' can spell).
layer_name_ok(<<>>) -> false;
layer_name_ok(Name) ->
    string:length(Name) =< 255 andalso
        nomatch =:= re:run(Name, "[<>/\\\\\":;?*|=`\\x00-\\x1f]", [unicode]) andalso
        lists:all(fun(C) -> C =< 16#FFFF end, unicode:characters_to_list(Name)).

%% A file that says AC1015 is read in its code page: characters beyond ASCII are
%% written as `\U+XXXX', which every reader since AutoCAD 2000 understands.
escape(Name) ->
    << <<(if C < 128 -> <<C>>;
             true -> iolist_to_binary(io_lib:format("\\U+~4.16.0B", [C]))
          end)/binary>> || <<C/utf8>> <= Name >>.

xyz(Code, {X, Y, Z}) -> [g(Code, X), g(Code + 10, Y), g(Code + 20, Z)].

g(Code, V) when is_float(V) -> [integer_to_binary(Code), $\n, float_to_binary(V, [short]), $\n];
g(Code, V) when is_integer(V) -> [integer_to_binary(Code), $\n, integer_to_binary(V), $\n];
g(Code, V) when is_binary(V) -> [integer_to_binary(Code), $\n, V, $\n].

%% @doc A DXF error in words.
-spec format_error(term()) -> binary().
format_error({dxf, 0, Why}) ->
    iolist_to_binary(io_lib:format("DXF file: ~ts", [why(Why)]));
format_error({dxf, Line, Why}) ->
    iolist_to_binary(io_lib:format("DXF file, line ~p: ~ts", [Line, why(Why)]));
format_error({not_exportable, I, polyline_not_flat}) ->
    iolist_to_binary(io_lib:format("primitive ~p is a polyline whose points are not all "
                                   "at one height; DXF cannot hold it", [I]));
format_error(Other) ->
    iolist_to_binary(io_lib:format("~0tp", [Other])).

why(binary_dxf) -> "binary DXF is not read; save the drawing as ASCII DXF";
why({too_big, Size, Max}) -> io_lib:format("~p bytes, more than the ~p allowed", [Size, Max]);
why({too_many_entities, Max}) -> io_lib:format("more than ~p entities", [Max]);
why(ends_inside_a_section) -> "the file ends inside a section (cut short?)";
why(ends_inside_the_entities) -> "the file ends inside the ENTITIES section (cut short?)";
why(group_without_value) -> "a group code without its value at the end of the file";
why({missing, Code}) -> io_lib:format("the entity lacks group ~p", [Code]);
why({bad_group_code, T}) -> io_lib:format("~tp is not a group code", [T]);
why({not_a_number, T}) -> io_lib:format("~tp is not a number", [T]);
why({not_an_integer, T}) -> io_lib:format("~tp is not an integer", [T]);
why({vertex_count, Said, Found}) ->
    io_lib:format("the polyline says ~p vertices but has ~p", [Said, Found]);
why(Other) -> io_lib:format("~0tp", [Other]).
