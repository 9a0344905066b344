%% @doc Recipes (seed 000 §3.2): one zip file per product, `Products/<name>.zprd',
%% holding the recipe settings object, the drawing and the metadata. Copying,
%% renaming and moving recipes is plain file handling, here and in any file manager.
%%
%% Inside the archive (all text, diff-friendly):
%% <ul>
%% <li>`recipe.json' — `format' (1), `description', `author', `modified' (UTC, RFC 3339)</li>
%% <li>`settings.json' — the recipe settings object, as a settings file</li>
%% <li>`drawing.json' — the drawing ({@link cell_recipe_drawing}), one primitive a line</li>
%% <li>`files/<name>' — machine specific files the process needs (optional)</li>
%% </ul>
%%
%% A recipe name follows the rules of file names on both Windows and Linux, so a
%% recipe copied to a USB stick comes back: 1 to 100 characters, none of
%% `/ \ : * ? " < > |' or control characters, no leading dot or space, no trailing dot
%% or space, not a reserved device name (CON, PRN, AUX, NUL, COM1-9, LPT1-9).
%%
%% An archive from outside (an upload, a file copied in by hand) is untrusted: see
%% {@link cell_recipe_zip} for the limits checked before anything is inflated. Every
%% part must be there and valid; nothing is ever extracted to disk, and nothing is
%% written outside `Products/'. Every file is written with `cell_file': a power cut
%% leaves the old recipe or the new one.
-module(cell_recipe).

-include_lib("kernel/include/file.hrl").

-export([save/3, save/4, load/1, load/2, info/1, info/2, list/0, list/1]).
-export([delete/1, delete/2, rename/2, rename/3, copy/2, copy/3]).
-export([import/2, import/3, export/1, export/2]).
-export([encode/2, decode/2, check_name/1, format_error/1]).

-export_type([name/0, recipe/0, info/0, options/0, error/0]).

-type name() :: binary().
-type recipe() :: #{description := binary(),
                    author := binary(),
                    modified := integer(),            %% UTC, milliseconds
                    settings := map(),
                    drawing := cell_recipe_drawing:drawing(),
                    files := #{binary() => binary()}}.
-type info() :: #{name := name(), description := binary(), author := binary(),
                  modified := integer(), bytes := non_neg_integer()}.
-type options() :: #{dir => file:filename_all(),      %% default: cell_config:dir(products)
                     schema => module(),              %% the recipe settings schema
                     sync => boolean(),               %% flush to disk (default true)
                     limits => map(),                 %% cell_recipe_zip:limits(), in part
                     replace => boolean()}.           %% import over an existing recipe
-type error() :: {bad_name, term(), term()}
               | {bad_who, term()}
               | {no_recipe, name()}
               | {exists, name()}
               | {archive, cell_recipe_zip:error()}
               | {missing_part, string()}
               | {unexpected_entry, string()}
               | {bad_part, string(), term()}
               | {invalid, list(), term()}
               | {file, file:filename_all(), term()}
               | {bad_option, atom()}.

-define(FORMAT, 1).
-define(EXT, ".zprd").
-define(META, "recipe.json").
-define(SETTINGS, "settings.json").
-define(DRAWING, "drawing.json").
-define(FILES, "files/").
-define(LOG, recipes).

%%====================================================================
%% Files
%%====================================================================

