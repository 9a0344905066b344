%% @doc A settings object for the tests with a secret field (a key), beside a plain one.
-module(cell_test_secret_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> vault.
name() -> vault.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => label, type => {string, 32}, default => <<"door">>},
     #{name => key, type => {string, 64}, default => <<>>, secret => true}].
