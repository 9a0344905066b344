%% Settings files for the router's tests: each object as `Settings/<name>.json' in a
%% root folder, before the cell starts there.
-module(router_test_settings).

-export([write/2]).

write(Root, Objects) ->
    cell_testkit:write_settings(Root, Objects).
