%% Settings files for the router's tests: each object as `Settings/<name>.json' in a
%% root folder, before the cell starts there.
-module(router_test_settings).

-export([write/2]).

write(Root, Objects) ->
    Dir = filename:join(Root, "Settings"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    maps:foreach(fun(Name, Fields) ->
                         ok = file:write_file(filename:join(Dir, atom_to_list(Name) ++ ".json"),
                                              jsx:encode(Fields))
                 end, Objects).
