%% DXF import and export: the four entities with their group codes, mirrored
%% extrusion, what is skipped and reported, malformed and hostile files refused with
%% the line named, and export/import round trips of random drawings.
-module(cell_recipe_dxf_tests).

-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(D, cell_recipe_drawing).
-define(X, cell_recipe_dxf).

dxf(Lines) -> iolist_to_binary([[L, "\r\n"] || L <- Lines]).

entities(Body) ->
    dxf(["999", "written by hand", "0", "SECTION", "2", "HEADER", "9", "$ACADVER", "1", "AC1015",
         "0", "ENDSEC", "0", "SECTION", "2", "ENTITIES"] ++ Body ++ ["0", "ENDSEC", "0", "EOF"]).

import_test() ->
    Text = entities(["0", "LINE", "5", "2A", "8", "Cut", "10", "1.5", "20", "-2", "30", "0",
                     "11", "1E+02", "21", ".25", "31", "0.0",
                     "0", "CIRCLE", "8", "Holes", "10", "5", "20", "5", "40", "2.5",
                     "0", "ARC", "8", "0", "10", "0", "20", "0", "30", "3", "40", "1",
                     "50", "0", "51", "90",
                     "0", "LWPOLYLINE", "8", "Outline", "90", "3", "70", "1", "38", "2",
                     "10", "0", "20", "0", "42", "0.5", "10", "10", "20", "0", "40", "0",
                     "41", "0", "10", "10", "20", "10",
                     "0", "TEXT", "8", "0", "10", "0", "20", "0", "1", "Panel A",
                     "0", "INSERT", "2", "FID", "10", "0", "20", "0",
                     "0", "TEXT", "8", "0", "10", "0", "20", "0", "1", "Panel B"]),
    {ok, C, Report} = ?X:import(Text),
    ?assertEqual(#{imported => 4, skipped => #{<<"TEXT">> => 2, <<"INSERT">> => 1}}, Report),
    ?assertEqual(<<"PanelDrawing">>, ?D:item_type(C)),
    [Line, Circle, Arc, Poly] = maps:get(children, C),
    ?assertEqual(?D:line({1.5, -2.0, 0.0}, {100.0, 0.25, 0.0}, #{<<"Layer">> => <<"Cut">>}), Line),
    ?assertEqual(?D:circle({5, 5}, 2.5, #{<<"Layer">> => <<"Holes">>}), Circle),
    ?assertEqual(?D:arc({0, 0, 3}, 1, 0, 90, #{<<"Layer">> => <<"0">>}), Arc),
    ?assertEqual(#{kind => polyline, attrs => #{<<"Layer">> => <<"Outline">>},
                   points => [{0.0, 0.0, 2.0}, {10.0, 0.0, 2.0}, {10.0, 10.0, 2.0}],
                   bulges => [0.5, 0.0, 0.0], closed => true}, Poly),
    ?assertMatch({ok, _}, ?D:validate(?D:new([C]))),
    %% unix line ends and a file without EOF read the same
    Unix = binary:replace(Text, <<"\r\n">>, <<"\n">>, [global]),
    ?assertEqual({ok, C, Report}, ?X:import(Unix)),
    NoEof = binary:part(Unix, 0, byte_size(Unix) - byte_size(<<"0\nEOF\n">>)),
    ?assertEqual({ok, C, Report}, ?X:import(NoEof)),
    ?assertMatch({ok, #{attrs := #{<<"ItemType">> := <<"Teach">>}}, _},
                 ?X:import(Text, #{item_type => <<"Teach">>})).

mirrored_extrusion_test() ->
    %% An arc drawn seen from below: (0, 0, -1) mirrors X. In the world it runs
    %% counter-clockwise from 90° to 180° around (-5, 0).
    Text = entities(["0", "ARC", "10", "5", "20", "0", "30", "0", "40", "2", "50", "0",
                     "51", "90", "210", "0", "220", "0", "230", "-1",
                     "0", "CIRCLE", "10", "1", "20", "2", "40", "3",
                     "210", "0", "220", "0.7071", "230", "0.7071"]),
    {ok, #{children := [Arc]}, #{skipped := Skipped}} = ?X:import(Text),
    #{center := {Cx, Cy, _}, start_angle := S, end_angle := E} = Arc,
    ?assertEqual({-5.0, 0.0}, {Cx, Cy}),
    ?assert(abs(S - 90.0) < 1.0e-9 andalso abs(E - 180.0) < 1.0e-9),
    ?assertEqual(#{<<"CIRCLE out of the XY plane">> => 1}, Skipped).

latin1_and_escapes_test() ->
    Text = entities(["0", "LINE", "8", <<"Fr", 16#e4, "sen">>, "10", "0", "20", "0", "11", "1",
                     "21", "1",
                     "0", "LINE", "8", <<"Bohrung \\U+00D8 3">>, "10", "0", "20", "0", "11",
                     "1", "21", "1"]),
    {ok, #{children := [A, B]}, _} = ?X:import(Text),
    ?assertEqual(<<"Fräsen"/utf8>>, ?D:attr(A, <<"Layer">>)),
    ?assertEqual(<<"Bohrung Ø 3"/utf8>>, ?D:attr(B, <<"Layer">>)).

degenerate_test() ->
    Text = entities(["0", "LWPOLYLINE", "90", "1", "10", "0", "20", "0",
                     "0", "CIRCLE", "10", "0", "20", "0", "40", "0"]),
    ?assertEqual({ok, ?D:container(#{<<"ItemType">> => <<"PanelDrawing">>}, []),
                  #{imported => 0,
                    skipped => #{<<"LWPOLYLINE with fewer than two vertices">> => 1,
                                 <<"CIRCLE with no radius">> => 1}}},
                 ?X:import(Text)).

malformed_test_() ->
    Line = ["0", "LINE", "10", "0", "20", "0", "11", "1", "21", "1"],
    Cut = fun(Bin, N) -> binary:part(Bin, 0, byte_size(Bin) - N) end,
    Good = entities(Line),
    Err = fun(L, Why) -> {error, {dxf, L, Why}} end,
    [?_assertEqual(Err(0, binary_dxf), ?X:import(<<"AutoCAD Binary DXF\r\n", 26, 0, 1, 2>>)),
     ?_assertEqual(Err(0, {too_big, byte_size(Good), 100}), ?X:import(Good, #{max_bytes => 100})),
     ?_assertEqual(Err(37, {too_many_entities, 2}),
                   ?X:import(entities(Line ++ Line ++ Line), #{max_entities => 2})),
     %% cut short inside the entities (a half upload)
     ?_assertEqual(Err(0, ends_inside_the_entities), ?X:import(Cut(Good, 20))),
     ?_assertEqual(Err(25, group_without_value), ?X:import(Cut(Good, 24))),
     ?_assertEqual(Err(15, group_without_value), ?X:import(dxf(["0", "SECTION", "2", "ENTITIES"] ++ Line ++ ["0"]))),
     ?_assertEqual(Err(19, {bad_group_code, <<"ten">>}),
                   ?X:import(entities(["0", "LINE", "ten", "0"]))),
     ?_assertEqual(Err(20, {not_a_number, <<"1,5">>}),
                   ?X:import(entities(["0", "LINE", "10", "1,5", "20", "0", "11", "1", "21", "1"]))),
     ?_assertEqual(Err(17, {missing, 11}),
                   ?X:import(entities(["0", "LINE", "10", "0", "20", "0", "21", "1"]))),
     ?_assertEqual(Err(19, {vertex_count, 3, 2}),
                   ?X:import(entities(["0", "LWPOLYLINE", "90", "3", "10", "0", "20", "0",
                                       "10", "1", "20", "1"]))),
     ?_assertEqual(Err(21, {missing, 20}),
                   ?X:import(entities(["0", "LWPOLYLINE", "90", "2", "10", "0", "10", "1",
                                       "20", "1"]))),
     ?_assertEqual(Err(1, {unexpected, 5, <<"x">>}), ?X:import(<<"5\nx\n">>)),
     ?_assertEqual({error, {bad_option, max_bytes}}, ?X:import(Good, #{max_bytes => -1})),
     ?_assertEqual({error, {bad_option, colour}}, ?X:import(Good, #{colour => red})),
     ?_assertMatch({error, {dxf, _, _}}, ?X:import(<<0, 1, 2, 3, 255, 10, 13>>)),
     ?_assertEqual({ok, ?D:container(#{<<"ItemType">> => <<"PanelDrawing">>}, []),
                    #{imported => 0, skipped => #{}}},
                   ?X:import(<<>>))].

error_text_test() ->
    ?assertEqual(<<"DXF file, line 20: <<\"1,5\">> is not a number">>,
                 ?X:format_error({dxf, 20, {not_a_number, <<"1,5">>}})),
    ?assertMatch(<<"DXF file: binary DXF", _/binary>>, ?X:format_error({dxf, 0, binary_dxf})).

export_test() ->
    D = ?D:new([?D:container(#{<<"ItemType">> => <<"Cut">>,
                               <<"Transform">> => ?D:matrix_to_text(?D:translation(10, 0, 0))},
                             [?D:line({0, 0}, {1, 1})]),
                ?D:polyface([{0, 0}, {1, 0}, {1, 1}, {0, 1}, {0.5, 2}], [[1, 2, 3], [1, 2, 3, 4, 5]],
                            #{<<"Layer">> => <<"bad/name">>})]),
    {ok, Text} = ?X:export(D),
    Bin = iolist_to_binary(Text),
    %% the transform is applied and the ItemType names the layer
    ?assertMatch({match, _}, re:run(Bin, "^0\nLINE\n100\nAcDbEntity\n8\nCut\n100\nAcDbLine\n"
                                  "10\n10.0\n20\n0.0\n", [multiline])),
    ?assertMatch({match, _}, re:run(Bin, "^\\$ACADVER\n1\nAC1015\n", [multiline])),
    %% a face of five corners is split in a triangle and a quad; a layer name DXF
    %% cannot hold falls back to the layer around it
    ?assertEqual(3, length(binary:matches(Bin, <<"3DFACE">>))),
    ?assertEqual(3, length(binary:matches(Bin, <<"8\n0\n">>))),
    %% the exported lines import back; 3DFACEs are not imported
    ?assertMatch({ok, #{children := [#{kind := line, from := {10.0, 0.0, 0.0}}]},
                  #{skipped := #{<<"3DFACE">> := 3}}}, ?X:import(Bin)),
    Bumpy = ?D:new([?D:polyline([{0, 0, 0}, {1, 1, 1}], false)]),
    ?assertEqual({error, {not_exportable, 1, polyline_not_flat}}, ?X:export(Bumpy)).

roundtrip_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_export_import(),
                                              [{to_file, user}, {numtests, 150}]))}.

%% Lines, circles, arcs and flat polylines exported to DXF import back exactly:
%% same kinds, same numbers to the last bit, same layers.
prop_export_import() ->
    ?FORALL(D, cell_recipe_gen:flat_drawing(),
            begin
                {ok, Text} = ?X:export(D),
                {ok, C, #{imported := N}} = ?X:import(iolist_to_binary(Text)),
                N =:= ?D:count(D) andalso maps:get(children, C) =:= ?D:primitives(D)
            end).
