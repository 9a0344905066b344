%% The public API of docs/api.md, held against the code: every function the document
%% lists is exported, has a -spec and a @doc; every export of a public module is either
%% listed or marked internal, so a new export forces a decision (a new exported type
%% too); the behaviours have exactly the callbacks listed; the panel's API paths are
%% those listed; the document speaks of the version the release and the apps carry.
%%
%% The lists are the fenced blocks of docs/api.md tagged `api-public', `api-internal',
%% `api-callbacks', `api-types', `api-internal-types', `api-http' and `api-version'.
%% Beams are read with beam_lib (names from the document never become atoms).
-module(cell_public_api_tests).
-include_lib("eunit/include/eunit.hrl").

%% -------------------------------------------------------------------------------------
%% The checks
%% -------------------------------------------------------------------------------------

%% Every public function is exported and has a -spec.
public_functions_exported_with_spec_test() ->
    Public = public(doc()),
    Beams = beams(),
    %% Each module's beam read once (a few hundred functions).
    Problems = lists:append(
                 [[io_lib:format("~ts/~b is listed public but not exported", [Name, A])
                   || not lists:member({F, A}, Exports)]
                  ++ [io_lib:format("~ts/~b is listed public but has no -spec", [Name, A])
                      || lists:member({F, A}, Exports), not maps:is_key({F, A}, Specs)]
                  || Mod <- lists:usort([M || {M, _, _} <- Public]),
                     Beam <- [beam(Mod, Beams)],
                     Exports <- [exports(Beam)],
                     Specs <- [specs(Beam)],
                     {M, F, A} <- Public, M =:= Mod,
                     Name <- [Mod ++ ":" ++ F]]),
    ?assertEqual([], flat(Problems)).

%% Every public function says what it does for a cell author: a %% @doc comment right
%% above its -spec.
public_functions_documented_test() ->
    Public = public(doc()),
    Beams = beams(),
    %% Each module's forms and source read once (a few hundred functions).
    Problems = [io_lib:format("~ts:~ts/~b has no %% @doc above its -spec", [Mod, F, A])
                || Mod <- lists:usort([M || {M, _, _} <- Public]),
                   Beam <- [beam(Mod, Beams)],
                   Specs <- [specs(Beam)],
                   Lines <- [source_lines(Beam)],
                   {M, F, A} <- Public, M =:= Mod,
                   #{{F, A} := Line} <- [Specs],
                   not documented(Lines, Line)],
    ?assertEqual([], flat(Problems)).

%% An export of a public module that the document neither lists nor marks internal is a
%% decision not made; an internal entry no longer exported is a stale document.
every_export_decided_test() ->
    Doc = doc(),
    Public = public(Doc),
    Internal = internal(Doc),
    Modules = public_modules(Doc),
    Beams = beams(),
    Exports = maps:from_list([{Mod, exports(beam(Mod, Beams))} || Mod <- Modules]),
    Listed = Public ++ Internal,
    Undecided = [io_lib:format("~ts:~ts/~b is exported but neither public nor internal in "
                               "docs/api.md", [Mod, F, A])
                 || Mod <- Modules,
                    {F, A} <- maps:get(Mod, Exports),
                    not lists:member({Mod, F, A}, Listed)],
    Stale = [io_lib:format("~ts:~ts/~b is listed internal but not exported", [Mod, F, A])
             || {Mod, F, A} <- Internal,
                not lists:member({F, A}, maps:get(Mod, Exports, []))],
    Twice = [io_lib:format("~ts:~ts/~b is listed both public and internal", [Mod, F, A])
             || {Mod, F, A} <- Public, lists:member({Mod, F, A}, Internal)],
    Outside = [io_lib:format("~ts is listed internal but is no public module", [Mod])
               || Mod <- lists:usort([M || {M, _, _} <- Internal]),
                  not lists:member(Mod, Modules)],
    ?assertEqual([], flat(Undecided ++ Stale ++ Twice ++ Outside)).

