%% @doc IO point values as a TwinCAT PLC stores them, and whether a PLC symbol can
%% hold a point of a given type.
%%
%% The point types and their Erlang values are the HAL's, defined once in
%% {@link cell_hal_type} (seed 000 §4.1) and laid out in ADS memory by
%% {@link cell_hal_type_codec}: what a task writes through the HAL, a Modbus device
%% or a TwinCAT PLC holds and reads back alike. This module adds what only ADS
%% knows:
%% <ul>
%% <li>the sizes a symbol of the type may have: a BOOL linked to one bit of an IO
%%   image has size 0 (and is read as one byte); a `char' may be a STRING(1) (two
%%   bytes with its terminator) or a BYTE;</li>
%% <li>`{bytes, N}': any structure or array of N bytes as a binary, for raw access
%%   by the client (not a point type: the HAL offers no such point);</li>
%% <li>which PLC declarations a type stands for ({@link compatible/2}).</li>
%% </ul>
%%
%% Strings are bytes as the PLC holds them (TwinCAT STRING is one byte per character,
%% Windows-1252); they are passed through unchanged.
-module(cell_hal_ads_types).

-include("cell_hal_ads.hrl").

-export([is_type/1, plc_size/1, sizes/1, encode/2, encode/3, decode/2, compatible/2,
         plc_name/1]).

-export_type([type/0, value/0]).

-type type() :: cell_hal_type:type() | {bytes, pos_integer()}.

-type value() :: cell_hal_type:value().

%% @doc Whether a term is a point type or `{bytes, N}'.
-spec is_type(term()) -> boolean().
is_type({bytes, N}) -> is_integer(N) andalso N >= 1;
is_type(T) -> cell_hal_type:is_type(T).

%% @doc The size of a value of the type in the PLC, in bytes (`char': the BYTE form).
-spec plc_size(type()) -> pos_integer().
plc_size({bytes, N}) -> N;
plc_size(T) -> cell_hal_type_codec:ads_size(T).

