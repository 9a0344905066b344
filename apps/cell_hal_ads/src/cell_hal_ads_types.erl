%% @doc IO point values as a TwinCAT PLC stores them: the types of seed 000 §4.1,
%% little-endian, and whether a PLC symbol can hold a point of a given type.
%%
%% <table>
%% <tr><th>type</th><th>TwinCAT</th><th>bytes</th><th>Erlang value</th></tr>
%% <tr><td>`bool'</td><td>BOOL (BIT in IO images)</td><td>1</td><td>`true | false'</td></tr>
%% <tr><td>`byte'</td><td>BYTE, USINT</td><td>1</td><td>0..255</td></tr>
%% <tr><td>`sbyte'</td><td>SINT</td><td>1</td><td>-128..127</td></tr>
%% <tr><td>`char'</td><td>STRING(1) or BYTE</td><td>2 or 1</td><td>a one-byte binary</td></tr>
%% <tr><td>`int16'</td><td>INT</td><td>2</td><td>integer</td></tr>
%% <tr><td>`uint16'</td><td>WORD, UINT</td><td>2</td><td>integer</td></tr>
%% <tr><td>`int32'</td><td>DINT</td><td>4</td><td>integer</td></tr>
%% <tr><td>`uint32'</td><td>DWORD, UDINT</td><td>4</td><td>integer</td></tr>
%% <tr><td>`int64'</td><td>LINT</td><td>8</td><td>integer</td></tr>
%% <tr><td>`uint64'</td><td>ULINT, LWORD</td><td>8</td><td>integer</td></tr>
%% <tr><td>`real'</td><td>REAL</td><td>4</td>
%%     <td>float (or `nan', `infinity', `neg_infinity')</td></tr>
%% <tr><td>`lreal'</td><td>LREAL</td><td>8</td><td>float (same)</td></tr>
%% <tr><td>`{string, N}'</td><td>STRING(N)</td><td>N + 1</td>
%%     <td>binary of at most N bytes, no NUL</td></tr>
%% <tr><td>`date'</td><td>DATE</td><td>4</td>
%%     <td>`{Y, M, D}' (seconds since 1970 on the wire)</td></tr>
%% <tr><td>`time'</td><td>TIME</td><td>4</td><td>milliseconds</td></tr>
%% <tr><td>`decimal'</td><td>none in the PLC: 16 bytes</td><td>16</td><td>a 16-byte binary</td></tr>
%% <tr><td>`{bytes, N}'</td><td>any structure or array</td><td>N</td><td>an N-byte binary</td></tr>
%% </table>
%%
%% Strings are bytes as the PLC holds them (TwinCAT STRING is one byte per character,
%% Windows-1252); they are passed through unchanged.
-module(cell_hal_ads_types).

-include("cell_hal_ads.hrl").

-export([is_type/1, plc_size/1, sizes/1, encode/2, encode/3, decode/2, compatible/2,
         plc_name/1]).

-export_type([type/0, value/0]).

-type type() :: bool | byte | sbyte | char | int16 | uint16 | int32 | uint32 | int64
              | uint64 | real | lreal | {string, pos_integer()} | date | time | decimal
              | {bytes, pos_integer()}.

-type value() :: boolean() | integer() | float() | nan | infinity | neg_infinity
               | binary() | calendar:date().

%% Seconds from year 0 (the calendar module's origin) to 1970-01-01.
-define(UNIX_EPOCH_SECONDS, 62167219200).
%% The longest STRING(N) TwinCAT declares.
-define(MAX_STRING, 65535).

%% @doc Whether a term is one of the types above.
-spec is_type(term()) -> boolean().
is_type({string, N}) -> is_integer(N) andalso N >= 1 andalso N =< ?MAX_STRING;
is_type({bytes, N}) -> is_integer(N) andalso N >= 1;
is_type(T) -> lists:member(T, [bool, byte, sbyte, char, int16, uint16, int32, uint32,
                               int64, uint64, real, lreal, date, time, decimal]).

%% @doc The size of a value of the type in the PLC, in bytes (`char': the BYTE form).
-spec plc_size(type()) -> pos_integer().
plc_size(bool) -> 1;
plc_size(byte) -> 1;
plc_size(sbyte) -> 1;
plc_size(char) -> 1;
plc_size(int16) -> 2;
plc_size(uint16) -> 2;
plc_size(int32) -> 4;
plc_size(uint32) -> 4;
plc_size(int64) -> 8;
plc_size(uint64) -> 8;
plc_size(real) -> 4;
plc_size(lreal) -> 8;
plc_size({string, N}) -> N + 1;
plc_size(date) -> 4;
plc_size(time) -> 4;
plc_size(decimal) -> 16;
plc_size({bytes, N}) -> N.

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
%% a `char' written to a STRING(1) gets its terminator.
-spec encode(type(), value(), non_neg_integer()) ->
          {ok, binary()} | {error, {bad_value, type(), term()}}.
encode(T, V, Size) ->
    case enc(T, V) of
        {ok, Bin} when T =:= char, Size =:= 2 -> {ok, <<Bin/binary, 0>>};
        {ok, Bin} -> {ok, Bin};
        error -> {error, {bad_value, T, V}}
    end.

enc(bool, true) -> {ok, <<1>>};
enc(bool, false) -> {ok, <<0>>};
enc(byte, V) when is_integer(V), V >= 0, V =< 16#FF -> {ok, <<V>>};
enc(sbyte, V) when is_integer(V), V >= -16#80, V =< 16#7F -> {ok, <<V:8/signed>>};
enc(char, <<C>>) -> {ok, <<C>>};
enc(int16, V) when is_integer(V), V >= -16#8000, V =< 16#7FFF -> {ok, <<V:16/little-signed>>};
enc(uint16, V) when is_integer(V), V >= 0, V =< 16#FFFF -> {ok, <<V:16/little>>};
enc(int32, V) when is_integer(V), V >= -16#80000000, V =< 16#7FFFFFFF ->
    {ok, <<V:32/little-signed>>};
enc(uint32, V) when is_integer(V), V >= 0, V =< 16#FFFFFFFF -> {ok, <<V:32/little>>};
enc(int64, V) when is_integer(V), V >= -16#8000000000000000, V =< 16#7FFFFFFFFFFFFFFF ->
    {ok, <<V:64/little-signed>>};
enc(uint64, V) when is_integer(V), V >= 0, V =< 16#FFFFFFFFFFFFFFFF -> {ok, <<V:64/little>>};
enc(real, V) -> float_bytes(V, 32);
enc(lreal, V) -> float_bytes(V, 64);
enc({string, N}, V) when is_binary(V), byte_size(V) =< N ->
    case binary:match(V, <<0>>) of
        nomatch -> {ok, <<V/binary, 0:((N + 1 - byte_size(V)) * 8)>>};
        _ -> error
    end;
enc(date, {Y, M, D} = Date) when is_integer(Y), is_integer(M), is_integer(D) ->
    case calendar:valid_date(Date) of
        true ->
            S = calendar:date_to_gregorian_days(Date) * 86400 - ?UNIX_EPOCH_SECONDS,
            case S >= 0 andalso S =< 16#FFFFFFFF of
                true -> {ok, <<S:32/little>>};
                false -> error
            end;
        false ->
            error
    end;
enc(time, V) when is_integer(V), V >= 0, V =< 16#FFFFFFFF -> {ok, <<V:32/little>>};
enc(decimal, V) when is_binary(V), byte_size(V) =:= 16 -> {ok, V};
enc({bytes, N}, V) when is_binary(V), byte_size(V) =:= N -> {ok, V};
enc(_, _) -> error.

%% Erlang floats have no NaN or infinities; the PLC's are named by atoms.
float_bytes(V, Bits) when is_integer(V) -> float_bytes(float(V), Bits);
float_bytes(V, 32) when is_float(V) ->
    %% Beyond the range of a REAL the bit syntax gives an infinity: refused.
    Bin = <<V:32/little-float>>,
    case float_value(Bin) of
        F when is_float(F) -> {ok, Bin};
        _ -> error
    end;
float_bytes(V, 64) when is_float(V) -> {ok, <<V:64/little-float>>};
float_bytes(nan, 32) -> {ok, <<16#7FC00000:32/little>>};
float_bytes(nan, 64) -> {ok, <<16#7FF8000000000000:64/little>>};
float_bytes(infinity, 32) -> {ok, <<16#7F800000:32/little>>};
float_bytes(infinity, 64) -> {ok, <<16#7FF0000000000000:64/little>>};
float_bytes(neg_infinity, 32) -> {ok, <<16#FF800000:32/little>>};
float_bytes(neg_infinity, 64) -> {ok, <<16#FFF0000000000000:64/little>>};
float_bytes(_, _) -> error.

%% @doc The value in the bytes the PLC gave for a point of the type.
-spec decode(type(), binary()) -> {ok, value()} | {error, {bad_size, type(), non_neg_integer()}}.
decode(bool, <<B>>) -> {ok, B =/= 0};
decode(byte, <<B>>) -> {ok, B};
decode(sbyte, <<B:8/signed>>) -> {ok, B};
decode(char, <<C, _/binary>> = Bin) when byte_size(Bin) =< 2 -> {ok, <<C>>};
decode(int16, <<V:16/little-signed>>) -> {ok, V};
decode(uint16, <<V:16/little>>) -> {ok, V};
decode(int32, <<V:32/little-signed>>) -> {ok, V};
decode(uint32, <<V:32/little>>) -> {ok, V};
decode(int64, <<V:64/little-signed>>) -> {ok, V};
decode(uint64, <<V:64/little>>) -> {ok, V};
decode(real, <<_:32>> = Bin) -> {ok, float_value(Bin)};
decode(lreal, <<_:64>> = Bin) -> {ok, float_value(Bin)};
decode({string, N}, Bin) when byte_size(Bin) =:= N + 1 ->
    case binary:match(Bin, <<0>>) of
        {Pos, _} -> {ok, binary:part(Bin, 0, Pos)};
        nomatch -> {ok, binary:part(Bin, 0, N)}
    end;
decode(date, <<S:32/little>>) ->
    {Date, _} = calendar:gregorian_seconds_to_datetime(S + ?UNIX_EPOCH_SECONDS),
    {ok, Date};
decode(time, <<V:32/little>>) -> {ok, V};
decode(decimal, <<_:16/binary>> = Bin) -> {ok, Bin};
decode({bytes, N}, Bin) when byte_size(Bin) =:= N -> {ok, Bin};
decode(T, Bin) -> {error, {bad_size, T, byte_size(Bin)}}.

float_value(<<V:32/little-float>>) -> V;
float_value(<<V:64/little-float>>) -> V;
float_value(<<_:32/little>> = Bin) -> special(Bin);
float_value(<<_:64/little>> = Bin) -> special(Bin).

%% An exponent of all ones: NaN when the fraction is not zero, else an infinity.
special(<<Bits:32/little>>) ->
    special(Bits bsr 31, Bits band 16#7FFFFF);
special(<<Bits:64/little>>) ->
    special(Bits bsr 63, Bits band 16#FFFFFFFFFFFFF).

special(_, Frac) when Frac =/= 0 -> nan;
special(0, 0) -> infinity;
special(1, 0) -> neg_infinity.

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
