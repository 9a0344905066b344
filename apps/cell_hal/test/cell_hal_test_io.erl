%% An IO group for the HAL's tests: one input and one output of every point type of
%% seed 000 §4.1, laid out on Modbus holding and input registers, coils and discrete
%% inputs from a base address, so the same module serves the simulated PLC and the
%% Modbus peers. `#{only => [Name]}' keeps some points.
-module(cell_hal_test_io).
-behaviour(cell_hal_group).

-export([points/1, types/0, sample/2]).

%% Every type with two sample values (the second one is what tests change to).
types() ->
    [{bool, false, true}, {byte, 0, 255}, {sbyte, -128, 127}, {char, $A, $z},
     {int16, -32768, 32767}, {uint16, 0, 65535}, {int32, -2147483648, 2147483647},
     {uint32, 0, 4294967295}, {int64, -9223372036854775808, 9223372036854775807},
     {uint64, 0, 18446744073709551615}, {real, -1.5, 3.25}, {lreal, 0.1, -2.0e300},
     {{string, 10}, <<"cellrt">>, <<"ABCDEFGHIJ">>}, {date, {2026, 11, 21}, {2106, 2, 7}},
     {time, 1500, 4294967295}, {decimal, <<1:128>>, <<16#FF:8, 0:112, 16#AB:8>>}].

sample(Type, N) ->
    {Type, A, B} = lists:keyfind(Type, 1, types()),
    element(N, {A, B}).

points(Opts) ->
    Base = maps:get(base, Opts, 0),
    Regs = fun(T) -> cell_hal_type_codec:registers(T) end,
    %% Inputs on input registers, outputs on holding registers, each type at the
    %% next free address.
    {Typed, _} = lists:mapfoldl(
                   fun({T, _, _}, A) ->
                           N = name(T),
                           {[#{name => list_to_atom(N ++ "_in"), dir => in, type => T,
                               address => list_to_binary("A1.IN." ++ N), caption => list_to_binary(N ++ " input"),
                               field => {input_register, Base + A}},
                             #{name => list_to_atom(N ++ "_out"), dir => out, type => T,
                               address => list_to_binary("A1.OUT." ++ N), caption => list_to_binary(N ++ " output"),
                               field => {holding_register, Base + A}}],
                            A + Regs(T)}
                   end, 0, types()),
    Bits = [#{name => coil_out, dir => out, type => bool, address => <<"A1.20.05">>,
              caption => <<"Start button light">>, field => {coil, Base}},
            #{name => coil_in, dir => in, type => bool, address => <<"A1.20.06">>,
              caption => <<"Coil read as input">>, field => {coil, Base + 1}},
            #{name => discrete_in, dir => in, type => bool, address => <<"A1.01.06">>,
              caption => <<"Start button">>, field => {discrete_input, Base}},
            #{name => bit_out, dir => out, type => bool, address => <<"A1.20.07">>,
              caption => <<"Bit 3 of a holding register">>,
              field => {holding_register, Base + 200, 3}},
            #{name => bit_in, dir => in, type => bool, address => <<"A1.01.07">>,
              caption => <<"Bit 12 of an input register">>,
              field => {input_register, Base + 200, 12}}],
    All = lists:append(Typed) ++ Bits,
    case maps:find(only, Opts) of
        {ok, Names} -> [P || #{name := N} = P <- All, lists:member(N, Names)];
        error -> All
    end.

name({string, N}) -> "string" ++ integer_to_list(N);
name(T) -> atom_to_list(T).
