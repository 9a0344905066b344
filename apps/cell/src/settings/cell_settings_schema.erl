%% @doc Settings objects declared in code (seed 000 §3.1): a module implementing this
%% behaviour names the object and lists its typed fields with their defaults (the
%% seed's "constructor defaults"), ranges, allowed values and docs. This module is the
%% pure side: defaults, validation of input from files, the web panel or code, the
%% pretty JSON the files hold, and field-level differences.
%%
%% Field types and their Erlang values:
%%
%% <table>
%% <tr><th>type</th><th>value</th><th>in the file</th></tr>
%% <tr><td>`boolean'</td><td>`true | false'</td><td>`true', `false'</td></tr>
%% <tr><td>`integer', `{integer, Min, Max}'</td><td>integer</td><td>number</td></tr>
%% <tr><td>`float', `{float, Min, Max}'</td><td>float</td><td>number (an integer
%%   is taken as a float)</td></tr>
%% <tr><td>`string', `{string, MaxChars}'</td><td>UTF-8 binary</td><td>string</td></tr>
%% <tr><td>`{enum, [atom()]}'</td><td>one of the atoms</td><td>string</td></tr>
%% <tr><td>`{list, T}', `{list, T, MaxLen}'</td><td>list</td><td>array</td></tr>
%% <tr><td>`{object, Module}'</td><td>map with atom keys</td><td>object</td></tr>
%% <tr><td>`{optional, T}'</td><td>`undefined' or a T</td><td>`null' or a T</td></tr>
%% </table>
%%
%% `Min' and `Max' may be `unbounded'; a plain `string' holds at most 1024 characters.
%% Input keys and enum values may be atoms (from code) or binaries (from files and the
%% network); binaries are matched against the declared names, never turned into atoms.
%% Fields missing from a file take their defaults, so a file written before a field was
%% added still loads. Names a schema lists in `obsolete/0' are accepted and dropped, so
%% a field can be retired without refusing the files that still hold it.
%%
%% Errors name the field: `{invalid, Path, Why}', where `Path' is the list of field
%% names (and 1-based list positions) from the top of the object; {@link
%% format_error/1} says it in words.
-module(cell_settings_schema).

-export([defaults/1, validate/2, validate/3, check_schema/1, fields/1, name/1]).
-export([to_json/2, from_json/2, from_json/3, json_decode/1, encode_value/2]).
-export([diff/3, format_error/1, format_change/1, format_path/1, get_path/2]).

-export_type([type/0, field/0, path/0, error/0, change/0, bound/0]).

-type bound() :: number() | unbounded.
-type type() :: boolean
              | integer | {integer, bound(), bound()}
              | float | {float, bound(), bound()}
              | string | {string, pos_integer()}
              | {enum, [atom(), ...]}
              | {list, type()} | {list, type(), non_neg_integer()}
              | {object, module()}
              | {optional, type()}.
-type field() :: #{name := atom(),
                   type := type(),
                   default => term(),   %% required except for objects, lists, optionals
                   doc => binary(),
                   unit => binary(),
                   secret => boolean()}.   %% never shown in a difference (hashes, keys)
-type path() :: [atom() | binary() | pos_integer()].
-type error() :: {invalid, path(), term()}.
-type change() :: #{path := path(), from := term(), to := term()}.

%% The object's name: the file is `Settings/<name>.json'.
-callback name() -> atom().
%% The fields, in the order the file lists them.
-callback fields() -> [field()].
%% A check across fields, run after every field is valid.
-callback check(map()) -> ok | {error, path(), term()}.
%% Names of fields no longer used: accepted in input and dropped.
-callback obsolete() -> [atom()].
-optional_callbacks([check/1, obsolete/0]).

-define(STRING_MAX, 1024).
-define(MAX_DEPTH, 16).
-define(JSON_DEPTH, 512).

%%====================================================================
%% Declarations
%%====================================================================

%% @doc The object's name.
-spec name(module()) -> atom().
name(Mod) -> Mod:name().

%% @doc The object's fields.
-spec fields(module()) -> [field()].
fields(Mod) -> Mod:fields().

