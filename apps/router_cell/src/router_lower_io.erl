%% @doc The IO of the lower routing robot: the spindle and the Z axis that plunges the
%% router bit into the panel. Its X and Y are NC axes, moved through an interpolation
%% channel (see router_cell's HAL), not through the PLC's IO.
-module(router_lower_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {spindle_at_speed, in, bool, <<"A3.01.01">>, <<"Spindle at speed">>},
        {plunged, in, bool, <<"A3.01.02">>, <<"Router bit at cutting depth">>},
        {spindle_run, out, bool, <<"A3.20.01">>, <<"Spindle run">>},
        {plunge, out, bool, <<"A3.20.02">>, <<"Plunge router bit">>}]).
