%% @doc A second schema claiming the name `machine': registering it must be refused.
-module(cell_test_machine_twin).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> machine.
name() -> machine.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => speed_override, type => {integer, 1, 200}, default => 100}].
