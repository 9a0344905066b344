%% @doc How each IO point type lies in a device's memory: Modbus registers and Beckhoff
%% ADS bytes. Pure functions; the values are those {@link cell_hal_type} accepts.
%%
%% <b>Modbus</b> (16-bit big-endian registers): a value of 32 or 64 bits spans 2 or 4
%% registers in the connection's word order, `big' (most significant word first,
%% "ABCD", the Modbus convention) or `little' (least significant word first, "CDAB").
%% BOOL in a whole register is true when the register is not 0 and is written as 1;
%% BYTE, SINT and STRING(1) sit in the low byte of one register (SINT is written sign
%% extended, so the register reads as the same INT); STRING(N) packs two characters a
%% register, the first in the high byte, padded with NUL; DATE is a UDINT of seconds
%% since 1970-01-01 and TIME a UDINT of milliseconds; the 16 bytes of a decimal fill 8
%% registers in order. Bits in coils, discrete inputs and inside registers are handled
%% by the Modbus driver's plan.
%%
%% <b>ADS</b> (little-endian, TwinCAT layout): BOOL is one byte (not 0 is true), STRING(N)
%% takes N + 1 bytes with a terminating NUL, DATE and TIME are 4-byte UDINTs, decimal
%% is 16 raw bytes.
-module(cell_hal_type_codec).

-export([registers/1, encode_registers/3, decode_registers/3]).
-export([ads_size/1, encode_ads/2, decode_ads/2]).

-export_type([word_order/0]).

-type word_order() :: big | little.

-define(EPOCH_DAYS, 719528).  %% calendar:date_to_gregorian_days({1970, 1, 1})

%%====================================================================
%% Modbus registers
%%====================================================================

%% @doc How many 16-bit registers a value of the type takes.
-spec registers(cell_hal_type:type()) -> pos_integer().
registers({string, N}) -> (N + 1) div 2;
registers(Type) -> (bytes(Type) + 1) div 2.

%% @doc A value as the bytes of its registers, two a register, in wire order.
-spec encode_registers(cell_hal_type:type(), cell_hal_type:value(), word_order()) ->
          binary().
encode_registers(bool, V, _) -> <<(bool_int(V)):16>>;
encode_registers(byte, V, _) -> <<V:16>>;
encode_registers(char, V, _) -> <<V:16>>;
encode_registers(sbyte, V, _) -> <<V:16/signed>>;
encode_registers({string, N}, V, _) -> pad(V, 2 * registers({string, N}));
encode_registers(decimal, V, _) -> V;
encode_registers(Type, V, Order) -> words(bytes_be(Type, V), Order).

%% @doc The value held by the bytes of a type's registers (exactly `2 * registers(Type)'
%% bytes).
-spec decode_registers(cell_hal_type:type(), binary(), word_order()) ->
          cell_hal_type:value().
decode_registers(bool, <<W:16>>, _) -> W =/= 0;
decode_registers(byte, <<_, B>>, _) -> B;
decode_registers(char, <<_, B>>, _) -> B;
decode_registers(sbyte, <<_, B:8/signed>>, _) -> B;
decode_registers({string, N}, Bin, _) -> unpad(binary:part(Bin, 0, N));
decode_registers(decimal, <<_:16/binary>> = Bin, _) -> Bin;
decode_registers(Type, Bin, Order) -> value_be(Type, words(Bin, Order)).

%% Big-endian bytes of the multi-byte numeric types, the most significant word first.
bytes_be(int16, V) -> <<V:16/signed>>;
bytes_be(uint16, V) -> <<V:16>>;
bytes_be(int32, V) -> <<V:32/signed>>;
bytes_be(uint32, V) -> <<V:32>>;
bytes_be(int64, V) -> <<V:64/signed>>;
bytes_be(uint64, V) -> <<V:64>>;
bytes_be(real, V) -> float_be(32, V);
bytes_be(lreal, V) -> float_be(64, V);
bytes_be(date, V) -> <<(date_seconds(V)):32>>;
bytes_be(time, V) -> <<V:32>>.

value_be(int16, <<V:16/signed>>) -> V;
value_be(uint16, <<V:16>>) -> V;
value_be(int32, <<V:32/signed>>) -> V;
value_be(uint32, <<V:32>>) -> V;
value_be(int64, <<V:64/signed>>) -> V;
value_be(uint64, <<V:64>>) -> V;
value_be(real, Bin) -> float_value(Bin);
value_be(lreal, Bin) -> float_value(Bin);
value_be(date, <<S:32>>) -> seconds_date(S);
value_be(time, <<V:32>>) -> V.

