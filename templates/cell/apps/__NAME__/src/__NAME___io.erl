%% @doc The IO group of the line: every point of the infeed conveyor and of the press,
%% where it is in the PLC's Modbus image, its wiring label and its caption: the words
%% it is shown with, beside its value, by cellrt's diagnostics in the node's shell
%% (`cell_diag' io, see the README). The same module runs on the simulated PLC (which
%% keeps each point by its name and ignores the field) and on the real one over Modbus
%% TCP.
%%
%% A point: `field' is `{discrete_input, A}' (a bool input), `{coil, A}' (a bool
%% output), `{input_register, A}' (a number read) or `{holding_register, A}' (a number
%% written). The group instance's `base' option shifts every address, so a second line
%% is a second instance of this module.
-module(__NAME___io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    B = maps:get(base, Opts, 0),
    [in(part_at_infeed, <<"X1.01">>, "Infeed: part at the stopper", {discrete_input, B}),
     in(part_in_press, <<"X2.01">>, "Press: part in the die", {discrete_input, B + 1}),
     in(ram_up, <<"X2.02">>, "Press: ram at the top", {discrete_input, B + 2}),
     in(ram_down, <<"X2.03">>, "Press: ram at the bottom", {discrete_input, B + 3}),
     #{name => force_kn, dir => in, type => int16, address => <<"IW2.10">>,
       caption => <<"Press: force at the bottom (kN)">>, field => {input_register, B}},
     out(infeed_belt, <<"Y1.01">>, "Infeed: belt run", {coil, B}),
     out(press_belt, <<"Y2.01">>, "Press: belt run", {coil, B + 1}),
     out(ram_lower, <<"Y2.02">>, "Press: lower the ram", {coil, B + 2}),
     #{name => stroke_depth, dir => out, type => int16, address => <<"QW2.10">>,
       caption => <<"Press: stroke depth (0.1 mm)">>, field => {holding_register, B}}].

in(Name, Address, Caption, Field) ->
    #{name => Name, dir => in, type => bool, address => Address,
      caption => list_to_binary(Caption), field => Field}.

out(Name, Address, Caption, Field) ->
    (in(Name, Address, Caption, Field))#{dir => out}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

points_test() ->
    Points = points(#{base => 100}),
    ?assertEqual(ok, cell_hal_group:check_points(Points)),
    %% No two points of a kind share an address.
    Fields = [F || #{field := F} <- Points],
    ?assertEqual(length(Fields), length(lists:usort(Fields))),
    ?assert(lists:member({coil, 102}, Fields)).
-endif.
