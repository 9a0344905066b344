%% @doc The IO of a loading conveyor segment (one instance per lane): the belt, the
%% SMEMA signals with the previous machine, the sensors at the entry and at the
%% stopper. The code reader above the stopper has its own group ({@link
%% router_reader_io}).
-module(router_loading_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {upstream_available, in, bool, <<"A1.01.01">>, <<"Previous machine: board available">>},
        {panel_at_entry, in, bool, <<"A1.01.02">>, <<"Panel at the entry">>},
        {panel_at_stop, in, bool, <<"A1.01.03">>, <<"Panel at the stopper">>},
        {magazine_low, in, bool, <<"A1.01.04">>, <<"Previous machine: panel magazine low">>},
        {belt_run, out, bool, <<"A1.20.01">>, <<"Belt run">>},
        {upstream_ready, out, bool, <<"A1.20.02">>, <<"Previous machine: ready to receive">>}]).