%% The generated cell project is what a cell author starts from: it calls cellrt only
%% through the public API (functions and types), so what it teaches stays promised.
template_calls_only_public_test() ->
    Doc = doc(),
    Allowed = lists:usort([{M, F} || {M, F, _} <- public(Doc)
                                     ++ functions(block(Doc, "api-types"))]),
    Files = filelib:wildcard(filename:join([top(), "templates", "**", "*.erl"])),
    ?assertNotEqual([], Files),
    Calls = lists:usort(
              [{filename:basename(File), M, F}
               || File <- Files,
                  {ok, Bin} <- [file:read_file(File)],
                  [M, F] <- case re:run(Bin, "\\b(cell_[a-z0-9_]*):([a-z][a-zA-Z0-9_]*)\\(",
                                        [global, {capture, all_but_first, list}]) of
                                {match, Ms} -> Ms;
                                nomatch -> []
                            end]),
    Problems = [io_lib:format("~ts calls ~ts:~ts, which docs/api.md does not list public",
                              [File, M, F])
                || {File, M, F} <- Calls, not lists:member({M, F}, Allowed)],
    ?assertEqual([], flat(Problems)).

%% Every exported type of a public module is listed public or internal, and every type
%% listed is exported.
every_type_decided_test() ->
    Doc = doc(),
    Beams = beams(),
    Public = functions(block(Doc, "api-types")),
    Internal = functions(block(Doc, "api-internal-types")),
    Undecided = [io_lib:format("type ~ts:~ts/~b is exported but neither public nor internal "
                               "in docs/api.md", [Mod, T, A])
                 || Mod <- public_modules(Doc),
                    {T, A} <- types(beam(Mod, Beams)),
                    not lists:member({Mod, T, A}, Public ++ Internal)],
    Missing = [io_lib:format("type ~ts:~ts/~b is listed but not exported", [Mod, T, A])
               || {Mod, T, A} <- Public ++ Internal,
                  not lists:member({T, A}, types(beam(Mod, Beams)))],
    ?assertEqual([], flat(Undecided ++ Missing)).

%% The behaviours a cell implements have exactly the callbacks listed, optional ones
%% marked so.
callbacks_test() ->
    Doc = doc(),
    Beams = beams(),
    Listed = callbacks(Doc),
    Modules = lists:usort([M || {M, _, _, _} <- Listed]),
    Problems = lists:append(
                 [begin
                      Forms = forms(beam(Mod, Beams)),
                      Optional = lists:append([Fs || {attribute, _, optional_callbacks, Fs} <- Forms]),
                      Actual = lists:sort([{Mod, atom_to_list(F), A, lists:member({F, A}, Optional)}
                                           || {attribute, _, callback, {{F, A}, _}} <- Forms]),
                      Mine = lists:sort([C || {M, _, _, _} = C <- Listed, M =:= Mod]),
                      [io_lib:format("~ts:~ts/~b is a callback (optional: ~p) not so listed",
                                     [M, F, A, O]) || {M, F, A, O} <- Actual -- Mine]
                      ++ [io_lib:format("~ts:~ts/~b is listed as a callback (optional: ~p) "
                                        "but the behaviour does not say so", [M, F, A, O])
                          || {M, F, A, O} <- Mine -- Actual]
                  end || Mod <- Modules]),
    ?assertEqual([], flat(Problems)).

%% The panel's API is the paths listed, no more and no fewer.
http_paths_test() ->
    Routed = lists:usort([unicode:characters_to_list(P) || {P, _, _} <- cell_web_routes:routes(),
                                                           is_list(P) orelse is_binary(P),
                                                           lists:prefix("/api", unicode:characters_to_list(P))]),
    Listed = lists:usort([P || [P | _] <- block(doc(), "api-http")]),
    ?assertEqual({[], []}, {Routed -- Listed, Listed -- Routed}).