%% @doc Saves a recipe; `author' and `modified' are set to `Who' and now. Fields
%% left out take their defaults (an empty description, default settings, an empty
%% drawing, no files); settings given in part are merged onto the defaults.
-spec save(name(), map(), binary()) -> ok | {error, error()}.
save(Name, Recipe, Who) ->
    save(Name, Recipe, Who, #{}).

%% @doc As {@link save/3} with options.
-spec save(name(), map(), binary(), options()) -> ok | {error, error()}.
save(Name, Recipe, Who, Opts) when is_map(Recipe) ->
    with(Opts, Name, fun(O, Path) ->
        case is_binary(Who) andalso Who =/= <<>> of
            true ->
                R = Recipe#{author => Who, modified => os:system_time(millisecond)},
                case encode(R, O) of
                    {ok, Bin} ->
                        ok = write(Path, Bin, O),
                        cell_log:info(?LOG, "recipe ~ts saved by ~ts", [Name, Who]);
                    {error, _} = E ->
                        E
                end;
            false ->
                {error, {bad_who, Who}}
        end
    end).

%% @doc Loads and checks a recipe.
-spec load(name()) -> {ok, recipe()} | {error, error()}.
load(Name) ->
    load(Name, #{}).

%% @doc As {@link load/1} with options.
-spec load(name(), options()) -> {ok, recipe()} | {error, error()}.
load(Name, Opts) ->
    with(Opts, Name, fun(O, Path) ->
        case read(Name, Path, O) of
            {ok, Bin} -> decode(Bin, O);
            {error, _} = E -> E
        end
    end).

%% @doc The metadata of a recipe, read without inflating its drawing.
-spec info(name()) -> {ok, info()} | {error, error()}.
info(Name) ->
    info(Name, #{}).

%% @doc As {@link info/1} with options.
-spec info(name(), options()) -> {ok, info()} | {error, error()}.
info(Name, Opts) ->
    with(Opts, Name, fun(O, Path) ->
        case read(Name, Path, O) of
            {ok, Bin} ->
                case entries(Bin, O, [?META]) of
                    {ok, #{?META := Meta}} ->
                        case meta(Meta) of
                            {ok, M} ->
                                {ok, (maps:remove(format, M))#{name => Name,
                                                               bytes => byte_size(Bin)}};
                            {error, _} = E ->
                                E
                        end;
                    {ok, _} ->
                        {error, {missing_part, ?META}};
                    {error, _} = E ->
                        E
                end;
            {error, _} = E ->
                E
        end
    end).

%% @doc The recipe names in the folder, sorted. Files whose names break the rules
%% (copied in by hand) are left out: they could not be loaded by name.
-spec list() -> [name()].
list() ->
    list(#{}).

%% @doc As {@link list/0} with options.
-spec list(options()) -> [name()].
list(Opts) ->
    {ok, #{dir := Dir}} = options(Opts),
    case file:list_dir_all(Dir) of
        {ok, Files} ->
            lists:sort([Name || F <- Files,
                                Name <- [recipe_name(F)],
                                Name =/= none, check_name(Name) =:= ok,
                                filelib:is_regular(filename:join(Dir, F))]);
        {error, _} ->
            []
    end.

recipe_name(F) ->
    Bin = case F of
              L when is_list(L) -> name_to_binary(L);
              B -> B
          end,
    Size = byte_size(Bin) - length(?EXT),
    case Bin of
        <<Name:Size/binary, ?EXT>> when Size > 0 -> Name;
        _ -> none
    end.

%% @doc Deletes a recipe.
-spec delete(name()) -> ok | {error, error()}.
delete(Name) ->
    delete(Name, #{}).

%% @doc As {@link delete/1} with options.
-spec delete(name(), options()) -> ok | {error, error()}.
delete(Name, Opts) ->
    with(Opts, Name, fun(O, Path) ->
        case filelib:is_regular(Path) of
            true ->
                case cell_file:delete(Path, sync(O)) of
                    ok -> cell_log:info(?LOG, "recipe ~ts deleted", [Name]);
                    {error, {P, Reason}} -> {error, {file, P, Reason}}
                end;
            false ->
                {error, {no_recipe, Name}}
        end
    end).

%% @doc Renames a recipe; an existing recipe of the new name is never replaced.
-spec rename(name(), name()) -> ok | {error, error()}.
rename(Old, New) ->
    rename(Old, New, #{}).

%% @doc As {@link rename/2} with options.
-spec rename(name(), name(), options()) -> ok | {error, error()}.
rename(Old, New, Opts) ->
    with(Opts, Old, fun(O, From) ->
        with(O, New, fun(O1, To) ->
            case {filelib:is_regular(From), filelib:is_file(To)} of
                {false, _} ->
                    {error, {no_recipe, Old}};
                {true, true} ->
                    {error, {exists, New}};
                {true, false} ->
                    case file:rename(From, To) of
                        ok ->
                            ok = sync_dir(O1),
                            cell_log:info(?LOG, "recipe ~ts renamed to ~ts", [Old, New]);
                        {error, Reason} ->
                            {error, {file, From, Reason}}
                    end
            end
        end)
    end).

%% @doc Copies a recipe under a new name; an existing recipe is never replaced.
-spec copy(name(), name()) -> ok | {error, error()}.
copy(Name, New) ->
    copy(Name, New, #{}).

%% @doc As {@link copy/2} with options.
-spec copy(name(), name(), options()) -> ok | {error, error()}.
copy(Name, New, Opts) ->
    with(Opts, Name, fun(O, From) ->
        with(O, New, fun(O1, To) ->
            case {read(Name, From, O1), filelib:is_file(To)} of
                {{error, _} = E, _} ->
                    E;
                {_, true} ->
                    {error, {exists, New}};
                {{ok, Bin}, false} ->
                    ok = write(To, Bin, O1),
                    cell_log:info(?LOG, "recipe ~ts copied to ~ts", [Name, New])
            end
        end)
    end).

%% @doc Takes in a recipe archive from outside (an upload) under `Name': checked in
%% full as untrusted input, then written in this runtime's own layout. An existing
%% recipe is replaced only with `#{replace => true}'.
-spec import(name(), binary()) -> ok | {error, error()}.
import(Name, Bin) ->
    import(Name, Bin, #{}).

%% @doc As {@link import/2} with options.
-spec import(name(), binary(), options()) -> ok | {error, error()}.
import(Name, Bin, Opts) when is_binary(Bin) ->
    with(Opts, Name, fun(O, Path) ->
        case {decode(Bin, O), filelib:is_file(Path) andalso not maps:get(replace, O, false)} of
            {{error, _} = E, _} ->
                E;
            {{ok, _}, true} ->
                {error, {exists, Name}};
            {{ok, Recipe}, false} ->
                {ok, Out} = encode(Recipe, O),
                ok = write(Path, Out, O),
                #{author := Author, modified := Modified} = Recipe,
                cell_log:info(?LOG, "recipe ~ts imported (by ~ts, ~ts)",
                              [Name, Author, iso_time(Modified)])
        end
    end).

%% @doc The recipe file as it is, to download or hand on.
-spec export(name()) -> {ok, binary()} | {error, error()}.
export(Name) ->
    export(Name, #{}).

%% @doc As {@link export/1} with options.
-spec export(name(), options()) -> {ok, binary()} | {error, error()}.
export(Name, Opts) ->
    with(Opts, Name, fun(O, Path) -> read(Name, Path, O) end).

%%====================================================================
%% Archive format
%%====================================================================

%% @doc A recipe as archive bytes; checks every part (see {@link save/3}).
-spec encode(map(), options()) -> {ok, binary()} | {error, error()}.
encode(Recipe, Opts) ->
    case options(Opts) of
        {ok, O} -> encode1(Recipe, O);
        {error, _} = E -> E
    end.

encode1(Recipe, #{schema := Schema}) ->
    Description = maps:get(description, Recipe, <<>>),
    Author = maps:get(author, Recipe, <<>>),
    Modified = maps:get(modified, Recipe, 0),
    Files = maps:get(files, Recipe, #{}),
    try
        case maps:keys(Recipe) -- [description, author, modified, settings, drawing, files] of
            [] -> ok;
            [Unknown | _] -> throw({invalid, [Unknown], unknown_field})
        end,
        text(Description, 4096) orelse throw({invalid, [description], {not_text, Description}}),
        text(Author, 256) orelse throw({invalid, [author], {not_text, Author}}),
        is_integer(Modified) orelse throw({invalid, [modified], {not_a_time, Modified}}),
        Settings = case cell_settings_schema:validate(Schema, maps:get(settings, Recipe, #{})) of
                       {ok, S} -> S;
                       {error, {invalid, P, W}} -> throw({invalid, [settings | P], W})
                   end,
        Drawing = case cell_recipe_drawing:validate(maps:get(drawing, Recipe,
                                                             cell_recipe_drawing:new())) of
                      {ok, D} -> D;
                      {error, {invalid, P2, W2}} -> throw({invalid, [drawing | P2], W2})
                  end,
        is_map(Files) orelse throw({invalid, [files], {not_a_map, Files}}),
        FileEntries = [begin
                           file_name_ok(F) orelse throw({invalid, [files, F], bad_file_name}),
                           is_binary(C) orelse throw({invalid, [files, F], not_a_binary}),
                           {?FILES ++ binary_to_list(F), C}
                       end || {F, C} <- lists:sort(maps:to_list(Files))],
        Meta = [{<<"format">>, ?FORMAT}, {<<"description">>, Description},
                {<<"author">>, Author}, {<<"modified">>, iso_time(Modified)}],
        {ok, cell_recipe_zip:write(
               [{?META, [jsx:encode(Meta, [space, {indent, 2}]), $\n]},
                {?SETTINGS, cell_settings_schema:to_json(Schema, Settings)},
                {?DRAWING, cell_recipe_drawing:to_json(Drawing)}
                | FileEntries])}
    catch
        throw:{invalid, _, _} = Why -> {error, Why}
    end.

%% @doc Reads archive bytes from anywhere as a recipe: every limit, every part.
-spec decode(binary(), options()) -> {ok, recipe()} | {error, error()}.
decode(Bin, Opts) ->
    case options(Opts) of
        {ok, #{schema := Schema} = O} ->
            case entries(Bin, O, all) of
                {ok, Parts} -> parts(Parts, Schema);
                {error, _} = E -> E
            end;
        {error, _} = E ->
            E
    end.

parts(#{?META := MetaBin, ?SETTINGS := SettingsBin, ?DRAWING := DrawingBin} = Parts, Schema) ->
    case {meta(MetaBin), cell_settings_schema:from_json(Schema, SettingsBin),
          cell_recipe_drawing:from_json(DrawingBin)} of
        {{ok, Meta}, {ok, Settings}, {ok, Drawing}} ->
            Files = maps:from_list([{list_to_binary(N), C}
                                    || {?FILES ++ N, C} <- maps:to_list(Parts)]),
            {ok, (maps:remove(format, Meta))#{settings => Settings, drawing => Drawing,
                                              files => Files}};
        {{error, _} = E, _, _} -> E;
        {_, {error, Why}, _} -> {error, {bad_part, ?SETTINGS, Why}};
        {_, _, {error, Why}} -> {error, {bad_part, ?DRAWING, Why}}
    end;
parts(Parts, _Schema) ->
    [Missing | _] = [P || P <- [?META, ?SETTINGS, ?DRAWING], not is_map_key(P, Parts)],
    {error, {missing_part, Missing}}.

%% The archive's entries by name: the three parts and `files/<name>', nothing else.
entries(Bin, #{limits := Limits}, Wanted) ->
    case cell_recipe_zip:read(Bin, Limits, Wanted) of
        {ok, Entries} ->
            try
                {ok, maps:from_list(
                       [{Name, Content} || {Name, Content} <- Entries,
                                           expected(Name, Content)])}
            catch
                throw:{unexpected_entry, _} = Why -> {error, Why}
            end;
        {error, Why} ->
            {error, {archive, Why}}
    end.

expected(?FILES, folder) -> false;
expected(?FILES ++ Name, Content) when is_binary(Content); Content =:= skipped ->
    (lists:all(fun(C) -> C < 128 end, Name) andalso file_name_ok(list_to_binary(Name)))
        orelse throw({unexpected_entry, ?FILES ++ Name}),
    true;
expected(Name, Content) when is_binary(Content); Content =:= skipped ->
    lists:member(Name, [?META, ?SETTINGS, ?DRAWING]) orelse throw({unexpected_entry, Name}),
    true;
expected(Name, _) ->
    throw({unexpected_entry, Name}).

meta(Bin) ->
    Bad = fun(Path, Why) -> {error, {bad_part, ?META, {invalid, Path, Why}}} end,
    case cell_settings_schema:json_decode(Bin) of
        {ok, #{<<"format">> := ?FORMAT, <<"description">> := D, <<"author">> := A,
               <<"modified">> := T} = M} when map_size(M) =:= 4 ->
            case {text(D, 4096), text(A, 256), parse_time(T)} of
                {false, _, _} -> Bad([description], {not_text, D});
                {_, false, _} -> Bad([author], {not_text, A});
                {_, _, error} -> Bad([modified], {not_a_time, T});
                {true, true, {ok, Ms}} ->
                    {ok, #{format => ?FORMAT, description => D, author => A, modified => Ms}}
            end;
        {ok, #{<<"format">> := F}} when F =/= ?FORMAT ->
            Bad([format], {unsupported_format, F});
        {ok, M} when is_map(M) ->
            case [K || K <- [<<"format">>, <<"description">>, <<"author">>, <<"modified">>],
                       not is_map_key(K, M)] of
                [K | _] -> Bad([K], missing);
                [] -> Bad([hd(maps:keys(M) -- [<<"format">>, <<"description">>, <<"author">>,
                                                 <<"modified">>])], unknown_field)
            end;
        {ok, Other} ->
            Bad([], {not_an_object, Other});
        {error, Why} ->
            {error, {bad_part, ?META, Why}}
    end.

text(B, Max) when is_binary(B) ->
    case unicode:characters_to_list(B) of
        L when is_list(L) -> length(L) =< Max;
        _ -> false
    end;
text(_, _) ->
    false.

iso_time(Ms) ->
    list_to_binary(calendar:system_time_to_rfc3339(Ms, [{unit, millisecond}, {offset, "Z"}])).

parse_time(Bin) when is_binary(Bin) ->
    %% calendar's parser raises on malformed text; this is the boundary for file input.
    try calendar:rfc3339_to_system_time(binary_to_list(Bin), [{unit, millisecond}]) of
        Ms -> {ok, Ms}
    catch
        error:_ -> error
    end;
parse_time(_) ->
    error.

%%====================================================================
%% Names
%%====================================================================

%% @doc Checks a recipe name against the rules of file names (see the module doc).
-spec check_name(term()) -> ok | {error, {bad_name, term(), term()}}.
check_name(Name) when is_binary(Name) ->
    case unicode:characters_to_list(Name) of
        Chars when is_list(Chars) ->
            case name_problem(Chars) of
                none -> ok;
                Why -> {error, {bad_name, Name, Why}}
            end;
        _ ->
            {error, {bad_name, Name, not_utf8}}
    end;
check_name(Name) ->
    {error, {bad_name, Name, not_a_binary}}.

name_problem([]) -> empty;
name_problem(Chars) when length(Chars) > 100 -> too_long;
name_problem([C | _]) when C =:= $.; C =:= $\s -> {bad_start, [C]};
name_problem(Chars) ->
    Last = lists:last(Chars),
    Bad = [C || C <- Chars, C < 32 orelse C =:= 127 orelse lists:member(C, "/\\:*?\"<>|")],
    Base = string:uppercase(hd(string:split(Chars, "."))),
    if
        Bad =/= [] -> {bad_character, [hd(Bad)]};
        Last =:= $.; Last =:= $\s -> {bad_end, [Last]};
        true ->
            case lists:member(string:trim(Base, trailing), reserved()) of
                true -> reserved_name;
                false -> none
            end
    end.

reserved() ->
    ["CON", "PRN", "AUX", "NUL"]
        ++ ["COM" ++ integer_to_list(N) || N <- lists:seq(1, 9)]
        ++ ["LPT" ++ integer_to_list(N) || N <- lists:seq(1, 9)].

%% The machine specific files inside a recipe: a file name by the same rules, in
%% ASCII, as zip tools disagree on other characters in entry names.
file_name_ok(Name) when is_binary(Name) ->
    check_name(Name) =:= ok andalso lists:all(fun(C) -> C < 128 end, binary_to_list(Name));
file_name_ok(_) ->
    false.

%%====================================================================
%% Helpers
%%====================================================================

with(Opts, Name, Fun) ->
    case {options(Opts), check_name(Name)} of
        {{ok, #{dir := Dir} = O}, ok} ->
            try Fun(O, path(Dir, Name))
            catch throw:{file, _, _} = Why -> {error, Why}
            end;
        {{error, _} = E, _} -> E;
        {_, {error, _} = E} -> E
    end.

%% Names are UTF-8 on disk whatever the emulator's file name encoding: with `utf8'
%% a file name is a list of characters, with `latin1' a list of raw bytes.
path(Dir, Name) ->
    File = <<Name/binary, ?EXT>>,
    filename:join(Dir, case file:native_name_encoding() of
                           utf8 -> unicode:characters_to_list(File);
                           latin1 -> binary_to_list(File)
                       end).

name_to_binary(L) ->
    case file:native_name_encoding() of
        utf8 -> unicode:characters_to_binary(L);
        latin1 -> list_to_binary(L)
    end.

read(Name, Path, #{limits := #{archive := Max}}) ->
    case file:read_file_info(Path) of
        {ok, #file_info{type = regular, size = Size}} when Size > Max ->
            {error, {archive, {too_big, Size, Max}}};
        {ok, #file_info{type = regular}} ->
            case file:read_file(Path) of
                {ok, Bin} -> {ok, Bin};
                {error, Reason} -> {error, {file, Path, Reason}}
            end;
        {ok, _} ->
            {error, {no_recipe, Name}};
        {error, enoent} ->
            {error, {no_recipe, Name}};
        {error, Reason} ->
            {error, {file, Path, Reason}}
    end.

write(Path, Bin, O) ->
    ok = ensure_dir(Path),
    case cell_file:write(Path, Bin, sync(O)) of
        ok -> ok;
        {error, {P, Reason}} -> throw({file, P, Reason})
    end.

ensure_dir(Path) ->
    case filelib:ensure_dir(Path) of
        ok -> ok;
        {error, Reason} -> throw({file, filename:dirname(Path), Reason})
    end.

sync(#{sync := Sync}) -> #{sync => Sync}.

sync_dir(#{sync := false}) ->
    ok;
sync_dir(#{dir := Dir}) ->
    case cell_file:fsync_dir(Dir) of
        ok -> ok;
        {error, Reason} -> throw({file, Dir, Reason})
    end.

options(Opts) when is_map(Opts) ->
    Known = [dir, schema, sync, limits, replace],
    case [K || K <- maps:keys(Opts), not lists:member(K, Known)] of
        [K | _] ->
            {error, {bad_option, K}};
        [] ->
            Defaults = #{dir => undefined, schema => undefined, sync => true, limits => #{},
                         replace => false},
            O = maps:merge(Defaults, Opts),
            Limits = maps:merge(cell_recipe_zip:default_limits(), maps:get(limits, O)),
            Checks = [{sync, is_boolean(maps:get(sync, O))},
                      {replace, is_boolean(maps:get(replace, O))},
                      {schema, is_atom(maps:get(schema, O))},
                      {limits, is_map(maps:get(limits, O)) andalso
                           map_size(Limits) =:= map_size(cell_recipe_zip:default_limits()) andalso
                           lists:all(fun(V) -> is_integer(V) andalso V > 0 end,
                                     maps:values(Limits))}],
            case [K || {K, false} <- Checks] of
                [K | _] ->
                    {error, {bad_option, K}};
                [] ->
                    {ok, O#{dir := case maps:get(dir, O) of
                                       undefined -> cell_config:dir(products);
                                       D -> D
                                   end,
                            schema := case maps:get(schema, O) of
                                          undefined -> cell_config:get(cell, recipe_settings,
                                                                       cell_recipe_settings);
                                          S -> S
                                      end,
                            limits := Limits}}
            end
    end;
options(_) ->
    {error, {bad_option, options}}.

%% @doc A recipe error in words an operator understands.
-spec format_error(term()) -> binary().
format_error({bad_name, Name, Why}) ->
    iolist_to_binary(io_lib:format("~tp is not a usable recipe name: ~ts", [Name, name_why(Why)]));
format_error({bad_who, Who}) ->
    iolist_to_binary(io_lib:format("~tp does not name who saves the recipe", [Who]));
format_error({no_recipe, Name}) ->
    iolist_to_binary(io_lib:format("there is no recipe ~ts", [Name]));
format_error({exists, Name}) ->
    iolist_to_binary(io_lib:format("a recipe ~ts exists already", [Name]));
format_error({archive, Why}) ->
    iolist_to_binary(["the recipe archive is refused: ", cell_recipe_zip:format_error(Why)]);
format_error({missing_part, Part}) ->
    iolist_to_binary(io_lib:format("the recipe archive lacks ~ts", [Part]));
format_error({unexpected_entry, Entry}) ->
    iolist_to_binary(io_lib:format("the recipe archive holds ~tp, which is not part of a "
                                   "recipe", [Entry]));
format_error({bad_part, ?DRAWING, Why}) ->
    iolist_to_binary([?DRAWING, ": ", cell_recipe_drawing:format_error(Why)]);
format_error({bad_part, Part, Why}) ->
    iolist_to_binary([Part, ": ", cell_settings_schema:format_error(Why)]);
format_error({invalid, _, _} = Why) ->
    cell_settings_schema:format_error(Why);
format_error({file, Path, Reason}) ->
    iolist_to_binary(io_lib:format("~ts: ~ts", [Path, file:format_error(Reason)]));
format_error(Other) ->
    iolist_to_binary(io_lib:format("~0tp", [Other])).

name_why(empty) -> "it is empty";
name_why(too_long) -> "longer than 100 characters";
name_why(not_utf8) -> "not valid UTF-8 text";
name_why(not_a_binary) -> "not text";
name_why(reserved_name) -> "a name Windows reserves for a device";
name_why({bad_start, C}) -> io_lib:format("it starts with ~tp", [C]);
name_why({bad_end, C}) -> io_lib:format("it ends with ~tp", [C]);
name_why({bad_character, C}) -> io_lib:format("it holds ~tp, which file names cannot", [C]).
