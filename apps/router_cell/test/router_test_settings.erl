%% Settings files for the router's tests: each object as `Settings/<name>.json' in a
%% root folder, before the cell starts there; and the cell started on them.
-module(router_test_settings).

-export([write/2, start_cell/3]).

write(Root, Objects) ->
    cell_testkit:write_settings(Root, Objects).

%% Writes the settings, starts the router cell on them and returns once its PLC is
%% connected and the physics has set every input (or fails after `Timeout' ms).
start_cell(Root, Objects, Timeout) ->
    ok = write(Root, Objects),
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = cell_testkit:await_connection(router_plc, Timeout),
    ok = router_sim:ready(Timeout).
