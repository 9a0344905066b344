%% @doc The product a device task holds (seed 000 §2.3.5): a map with at least
%% `serial', `recipe' and `failed', plus the task's own fields.
%%
%% Each task keeps its product in `Data/<Zone>@<Lane>.product', written durably and
%% atomically at every change (cell_file: temp file, fsync, rename, folder fsync), so a
%% crash or a power cut at any instant leaves the old product or the new one. The file
%% is removed when the task holds none. A damaged file is reported, never dropped.
-module(cell_product).

-export([new/2, new/3, path/2, file_name/2, load/1, save/2, delete/1, serial/1,
         validate/1]).

-export_type([product/0]).

-type product() :: #{serial := binary(), recipe := binary(), failed := boolean(),
                     atom() => term()}.

%% @doc A new good product.
-spec new(binary(), binary()) -> product().
new(Serial, Recipe) ->
    new(Serial, Recipe, #{}).

-spec new(binary(), binary(), map()) -> product().
new(Serial, Recipe, Fields) when is_binary(Serial), is_binary(Recipe), is_map(Fields) ->
    Fields#{serial => Serial, recipe => Recipe, failed => false}.

%% @doc The product file of a task.
-spec path(binary(), binary()) -> file:filename().
path(Zone, Lane) ->
    filename:join(cell_config:dir(data), file_name(Zone, Lane)).

%% @doc `<Zone>@<Lane>.product', with characters a file name cannot hold replaced.
-spec file_name(binary(), binary()) -> string().
file_name(Zone, Lane) ->
    unicode:characters_to_list([safe(Zone), "@", safe(Lane), ".product"]).

safe(Name) ->
    [case C of
         $/ -> $_; $\\ -> $_; $: -> $_; $* -> $_; $? -> $_; $" -> $_;
         $< -> $_; $> -> $_; $| -> $_; 0 -> $_;
         _ -> C
     end || C <- unicode:characters_to_list(Name)].

%% @doc Loads a task's product: `undefined' when the task holds none.
-spec load(file:filename()) ->
          {ok, product() | undefined} | {error, {corrupt, atom()} | {bad_product, term()}
                                         | {file:filename(), term()}}.
load(Path) ->
    case cell_file:read_term(Path) of
        {ok, Product} ->
            case validate(Product) of
                ok -> {ok, Product};
                Error -> Error
            end;
        {error, enoent} -> {ok, undefined};
        {error, _} = Error -> Error
    end.

%% @doc Saves a product durably; `undefined' deletes the file.
-spec save(file:filename(), product() | undefined) -> ok | cell_file:error().
save(Path, undefined) ->
    delete(Path);
save(Path, Product) ->
    cell_file:write_term(Path, Product).

-spec delete(file:filename()) -> ok | cell_file:error().
delete(Path) ->
    cell_file:delete(Path).

-spec serial(product() | undefined) -> binary() | undefined.
serial(undefined) -> undefined;
serial(#{serial := S}) -> S.

%% @doc A product has a binary serial and recipe and a boolean failed flag.
-spec validate(term()) -> ok | {error, {bad_product, term()}}.
validate(#{serial := S, recipe := R, failed := F}) when is_binary(S), S =/= <<>>,
                                                       is_binary(R), is_boolean(F) ->
    ok;
validate(Other) ->
    {error, {bad_product, Other}}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

file_name_test_() ->
    [?_assertEqual("Loading@Front Lane.product", file_name(<<"Loading">>, <<"Front Lane">>)),
     ?_assertEqual("a_b@c_d.product", file_name(<<"a/b">>, <<"c:d">>)),
     ?_assertEqual("Sägen@Vorn.product", file_name(<<"Sägen"/utf8>>, <<"Vorn">>))].

validate_test_() ->
    [?_assertEqual(ok, validate(new(<<"P1">>, <<"r">>))),
     ?_assertEqual(ok, validate(new(<<"P1">>, <<"r">>, #{modules => 4}))),
     ?_assertMatch({error, _}, validate(#{serial => <<>>, recipe => <<>>, failed => false})),
     ?_assertMatch({error, _}, validate(#{serial => "P1", recipe => <<>>, failed => false})),
     ?_assertMatch({error, _}, validate(#{serial => <<"P1">>, recipe => <<>>})),
     ?_assertMatch({error, _}, validate([]))].

save_load_test() ->
    Dir = filename:join(["/tmp", "cell_product_test",
                         os:getpid() ++ "-" ++ integer_to_list(erlang:unique_integer([positive]))]),
    _ = file:del_dir_r(Dir),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    P = filename:join(Dir, file_name(<<"Z">>, <<"L">>)),
    ?assertEqual({ok, undefined}, load(P)),
    Prod = new(<<"S1">>, <<"recipe-a">>, #{cuts_done => 3}),
    ok = save(P, Prod),
    ?assertEqual({ok, Prod}, load(P)),
    ok = save(P, undefined),
    ?assertEqual({ok, undefined}, load(P)),
    ok = file:write_file(P, <<"garbage">>),
    ?assertEqual({error, {corrupt, not_a_cellrt_file}}, load(P)),
    ok = cell_file:write_term(P, {not_a_product}),
    ?assertMatch({error, {bad_product, _}}, load(P)).
-endif.
