%% @doc One beacon rule (an element of the `beacon' list of {@link
%% cell_monitor_settings}): which lamp lights, steady or blinking, while which
%% condition of the cell holds. The conditions are those of {@link cell_beacon}.
-module(cell_monitor_beacon_rule).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

%% @doc Its name (it is only ever nested in the `monitor' object, never a file of its own).
-spec name() -> beacon_rule.
name() -> beacon_rule.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => lamp, type => {enum, cell_beacon:lamps()}, default => red,
       doc => <<"The lamp: red, yellow, green or blue.">>},
     #{name => condition, type => {enum, cell_beacon:conditions()}, default => alarm,
       doc => <<"While what the lamp is lit: alarm, error (the operator is needed), "
                "warning, estop, service_mode, a cell state (off, down, setup), idle "
                "(starved or blocked), starved, blocked, processing (active or "
                "executing), active, executing.">>},
     #{name => mode, type => {enum, [steady, blinking]}, default => steady,
       doc => <<"Steady or blinking; where rules meet on one lamp, blinking wins.">>}].
