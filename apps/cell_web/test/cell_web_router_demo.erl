%% The default cell (the simulated router, its physics in this VM) with the operator
%% panel, for the browser tests of the machine's actions: started by a browser test
%% (test/browser/demo_cell.mjs, `main: "cell_web_router_demo:main()"'), driven through
%% its standard input one command a line, each answered `OK ...' (or `ERR ...') once
%% the cell has taken it.
%%
%% Commands: `start' (the operator's Start) · `stop' · `sync' · `quit'.
-module(cell_web_router_demo).

-export([main/0]).

-define(WAIT_MS, 60000).

-spec main() -> no_return().
main() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false),
    Root = os:getenv("CELLRT_ROOT"),
    %% A fast machine without mistakes of its own, and no panels: what happens is the
    %% user's doing.
    ok = cell_testkit:write_settings(
           Root, #{machine => #{simulation_mode => true, cell_name => <<"Demo router">>},
                   router_sim => #{time_scale => 0.05, arrival_ms => 0, upstream_capacity => 0,
                                   product_lost_rate => 0.0, jam_rate => 0.0,
                                   magazine_low_s => 0},
                   router => #{hal_poll_ms => 10}}),
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = cell_testkit:await_connection(router_plc, ?WAIT_MS),
    ok = router_sim:ready(?WAIT_MS),
    io:format("PORT ~p~n", [cell_web:port()]),
    loop().

loop() ->
    case io:get_line("") of
        eof ->
            erlang:halt(0);
        Line when is_list(Line) ->
            Text = string:trim(Line),
            Reply = case Text of
                        "quit" -> io:format("OK quit~n"), erlang:halt(0);
                        "start" -> cell_controller:start(<<"demo">>);
                        "stop" -> cell_controller:stop(<<"demo">>);
                        "sync" -> ok;
                        _ -> {error, unknown_command}
                    end,
            ok = cell_controller:sync(),
            case Reply of
                ok -> io:format("OK ~s~n", [Text]);
                {error, Why} -> io:format("ERR ~0tp ~s~n", [Why, Text])
            end,
            loop()
    end.
