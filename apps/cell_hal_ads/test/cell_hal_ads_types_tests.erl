%% Unit tests of PLC values: both sides of every limit.
-module(cell_hal_ads_types_tests).
-include_lib("eunit/include/eunit.hrl").

-define(E(T, V), cell_hal_ads_types:encode(T, V)).
-define(D(T, B), cell_hal_ads_types:decode(T, B)).
-define(BAD(T, V), ?_assertEqual({error, {bad_value, T, V}}, ?E(T, V))).

integer_limits_test_() ->
    Limits = [{byte, 0, 255}, {sbyte, -128, 127}, {int16, -32768, 32767}, {uint16, 0, 65535},
              {int32, -2147483648, 2147483647}, {uint32, 0, 4294967295},
              {int64, -9223372036854775808, 9223372036854775807},
              {uint64, 0, 18446744073709551615}, {time, 0, 4294967295}],
    lists:append(
      [[?_assertEqual({ok, Lo}, round_trip(T, Lo)),
        ?_assertEqual({ok, Hi}, round_trip(T, Hi)),
        ?BAD(T, Lo - 1), ?BAD(T, Hi + 1), ?BAD(T, 1.0), ?BAD(T, <<"1">>)]
       || {T, Lo, Hi} <- Limits]).

round_trip(T, V) ->
    {ok, B} = ?E(T, V),
    ?assertEqual(cell_hal_ads_types:plc_size(T), byte_size(B)),
    ?D(T, B).

