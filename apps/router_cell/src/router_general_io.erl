%% @doc The router's general IO, the points the cell's monitor watches and drives
%% ({@link cell_monitor}): the emergency-stop circuit, the service key switch, the two
%% safety doors and their lock, the compressed air, and the beacon's lamps.
%%
%% The doors' lock is released by `door_unlock' (the lock holds while it is off);
%% `doors_locked' is the safety relay's answer: both doors closed and the lock held.
%% `air_pressure' is the supply pressure in bar, `air_ok' the pressure switch.
-module(router_general_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {estop_ok, in, bool, <<"A0.01.01">>, <<"Emergency-stop circuit closed">>},
        {service_key, in, bool, <<"A0.01.02">>, <<"Service key switch in service">>},
        {door_loading_closed, in, bool, <<"A0.01.03">>, <<"Safety door loading side closed">>},
        {door_unloading_closed, in, bool, <<"A0.01.04">>,
         <<"Safety door unloading side closed">>},
        {doors_locked, in, bool, <<"A0.01.05">>, <<"Safety doors closed and locked">>},
        {air_ok, in, bool, <<"A0.01.06">>, <<"Air pressure switch OK">>},
        {air_pressure, in, lreal, <<"A0.30.01">>, <<"Air pressure (bar)">>},
        {door_unlock, out, bool, <<"A0.20.01">>, <<"Release the safety doors' lock">>},
        {beacon_red, out, bool, <<"A0.20.02">>, <<"Beacon red">>},
        {beacon_yellow, out, bool, <<"A0.20.03">>, <<"Beacon yellow">>},
        {beacon_green, out, bool, <<"A0.20.04">>, <<"Beacon green">>},
        {beacon_blue, out, bool, <<"A0.20.05">>, <<"Beacon blue">>}]).
