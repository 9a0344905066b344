%% @doc A supervisor for tests: runs the child specs it is given, one_for_one.
-module(cell_test_sup).
-behaviour(supervisor).

-export([start_link/1, start_link/2, stop/1, init/1]).

start_link(Specs) ->
    start_link(Specs, #{}).

%% With restart flags of the test's own (a model that kills its children often).
start_link(Specs, Flags) ->
    supervisor:start_link(?MODULE, {Specs, Flags}).

stop(Sup) ->
    gen_server:stop(Sup).

init({Specs, Flags}) ->
    {ok, {maps:merge(#{strategy => one_for_one, intensity => 5, period => 10}, Flags), Specs}}.