%% Reverses the order of 16-bit words for the `little' word order (its own inverse).
words(Bin, big) -> Bin;
words(Bin, little) -> << <<W:16>> || <<W:16>> <= reverse_words(Bin) >>.

reverse_words(Bin) ->
    list_to_binary(lists:reverse([<<W:16>> || <<W:16>> <= Bin])).

%%====================================================================
%% ADS (little-endian)
%%====================================================================

%% @doc The size in bytes of a type in a TwinCAT PLC's memory.
-spec ads_size(cell_hal_type:type()) -> pos_integer().
ads_size({string, N}) -> N + 1;
ads_size(Type) -> bytes(Type).

%% @doc A value as TwinCAT holds it (little-endian).
-spec encode_ads(cell_hal_type:type(), cell_hal_type:value()) -> binary().
encode_ads(bool, V) -> <<(bool_int(V))>>;
encode_ads(byte, V) -> <<V>>;
encode_ads(char, V) -> <<V>>;
encode_ads(sbyte, V) -> <<V:8/signed>>;
encode_ads({string, N}, V) -> pad(V, N + 1);
encode_ads(decimal, V) -> V;
encode_ads(Type, V) -> reverse_bytes(bytes_be(Type, V)).

%% @doc The value held by a type's bytes (exactly `ads_size(Type)' bytes).
-spec decode_ads(cell_hal_type:type(), binary()) -> cell_hal_type:value().
decode_ads(bool, <<B>>) -> B =/= 0;
decode_ads(byte, <<B>>) -> B;
decode_ads(char, <<B>>) -> B;
decode_ads(sbyte, <<B:8/signed>>) -> B;
decode_ads({string, N}, Bin) when byte_size(Bin) =:= N + 1 -> unpad(binary:part(Bin, 0, N));
decode_ads(decimal, <<_:16/binary>> = Bin) -> Bin;
decode_ads(Type, Bin) -> value_be(Type, reverse_bytes(Bin)).

reverse_bytes(Bin) -> list_to_binary(lists:reverse(binary_to_list(Bin))).

%%====================================================================
%% Shared
%%====================================================================