%% @doc Every symbol size that can hold the type: a BOOL linked to one bit of an IO
%% image has size 0 (and is read as one byte), `char' may be STRING(1) or BYTE.
-spec sizes(type()) -> [non_neg_integer()].
sizes(bool) -> [1, 0];
sizes(char) -> [1, 2];
sizes(T) -> [plc_size(T)].

%% @doc The bytes of a value, in the type's own size.
-spec encode(type(), value()) -> {ok, binary()} | {error, {bad_value, type(), term()}}.
encode(T, V) ->
    encode(T, V, plc_size(T)).

%% @doc The bytes of a value for a symbol of `Size' bytes (one of {@link sizes/1}):
%% a `char' written to a STRING(1) gets its terminator. A value the type does not
%% accept ({@link cell_hal_type:check/2}) is refused.
-spec encode(type(), value(), non_neg_integer()) ->
          {ok, binary()} | {error, {bad_value, type(), term()}}.
encode({bytes, N} = T, V, _) ->
    case is_binary(V) andalso byte_size(V) =:= N of
        true -> {ok, V};
        false -> {error, {bad_value, T, V}}
    end;
encode(T, V, Size) ->
    case cell_hal_type:check(T, V) of
        {ok, V1} when T =:= char, Size =:= 2 ->
            {ok, <<(cell_hal_type_codec:encode_ads(T, V1))/binary, 0>>};
        {ok, V1} ->
            {ok, cell_hal_type_codec:encode_ads(T, V1)};
        error ->
            {error, {bad_value, T, V}}
    end.

%% @doc The value in the bytes the PLC gave for a point of the type.
-spec decode(type(), binary()) -> {ok, value()} | {error, {bad_size, type(), non_neg_integer()}}.
decode(char, <<C, _/binary>> = Bin) when byte_size(Bin) =< 2 ->
    {ok, C};
decode({bytes, N}, Bin) when byte_size(Bin) =:= N ->
    {ok, Bin};
decode(T, Bin) ->
    case T =/= char andalso not is_bytes(T) andalso
        byte_size(Bin) =:= cell_hal_type_codec:ads_size(T) of
        true -> {ok, cell_hal_type_codec:decode_ads(T, Bin)};
        false -> {error, {bad_size, T, byte_size(Bin)}}
    end.

is_bytes({bytes, _}) -> true;
is_bytes(_) -> false.

%% @doc Whether a PLC symbol can hold a point of the type: its size must fit, its ADS
%% data type id must be the type's, and when its type name is an elementary IEC type
%% it must be one the type stands for. An alias or enumeration (a name the PLC
%% project declared) is judged by size and the type's own data type id. `decimal' and `{bytes, N}'
%% take any symbol of their size.
-spec compatible(type(), cell_hal_ads_codec:symbol()) -> boolean().
compatible(T, #{size := Size, data_type := DataType, type := TypeName}) ->
    Name = << <<(upper(C))>> || <<C>> <= TypeName >>,
    lists:member(Size, sizes(T)) andalso
        case accepted(T) of
            any ->
                true;
            {[Canonical | _] = Ids, Names} ->
                (lists:member(Name, Names) andalso lists:member(DataType, Ids))
                    orelse (DataType =:= Canonical andalso not elementary(Name))
        end.

upper(C) when C >= $a, C =< $z -> C - 32;
upper(C) -> C.

accepted(bool) -> {[?ADST_BIT, ?ADST_UINT8], [<<"BOOL">>, <<"BIT">>]};
accepted(byte) -> {[?ADST_UINT8], [<<"BYTE">>, <<"USINT">>]};
accepted(sbyte) -> {[?ADST_INT8], [<<"SINT">>]};
accepted(char) -> {[?ADST_STRING, ?ADST_UINT8], [<<"STRING(1)">>, <<"BYTE">>, <<"USINT">>]};
accepted(int16) -> {[?ADST_INT16], [<<"INT">>]};
accepted(uint16) -> {[?ADST_UINT16], [<<"WORD">>, <<"UINT">>]};
accepted(int32) -> {[?ADST_INT32], [<<"DINT">>]};
accepted(uint32) -> {[?ADST_UINT32], [<<"DWORD">>, <<"UDINT">>]};
accepted(int64) -> {[?ADST_INT64], [<<"LINT">>]};
accepted(uint64) -> {[?ADST_UINT64], [<<"ULINT">>, <<"LWORD">>]};
accepted(real) -> {[?ADST_REAL32], [<<"REAL">>]};
accepted(lreal) -> {[?ADST_REAL64], [<<"LREAL">>]};
accepted({string, N}) ->
    {[?ADST_STRING], [plc_name({string, N}) | [<<"STRING">> || N =:= 80]]};
accepted(date) -> {[?ADST_UINT32], [<<"DATE">>, <<"D">>]};
accepted(time) -> {[?ADST_UINT32], [<<"TIME">>, <<"T">>]};
accepted(decimal) -> any;
accepted({bytes, _}) -> any.

elementary(<<"STRING", _/binary>>) -> true;
elementary(<<"WSTRING", _/binary>>) -> true;
elementary(<<"ARRAY", _/binary>>) -> true;
elementary(Name) ->
    lists:member(Name, [<<"BOOL">>, <<"BIT">>, <<"BYTE">>, <<"USINT">>, <<"SINT">>,
                        <<"INT">>, <<"WORD">>, <<"UINT">>, <<"DINT">>, <<"DWORD">>,
                        <<"UDINT">>, <<"LINT">>, <<"ULINT">>, <<"LWORD">>, <<"REAL">>,
                        <<"LREAL">>, <<"DATE">>, <<"D">>, <<"TIME">>, <<"T">>,
                        <<"TOD">>, <<"TIME_OF_DAY">>, <<"DT">>, <<"DATE_AND_TIME">>,
                        <<"LTIME">>]).

%% @doc The TwinCAT declaration a point of the type expects, for messages.
-spec plc_name(type()) -> binary().
plc_name(bool) -> <<"BOOL">>;
plc_name(byte) -> <<"BYTE">>;
plc_name(sbyte) -> <<"SINT">>;
plc_name(char) -> <<"STRING(1)">>;
plc_name(int16) -> <<"INT">>;
plc_name(uint16) -> <<"UINT">>;
plc_name(int32) -> <<"DINT">>;
plc_name(uint32) -> <<"UDINT">>;
plc_name(int64) -> <<"LINT">>;
plc_name(uint64) -> <<"ULINT">>;
plc_name(real) -> <<"REAL">>;
plc_name(lreal) -> <<"LREAL">>;
plc_name({string, N}) -> iolist_to_binary(["STRING(", integer_to_list(N), ")"]);
plc_name(date) -> <<"DATE">>;
plc_name(time) -> <<"TIME">>;
plc_name(decimal) -> <<"16 bytes">>;
plc_name({bytes, N}) -> iolist_to_binary([integer_to_list(N), " bytes"]).
