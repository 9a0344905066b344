%% @doc The settings object `oee' (`Settings/oee.json'): what the statistics page
%% measures the cell's performance against. Read when the page asks for its charts,
%% so a change shows at once.
-module(cell_web_oee_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, ideal_cycle_ms/0]).

-spec name() -> oee.
name() -> oee.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => ideal_cycle_s, type => {float, 0.01, 86400.0}, default => 60.0, unit => <<"s">>,
       doc => <<"The shortest time between two products leaving the cell when nothing "
                "holds it up: the performance of the OEE is this time times the products "
                "out, divided by the run time.">>}].

%% @doc The ideal cycle time in milliseconds.
-spec ideal_cycle_ms() -> float().
ideal_cycle_ms() ->
    maps:get(ideal_cycle_s, cell_web_settings:current(?MODULE)) * 1000.
