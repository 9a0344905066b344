%% @doc A supervisor for tests: runs the child specs it is given, one_for_one.
-module(cell_test_sup).
-behaviour(supervisor).

-export([start_link/1, stop/1, init/1]).

start_link(Specs) ->
    supervisor:start_link(?MODULE, Specs).

stop(Sup) ->
    gen_server:stop(Sup).

init(Specs) ->
    {ok, {#{strategy => one_for_one, intensity => 5, period => 10}, Specs}}.
