%% An IO group for the tests of a code reader wired through the PLC
%% (cell_hal_code_reader_io): its trigger, done, no-read, result and read counter, and
%% a point of each wrong kind to be refused.
-module(cell_hal_test_reader_io).
-behaviour(cell_hal_group).

-export([points/1]).

points(_Opts) ->
    [#{name => trigger, dir => out, type => bool, address => <<"A2.20.01">>,
       caption => <<"Reader: trigger">>, field => {coil, 0}},
     #{name => done, dir => in, type => bool, address => <<"A2.01.01">>,
       caption => <<"Reader: done">>, field => {discrete_input, 0}},
     #{name => no_read, dir => in, type => bool, address => <<"A2.01.02">>,
       caption => <<"Reader: no read">>, field => {discrete_input, 1}},
     #{name => result, dir => in, type => {string, 20}, address => <<"A2.30.01">>,
       caption => <<"Reader: result">>, field => {input_register, 0}},
     #{name => read_count, dir => in, type => uint16, address => <<"A2.30.02">>,
       caption => <<"Reader: read counter">>, field => {input_register, 10}},
     #{name => lamp, dir => out, type => int16, address => <<"A2.40.01">>,
       caption => <<"Not a trigger">>, field => {holding_register, 0}}].
