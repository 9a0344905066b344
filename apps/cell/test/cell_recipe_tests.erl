%% Recipes: names, save/load round trips of random recipes, file handling (list,
%% info, rename, copy, delete), and archives from outside that must be refused:
%% absolute paths, `..', oversized, zip bombs (real and lying), many entries,
%% missing parts, malformed JSON, damaged bytes. Nothing may be written outside
%% Products/, nothing changed by a refused import.
-module(cell_recipe_tests).

-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(R, cell_recipe).
-define(D, cell_recipe_drawing).

%%====================================================================
%% Helpers
%%====================================================================

tmp_dir(What) ->
    Dir = filename:join(cell_test_dir:new("recipe", What), "Products"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Dir.

opts(Dir) -> #{dir => Dir, sync => false}.

%% Everything under the folder above Products/, so a stray write anywhere shows.
tree(Dir) ->
    Top = filename:dirname(Dir),
    lists:sort(filelib:wildcard("**", Top)).

recipe() ->
    #{description => <<"Panel 4711, two up"/utf8>>,
      settings => #{board_length => 160.0, fixture_id => <<"F7">>},
      drawing => ?D:new([?D:container(#{<<"ItemType">> => <<"PanelDrawing">>},
                                      [?D:line({0, 0}, {160, 0}), ?D:circle({5, 5}, 1.5)]),
                         ?D:line({0, 10}, {160, 10}, #{<<"ItemType">> => <<"Cut">>,
                                                       <<"ExecOrder">> => <<"1">>})]),
      files => #{<<"program.nc">> => <<"G0 X0 Y0\nG1 X160\n">>}}.

%% A zip written byte by byte, so a test can say anything in it: names, declared
%% sizes, flags, methods. Each entry: {Name, Data, Overrides}.
raw_zip(Entries) ->
    {Locals, Centrals, _} =
        lists:foldl(
          fun({Name, Data, O}, {Ls, Cs, Offset}) ->
                  Method = maps:get(method, O, 0),
                  Comp = case Method of 8 -> deflate(Data); _ -> Data end,
                  Crc = maps:get(crc, O, erlang:crc32(Data)),
                  USize = maps:get(usize, O, byte_size(Data)),
                  Flags = maps:get(flags, O, 0),
                  N = byte_size(Name),
                  Local = <<16#04034b50:32/little, 20:16/little, Flags:16/little,
                            Method:16/little, 0:16, 0:16, Crc:32/little,
                            (byte_size(Comp)):32/little, USize:32/little, N:16/little,
                            0:16, Name/binary, Comp/binary>>,
                  Central = <<16#02014b50:32/little, 20:16/little, 20:16/little,
                              Flags:16/little, Method:16/little, 0:16, 0:16, Crc:32/little,
                              (byte_size(Comp)):32/little, USize:32/little, N:16/little,
                              0:16, 0:16, 0:16, 0:16, 0:32, Offset:32/little, Name/binary>>,
                  {[Local | Ls], [Central | Cs], Offset + byte_size(Local)}
          end, {[], [], 0}, Entries),
    L = iolist_to_binary(lists:reverse(Locals)),
    C = iolist_to_binary(lists:reverse(Centrals)),
    Count = length(Entries),
    <<L/binary, C/binary, 16#06054b50:32/little, 0:16, 0:16, Count:16/little,
      Count:16/little, (byte_size(C)):32/little, (byte_size(L)):32/little, 0:16>>.

deflate(Data) ->
    Z = zlib:open(),
    ok = zlib:deflateInit(Z, default, deflated, -15, 8, default),
    Out = iolist_to_binary(zlib:deflate(Z, Data, finish)),
    ok = zlib:deflateEnd(Z),
    ok = zlib:close(Z),
    Out.

%% The three parts of a good recipe, as raw entries.
good_parts() ->
    {ok, Bin} = ?R:encode(recipe(), #{}),
    {ok, Entries} = cell_recipe_zip:read(Bin, cell_recipe_zip:default_limits()),
    [{list_to_binary(N), C, #{}} || {N, C} <- Entries].

%%====================================================================
%% Names
%%====================================================================

names_test_() ->
    Good = [<<"Board A-12_rev.3">>, <<"Fräsplatte Ø3"/utf8>>, <<"COM10">>, <<"CONSOLE">>,
            <<"x">>, binary:copy(<<"é"/utf8>>, 100), <<"a.b.c">>, <<"base (copy)">>],
    Bad = [{<<>>, empty}, {binary:copy(<<"a">>, 101), too_long},
           {<<"a/b">>, {bad_character, "/"}}, {<<"a\\b">>, {bad_character, "\\"}},
           {<<"a:b">>, {bad_character, ":"}}, {<<"a*b">>, {bad_character, "*"}},
           {<<"a?b">>, {bad_character, "?"}}, {<<"a\"b">>, {bad_character, "\""}},
           {<<"a<b">>, {bad_character, "<"}}, {<<"a|b">>, {bad_character, "|"}},
           {<<"a\tb">>, {bad_character, "\t"}}, {<<"a", 127, "b">>, {bad_character, [127]}},
           {<<"..">>, {bad_start, "."}}, {<<".hidden">>, {bad_start, "."}},
           {<<" lead">>, {bad_start, " "}}, {<<"trail.">>, {bad_end, "."}},
           {<<"trail ">>, {bad_end, " "}}, {<<"CON">>, reserved_name},
           {<<"con.txt">>, reserved_name}, {<<"Com1">>, reserved_name},
           {<<"LPT9.old">>, reserved_name}, {<<"NUL ">>, {bad_end, " "}},
           {<<255, 254>>, not_utf8}, {"text", not_a_binary}, {atom, not_a_binary}],
    [?_assertEqual(ok, ?R:check_name(N)) || N <- Good]
        ++ [?_assertEqual({error, {bad_name, N, Why}}, ?R:check_name(N)) || {N, Why} <- Bad].

bad_name_everywhere_test() ->
    Dir = tmp_dir("badname"),
    O = opts(Dir),
    Before = tree(Dir),
    Bad = <<"sub/../escape">>,
    Err = {error, {bad_name, Bad, {bad_character, "/"}}},
    ?assertEqual(Err, ?R:save(Bad, recipe(), <<"anna">>, O)),
    ?assertEqual(Err, ?R:load(Bad, O)),
    ?assertEqual(Err, ?R:delete(Bad, O)),
    ?assertEqual(Err, ?R:export(Bad, O)),
    {ok, Good} = ?R:encode(recipe(), O),
    ?assertEqual(Err, ?R:import(Bad, Good, O)),
    ?assertEqual(Before, tree(Dir)).

%%====================================================================
%% Files
%%====================================================================

save_load_test() ->
    Dir = tmp_dir("saveload"),
    O = opts(Dir),
    T0 = os:system_time(millisecond),
    ?assertEqual(ok, ?R:save(<<"Panel 4711">>, recipe(), <<"anna">>, O)),
    {ok, R} = ?R:load(<<"Panel 4711">>, O),
    ?assertMatch(#{description := <<"Panel 4711, two up"/utf8>>, author := <<"anna">>,
                   files := #{<<"program.nc">> := <<"G0 X0 Y0\nG1 X160\n">>}}, R),
    ?assert(maps:get(modified, R) >= T0),
    %% settings given in part take the defaults for the rest
    ?assertEqual(#{board_length => 160.0, board_width => 100.0, board_thickness => 1.6,
                   fixture_id => <<"F7">>}, maps:get(settings, R)),
    {ok, Drawing} = ?D:validate(maps:get(drawing, recipe())),
    ?assertEqual(Drawing, maps:get(drawing, R)),
    %% the file is an ordinary zip with the parts as text
    {ok, Names} = zip:list_dir(filename:join(Dir, "Panel 4711.zprd")),
    ?assertEqual(["drawing.json", "files/program.nc", "recipe.json", "settings.json"],
                 lists:sort([N || {zip_file, N, _, _, _, _} <- Names])),
    {ok, Info} = ?R:info(<<"Panel 4711">>, O),
    ?assertMatch(#{name := <<"Panel 4711">>, author := <<"anna">>,
                   description := <<"Panel 4711, two up"/utf8>>}, Info),
    ?assertEqual(maps:get(modified, R), maps:get(modified, Info)),
    ?assert(maps:get(bytes, Info) > 100),
    %% a refused save changes nothing
    ?assertEqual({error, {invalid, [settings, board_length], {out_of_range, 0.5, 1.0, 2000.0}}},
                 ?R:save(<<"Panel 4711">>, #{settings => #{board_length => 0.5}}, <<"bert">>, O)),
    ?assertEqual({error, {invalid, [drawing, children, 1, radius], {not_positive, -1}}},
                 ?R:save(<<"Panel 4711">>, #{drawing => ?D:new([#{kind => circle, attrs => #{},
                                                                   center => {0, 0, 0},
                                                                   radius => -1}])},
                         <<"bert">>, O)),
    ?assertEqual({error, {invalid, [files, <<"../x">>], bad_file_name}},
                 ?R:save(<<"Panel 4711">>, #{files => #{<<"../x">> => <<>>}}, <<"bert">>, O)),
    ?assertEqual({error, {bad_who, <<>>}}, ?R:save(<<"Panel 4711">>, #{}, <<>>, O)),
    ?assertEqual({error, {invalid, [colour], unknown_field}},
                 ?R:save(<<"Panel 4711">>, #{colour => red}, <<"bert">>, O)),
    ?assertEqual({error, {invalid, [description], {not_text, 42}}},
                 ?R:save(<<"Panel 4711">>, #{description => 42}, <<"bert">>, O)),
    ?assertEqual({ok, R}, ?R:load(<<"Panel 4711">>, O)),
    %% the defaults make a recipe
    ok = ?R:save(<<"empty">>, #{}, <<"bert">>, O),
    ?assertMatch({ok, #{description := <<>>, files := #{}, drawing := #{children := []}}},
                 ?R:load(<<"empty">>, O)),
    ?assertEqual({error, {bad_option, colour}}, ?R:load(<<"empty">>, #{colour => red})).

file_handling_test() ->
    Dir = tmp_dir("files"),
    O = opts(Dir),
    ok = ?R:save(<<"B">>, recipe(), <<"anna">>, O),
    ok = ?R:save(<<"A">>, #{}, <<"anna">>, O),
    %% files whose names break the rules are not recipes
    ok = file:write_file(filename:join(Dir, "CON.zprd"), <<"x">>),
    ok = file:write_file(filename:join(Dir, "notes.txt"), <<"x">>),
    ?assertEqual([<<"A">>, <<"B">>], ?R:list(O)),
    ?assertEqual(ok, ?R:copy(<<"B">>, <<"C">>, O)),
    ?assertEqual(?R:load(<<"B">>, O), ?R:load(<<"C">>, O)),
    ?assertEqual({error, {exists, <<"A">>}}, ?R:copy(<<"B">>, <<"A">>, O)),
    ?assertEqual({error, {exists, <<"A">>}}, ?R:rename(<<"C">>, <<"A">>, O)),
    ?assertEqual(ok, ?R:rename(<<"C">>, <<"D">>, O)),
    ?assertEqual({error, {no_recipe, <<"C">>}}, ?R:load(<<"C">>, O)),
    ?assertEqual({error, {no_recipe, <<"C">>}}, ?R:rename(<<"C">>, <<"E">>, O)),
    ?assertEqual({error, {no_recipe, <<"C">>}}, ?R:copy(<<"C">>, <<"E">>, O)),
    ?assertEqual([<<"A">>, <<"B">>, <<"D">>], ?R:list(O)),
    ?assertEqual(ok, ?R:delete(<<"D">>, O)),
    ?assertEqual({error, {no_recipe, <<"D">>}}, ?R:delete(<<"D">>, O)),
    {ok, Bytes} = ?R:export(<<"B">>, O),
    {ok, Bytes} = file:read_file(filename:join(Dir, "B.zprd")),
    %% import: a new name, never over an existing recipe unless asked
    ?assertEqual(ok, ?R:import(<<"Uploaded">>, Bytes, O)),
    ?assertEqual(?R:load(<<"B">>, O), ?R:load(<<"Uploaded">>, O)),
    ?assertEqual({error, {exists, <<"A">>}}, ?R:import(<<"A">>, Bytes, O)),
    ?assertEqual(ok, ?R:import(<<"A">>, Bytes, O#{replace => true})),
    ?assertEqual(?R:load(<<"B">>, O), ?R:load(<<"A">>, O)),
    ?assertEqual([], filelib:wildcard("*.tmp-*", Dir)),
    %% an empty or missing folder lists nothing
    ?assertEqual([], ?R:list(#{dir => filename:join(Dir, "nowhere")})).

durable_save_test() ->
    Dir = tmp_dir("durable"),
    ok = ?R:save(<<"P">>, recipe(), <<"anna">>, #{dir => Dir}),
    ok = ?R:rename(<<"P">>, <<"Q">>, #{dir => Dir}),
    ?assertMatch({ok, _}, ?R:load(<<"Q">>, #{dir => Dir})).

%%====================================================================
%% Archives from outside
%%====================================================================

refused(Dir, Bin, Opts) ->
    O = maps:merge(opts(Dir), Opts),
    Before = tree(Dir),
    Result = ?R:import(<<"Upload">>, Bin, O),
    ?assertEqual(Before, tree(Dir)),
    ?assertMatch({error, _}, Result),
    %% every refusal can be told to an operator
    {error, Why} = Result,
    ?assert(is_binary(?R:format_error(Why))),
    Why.

unsafe_names_test() ->
    Dir = tmp_dir("unsafe"),
    Parts = good_parts(),
    [?assertEqual({archive, {unsafe_entry, binary_to_list(Name)}},
                  refused(Dir, raw_zip(Parts ++ [{Name, <<"evil">>, #{}}]), #{}))
     || Name <- [<<"/etc/cron.d/evil">>, <<"files/../../evil">>, <<"../Settings/machine.json">>,
                 <<"files/..">>, <<"C:/Windows/evil">>, <<"files\\..\\evil">>,
                 <<"files/a", 0, "b">>]].

unexpected_and_missing_test() ->
    Dir = tmp_dir("parts"),
    Parts = good_parts(),
    ?assertEqual({unexpected_entry, "run.sh"},
                 refused(Dir, raw_zip(Parts ++ [{<<"run.sh">>, <<"rm -rf /">>, #{}}]), #{})),
    %% names beyond ASCII, flagged as UTF-8 or not, are not machine files of ours
    ?assertMatch({unexpected_entry, "files/Fr" ++ _},
                 refused(Dir, raw_zip(Parts ++ [{<<"files/Fräs.nc"/utf8>>, <<"x">>,
                                                 #{flags => 16#800}}]), #{})),
    ?assertMatch({unexpected_entry, "files/Fr" ++ _},
                 refused(Dir, raw_zip(Parts ++ [{<<"files/Fräs.nc"/utf8>>, <<"x">>, #{}}]), #{})),
    ?assertEqual({unexpected_entry, "files/sub/x"},
                 refused(Dir, raw_zip(Parts ++ [{<<"files/sub/x">>, <<"x">>, #{}}]), #{})),
    [?assertEqual({missing_part, binary_to_list(Part)},
                  refused(Dir, raw_zip(lists:keydelete(Part, 1, Parts)), #{}))
     || Part <- [<<"recipe.json">>, <<"settings.json">>, <<"drawing.json">>]],
    ?assertEqual({archive, {duplicate_entry, "drawing.json"}},
                 refused(Dir, raw_zip(Parts ++ [lists:keyfind(<<"drawing.json">>, 1, Parts)]), #{})),
    %% a folder entry for files/, as zip tools write it, is fine
    ?assertEqual(ok, ?R:import(<<"Folder">>, raw_zip([{<<"files/">>, <<>>, #{}} | Parts]),
                               opts(Dir))).

malformed_parts_test() ->
    Dir = tmp_dir("malformed"),
    Parts = good_parts(),
    With = fun(Name, Data) -> raw_zip(lists:keyreplace(Name, 1, Parts, {Name, Data, #{}})) end,
    ?assertEqual({bad_part, "settings.json", not_json},
                 refused(Dir, With(<<"settings.json">>, <<"{\"board_length\": ">>), #{})),
    ?assertEqual({bad_part, "settings.json",
                  {invalid, [board_length], {out_of_range, 9999.0, 1.0, 2000.0}}},
                 refused(Dir, With(<<"settings.json">>, <<"{\"board_length\": 9999}">>), #{})),
    ?assertEqual({bad_part, "drawing.json", not_json},
                 refused(Dir, With(<<"drawing.json">>, <<0, 1, 2>>), #{})),
    ?assertEqual({bad_part, "drawing.json", {invalid, [], {not_a_container, line}}},
                 refused(Dir, With(<<"drawing.json">>,
                                   <<"{\"kind\":\"line\",\"attributes\":{},\"from\":[0,0,0],"
                                     "\"to\":[1,1,1]}">>), #{})),
    ?assertEqual({bad_part, "recipe.json", {invalid, [format], {unsupported_format, 2}}},
                 refused(Dir, With(<<"recipe.json">>,
                                   <<"{\"format\":2,\"description\":\"\",\"author\":\"a\","
                                     "\"modified\":\"2024-01-01T00:00:00Z\"}">>), #{})),
    ?assertEqual({bad_part, "recipe.json", {invalid, [modified], {not_a_time, <<"yesterday">>}}},
                 refused(Dir, With(<<"recipe.json">>,
                                   <<"{\"format\":1,\"description\":\"\",\"author\":\"a\","
                                     "\"modified\":\"yesterday\"}">>), #{})),
    ?assertEqual({bad_part, "recipe.json", {invalid, [<<"author">>], missing}},
                 refused(Dir, With(<<"recipe.json">>,
                                   <<"{\"format\":1,\"description\":\"\","
                                     "\"modified\":\"2024-01-01T00:00:00Z\"}">>), #{})),
    ?assertEqual({bad_part, "recipe.json", {invalid, [<<"x">>], unknown_field}},
                 refused(Dir, With(<<"recipe.json">>,
                                   <<"{\"format\":1,\"description\":\"\",\"author\":\"a\",\"x\":1,"
                                     "\"modified\":\"2024-01-01T00:00:00Z\"}">>), #{})).

sizes_and_bombs_test() ->
    Dir = tmp_dir("bombs"),
    Parts = good_parts(),
    Good = raw_zip(Parts),
    %% the archive itself too big
    ?assertMatch({archive, {too_big, _, 1000}}, refused(Dir, Good, #{limits => #{archive => 1000}})),
    %% one entry declared too big, and all of them together
    ?assertMatch({archive, {entry_too_big, "recipe.json", _, 100}},
                 refused(Dir, Good, #{limits => #{entry => 100}})),
    ?assertMatch({archive, {total_too_big, _, 300}}, refused(Dir, Good, #{limits => #{total => 300}})),
    %% a real bomb: 8 MiB of zeros in a few kB, refused on its ratio before inflating
    Zeros = binary:copy(<<0>>, 8 * 1024 * 1024),
    Bomb = raw_zip(Parts ++ [{<<"files/zeros.bin">>, Zeros, #{method => 8}}]),
    ?assert(byte_size(Bomb) < 64 * 1024),
    ?assertEqual({archive, {bomb, "files/zeros.bin"}}, refused(Dir, Bomb, #{})),
    %% a lying bomb: declares 1 kB, inflates to 8 MiB; stopped while inflating
    Liar = raw_zip(Parts ++ [{<<"files/zeros.bin">>, Zeros, #{method => 8, usize => 1024}}]),
    ?assertEqual({archive, {bomb, "files/zeros.bin"}}, refused(Dir, Liar, #{})),
    %% declares more than it holds
    Short = raw_zip(Parts ++ [{<<"files/a.txt">>, <<"hello">>, #{method => 8, usize => 6}}]),
    ?assertEqual({archive, {corrupt_entry, "files/a.txt", size_mismatch}}, refused(Dir, Short, #{})),
    %% many entries: refused from the end record, before the directory is listed
    Many = raw_zip(Parts ++ [{<<"files/f", (integer_to_binary(I))/binary>>, <<>>, #{}}
                             || I <- lists:seq(1, 1000)]),
    ?assertEqual({archive, {too_many_entries, 1004, 1000}}, refused(Dir, Many, #{})).

damaged_test() ->
    Dir = tmp_dir("damaged"),
    Parts = good_parts(),
    Good = raw_zip(Parts),
    ?assertMatch({archive, {not_a_zip, _}}, refused(Dir, <<"PK not really">>, #{})),
    ?assertMatch({archive, {not_a_zip, _}}, refused(Dir, <<>>, #{})),
    ?assertMatch({archive, {not_a_zip, _}},
                 refused(Dir, crypto:strong_rand_bytes(4096), #{})),
    %% cut short: the end record is gone
    ?assertMatch({archive, {not_a_zip, _}},
                 refused(Dir, binary:part(Good, 0, byte_size(Good) - 30), #{})),
    %% a flipped byte in an entry: the CRC tells
    {Name, Data, _} = lists:keyfind(<<"settings.json">>, 1, Parts),
    BadCrc = raw_zip(lists:keyreplace(Name, 1, Parts,
                                      {Name, Data, #{crc => erlang:crc32(Data) bxor 1}})),
    ?assertEqual({archive, {corrupt_entry, "settings.json", bad_crc}}, refused(Dir, BadCrc, #{})),
    Encrypted = raw_zip(lists:keyreplace(Name, 1, Parts, {Name, Data, #{flags => 1}})),
    ?assertEqual({archive, {corrupt_entry, "settings.json", encrypted}},
                 refused(Dir, Encrypted, #{})),
    Garbled = raw_zip(lists:keyreplace(Name, 1, Parts, {Name, <<"not deflate">>, #{method => 8}})),
    Why = refused(Dir, binary:replace(Garbled, deflate(<<"not deflate">>), <<255, 255, 255>>), #{}),
    ?assertMatch({archive, _}, Why),
    %% a recipe file damaged on disk is refused at load, and named
    ok = file:write_file(filename:join(Dir, "Broken.zprd"), binary:part(Good, 0, 200)),
    ?assertMatch({error, {archive, {not_a_zip, _}}}, ?R:load(<<"Broken">>, opts(Dir))),
    ?assertMatch({error, {archive, _}}, ?R:info(<<"Broken">>, opts(Dir))).

%%====================================================================
%% Property: any recipe survives its file
%%====================================================================

roundtrip_test_() ->
    {timeout, 300, ?_assert(proper:quickcheck(prop_save_load(),
                                              [{to_file, user}, {numtests, 60}]))}.

prop_save_load() ->
    Dir = tmp_dir("prop"),
    O = opts(Dir),
    ?FORALL({Drawing, Settings, Description, Files},
            {cell_recipe_gen:drawing(), cell_settings_gen:object(cell_recipe_settings),
             proper_unicode:utf8(40),
             ?LET(L, list({elements([<<"a.nc">>, <<"b.txt">>, <<"c">>]), binary()}),
                  maps:from_list(L))},
            begin
                Recipe = #{drawing => Drawing, settings => Settings,
                           description => Description, files => Files},
                ok = ?R:save(<<"Random">>, Recipe, <<"prop">>, O),
                {ok, Loaded} = ?R:load(<<"Random">>, O),
                {ok, S} = cell_settings_schema:validate(cell_recipe_settings, Settings),
                maps:without([author, modified], Loaded) =:= Recipe#{settings := S}
                    andalso maps:get(author, Loaded) =:= <<"prop">>
            end).
