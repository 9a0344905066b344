%% @doc The IO of the upper manipulator robot: taught positions (home, the module nest
%% of each lane, the unloading conveyor of each lane), the gripper and its sensors. A
%% move is commanded by writing the position, then a new `command' number; the robot
%% answers with the same number in `done' once there.
-module(router_upper_io).
-behaviour(cell_hal_group).

-export([points/1, position/2]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {done, in, int32, <<"A4.30.01">>, <<"Move done (command number)">>},
        {gripper_closed, in, bool, <<"A4.01.01">>, <<"Gripper closed">>},
        {product_present, in, bool, <<"A4.01.02">>, <<"Product in gripper">>},
        {target, out, int16, <<"A4.40.01">>, <<"Position: 0 home, 1/2 nest, 3/4 unloading">>},
        {command, out, int32, <<"A4.40.02">>, <<"Move command number">>},
        {gripper_close, out, bool, <<"A4.20.01">>, <<"Close gripper">>}]).

%% @doc The number of a taught position.
-spec position(home | nest | unloading, front | rear) -> 0..4.
position(home, _) -> 0;
position(nest, front) -> 1;
position(nest, rear) -> 2;
position(unloading, front) -> 3;
position(unloading, rear) -> 4.
