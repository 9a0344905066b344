%% The HAL started once for a PropEr model's runs: a root folder of the model's own
%% under /tmp (made empty first), the console quiet but for critical lines, and the
%% model's named table with its run counter. The models start a connection of their
%% own for each run.
-module(cell_hal_prop_env).

-export([start/2, stop/2]).

-spec start(string(), atom()) -> {file:filename(), [atom()]}.
start(Name, Tab) ->
    Root = filename:join(["/tmp", Name, os:getpid()]),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, Root),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    _ = ets:new(Tab, [named_table, public]),
    true = ets:insert(Tab, {run, 0}),
    {Root, Apps}.

-spec stop({file:filename(), [atom()]}, atom()) -> ok.
stop({Root, Apps}, Tab) ->
    ets:delete(Tab),
    [application:stop(A) || A <- lists:reverse(Apps)],
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    ok.
