%% An IO group for the device-task IO suite: a conveyor's sensor, motor and counter.
-module(cell_io_test_group).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [map()].
points(_Opts) ->
    [#{name => sensor, dir => in, type => bool, address => <<"A1.01.01">>,
       caption => <<"Panel on segment">>, field => sensor},
     #{name => count, dir => in, type => int16, address => <<"A1.02.00">>,
       caption => <<"Panels counted">>, field => count},
     #{name => motor, dir => out, type => bool, address => <<"A1.20.01">>,
       caption => <<"Belt motor">>, field => motor}].