%% Every key the release's configuration sets for an app of cellrt is listed, and
%% every environment variable the configuration reads.
config_test() ->
    Doc = doc(),
    {ok, [Config]} = file:consult(filename:join([top(), "config", "sys.config.src"])),
    Set = lists:usort([atom_to_list(App) ++ ":" ++ atom_to_list(Key)
                       || {App, Env} <- Config, lists:prefix("cell", atom_to_list(App)),
                          {Key, _} <- Env]),
    Listed = [Entry || [Entry | _] <- block(Doc, "api-config")],
    Read = lists:usort(
             lists:append([Vars || File <- ["sys.config.src", "vm.args.src"],
                                   {ok, Bin} <- [file:read_file(filename:join([top(), "config", File]))],
                                   Vars <- [case re:run(Bin, "\\$\\{(CELLRT_[A-Z_]+)",
                                                        [global, {capture, all_but_first, list}]) of
                                                {match, Ms} -> lists:append(Ms);
                                                nomatch -> []
                                            end]])),
    Env = [Var || [Var | _] <- block(Doc, "api-env")],
    ?assertEqual({[], []}, {Set -- Listed, Read -- Env}),
    ?assertMatch([_, _ | _], Read).

%% The document speaks of the version the release is, and every app of cellrt carries it.
version_test() ->
    [[Version]] = block(doc(), "api-version"),
    {ok, Config} = file:consult(filename:join(top(), "rebar.config")),
    {relx, Relx} = lists:keyfind(relx, 1, Config),
    [Release] = [V || {release, {cellrt, V}, _} <- Relx],
    Apps = [{filename:basename(File), Vsn}
            || File <- filelib:wildcard(filename:join(top(), "apps/*/src/*.app.src")),
               {ok, [{application, _, Props}]} <- [file:consult(File)],
               {vsn, Vsn} <- [lists:keyfind(vsn, 1, Props)]],
    ?assertEqual(Version, Release),
    ?assertEqual([], [{App, Vsn} || {App, Vsn} <- Apps, Vsn =/= Version]),
    ?assertMatch([_, _, _ | _], Apps).

%% The reader of the document is right about what it reads.
parse_test_() ->
    Text = <<"intro\n```api-public\ncell_task:id/1   the id\n\n# comment\n```\n"
             "```erlang\nnot:this/1\n```\n```api-callbacks\ncell_task:handle_info/2 optional\n```\n">>,
    [?_assertEqual([["cell_task:id/1", "the", "id"]], block(Text, "api-public")),
     ?_assertEqual([{"cell_task", "id", 1}], functions(block(Text, "api-public"))),
     ?_assertEqual([{"cell_task", "handle_info", 2, true}], callbacks(Text)),
     ?_assertError({bad_entry, "nocolon/1"}, functions([["nocolon/1"]]))].

%% -------------------------------------------------------------------------------------
%% The document
%% -------------------------------------------------------------------------------------

top() ->
    case os:getenv("CELLRT_TOP") of
        false -> {ok, Cwd} = file:get_cwd(), Cwd;
        Top -> Top
    end.

doc() ->
    {ok, Bin} = file:read_file(filename:join([top(), "docs", "api.md"])),
    Bin.

public(Doc) -> functions(block(Doc, "api-public")).
internal(Doc) -> functions(block(Doc, "api-internal")).

public_modules(Doc) -> lists:usort([M || {M, _, _} <- public(Doc)]).

callbacks(Doc) ->
    [{M, F, A, Rest =:= ["optional"]}
     || [Entry | Rest] <- block(Doc, "api-callbacks"), {M, F, A} <- functions([[Entry]])].

functions(Lines) ->
    [case re:run(Entry, "^([a-z][a-z0-9_]*):([a-z][a-zA-Z0-9_]*)/([0-9]+)$",
                 [{capture, all_but_first, list}]) of
         {match, [M, F, A]} -> {M, F, list_to_integer(A)};
         nomatch -> erlang:error({bad_entry, Entry})
     end || [Entry | _] <- Lines].

