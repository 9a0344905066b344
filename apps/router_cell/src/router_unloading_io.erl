%% @doc The IO of an unloading conveyor segment (one instance per lane): the belt, the
%% sensors at the entry (where the upper robot puts modules down) and at the exit, and
%% the SMEMA signals with the next machine.
-module(router_unloading_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {panel_at_entry, in, bool, <<"A5.01.01">>, <<"Modules at the entry">>},
        {panel_at_exit, in, bool, <<"A5.01.02">>, <<"Modules at the exit">>},
        {downstream_ready, in, bool, <<"A5.01.03">>, <<"Next machine: ready to receive">>},
        {belt_run, out, bool, <<"A5.20.01">>, <<"Belt run">>},
        {board_available, out, bool, <<"A5.20.02">>, <<"Next machine: board available">>}]).
