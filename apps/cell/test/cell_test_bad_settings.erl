%% @doc A settings schema with a mistake in it: its default is out of its own range.
-module(cell_test_bad_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> bad.
name() -> bad.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => speed, type => {integer, 1, 100}, default => 0}].
