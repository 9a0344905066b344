%% @doc The IO of a work segment (one instance per lane): the belt that brings a panel
%% into the routing fixture and takes the frame out, and the sensors of the fixture:
%% panel in position, and the nest that holds the modules once routed. The fixture's
%% clamps have their own group ({@link router_clamps_io}), driven by their unit.
-module(router_work_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {panel_in_position, in, bool, <<"A2.01.01">>, <<"Panel in position">>},
        {nest_empty, in, bool, <<"A2.01.03">>, <<"Module nest empty">>},
        {belt_run, out, bool, <<"A2.20.01">>, <<"Belt run">>}]).
