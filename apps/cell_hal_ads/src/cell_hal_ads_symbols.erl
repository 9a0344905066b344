%% @doc PLC symbol names: the uploaded symbol table, the image-based "*Name" wildcard
%% of seed 000 §4.1.2, and the check that a symbol can hold a point of a given type
%% before it is used. Pure.
%%
%% TwinCAT symbol names are case-insensitive: "MAIN.GeneralInputs" and
%% "main.generalinputs" name one variable. A name starting with `*' matches every
%% symbol whose name ends with the rest ("*ManipulatorInputs.FailPaletteIsIn" matches
%% "Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn"); it must match exactly one.
-module(cell_hal_ads_symbols).

-export([new/1, count/1, to_list/1, lookup/2, is_wildcard/1, check_name/1, check_type/3,
         read_size/1, key/1]).

-export_type([table/0, lookup_error/0]).

-opaque table() :: #{binary() => cell_hal_ads_codec:symbol()}.

-type lookup_error() :: {unknown_symbol, binary()}
                      | {ambiguous_symbol, binary(), [binary()]}.

%% How many candidates an ambiguity error names.
-define(MAX_CANDIDATES, 5).

%% @doc A table of uploaded symbol entries, by name. Entries without a name are left
%% out; of two entries with one name, the first is kept.
-spec new([cell_hal_ads_codec:symbol()]) -> table().
new(Symbols) ->
    lists:foldl(fun(#{name := <<>>}, T) -> T;
                   (#{name := Name} = S, T) ->
                        K = key(Name),
                        case maps:is_key(K, T) of
                            true -> T;
                            false -> T#{K => S}
                        end
                end, #{}, Symbols).

%% @doc How many symbols the table holds.
-spec count(table()) -> non_neg_integer().
count(Table) ->
    map_size(Table).

%% @doc Every symbol of the table.
-spec to_list(table()) -> [cell_hal_ads_codec:symbol()].
to_list(Table) ->
    maps:values(Table).

%% @doc The symbol a name or "*Suffix" pattern stands for.
-spec lookup(binary(), table()) -> {ok, cell_hal_ads_codec:symbol()} | {error, lookup_error()}.
lookup(<<"*", Suffix/binary>> = Pattern, Table) ->
    K = key(Suffix),
    N = byte_size(K),
    Matches = [S || {Name, S} <- maps:to_list(Table),
                    byte_size(Name) >= N,
                    binary:part(Name, byte_size(Name) - N, N) =:= K],
    case Matches of
        [S] -> {ok, S};
        [] -> {error, {unknown_symbol, Pattern}};
        Many ->
            Names = lists:sort([Name || #{name := Name} <- Many]),
            {error, {ambiguous_symbol, Pattern, lists:sublist(Names, ?MAX_CANDIDATES)}}
    end;
lookup(Name, Table) ->
    case maps:find(key(Name), Table) of
        {ok, S} -> {ok, S};
        error -> {error, {unknown_symbol, Name}}
    end.

%% @doc Whether a name is a "*Suffix" pattern.
-spec is_wildcard(binary()) -> boolean().
is_wildcard(<<"*", _/binary>>) -> true;
is_wildcard(_) -> false.

%% @doc A name the PLC can be asked for: not empty, no NUL, a `*' only as the first
%% character and followed by something.
-spec check_name(term()) -> ok | {error, {bad_name, term()}}.
check_name(<<"*", Rest/binary>> = Name) ->
    plain_name(Rest, Name);
check_name(Name) ->
    plain_name(Name, Name).

plain_name(Plain, Name) when is_binary(Plain), byte_size(Plain) > 0,
                             byte_size(Name) < 65536 ->
    case binary:match(Plain, [<<0>>, <<"*">>]) of
        nomatch -> ok;
        _ -> {error, {bad_name, Name}}
    end;
plain_name(_, Name) ->
    {error, {bad_name, Name}}.

%% @doc Whether the symbol found for `Name' can hold a point of `Type'; if not, an
%% error naming the symbol, the expected declaration and what the PLC has.
-spec check_type(binary(), cell_hal_ads_types:type(), cell_hal_ads_codec:symbol()) ->
          ok | {error, {type_mismatch, binary(), #{expected := binary(),
                                                   plc_type := binary(),
                                                   size := non_neg_integer()}}}.
check_type(Name, Type, #{type := PlcType, size := Size} = Symbol) ->
    case cell_hal_ads_types:compatible(Type, Symbol) of
        true -> ok;
        false -> {error, {type_mismatch, Name, #{expected => cell_hal_ads_types:plc_name(Type),
                                                 plc_type => PlcType, size => Size}}}
    end.

%% @doc How many bytes to read for a symbol: a bit is read as one byte.
-spec read_size(cell_hal_ads_codec:symbol()) -> non_neg_integer().
read_size(#{size := 0}) -> 1;
read_size(#{size := Size}) -> Size.

%% @doc The case-insensitive key of a name (ASCII letters folded).
-spec key(binary()) -> binary().
key(Name) ->
    << <<(upper(C))>> || <<C>> <= Name >>.

upper(C) when C >= $a, C =< $z -> C - 32;
upper(C) -> C.
