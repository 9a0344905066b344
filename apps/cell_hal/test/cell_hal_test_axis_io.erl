%% An IO group for the tests of a simulated axis publishing its position and velocity
%% into the PLC's image (cell_hal_axis_sim's `publish'), as an NC does into the PLC's
%% axis structure.
-module(cell_hal_test_axis_io).
-behaviour(cell_hal_group).

-export([points/1]).

points(_Opts) ->
    [#{name => x_pos, dir => in, type => lreal, address => <<"NcToPlc.ActPos">>,
       caption => <<"X: actual position">>, unit => <<"mm">>, field => {input_register, 0}},
     #{name => x_vel, dir => in, type => lreal, address => <<"NcToPlc.ActVelo">>,
       caption => <<"X: actual velocity">>, unit => <<"mm/s">>, field => {input_register, 4}},
     %% Where a PLC without an NC of its own is told its axis's position.
     #{name => x_told, dir => out, type => real, address => <<"PlcFromNc.ActPos">>,
       caption => <<"X: actual position, as told">>, unit => <<"mm">>,
       field => {holding_register, 0}}].