%% The lines of the fenced blocks tagged `Tag', each split into its words; blank lines
%% and lines starting with `#' left out.
block(Doc, Tag) ->
    Lines = [string:trim(L) || L <- string:split(unicode:characters_to_list(Doc), "\n", all)],
    in_blocks(Lines, "```" ++ Tag, false, []).

in_blocks([], _Open, _In, Acc) ->
    lists:reverse(Acc);
in_blocks([Open | Rest], Open, false, Acc) ->
    in_blocks(Rest, Open, true, Acc);
in_blocks([_ | Rest], Open, false, Acc) ->
    in_blocks(Rest, Open, false, Acc);
in_blocks(["```" | Rest], Open, true, Acc) ->
    in_blocks(Rest, Open, false, Acc);
in_blocks([L | Rest], Open, true, Acc) ->
    case string:lexemes(L, " \t") of
        [] -> in_blocks(Rest, Open, true, Acc);
        ["#" ++ _ | _] -> in_blocks(Rest, Open, true, Acc);
        Words -> in_blocks(Rest, Open, true, [Words | Acc])
    end.

%% -------------------------------------------------------------------------------------
%% The code, as its beams say
%% -------------------------------------------------------------------------------------

%% Every beam on the code path by its module's name, the first of a name as the code
%% server finds it: each directory listed once (looking for each module on its own
%% listed the whole path again, seconds on a busy machine).
beams() ->
    maps:from_list(lists:reverse([{filename:basename(F, ".beam"), filename:join(Dir, F)}
                                  || Dir <- code:get_path(),
                                     {ok, Files} <- [file:list_dir(Dir)],
                                     F <- Files, filename:extension(F) =:= ".beam"])).

beam(Mod, Beams) ->
    case Beams of
        #{Mod := Path} -> Path;
        #{} -> erlang:error({no_such_module, Mod})
    end.

%% The exports, names as strings; what the compiler adds left out, and what eunit
%% exports from a module's own tests in this (the test) build.
exports(Beam) ->
    {ok, {_, [{exports, Exports}]}} = beam_lib:chunks(Beam, [exports]),
    [{Name, A} || {F, A} <- Exports,
                  not lists:member({F, A}, [{module_info, 0}, {module_info, 1},
                                            {behaviour_info, 1}]),
                  Name <- [atom_to_list(F)],
                  not eunit_test(Name, A)].

eunit_test("test", 0) -> true;
eunit_test(Name, 0) -> lists:suffix("_test", Name) orelse lists:suffix("_test_", Name);
eunit_test(_, _) -> false.

types(Beam) ->
    [{atom_to_list(T), A} || {attribute, _, export_type, Types} <- forms(Beam), {T, A} <- Types].

forms(Beam) ->
    case beam_lib:chunks(Beam, [abstract_code]) of
        {ok, {_, [{abstract_code, {raw_abstract_v1, Forms}}]}} -> Forms;
        _ -> erlang:error({no_abstract_code, Beam})
    end.

%% Each specified function and the line its -spec starts on.
specs(Beam) ->
    maps:from_list([{{atom_to_list(F), A}, erl_anno:line(Anno)}
                    || {attribute, Anno, spec, {Name, _}} <- forms(Beam),
                       {F, A} <- [case Name of {_, F0, A0} -> {F0, A0}; FA -> FA end]]).

source_lines(Beam) ->
    [File | _] = [F || {attribute, _, file, {F, _}} <- forms(Beam)],
    {ok, Bin} = file:read_file(File),
    list_to_tuple(string:split(unicode:characters_to_list(Bin), "\n", all)).

%% The comment block right above line `Line' holds a @doc.
documented(Lines, Line) ->
    above(Lines, Line - 1).

above(_Lines, 0) ->
    false;
above(Lines, N) ->
    case string:trim(element(N, Lines), leading) of
        "%" ++ _ = Comment -> string:find(Comment, "@doc") =/= nomatch orelse above(Lines, N - 1);
        _ -> false
    end.

flat(Messages) ->
    [lists:flatten(M) || M <- Messages].