little_endian_test_() ->
    [?_assertEqual({ok, <<16#34, 16#12>>}, ?E(uint16, 16#1234)),
     ?_assertEqual({ok, <<16#FF, 16#FF, 16#FF, 16#FF>>}, ?E(int32, -1)),
     ?_assertEqual({ok, <<0, 0, 16#C0, 16#3F>>}, ?E(real, 1.5)),
     ?_assertEqual({ok, <<0, 0, 0, 0, 0, 0, 16#F8, 16#3F>>}, ?E(lreal, 1.5)),
     ?_assertEqual({ok, 16#1234}, ?D(uint16, <<16#34, 16#12>>))].

bool_test_() ->
    [?_assertEqual({ok, <<1>>}, ?E(bool, true)),
     ?_assertEqual({ok, <<0>>}, ?E(bool, false)),
     ?_assertEqual({ok, true}, ?D(bool, <<2>>)),
     ?_assertEqual({ok, false}, ?D(bool, <<0>>)),
     ?BAD(bool, 1),
     ?_assertEqual({error, {bad_size, bool, 2}}, ?D(bool, <<0, 0>>))].

float_test_() ->
    [?_assertEqual({ok, 2.0}, round_trip(real, 2)),
     ?_assertEqual({ok, 3.4028234663852886e38}, round_trip(real, 3.4028234663852886e38)),
     ?BAD(real, 1.0e39),
     ?_assertEqual({ok, 1.0e300}, round_trip(lreal, 1.0e300)),
     ?_assertEqual({ok, nan}, round_trip(real, nan)),
     ?_assertEqual({ok, infinity}, round_trip(lreal, infinity)),
     ?_assertEqual({ok, neg_infinity}, round_trip(real, neg_infinity)),
     %% any NaN the PLC holds, whatever its payload
     ?_assertEqual({ok, nan}, ?D(real, <<1, 0, 16#80, 16#FF>>)),
     ?_assertEqual({ok, nan}, ?D(lreal, <<1, 0, 0, 0, 0, 0, 16#F0, 16#7F>>)),
     ?BAD(lreal, <<"1.0">>)].

string_test_() ->
    [?_assertEqual({ok, <<"abc", 0, 0, 0>>}, ?E({string, 5}, <<"abc">>)),
     ?_assertEqual({ok, <<"abcde", 0>>}, ?E({string, 5}, <<"abcde">>)),
     ?BAD({string, 5}, <<"abcdef">>),
     ?BAD({string, 5}, <<"a", 0, "b">>),
     ?BAD({string, 5}, "abc"),
     ?_assertEqual({ok, <<>>}, round_trip({string, 3}, <<>>)),
     ?_assertEqual({ok, <<"ab">>}, ?D({string, 3}, <<"ab", 0, "x">>)),
     %% no terminator where one belongs: the declared length
     ?_assertEqual({ok, <<"abc">>}, ?D({string, 3}, <<"abcd">>)),
     ?_assertEqual({error, {bad_size, {string, 3}, 3}}, ?D({string, 3}, <<"abc">>))].

char_test_() ->
    %% a character code, as every HAL driver gives it (cell_hal_type)
    [?_assertEqual({ok, <<"A">>}, ?E(char, $A)),
     ?_assertEqual({ok, <<"A", 0>>}, cell_hal_ads_types:encode(char, $A, 2)),
     ?_assertEqual({ok, $A}, ?D(char, <<"A", 0>>)),
     ?_assertEqual({ok, $A}, ?D(char, <<"A">>)),
     ?_assertEqual({ok, 255}, round_trip(char, 255)),
     ?_assertEqual({ok, 0}, round_trip(char, 0)),
     ?BAD(char, 256),
     ?BAD(char, -1),
     ?BAD(char, <<"A">>),
     ?_assertEqual({error, {bad_size, char, 3}}, ?D(char, <<"ABC">>)),
     ?_assertEqual({error, {bad_size, char, 0}}, ?D(char, <<>>))].

%% Every value the HAL's type check accepts is laid out as cell_hal_type_codec lays
%% it out for ADS: one definition of a point's value across drivers.
same_as_hal_test_() ->
    Samples = [{bool, true}, {byte, 7}, {sbyte, -7}, {char, $z}, {int16, -2}, {uint16, 2},
               {int32, -70000}, {uint32, 70000}, {int64, -1 bsl 40}, {uint64, 1 bsl 40},
               {real, 0.1}, {real, 3}, {lreal, 0.1}, {lreal, nan}, {{string, 4}, <<"ab">>},
               {date, {2026, 11, 21}}, {time, 1500}, {decimal, <<9:128>>}],
    [?_assertEqual({ok, cell_hal_type_codec:encode_ads(T, element(2, cell_hal_type:check(T, V)))},
                   ?E(T, V)) || {T, V} <- Samples] ++
    %% a REAL is rounded as the HAL rounds it: what was written reads back equal
    [?_assertEqual(cell_hal_type:check(real, 0.1), round_trip(real, 0.1))].

date_test_() ->
    [?_assertEqual({ok, <<0:32>>}, ?E(date, {1970, 1, 1})),
     ?_assertEqual({ok, <<86400:32/little>>}, ?E(date, {1970, 1, 2})),
     ?BAD(date, {1969, 12, 31}),
     ?_assertEqual({ok, {2106, 2, 7}}, round_trip(date, {2106, 2, 7})),
     ?BAD(date, {2106, 2, 8}),
     ?BAD(date, {2023, 2, 29}),
     ?_assertEqual({ok, {2024, 2, 29}}, round_trip(date, {2024, 2, 29})),
     %% a DATE with a time of day (not from a PLC, but possible) is that day
     ?_assertEqual({ok, {1970, 1, 2}}, ?D(date, <<(86400 + 3600):32/little>>))].

raw_test_() ->
    [?_assertEqual({ok, <<0:128>>}, round_trip(decimal, <<0:128>>)),
     ?BAD(decimal, <<0:120>>),
     ?_assertEqual({ok, <<1, 2, 3>>}, round_trip({bytes, 3}, <<1, 2, 3>>)),
     ?BAD({bytes, 3}, <<1, 2>>)].

is_type_test_() ->
    [?_assert(cell_hal_ads_types:is_type(T))
     || T <- [bool, byte, sbyte, char, int16, uint16, int32, uint32, int64, uint64, real,
              lreal, {string, 1}, {string, 65535}, date, time, decimal, {bytes, 1}]] ++
    [?_assertNot(cell_hal_ads_types:is_type(T))
     || T <- [word, {string, 0}, {string, 65536}, {bytes, 0}, "bool", {string, a}]].

sym(Type, DataType, Size) ->
    #{name => <<"S">>, type => Type, data_type => DataType, size => Size, comment => <<>>,
      group => 0, offset => 0, flags => 0}.

compatible_test_() ->
    C = fun cell_hal_ads_types:compatible/2,
    [?_assert(C(int32, sym(<<"DINT">>, 3, 4))),
     ?_assertNot(C(int32, sym(<<"INT">>, 2, 2))),
     ?_assertNot(C(int32, sym(<<"UDINT">>, 19, 4))),
     ?_assert(C(uint32, sym(<<"dword">>, 19, 4))),
     ?_assert(C(time, sym(<<"TIME">>, 19, 4))),
     ?_assertNot(C(time, sym(<<"UDINT">>, 19, 4))),
     ?_assertNot(C(uint32, sym(<<"TIME">>, 19, 4))),
     ?_assert(C(date, sym(<<"DATE">>, 19, 4))),
     %% an enumeration or alias the project declared: judged by data type and size
     ?_assert(C(int16, sym(<<"E_MachineState">>, 2, 2))),
     ?_assertNot(C(int16, sym(<<"E_MachineState">>, 3, 4))),
     ?_assert(C(bool, sym(<<"BOOL">>, 33, 1))),
     ?_assert(C(bool, sym(<<"BOOL">>, 17, 1))),
     ?_assert(C(bool, sym(<<"BIT">>, 33, 0))),
     ?_assertNot(C(bool, sym(<<"MyByte">>, 17, 1))),
     ?_assertNot(C(bool, sym(<<"BYTE">>, 17, 1))),
     ?_assert(C(char, sym(<<"STRING(1)">>, 30, 2))),
     ?_assert(C(char, sym(<<"BYTE">>, 17, 1))),
     ?_assert(C({string, 80}, sym(<<"STRING(80)">>, 30, 81))),
     ?_assert(C({string, 80}, sym(<<"STRING">>, 30, 81))),
     ?_assertNot(C({string, 20}, sym(<<"STRING(80)">>, 30, 81))),
     ?_assertNot(C({string, 80}, sym(<<"WSTRING(80)">>, 31, 162))),
     ?_assert(C(decimal, sym(<<"ST_Decimal">>, 65, 16))),
     ?_assertNot(C(decimal, sym(<<"ST_Decimal">>, 65, 15))),
     ?_assert(C({bytes, 6}, sym(<<"ARRAY [0..5] OF BYTE">>, 65, 6))),
     ?_assertNot(C(int32, sym(<<"ARRAY [0..0] OF DINT">>, 3, 4)))].

plc_name_test_() ->
    [?_assertEqual(<<"STRING(12)">>, cell_hal_ads_types:plc_name({string, 12})),
     ?_assertEqual(<<"LREAL">>, cell_hal_ads_types:plc_name(lreal)),
     ?_assertEqual(<<"7 bytes">>, cell_hal_ads_types:plc_name({bytes, 7}))].
