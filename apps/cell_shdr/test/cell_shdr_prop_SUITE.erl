%% The PropEr state-machine models of the SHDR adapter's cache and protocol
%% (prop_cell_shdr, prop_cell_shdr_par) against a running cell and adapter, over real
%% TCP, with the scripted HAL: 1,000 sequential runs with client connections killed
%% and closed, and 1,000 parallel runs where changes, snapshots and kills race.
-module(cell_shdr_prop_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([sequential/1, parallel/1]).

all() ->
    [sequential, parallel].

init_per_suite(Config) ->
    Root = filename:join(?config(priv_dir, Config), "root"),
    {ok, _} = cell_shdr_test_hal:start(),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    _ = [application:load(A) || A <- [cell_base, cell, cell_shdr]],
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, #{name => <<"prop">>, tasks => []}),
    ok = application:set_env(cell_shdr, port, 0),
    ok = application:set_env(cell_shdr, hal_module, cell_shdr_test_hal),
    {ok, _} = application:ensure_all_started(cell_shdr),
    _ = sys:get_state(cell_shdr_listener),
    ok = prop_cell_shdr:setup(),
    Config.

end_per_suite(_Config) ->
    _ = application:stop(cell_shdr),
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    cell_shdr_test_hal:stop(),
    ok = application:unset_env(cell, cell_spec),
    ok.

sequential(_Config) ->
    ?assert(prop_cell_shdr:prop_sequential(1000)).

parallel(_Config) ->
    ?assert(prop_cell_shdr_par:prop_parallel(1000)).