%% Bytes of the fixed-size types (the seed's table).
bytes(bool) -> 1;
bytes(byte) -> 1;
bytes(sbyte) -> 1;
bytes(char) -> 1;
bytes(int16) -> 2;
bytes(uint16) -> 2;
bytes(int32) -> 4;
bytes(uint32) -> 4;
bytes(real) -> 4;
bytes(date) -> 4;
bytes(time) -> 4;
bytes(int64) -> 8;
bytes(uint64) -> 8;
bytes(lreal) -> 8;
bytes(decimal) -> 16.

bool_int(true) -> 1;
bool_int(false) -> 0.

pad(Bin, Size) -> <<Bin/binary, 0:((Size - byte_size(Bin)) * 8)>>.

%% A PLC string ends at its first NUL.
unpad(Bin) ->
    case binary:match(Bin, <<0>>) of
        {Pos, 1} -> binary:part(Bin, 0, Pos);
        nomatch -> Bin
    end.

%% IEEE 754 with the three values an Erlang float cannot hold.
float_be(32, nan) -> <<16#7FC00000:32>>;
float_be(32, infinity) -> <<16#7F800000:32>>;
float_be(32, neg_infinity) -> <<16#FF800000:32>>;
float_be(64, nan) -> <<16#7FF8000000000000:64>>;
float_be(64, infinity) -> <<16#7FF0000000000000:64>>;
float_be(64, neg_infinity) -> <<16#FFF0000000000000:64>>;
float_be(Bits, V) -> <<V:Bits/float>>.

float_value(<<S:1, 255:8, M:23>>) -> special(S, M);
float_value(<<S:1, 2047:11, M:52>>) -> special(S, M);
float_value(<<V:32/float>>) -> V;
float_value(<<V:64/float>>) -> V.

special(_, M) when M =/= 0 -> nan;
special(0, 0) -> infinity;
special(1, 0) -> neg_infinity.

date_seconds(Date) -> (calendar:date_to_gregorian_days(Date) - ?EPOCH_DAYS) * 86400.

%% A DATE is midnight; a time of day in the seconds (a DT read as DATE) is dropped.
seconds_date(S) -> calendar:gregorian_days_to_date(?EPOCH_DAYS + S div 86400).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

register_vectors_test_() ->
    V = fun(T, X, O, Bin) ->
                [?_assertEqual(Bin, encode_registers(T, X, O)),
                 ?_assertEqual(X, decode_registers(T, Bin, O)),
                 ?_assertEqual(byte_size(Bin), 2 * registers(T))]
        end,
    lists:append(
      [V(bool, true, big, <<0, 1>>),
       V(bool, false, big, <<0, 0>>),
       V(byte, 255, big, <<0, 255>>),
       V(char, $A, big, <<0, $A>>),
       V(sbyte, -1, big, <<255, 255>>),
       V(sbyte, -128, big, <<255, 128>>),
       V(int16, -2, big, <<16#FF, 16#FE>>),
       V(uint16, 16#1234, little, <<16#12, 16#34>>),
       V(int32, 16#12345678, big, <<16#12, 16#34, 16#56, 16#78>>),
       V(int32, 16#12345678, little, <<16#56, 16#78, 16#12, 16#34>>),
       V(int32, -1, little, <<255, 255, 255, 255>>),
       V(uint32, 16#89ABCDEF, big, <<16#89, 16#AB, 16#CD, 16#EF>>),
       V(int64, 16#0102030405060708, big, <<1, 2, 3, 4, 5, 6, 7, 8>>),
       V(int64, 16#0102030405060708, little, <<7, 8, 5, 6, 3, 4, 1, 2>>),
       V(uint64, 16#FFFFFFFFFFFFFFFF, little, <<16#FFFFFFFFFFFFFFFF:64>>),
       V(uint64, 16#0102030405060708, little, <<7, 8, 5, 6, 3, 4, 1, 2>>),
       V(real, 1.0, big, <<16#3F, 16#80, 0, 0>>),
       V(real, 1.0, little, <<0, 0, 16#3F, 16#80>>),
       V(real, -2.5, big, <<16#C0, 16#20, 0, 0>>),
       V(lreal, 1.0, big, <<16#3F, 16#F0, 0:48>>),
       V(lreal, 1.0, little, <<0:48, 16#3F, 16#F0>>),
       V(real, infinity, big, <<16#7F, 16#80, 0, 0>>),
       V(real, neg_infinity, little, <<0, 0, 16#FF, 16#80>>),
       V(real, nan, big, <<16#7F, 16#C0, 0, 0>>),
       V(lreal, nan, big, <<16#7F, 16#F8, 0:48>>),
       V(lreal, neg_infinity, big, <<16#FF, 16#F0, 0:48>>),
       V({string, 3}, <<"ABC">>, big, <<"ABC", 0>>),
       V({string, 4}, <<"AB">>, little, <<"AB", 0, 0>>),
       V({string, 1}, <<>>, big, <<0, 0>>),
       V(date, {1970, 1, 2}, big, <<0, 1, 16#51, 16#80>>),
       V(date, {1970, 1, 2}, little, <<16#51, 16#80, 0, 1>>),
       V(date, {2106, 2, 7}, big, <<(49710 * 86400):32>>),
       V(time, 1500, big, <<0, 0, 16#05, 16#DC>>),
       V(decimal, <<1:128>>, little, <<1:128>>)]).

register_reads_test_() ->
    [?_assertEqual(true, decode_registers(bool, <<16#80, 0>>, big)),
     ?_assertEqual(16#34, decode_registers(byte, <<16#12, 16#34>>, big)),
     ?_assertEqual(-1, decode_registers(sbyte, <<0, 255>>, big)),
     ?_assertEqual(<<"AB">>, decode_registers({string, 4}, <<"AB", 0, "C">>, big)),
     ?_assertEqual(<<"ABC">>, decode_registers({string, 3}, <<"ABCD">>, big)),
     ?_assertEqual(nan, decode_registers(real, <<16#FF, 16#C0, 0, 1>>, big)),
     ?_assertEqual({1970, 1, 2}, decode_registers(date, <<(86400 + 3600):32>>, big))].

ads_vectors_test_() ->
    V = fun(T, X, Bin) ->
                [?_assertEqual(Bin, encode_ads(T, X)),
                 ?_assertEqual(X, decode_ads(T, Bin)),
                 ?_assertEqual(byte_size(Bin), ads_size(T))]
        end,
    lists:append(
      [V(bool, true, <<1>>),
       V(bool, false, <<0>>),
       V(byte, 200, <<200>>),
       V(sbyte, -2, <<254>>),
       V(char, $Z, <<$Z>>),
       V(int16, -2, <<16#FE, 16#FF>>),
       V(uint16, 16#1234, <<16#34, 16#12>>),
       V(int32, 16#12345678, <<16#78, 16#56, 16#34, 16#12>>),
       V(uint32, 16#89ABCDEF, <<16#EF, 16#CD, 16#AB, 16#89>>),
       V(int64, -2, <<16#FE, 255, 255, 255, 255, 255, 255, 255>>),
       V(uint64, 1, <<1, 0:56>>),
       V(real, 1.0, <<0, 0, 16#80, 16#3F>>),
       V(lreal, 1.0, <<0:48, 16#F0, 16#3F>>),
       V(real, nan, <<0, 0, 16#C0, 16#7F>>),
       V({string, 4}, <<"AB">>, <<"AB", 0, 0, 0>>),
       V({string, 2}, <<"AB">>, <<"AB", 0>>),
       V(date, {1970, 1, 2}, <<16#80, 16#51, 1, 0>>),
       V(time, 1500, <<16#DC, 16#05, 0, 0>>),
       V(decimal, <<7:128>>, <<7:128>>)]).

ads_reads_test_() ->
    [?_assertEqual(true, decode_ads(bool, <<2>>)),
     ?_assertEqual(<<"AB">>, decode_ads({string, 3}, <<"AB", 0, "Z">>)),
     ?_assertEqual(<<"ABC">>, decode_ads({string, 3}, <<"ABCD">>))].
-endif.
