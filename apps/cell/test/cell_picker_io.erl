%% The picker's IO (seed 001's example): two cylinders with a valve coil and an end
%% sensor each way, the magnet, and the sensor at the end of the feeding conveyor.
%% Coils and discrete inputs from `base', so the same module serves a Modbus PLC and
%% the simulation.
-module(cell_picker_io).
-behaviour(cell_hal_group).

-export([points/1]).

points(Opts) ->
    B = maps:get(base, Opts, 0),
    Out = fun(N, Name, Caption) ->
                  #{name => Name, dir => out, type => bool, caption => Caption,
                    address => iolist_to_binary(io_lib:format("A2.20.~2..0b", [N])),
                    field => {coil, B + N}}
          end,
    In = fun(N, Name, Caption) ->
                 #{name => Name, dir => in, type => bool, caption => Caption,
                   address => iolist_to_binary(io_lib:format("A2.01.~2..0b", [N])),
                   field => {discrete_input, B + N}}
         end,
    [Out(0, lift_up, <<"Vertical lift: up">>),
     Out(1, lift_down, <<"Vertical lift: down">>),
     Out(2, move_left, <<"Horizontal move: left">>),
     Out(3, move_right, <<"Horizontal move: right">>),
     Out(4, magnet, <<"Magnet on (MagnetEin)">>),
     In(0, lift_is_up, <<"Vertical lift is up">>),
     In(1, lift_is_down, <<"Vertical lift is down">>),
     In(2, is_left, <<"Horizontal move is left">>),
     In(3, is_right, <<"Horizontal move is right">>),
     In(4, part_is_at_end, <<"Part at the end of the conveyor (PartIsAtEnd)">>)].
