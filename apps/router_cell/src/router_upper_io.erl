%% @doc The IO of the upper manipulator robot: the gripper and its sensors, where the
%% machine sees the gripper (an in-position signal per taught position: home, the
%% module nest and the unloading segment of each lane), and where its NC axes stand.
%% The robot's X and Y are NC axes moved through an interpolation channel (see
%% router_cell's HAL), not through the PLC's IO; as TwinCAT's NC gives the PLC its
%% axes' actual data, the NC writes their actual positions into the PLC, whose program
%% (the physics, in simulation) tells from them which position the gripper is at.
-module(router_upper_io).
-behaviour(cell_hal_group).

-export([points/1, at/2]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {gripper_closed, in, bool, <<"A4.01.01">>, <<"Gripper closed">>},
        {product_present, in, bool, <<"A4.01.02">>, <<"Product in gripper">>},
        {at_home, in, bool, <<"A4.02.01">>, <<"In position: home (scrap bin)">>},
        {at_nest_front, in, bool, <<"A4.02.02">>, <<"In position: front module nest">>},
        {at_nest_rear, in, bool, <<"A4.02.03">>, <<"In position: rear module nest">>},
        {at_unloading_front, in, bool, <<"A4.02.04">>,
         <<"In position: front unloading segment">>},
        {at_unloading_rear, in, bool, <<"A4.02.05">>,
         <<"In position: rear unloading segment">>},
        {x_actual, out, real, <<"A4.40.01">>, <<"X axis actual position (from the NC), mm">>},
        {y_actual, out, real, <<"A4.40.02">>, <<"Y axis actual position (from the NC), mm">>},
        {gripper_close, out, bool, <<"A4.20.01">>, <<"Close gripper">>}]).

%% @doc The in-position signal of a taught position.
-spec at(home | nest | unloading, front | rear) -> atom().
at(home, _) -> at_home;
at(nest, front) -> at_nest_front;
at(nest, rear) -> at_nest_rear;
at(unloading, front) -> at_unloading_front;
at(unloading, rear) -> at_unloading_rear.
