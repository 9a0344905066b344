%% IO groups for the tests of the HAL over ADS.
%%
%% `#{kind => types}': one input and one output of every point type of seed 000 §4.1,
%% structure based (§4.1.1): the input `int16_in' is the member ".Int16" of the group's
%% `input_struct', the output `int16_out' the member ".Int16" of its `output_struct'.
%% `#{kind => points, count => N}': N DINT inputs ".P000" ... of `input_struct'.
%% `#{kind => list, points => [{Name, Dir, Type, Field}]}': points as given.
-module(cell_hal_ads_test_io).
-behaviour(cell_hal_group).

-export([points/1, types/0, field/1]).

%% Every type with the PLC declaration that holds it and two sample values.
types() ->
    [{bool, "BOOL", 33, false, true},
     {byte, "BYTE", 17, 0, 255},
     {sbyte, "SINT", 16, -128, 127},
     {char, "STRING(1)", 30, $A, $z},
     {int16, "INT", 2, -32768, 32767},
     {uint16, "UINT", 18, 0, 65535},
     {int32, "DINT", 3, -2147483648, 2147483647},
     {uint32, "UDINT", 19, 0, 4294967295},
     {int64, "LINT", 20, -9223372036854775808, 9223372036854775807},
     {uint64, "ULINT", 21, 0, 18446744073709551615},
     {real, "REAL", 4, -1.5, 3.25},
     {lreal, "LREAL", 5, 0.1, -2.0e300},
     {{string, 10}, "STRING(10)", 30, <<"cellrt">>, <<"ABCDEFGHIJ">>},
     {date, "DATE", 19, {2026, 11, 21}, {2106, 2, 7}},
     {time, "TIME", 19, 1500, 4294967295},
     {decimal, "ST_Decimal", 65, <<1:128>>, <<16#FF:8, 0:112, 16#AB:8>>}].

%% The structure member of a type: ".Int16", ".String10".
field({string, N}) -> "String" ++ integer_to_list(N);
field(T) ->
    [C | Rest] = atom_to_list(T),
    [C - 32 | Rest].

points(#{kind := types}) ->
    lists:append(
      [[#{name => name(T, "_in"), dir => in, type => T,
          address => list_to_binary("A1.IN." ++ field(T)),
          caption => list_to_binary(field(T) ++ " input"),
          field => list_to_binary("." ++ field(T))},
        #{name => name(T, "_out"), dir => out, type => T,
          address => list_to_binary("A1.OUT." ++ field(T)),
          caption => list_to_binary(field(T) ++ " output"),
          field => list_to_binary("." ++ field(T))}]
       || {T, _, _, _, _} <- types()]);
points(#{kind := points, count := N}) ->
    [#{name => list_to_atom(lists:flatten(io_lib:format("p~3..0b", [I]))), dir => in,
       type => int32, address => list_to_binary(io_lib:format("A2.~3..0b", [I])),
       caption => <<"Group point">>,
       field => list_to_binary(io_lib:format(".P~3..0b", [I]))}
     || I <- lists:seq(0, N - 1)];
points(#{kind := list, points := Points}) ->
    [#{name => Name, dir => Dir, type => T, address => atom_to_binary(Name),
       caption => <<"Test point">>, field => Field}
     || {Name, Dir, T, Field} <- Points].

name({string, N}, Suffix) -> list_to_atom("string" ++ integer_to_list(N) ++ Suffix);
name(T, Suffix) -> list_to_atom(atom_to_list(T) ++ Suffix).
