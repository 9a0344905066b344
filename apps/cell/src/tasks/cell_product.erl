%% @doc The product a device task holds (seed 000 §2.3.5): a map with at least
%% `serial', `recipe' and `failed', plus the task's own fields.
%%
%% Each task keeps its product in `Data/<Zone>@<Lane>.product', a record file of
%% cell_file: written in place, durably and atomically, at every change, so a crash or
%% a power cut at any instant leaves the old product or the new one. When the task holds
%% none the file says so. A damaged file is reported, never dropped.
-module(cell_product).

-export([new/2, new/3, path/2, file_name/2, load/1, save/2, save/3, delete/1, delete/2,
         serial/1, validate/1, stored/3]).

-export_type([product/0, stored/0, marker/0]).

-type product() :: #{serial := binary(), recipe := binary(), failed := boolean(),
                     atom() => term()}.
%% What a product file holds: the product, its generation and, while it moves
%% between two tasks, a marker. The generation grows at every change of owner, so of
%% two files naming the same serial the one with the higher generation is the owner;
%% the other is a stale copy a crash left behind. The marker says which side the
%% product came from (`upstream': this task is taking it in; `downstream': it was
%% leaving this task) over which link.
%%
%% Files are decoded with `binary_to_term/2''s `safe', which refuses atoms the node does
%% not know yet: every atom of this record is named in this module's code (see
%% valid_marker/1), so a node just started reads a file whoever wrote it and whichever
%% modules it has loaded (the handshake, which writes the marker, may not be). The
%% product's own fields are the task module's atoms, loaded before the file is read;
%% the link is named by the task's spec.
-type stored() :: #{product := product(), gen := pos_integer(), marker := marker()}.
-type marker() :: undefined | #{link := atom(), from := upstream | downstream,
                                phase := in_transit}.

%% @doc A new good product.
-spec new(binary(), binary()) -> product().
new(Serial, Recipe) ->
    new(Serial, Recipe, #{}).

%% @doc A new good product with the task's own fields (cuts done, the lane ...).
-spec new(binary(), binary(), map()) -> product().
new(Serial, Recipe, Fields) when is_binary(Serial), is_binary(Recipe), is_map(Fields) ->
    Fields#{serial => Serial, recipe => Recipe, failed => false}.

%% @doc The product file of a task, as a binary: it is written at every transfer, and
%% a binary name goes to the system as it is.
-spec path(binary(), binary()) -> binary().
path(Zone, Lane) ->
    unicode:characters_to_binary(filename:join(cell_config:dir(data), file_name(Zone, Lane)),
                                 unicode, file:native_name_encoding()).

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

%% @doc What a file holds for a product of a generation and a marker.
-spec stored(product(), pos_integer(), marker()) -> stored().
stored(Product, Gen, Marker) ->
    #{product => Product, gen => Gen, marker => Marker}.

%% @doc Loads a task's product file: `undefined' when the task holds none.
-spec load(file:filename_all()) ->
          {ok, stored() | undefined} | {error, {corrupt, atom()} | {bad_product, term()}
                                        | {file:filename_all(), term()}}.
load(Path) ->
    case cell_file:get_record(Path) of
        {ok, undefined} -> {ok, undefined};
        {ok, #{product := Product, gen := Gen, marker := Marker} = Stored}
          when is_integer(Gen), Gen > 0 ->
            case {validate(Product), valid_marker(Marker)} of
                {ok, true} -> {ok, Stored};
                {ok, false} -> {error, {bad_product, Marker}};
                {Error, _} -> Error
            end;
        {ok, Other} -> {error, {bad_product, Other}};
        {error, enoent} -> {ok, undefined};
        {error, _} = Error -> Error
    end.

valid_marker(undefined) -> true;
valid_marker(#{link := L, from := From, phase := in_transit})
  when From =:= upstream; From =:= downstream ->
    is_atom(L);
valid_marker(_) -> false.

%% @doc Saves a product durably; `undefined' when the task holds none.
-spec save(file:filename_all(), stored() | undefined) -> ok | cell_file:error().
save(Path, Stored) ->
    save(Path, Stored, #{}).

%% @doc As {@link save/2}; `#{sync => false}' when a crash losing this write is
%% harmless (a stale copy the generations recognise, a marker merely left set).
-spec save(file:filename_all() | cell_file:record_file(), stored() | undefined,
           cell_file:options()) ->
          ok | cell_file:error().
save(Path, Stored, Opts) ->
    cell_file:put_record(Path, Stored, Opts).

%% @doc The task holds no product: its file says so.
-spec delete(file:filename_all()) -> ok | cell_file:error().
delete(Path) ->
    delete(Path, #{}).

-spec delete(file:filename_all() | cell_file:record_file(), cell_file:options()) ->
          ok | cell_file:error().
delete(Path, Opts) ->
    cell_file:put_record(Path, undefined, Opts).

%% @doc A product's serial; `undefined' for no product.
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
    Prod = stored(new(<<"S1">>, <<"recipe-a">>, #{cuts_done => 3}), 1, undefined),
    ok = save(P, Prod),
    ?assertEqual({ok, Prod}, load(P)),
    Moving = stored(new(<<"S1">>, <<"r">>), 4,
                    #{link => l1, from => upstream, phase => in_transit}),
    ok = save(P, Moving, #{sync => false}),
    ?assertEqual({ok, Moving}, load(P)),
    ok = save(P, undefined),
    ?assertEqual({ok, undefined}, load(P)),
    ok = file:write_file(P, <<"garbage">>),
    ?assertEqual({error, {corrupt, not_a_cellrt_file}}, load(P)),
    ok = cell_file:write_term(P, {not_a_product}),
    ?assertMatch({error, {bad_product, _}}, load(P)),
    ok = cell_file:write_term(P, Prod#{gen => 0}),
    ?assertMatch({error, {bad_product, _}}, load(P)),
    ok = cell_file:write_term(P, Prod#{marker => nonsense}),
    ?assertMatch({error, {bad_product, _}}, load(P)),
    ok = cell_file:write_term(P, Moving#{marker => #{link => l1, from => a,
                                                     phase => in_transit}}),
    ?assertMatch({error, {bad_product, _}}, load(P)).
-endif.
