%% @doc The IO of the lower routing robot: the spindle, the Z axis that plunges the
%% router bit into the panel, and the XY motion the robot's controller interpolates.
%% A motion is commanded by writing its target, path length and feed, then a new
%% `command' number; the controller answers with the same number in `done' once there.
-module(router_lower_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {spindle_at_speed, in, bool, <<"A3.01.01">>, <<"Spindle at speed">>},
        {plunged, in, bool, <<"A3.01.02">>, <<"Router bit at cutting depth">>},
        {done, in, int32, <<"A3.30.01">>, <<"Motion done (command number)">>},
        {pos_x, in, lreal, <<"A3.30.02">>, <<"Position X (mm)">>},
        {pos_y, in, lreal, <<"A3.30.03">>, <<"Position Y (mm)">>},
        {spindle_run, out, bool, <<"A3.20.01">>, <<"Spindle run">>},
        {plunge, out, bool, <<"A3.20.02">>, <<"Plunge router bit">>},
        {target_x, out, lreal, <<"A3.40.01">>, <<"Target X (mm)">>},
        {target_y, out, lreal, <<"A3.40.02">>, <<"Target Y (mm)">>},
        {path_mm, out, lreal, <<"A3.40.03">>, <<"Path length (mm)">>},
        {feed, out, lreal, <<"A3.40.04">>, <<"Feed (mm/s)">>},
        {command, out, int32, <<"A3.40.05">>, <<"Motion command number">>}]).
