%% @doc The IO point types of seed 000 §4.1 and their Erlang values: which values a
%% type accepts, the conditions a task may wait for, and how a value reads in a log.
%%
%% <table>
%% <tr><th>type</th><th>TwinCAT</th><th>bytes</th><th>Erlang value</th></tr>
%% <tr><td>`bool'</td><td>BOOL</td><td>1</td><td>`true | false'</td></tr>
%% <tr><td>`byte'</td><td>BYTE, USINT</td><td>1</td><td>0..255</td></tr>
%% <tr><td>`sbyte'</td><td>SINT</td><td>1</td><td>-128..127</td></tr>
%% <tr><td>`char'</td><td>STRING(1), BYTE</td><td>1</td><td>a character code 0..255</td></tr>
%% <tr><td>`int16'</td><td>INT</td><td>2</td><td>-32768..32767</td></tr>
%% <tr><td>`uint16'</td><td>WORD, UINT</td><td>2</td><td>0..65535</td></tr>
%% <tr><td>`int32'</td><td>DINT</td><td>4</td><td>-2^31..2^31-1</td></tr>
%% <tr><td>`uint32'</td><td>DWORD, UDINT</td><td>4</td><td>0..2^32-1</td></tr>
%% <tr><td>`int64'</td><td>LINT</td><td>8</td><td>-2^63..2^63-1</td></tr>
%% <tr><td>`uint64'</td><td>ULINT</td><td>8</td><td>0..2^64-1</td></tr>
%% <tr><td>`real'</td><td>REAL</td><td>4</td><td>a float (single precision), `nan', `infinity',
%%   `neg_infinity'</td></tr>
%% <tr><td>`lreal'</td><td>LREAL</td><td>8</td><td>a float, `nan', `infinity',
%%   `neg_infinity'</td></tr>
%% <tr><td>`{string, N}'</td><td>STRING(N)</td><td>N + 1</td><td>a binary of at most N bytes,
%%   no NUL</td></tr>
%% <tr><td>`date'</td><td>DATE</td><td>4</td><td>`{Y, M, D}', 1970-01-01..2106-02-07</td></tr>
%% <tr><td>`time'</td><td>TIME</td><td>4</td><td>milliseconds, 0..2^32-1</td></tr>
%% <tr><td>`decimal'</td><td>(none: 16 raw bytes)</td><td>16</td><td>a 16-byte binary</td></tr>
%% </table>
%%
%% A REAL holds less than an Erlang float: a value is rounded to single precision when
%% it is checked, so what a task wrote and what it reads back are equal.
%%
%% These values are the same for every driver: the simulation keeps them as they
%% are, Modbus and ADS lay them out in their own ways ({@link cell_hal_type_codec}),
%% and a task reads and writes the same terms whichever PLC is behind a point (a
%% `char' is a character code, never a one-byte binary; NaN and the infinities are
%% the atoms above).
-module(cell_hal_type).

-export([is_type/1, check/2, check_cond/2, holds/2]).
-export([format/2, name/1]).

-export_type([type/0, value/0, condition/0]).

-type type() :: bool | byte | sbyte | char | int16 | uint16 | int32 | uint32
              | int64 | uint64 | real | lreal | {string, pos_integer()} | date | time
              | decimal.
-type special_float() :: nan | infinity | neg_infinity.
-type value() :: boolean() | integer() | float() | special_float() | binary()
               | calendar:date().
-type condition() :: {eq | ne | gt | ge | lt | le, value()}.

%% The longest STRING(N) a point may declare; drivers may allow less.
-define(MAX_STRING, 65535).
%% 2106-02-07 is the last day whose midnight fits DATE's 32-bit seconds.
-define(LAST_DATE, {2106, 2, 7}).
-define(MAX_REAL, 3.4028234663852886e38).

%% @doc Whether a term names a point type.
-spec is_type(term()) -> boolean().
is_type({string, N}) -> is_integer(N) andalso N >= 1 andalso N =< ?MAX_STRING;
is_type(T) -> lists:member(T, [bool, byte, sbyte, char, int16, uint16, int32, uint32,
                               int64, uint64, real, lreal, date, time, decimal]).

%% @doc Checks a value against a type and returns it in its stored form (an integer
%% for a REAL becomes a float rounded to single precision), or `error'.
-spec check(type(), term()) -> {ok, value()} | error.
check(bool, V) when is_boolean(V) -> {ok, V};
check(real, V) when V =:= nan; V =:= infinity; V =:= neg_infinity -> {ok, V};
check(lreal, V) when V =:= nan; V =:= infinity; V =:= neg_infinity -> {ok, V};
check(real, V) when is_number(V) ->
    case to_float(V) of
        F when is_float(F), abs(F) =< ?MAX_REAL ->
            <<R:32/float>> = <<F:32/float>>,
            {ok, R};
        _ ->
            error
    end;
check(lreal, V) when is_number(V) ->
    case to_float(V) of
        F when is_float(F) -> {ok, F};
        _ -> error
    end;
check({string, N}, V) when is_binary(V), byte_size(V) =< N ->
    case binary:match(V, <<0>>) of
        nomatch -> {ok, V};
        _ -> error
    end;
check(date, {Y, M, D} = V) when is_integer(Y), is_integer(M), is_integer(D) ->
    case Y >= 1970 andalso V =< ?LAST_DATE andalso calendar:valid_date(V) of
        true -> {ok, V};
        false -> error
    end;
check(decimal, V) when is_binary(V), byte_size(V) =:= 16 -> {ok, V};
check(Type, V) when is_integer(V) ->
    case range(Type) of
        {Lo, Hi} when V >= Lo, V =< Hi -> {ok, V};
        _ -> error
    end;
check(_, _) ->
    error.

to_float(V) when is_float(V) -> V;
to_float(V) ->
    try float(V) catch error:badarg -> error end.

range(byte) -> {0, 255};
range(sbyte) -> {-128, 127};
range(char) -> {0, 255};
range(int16) -> {-32768, 32767};
range(uint16) -> {0, 65535};
range(int32) -> {-(1 bsl 31), (1 bsl 31) - 1};
range(uint32) -> {0, (1 bsl 32) - 1};
range(int64) -> {-(1 bsl 63), (1 bsl 63) - 1};
range(uint64) -> {0, (1 bsl 64) - 1};
range(time) -> {0, (1 bsl 32) - 1};
range(_) -> none.

%% @doc Checks a condition a task waits for. Ordering (`gt', `ge', `lt', `le') is
%% offered for numbers, characters, dates and times; every type has `eq' and `ne'.
%% A number compared with a REAL or LREAL point may be an integer. A condition that
%% could never hold because its value does not fit the type is refused here, so that
%% no task waits for it forever.
-spec check_cond(type(), term()) -> {ok, condition()} | error.
check_cond(Type, {Op, V}) when Op =:= eq; Op =:= ne; Op =:= gt; Op =:= ge;
                               Op =:= lt; Op =:= le ->
    Ordered = Op =:= eq orelse Op =:= ne orelse ordered(Type),
    case Ordered andalso cond_value(Type, V) of
        {ok, V1} -> {ok, {Op, V1}};
        _ -> error
    end;
check_cond(_, _) ->
    error.

ordered(bool) -> false;
ordered({string, _}) -> false;
ordered(decimal) -> false;
ordered(_) -> true.

%% A float point compared with a number: any number will do (no rounding, a task
%% may wait for "above 12.5" on a REAL). Any other type takes a value of its own.
cond_value(T, V) when (T =:= real orelse T =:= lreal), is_number(V) -> {ok, V};
cond_value(T, V) -> check(T, V).

%% @doc Whether a value satisfies a condition. NaN equals nothing, not even itself.
-spec holds(condition(), value()) -> boolean().
holds({Op, R}, V) when V =:= nan; R =:= nan -> Op =:= ne;
holds({eq, R}, V) -> same(V, R);
holds({ne, R}, V) -> not same(V, R);
holds({gt, R}, V) -> less(R, V);
holds({ge, R}, V) -> less(R, V) orelse same(V, R);
holds({lt, R}, V) -> less(V, R);
holds({le, R}, V) -> less(V, R) orelse same(V, R).

same(A, B) when is_number(A), is_number(B) -> A == B;
same(A, B) -> A =:= B.

less(neg_infinity, B) -> B =/= neg_infinity;
less(_, neg_infinity) -> false;
less(infinity, _) -> false;
less(A, infinity) -> A =/= infinity;
less(A, B) -> A < B.

%% @doc A value as an operator reads it: `true', `12.5', `"ABC"', `2026-11-21',
%% `1500 ms'.
-spec format(type(), value()) -> iodata().
format(_, V) when is_boolean(V) -> atom_to_list(V);
format({string, _}, V) -> [$", V, $"];
format(decimal, V) -> ["0x", binary:encode_hex(V)];
format(date, {Y, M, D}) -> io_lib:format("~4..0w-~2..0w-~2..0w", [Y, M, D]);
format(time, V) -> [integer_to_list(V), " ms"];
format(char, V) when V >= 32, V < 127 -> [$', V, $'];
format(_, V) when is_integer(V) -> integer_to_list(V);
format(_, V) when is_float(V) -> float_to_list(V, [short]);
format(_, V) -> io_lib:format("~tp", [V]).

%% @doc The TwinCAT name of a type, as the seed's table gives it.
-spec name(type()) -> iodata().
name(bool) -> "BOOL";
name(byte) -> "BYTE";
name(sbyte) -> "SINT";
name(char) -> "STRING(1)";
name(int16) -> "INT";
name(uint16) -> "UINT";
name(int32) -> "DINT";
name(uint32) -> "UDINT";
name(int64) -> "LINT";
name(uint64) -> "ULINT";
name(real) -> "REAL";
name(lreal) -> "LREAL";
name({string, N}) -> ["STRING(", integer_to_list(N), ")"];
name(date) -> "DATE";
name(time) -> "TIME";
name(decimal) -> "16 bytes (decimal)".

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

all_types() ->
    [bool, byte, sbyte, char, int16, uint16, int32, uint32, int64, uint64, real, lreal,
     {string, 1}, {string, 80}, date, time, decimal].

is_type_test_() ->
    [?_assert(is_type(T)) || T <- all_types()] ++
    [?_assertNot(is_type(T)) || T <- [{string, 0}, {string, 65536}, string, int8, float,
                                       {string, -1}, {string, a}, "bool"]].

integer_limits_test_() ->
    Limits = [{byte, 0, 255}, {sbyte, -128, 127}, {char, 0, 255}, {int16, -32768, 32767},
              {uint16, 0, 65535}, {int32, -2147483648, 2147483647},
              {uint32, 0, 4294967295}, {int64, -9223372036854775808, 9223372036854775807},
              {uint64, 0, 18446744073709551615}, {time, 0, 4294967295}],
    lists:append(
      [[?_assertEqual({ok, Lo}, check(T, Lo)), ?_assertEqual({ok, Hi}, check(T, Hi)),
        ?_assertEqual(error, check(T, Lo - 1)), ?_assertEqual(error, check(T, Hi + 1)),
        ?_assertEqual(error, check(T, 1.0)), ?_assertEqual(error, check(T, true))]
       || {T, Lo, Hi} <- Limits]).

bool_test_() ->
    [?_assertEqual({ok, true}, check(bool, true)),
     ?_assertEqual({ok, false}, check(bool, false)),
     ?_assertEqual(error, check(bool, 1)),
     ?_assertEqual(error, check(bool, nil))].

real_test_() ->
    [?_assertEqual({ok, 1.5}, check(real, 1.5)),
     ?_assertEqual({ok, 2.0}, check(real, 2)),
     ?_assertEqual({ok, 0.10000000149011612}, check(real, 0.1)),
     ?_assertEqual({ok, ?MAX_REAL}, check(real, ?MAX_REAL)),
     ?_assertEqual(error, check(real, 3.5e38)),
     ?_assertEqual(error, check(real, -3.5e38)),
     ?_assertEqual({ok, 0.1}, check(lreal, 0.1)),
     ?_assertEqual({ok, 1.0e300}, check(lreal, 1.0e300)),
     ?_assertEqual(error, check(lreal, 1 bsl 1100)),
     ?_assertEqual({ok, nan}, check(real, nan)),
     ?_assertEqual({ok, neg_infinity}, check(lreal, neg_infinity)),
     ?_assertEqual(error, check(real, inf)),
     ?_assertEqual(error, check(real, <<"1">>))].

string_test_() ->
    [?_assertEqual({ok, <<"ABC">>}, check({string, 3}, <<"ABC">>)),
     ?_assertEqual({ok, <<>>}, check({string, 3}, <<>>)),
     ?_assertEqual(error, check({string, 3}, <<"ABCD">>)),
     ?_assertEqual(error, check({string, 3}, <<"A", 0, "B">>)),
     ?_assertEqual(error, check({string, 3}, "ABC"))].

date_test_() ->
    [?_assertEqual({ok, {1970, 1, 1}}, check(date, {1970, 1, 1})),
     ?_assertEqual({ok, {2106, 2, 7}}, check(date, {2106, 2, 7})),
     ?_assertEqual(error, check(date, {2106, 2, 8})),
     ?_assertEqual(error, check(date, {1969, 12, 31})),
     ?_assertEqual(error, check(date, {2023, 2, 29})),
     ?_assertEqual({ok, {2024, 2, 29}}, check(date, {2024, 2, 29})),
     ?_assertEqual(error, check(date, {2024, 13, 1})),
     ?_assertEqual(error, check(date, 19000))].

decimal_test_() ->
    [?_assertMatch({ok, _}, check(decimal, <<0:128>>)),
     ?_assertEqual(error, check(decimal, <<0:120>>)),
     ?_assertEqual(error, check(decimal, <<0:136>>))].

cond_test_() ->
    [?_assertEqual({ok, {eq, true}}, check_cond(bool, {eq, true})),
     ?_assertEqual(error, check_cond(bool, {gt, false})),
     ?_assertEqual(error, check_cond(bool, {eq, 1})),
     ?_assertEqual({ok, {gt, 12.5}}, check_cond(real, {gt, 12.5})),
     ?_assertEqual({ok, {gt, 1.0e300}}, check_cond(real, {gt, 1.0e300})),
     ?_assertEqual({ok, {le, 3}}, check_cond(int16, {le, 3})),
     ?_assertEqual(error, check_cond(int16, {le, 2.5})),
     ?_assertEqual(error, check_cond(int16, {eq, 70000})),
     ?_assertEqual(error, check_cond(uint16, {gt, -1})),
     ?_assertEqual({ok, {ge, {2026, 1, 1}}}, check_cond(date, {ge, {2026, 1, 1}})),
     ?_assertEqual(error, check_cond({string, 4}, {gt, <<"A">>})),
     ?_assertEqual({ok, {eq, <<"OK">>}}, check_cond({string, 4}, {eq, <<"OK">>})),
     ?_assertEqual(error, check_cond({string, 1}, {eq, <<"OK">>})),
     ?_assertEqual(error, check_cond(int16, {between, 1})),
     ?_assertEqual(error, check_cond(int16, eq))].

holds_test_() ->
    [?_assert(holds({eq, true}, true)),
     ?_assertNot(holds({eq, true}, false)),
     ?_assert(holds({ne, 1}, 2)),
     ?_assert(holds({eq, 2}, 2.0)),
     ?_assert(holds({gt, 2}, 3)),
     ?_assertNot(holds({gt, 3}, 3)),
     ?_assert(holds({ge, 3}, 3)),
     ?_assert(holds({lt, 3}, 2.5)),
     ?_assert(holds({le, 3}, 3.0)),
     ?_assertNot(holds({eq, nan}, nan)),
     ?_assert(holds({ne, nan}, nan)),
     ?_assertNot(holds({gt, 0}, nan)),
     ?_assert(holds({gt, 1.0e300}, infinity)),
     ?_assert(holds({lt, -1.0e300}, neg_infinity)),
     ?_assertNot(holds({lt, neg_infinity}, neg_infinity)),
     ?_assert(holds({le, infinity}, infinity)),
     ?_assert(holds({gt, {2026, 1, 1}}, {2026, 2, 1}))].

format_test_() ->
    [?_assertEqual("true", lists:flatten(format(bool, true))),
     ?_assertEqual("\"AB\"", binary_to_list(iolist_to_binary(format({string, 2}, <<"AB">>)))),
     ?_assertEqual("2026-11-21", lists:flatten(format(date, {2026, 11, 21}))),
     ?_assertEqual("1500 ms", lists:flatten(format(time, 1500))),
     ?_assertEqual("'A'", lists:flatten(format(char, $A))),
     ?_assertEqual("-5", lists:flatten(format(int16, -5))),
     ?_assertEqual("nan", lists:flatten(format(real, nan))),
     ?_assertEqual("12.5", lists:flatten(format(real, 12.5))),
     ?_assertEqual("0.1", lists:flatten(format(lreal, 0.1))),
     ?_assertEqual("STRING(80)", lists:flatten(name({string, 80})))].
-endif.
