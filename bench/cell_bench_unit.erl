%% The unit the unit benchmarks run: its Automatic sequence is a cell_bench_seq chosen
%% by the args (`bench' => steps | sensor, and that sequence's own args), and its one
%% IO point is the sensor input of the group module below.
-module(cell_bench_unit).
-behaviour(cell_unit).
-behaviour(cell_hal_group).

-export([unit/1, points/1]).

-spec unit(map()) -> map().
unit(Args) ->
    #{sequences => #{automatic => {cell_bench_seq, Args}}}.

-spec points(map()) -> [cell_hal_group:point_def()].
points(_Opts) ->
    [#{name => sensor, dir => in, type => bool, address => <<"A1.01.00">>,
       caption => <<"Sensor">>, field => {discrete_input, 0}}].