%% @doc Checks a schema module once, at registration: unique field names, known types,
%% sane bounds, defaults that pass their own type, nested schemas that do not nest
%% themselves.
-spec check_schema(module()) -> ok | {error, {bad_schema, module(), term()}}.
check_schema(Mod) ->
    try check_schema(Mod, []) of
        ok -> ok
    catch
        throw:{bad_schema, Why} -> {error, {bad_schema, Mod, Why}}
    end.

check_schema(Mod, Seen) ->
    lists:member(Mod, Seen) andalso throw({bad_schema, {nests_itself, Mod}}),
    _ = code:ensure_loaded(Mod),
    erlang:function_exported(Mod, fields, 0) orelse throw({bad_schema, {no_fields, Mod}}),
    Fields = Mod:fields(),
    is_list(Fields) orelse throw({bad_schema, {fields_not_a_list, Mod}}),
    Names = [field_name(F) || F <- Fields],
    case Names -- lists:usort(Names) of
        [] -> ok;
        [Dup | _] -> throw({bad_schema, {duplicate_field, Dup}})
    end,
    lists:foreach(fun(F) -> check_field(F, [Mod | Seen]) end, Fields),
    ok.

field_name(#{name := N}) when is_atom(N) -> N;
field_name(F) -> throw({bad_schema, {bad_field, F}}).

check_field(#{name := N, type := T} = F, Seen) ->
    check_type(T, N, Seen),
    case default_of(F) of
        {ok, D} ->
            case validate_value(T, D, [N], none) of
                {ok, _} -> ok;
                {error, E} -> throw({bad_schema, {bad_default, N, E}})
            end;
        error ->
            throw({bad_schema, {no_default, N}})
    end;
check_field(F, _) ->
    throw({bad_schema, {bad_field, F}}).

check_type(boolean, _, _) -> ok;
check_type(integer, _, _) -> ok;
check_type(float, _, _) -> ok;
check_type(string, _, _) -> ok;
check_type({integer, Min, Max}, N, _) -> check_bounds(Min, Max, N, fun is_integer/1);
check_type({float, Min, Max}, N, _) -> check_bounds(Min, Max, N, fun is_number/1);
check_type({string, Max}, _, _) when is_integer(Max), Max > 0 -> ok;
check_type({enum, [_ | _] = L}, N, _) ->
    lists:all(fun is_atom/1, L) andalso length(L) =:= length(lists:usort(L))
        orelse throw({bad_schema, {bad_enum, N}}),
    ok;
check_type({list, T}, N, Seen) -> check_type(T, N, Seen);
check_type({list, T, Max}, N, Seen) when is_integer(Max), Max >= 0 -> check_type(T, N, Seen);
check_type({object, Mod}, _, Seen) when is_atom(Mod) -> check_schema(Mod, Seen);
check_type({optional, T}, N, Seen) -> check_type(T, N, Seen);
check_type(T, N, _) -> throw({bad_schema, {bad_type, N, T}}).

check_bounds(Min, Max, N, IsT) ->
    Ok = fun(unbounded) -> true; (B) -> IsT(B) end,
    (Ok(Min) andalso Ok(Max) andalso
     (Min =:= unbounded orelse Max =:= unbounded orelse Min =< Max))
        orelse throw({bad_schema, {bad_bounds, N}}),
    ok.

default_of(#{default := D}) -> {ok, D};
default_of(#{type := {object, Mod}}) -> {ok, defaults(Mod)};
default_of(#{type := {list, _}}) -> {ok, []};
default_of(#{type := {list, _, _}}) -> {ok, []};
default_of(#{type := {optional, _}}) -> {ok, undefined};
default_of(_) -> error.

%% @doc The object as its schema builds it: every field at its default.
-spec defaults(module()) -> map().
defaults(Mod) ->
    maps:from_list([{N, default(F)} || #{name := N} = F <- Mod:fields()]).

default(#{type := {object, Mod}} = F) ->
    %% A declared default for a nested object overrides some of its fields.
    case F of
        #{default := D} -> {ok, V} = validate_object(Mod, D, defaults(Mod), [], 0), V;
        _ -> defaults(Mod)
    end;
default(#{type := T} = F) ->
    {ok, D} = default_of(F),
    {ok, V} = validate_value(T, D, [], none),
    V.

%%====================================================================
%% Validation
%%====================================================================

%% @doc Validates `Input' as a whole object: fields it leaves out take their defaults.
-spec validate(module(), term()) -> {ok, map()} | {error, error()}.
validate(Mod, Input) ->
    validate(Mod, Input, defaults(Mod)).

%% @doc Validates `Input' as changes to `Base' (a valid object): fields it leaves out
%% keep their value in `Base', nested objects merge field by field, lists are replaced
%% whole.
-spec validate(module(), term(), map()) -> {ok, map()} | {error, error()}.
validate(Mod, Input, Base) ->
    validate_object(Mod, Input, Base, [], 0).

validate_object(_Mod, _Input, _Base, Path, Depth) when Depth > ?MAX_DEPTH ->
    {error, {invalid, Path, too_deep}};
validate_object(Mod, Input, Base, Path, Depth) when is_map(Input) ->
    Fields = Mod:fields(),
    Obsolete = obsolete(Mod),
    case match_keys(maps:to_list(Input), Fields, Obsolete, Path, #{}) of
        {ok, Given} ->
            case fold_fields(Fields, Given, Base, Path, Depth, #{}) of
                {ok, Obj} -> run_check(Mod, Obj, Path);
                {error, _} = E -> E
            end;
        {error, _} = E ->
            E
    end;
validate_object(_Mod, Input, _Base, Path, _Depth) ->
    {error, {invalid, Path, {wrong_type, object, Input}}}.

obsolete(Mod) ->
    case erlang:function_exported(Mod, obsolete, 0) of
        true -> Mod:obsolete();
        false -> []
    end.

%% Maps every input key onto a declared field: atoms by identity, binaries by name.
match_keys([], _Fields, _Obsolete, _Path, Acc) ->
    {ok, Acc};
match_keys([{K, V} | Rest], Fields, Obsolete, Path, Acc) ->
    case find_field(K, Fields) of
        {ok, #{name := N} = F} when not is_map_key(N, Acc) ->
            match_keys(Rest, Fields, Obsolete, Path, Acc#{N => {F, V}});
        {ok, #{name := N}} ->
            {error, {invalid, Path ++ [N], duplicate_field}};
        error ->
            case lists:any(fun(O) -> same_name(K, O) end, Obsolete) of
                true -> match_keys(Rest, Fields, Obsolete, Path, Acc);
                false -> {error, {invalid, Path ++ [K], unknown_field}}
            end
    end.

find_field(_K, []) -> error;
find_field(K, [#{name := N} = F | Rest]) ->
    case same_name(K, N) of
        true -> {ok, F};
        false -> find_field(K, Rest)
    end.

same_name(K, N) when is_atom(K) -> K =:= N;
same_name(K, N) when is_binary(K) -> K =:= atom_to_binary(N, utf8);
same_name(_, _) -> false.

fold_fields([], _Given, _Base, _Path, _Depth, Acc) ->
    {ok, Acc};
fold_fields([#{name := N, type := T} = F | Rest], Given, Base, Path, Depth, Acc) ->
    Old = case Base of
              #{N := B} -> B;
              _ -> default(F)
          end,
    case Given of
        #{N := {_, V}} ->
            case validate_field(T, V, Old, Path ++ [N], Depth) of
                {ok, Val} -> fold_fields(Rest, Given, Base, Path, Depth, Acc#{N => Val});
                {error, _} = E -> E
            end;
        _ ->
            fold_fields(Rest, Given, Base, Path, Depth, Acc#{N => Old})
    end.

validate_field({object, Mod}, V, Old, Path, Depth) ->
    validate_object(Mod, V, Old, Path, Depth + 1);
validate_field({optional, {object, Mod}}, V, Old, Path, Depth) when is_map(V) ->
    Base = case Old of
               undefined -> defaults(Mod);
               _ -> Old
           end,
    validate_object(Mod, V, Base, Path, Depth + 1);
validate_field(T, V, _Old, Path, Depth) ->
    validate_value(T, V, Path, Depth).

run_check(Mod, Obj, Path) ->
    case erlang:function_exported(Mod, check, 1) of
        false ->
            {ok, Obj};
        true ->
            case Mod:check(Obj) of
                ok -> {ok, Obj};
                {error, P, Why} -> {error, {invalid, Path ++ P, Why}}
            end
    end.

%% Depth `none' validates a default from the schema itself (no depth limit needed).
validate_value(T, V, Path, Depth) ->
    try value(T, V, Path, Depth) of
        Val -> {ok, Val}
    catch
        throw:{invalid, _, _} = E -> {error, E}
    end.

value(boolean, V, _, _) when is_boolean(V) -> V;
value(boolean, V, P, _) -> bad(P, {wrong_type, boolean, V});
value(integer, V, P, D) -> value({integer, unbounded, unbounded}, V, P, D);
value({integer, Min, Max}, V, P, _) when is_integer(V) -> in_range(V, Min, Max, P);
value({integer, _, _}, V, P, _) -> bad(P, {wrong_type, integer, V});
value(float, V, P, D) -> value({float, unbounded, unbounded}, V, P, D);
value({float, Min, Max}, V, P, _) when is_number(V) -> in_range(float(V), Min, Max, P);
value({float, _, _}, V, P, _) -> bad(P, {wrong_type, float, V});
value(string, V, P, D) -> value({string, ?STRING_MAX}, V, P, D);
value({string, Max}, V, P, _) when is_binary(V) ->
    case unicode:characters_to_list(V, utf8) of
        L when is_list(L) ->
            length(L) =< Max orelse bad(P, {too_long, Max}),
            V;
        _ ->
            bad(P, not_utf8)
    end;
value({string, _}, V, P, _) -> bad(P, {wrong_type, string, V});
value({enum, Allowed}, V, P, _) when is_atom(V); is_binary(V) ->
    case [A || A <- Allowed, same_name(V, A)] of
        [A] -> A;
        [] -> bad(P, {not_one_of, V, Allowed})
    end;
value({enum, _}, V, P, _) -> bad(P, {wrong_type, enum, V});
value({list, T}, V, P, D) -> list(T, V, unbounded, P, D);
value({list, T, Max}, V, P, D) -> list(T, V, Max, P, D);
value({object, Mod}, V, P, D) ->
    Depth = case D of none -> 0; _ -> D + 1 end,
    case validate_object(Mod, V, defaults(Mod), P, Depth) of
        {ok, Obj} -> Obj;
        {error, E} -> throw(E)
    end;
value({optional, _}, V, _, _) when V =:= undefined; V =:= null -> undefined;
value({optional, T}, V, P, D) -> value(T, V, P, D).

list(T, V, Max, P, D) when is_list(V) ->
    Max =:= unbounded orelse length(V) =< Max orelse bad(P, {too_long, Max}),
    {Vals, _} = lists:mapfoldl(fun(E, I) -> {value(T, E, P ++ [I], D), I + 1} end, 1, V),
    Vals;
list(_T, V, _Max, P, _D) ->
    bad(P, {wrong_type, list, V}).

in_range(V, Min, Max, P) ->
    (Min =:= unbounded orelse V >= Min) andalso (Max =:= unbounded orelse V =< Max)
        orelse bad(P, {out_of_range, V, Min, Max}),
    V.

-spec bad(path(), term()) -> no_return().
bad(Path, Why) -> throw({invalid, Path, Why}).

%%====================================================================
%% JSON
%%====================================================================

%% @doc The object as pretty JSON: two-space indent, fields in declaration order, one
%% field a line, a final newline. Stable, so files diff well.
-spec to_json(module(), map()) -> binary().
to_json(Mod, Obj) ->
    <<(jsx:encode(encode_value({object, Mod}, Obj), [space, {indent, 2}]))/binary, "\n">>.

%% @doc A value as jsx takes it (objects as ordered proplists).
-spec encode_value(type(), term()) -> term().
encode_value({object, Mod}, Obj) ->
    case [{atom_to_binary(N, utf8), encode_value(T, maps:get(N, Obj))}
          || #{name := N, type := T} <- Mod:fields()] of
        [] -> [{}];
        Pairs -> Pairs
    end;
encode_value({optional, _}, undefined) -> null;
encode_value({optional, T}, V) -> encode_value(T, V);
encode_value({list, T}, L) -> [encode_value(T, E) || E <- L];
encode_value({list, T, _}, L) -> [encode_value(T, E) || E <- L];
encode_value({enum, _}, A) -> atom_to_binary(A, utf8);
encode_value(_, V) -> V.

%% @doc Parses a settings file's text and validates it as a whole object.
-spec from_json(module(), binary()) -> {ok, map()} | {error, error() | not_json}.
from_json(Mod, Bin) ->
    from_json(Mod, Bin, defaults(Mod)).

%% @doc Parses JSON text and validates it as changes to `Base'.
-spec from_json(module(), binary(), map()) -> {ok, map()} | {error, error() | not_json}.
from_json(Mod, Bin, Base) ->
    case json_decode(Bin) of
        {ok, Term} -> validate(Mod, Term, Base);
        {error, _} = E -> E
    end.

%% @doc Parses JSON text: objects become maps with binary keys (a key given twice is
%% refused: the file would mean two things), arrays lists, `null' the atom `null'.
%% Nesting deeper than any object here needs is refused as `too_deep'.
-spec json_decode(binary()) ->
          {ok, term()} | {error, not_json | {invalid, path(), duplicate_field | too_deep}}.
json_decode(Bin) when is_binary(Bin) ->
    try jsx:decode(Bin, [{return_maps, false}]) of
        Term ->
            try {ok, to_map(Term, [], 0)}
            catch throw:{invalid, RevPath, Why} -> {error, {invalid, lists:reverse(RevPath), Why}}
            end
    catch
        error:_ -> {error, not_json}
    end.

%% The path is kept reversed while walking, so a deep document costs linear time.
to_map(_Term, RevPath, Depth) when Depth > ?JSON_DEPTH ->
    throw({invalid, RevPath, too_deep});
to_map([{}], _RevPath, _Depth) ->
    #{};
to_map([{K, _} | _] = Pairs, RevPath, Depth) when is_binary(K) ->
    lists:foldl(fun({Key, V}, Acc) ->
                        is_map_key(Key, Acc)
                            andalso throw({invalid, [Key | RevPath], duplicate_field}),
                        Acc#{Key => to_map(V, [Key | RevPath], Depth + 1)}
                end, #{}, Pairs);
to_map(List, RevPath, Depth) when is_list(List) ->
    {L, _} = lists:mapfoldl(fun(E, I) -> {to_map(E, [I | RevPath], Depth + 1), I + 1} end,
                            1, List),
    L;
to_map(V, _RevPath, _Depth) ->
    V.

%%====================================================================
%% Differences and messages
%%====================================================================

%% @doc The fields that differ between two valid objects, in declaration order. Nested
%% objects and lists of equal length are compared element by element.
-spec diff(module(), map(), map()) -> [change()].
diff(Mod, A, B) ->
    diff_object(Mod, A, B, []).

diff_object(Mod, A, B, Path) ->
    lists:append([hide(F, diff_value(T, maps:get(N, A), maps:get(N, B), Path ++ [N]))
                  || #{name := N, type := T} = F <- Mod:fields()]).

%% A secret field's change is listed (who changed it and when matters) without its
%% values: a difference goes to the log and to the panel.
hide(#{secret := true}, Changes) ->
    [C#{from => <<"(hidden)">>, to => <<"(hidden)">>} || C <- Changes];
hide(_Field, Changes) ->
    Changes.

diff_value(_T, Same, Same, _Path) ->
    [];
diff_value({object, Mod}, A, B, Path) ->
    diff_object(Mod, A, B, Path);
diff_value({optional, T}, A, B, Path) when A =/= undefined, B =/= undefined ->
    diff_value(T, A, B, Path);
diff_value({list, T}, A, B, Path) when length(A) =:= length(B) ->
    diff_list(T, A, B, Path);
diff_value({list, T, _}, A, B, Path) when length(A) =:= length(B) ->
    diff_list(T, A, B, Path);
diff_value(_T, A, B, Path) ->
    [#{path => Path, from => A, to => B}].

diff_list(T, A, B, Path) ->
    Idx = lists:seq(1, length(A)),
    lists:append([diff_value(T, X, Y, Path ++ [I]) || {I, X, Y} <- lists:zip3(Idx, A, B)]).

%% @doc The value at `Path' in an object.
-spec get_path(term(), path()) -> {ok, term()} | error.
get_path(V, []) -> {ok, V};
get_path(M, [K | Rest]) when is_map(M) ->
    case M of
        #{K := V} -> get_path(V, Rest);
        _ -> error
    end;
get_path(L, [I | Rest]) when is_list(L), is_integer(I), I >= 1, I =< length(L) ->
    get_path(lists:nth(I, L), Rest);
get_path(_, _) -> error.

%% @doc A path as people write it: `axes[2].speed'.
-spec format_path(path()) -> binary().
format_path([]) -> <<"(the whole object)">>;
format_path(Path) ->
    iolist_to_binary(
      lists:foldl(fun(I, Acc) when is_integer(I) -> [Acc, $[, integer_to_list(I), $]];
                     (K, []) -> name_text(K);
                     (K, Acc) -> [Acc, $., name_text(K)]
                  end, [], Path)).

name_text(K) when is_atom(K) -> atom_to_binary(K, utf8);
name_text(K) when is_binary(K) -> K.

%% @doc One change as a line: `speed_override: 50 -> 80'.
-spec format_change(change()) -> binary().
format_change(#{path := P, from := A, to := B}) ->
    iolist_to_binary([format_path(P), ": ", show(A), " -> ", show(B)]).

%% @doc An error in words an operator understands.
-spec format_error(term()) -> binary().
format_error({invalid, Path, Why}) ->
    iolist_to_binary([format_path(Path), ": ", why(Why)]);
format_error(not_json) ->
    <<"the text is not valid JSON">>;
format_error(Other) ->
    iolist_to_binary(io_lib:format("~0tp", [Other])).

why(unknown_field) -> "unknown field";
why(duplicate_field) -> "given more than once";
why(not_utf8) -> "not valid UTF-8 text";
why(too_deep) -> "objects nested too deep";
why({wrong_type, T, V}) -> ["expected ", type_text(T), ", got ", show(V)];
why({out_of_range, V, Min, Max}) ->
    [show(V), " is out of range ", bound_text(Min), "..", bound_text(Max)];
why({too_long, Max}) -> ["longer than ", integer_to_list(Max)];
why({not_one_of, V, Allowed}) ->
    [show(V), " is not one of ", lists:join(", ", [atom_to_list(A) || A <- Allowed])];
why(Other) -> io_lib:format("~0tp", [Other]).

type_text(enum) -> "one of the listed names";
type_text(object) -> "an object";
type_text(list) -> "a list";
type_text(T) -> ["a ", atom_to_list(T)].

bound_text(unbounded) -> "";
bound_text(N) -> show(N).

show(V) when is_binary(V), byte_size(V) > 60 -> [$", binary:part(V, 0, 57), "...\""];
show(V) when is_binary(V) -> [$", V, $"];
show(V) when is_float(V), V == trunc(V), abs(V) < 1.0e15 -> [integer_to_list(trunc(V)), ".0"];
show(V) when is_float(V) -> float_to_list(V, [short]);
show(V) ->
    S = io_lib:format("~0tp", [V]),
    case iolist_size(S) > 60 of
        true -> [string:slice(unicode:characters_to_binary(S), 0, 57), "..."];
        false -> S
    end.
