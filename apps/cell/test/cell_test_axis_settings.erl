%% @doc A nested settings object for the tests: one axis of a robot.
-module(cell_test_axis_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

-spec name() -> axis.
name() -> axis.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => id, type => {enum, [x, y, z]}, default => x},
     #{name => speed, type => {integer, 1, 100}, default => 10, unit => <<"%">>},
     #{name => low, type => {float, -500, 500}, default => -100.0},
     #{name => high, type => {float, -500, 500}, default => 100.0}].

%% The travel limits must not cross.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{low := L, high := H}) when L =< H -> ok;
check(#{low := L, high := H}) -> {error, [high], {below_low, H, L}}.
