%% What the router benchmark and the soak run share: the default cell started in this
%% node on a fresh root folder with given settings, stopped again, and the products
%% the unloading segments hand out, waited for as events.
-module(router_bench_cell).

-export([start/1, stop/0, await_out/2, settings/1, write_settings/2, panels_per_hour/2]).

%% The applications of the release, in its order.
-define(APPS, [router_cell, cell_shdr, cell_web, cell_inspect]).

%% @doc Starts the router cell (and, with `with_panel', the SHDR adapter, the web
%% panel on ports of their own and the inspection, as the release runs them) on the
%% root folder `CELLRT_ROOT' names, emptied first, with these settings objects written
%% to `Settings/'; returns when its PLC's points
%% have been read. With `plc => real' the settings put the cell in real mode (its PLC
%% elsewhere, a virtual PLC say): no physics runs here, and the connection up is the
%% PLC's points read.
-spec start(#{settings := #{atom() => map()}, with_panel => boolean(),
              plc => sim | real}) -> ok.
start(#{settings := Objects} = Opts) ->
    quiet(),
    Root = os:getenv("CELLRT_ROOT"),
    ok = write_settings(Root, Objects),
    _ = [application:load(A) || A <- [cell_base, cell | ?APPS]],
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_module, router_cell),
    ok = application:set_env(cell_web, port, 0),
    ok = application:set_env(cell_shdr, port, 0),
    Apps = case maps:get(with_panel, Opts, false) of
               true -> ?APPS;
               false -> [router_cell]
           end,
    _ = [{ok, _} = application:ensure_all_started(A) || A <- Apps],
    case cell_hal:subscribe_connection(router_plc) of
        {ok, up} -> ok;
        {ok, down} -> receive {cell_hal_conn, router_plc, up} -> ok end
    end,
    %% The tasks find the machine as it is at their first Start.
    case maps:get(plc, Opts, sim) of
        sim -> ok = router_sim:ready(60000);
        real -> ok
    end.

%% @doc Empties the root folder `Root' and writes these settings objects to its
%% `Settings/', one JSON file each.
-spec write_settings(file:filename(), #{atom() => map()}) -> ok.
write_settings(Root, Objects) ->
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    Dir = filename:join(Root, "Settings"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    maps:foreach(fun(Name, Fields) ->
                         ok = file:write_file(filename:join(Dir, atom_to_list(Name) ++ ".json"),
                                              jsx:encode(Fields))
                 end, Objects).

%% @doc Starts the cell as {@link start/1} does, lets it pass `Warmup' panels, then
%% returns the panels per hour of wall-clock time of the next `Panels' (from the last
%% of the warm-up out to the last of them out); the cell stopped again.
-spec panels_per_hour(map(), #{warmup := pos_integer(), panels := pos_integer(),
                               timeout := timeout()}) -> float().
panels_per_hour(Opts, #{warmup := Warmup, panels := Panels, timeout := Timeout}) ->
    ok = start(Opts),
    try
        ok = cell_events:subscribe([item_transfer_out]),
        ok = cell_controller:start(<<"bench">>),
        [T0 | _] = lists:reverse(await_out(Warmup, Timeout)),
        Times = await_out(Panels, Timeout),
        ok = cell_controller:stop(<<"bench">>),
        Panels / ((lists:last(Times) - T0) / 3.6e9)
    after
        stop()
    end.

%% @doc Stops the cell, its physics and the database, as the node would.
-spec stop() -> ok.
stop() ->
    _ = [application:stop(A) || A <- lists:reverse(?APPS) ++ [cell, mnesia]],
    %% A new node would have a new simulated PLC.
    cell_hal_sim_sup:stop_device(router_plc).

%% @doc Waits until `N' products have left the cell (the caller subscribed to
%% `item_transfer_out'); returns the time each left, in µs of the monotonic clock.
-spec await_out(non_neg_integer(), timeout()) -> [integer()].
await_out(N, Timeout) ->
    await_out(N, Timeout, []).

await_out(0, _Timeout, Acc) ->
    lists:reverse(Acc);
await_out(N, Timeout, Acc) ->
    receive
        {cell_event, #{type := item_transfer_out, task := T}}
          when T =:= unloading_front; T =:= unloading_rear ->
            await_out(N - 1, Timeout, [erlang:monotonic_time(microsecond) | Acc]);
        {cell_event, _} ->
            await_out(N, Timeout, Acc)
    after Timeout ->
        erlang:error({products_stopped, N, cell_controller:tasks(), cell_alarms:list()})
    end.

%% @doc The settings of a machine that passes panels as fast as it can: a panel always
%% waiting upstream, no faults, physical delays at `Scale' of the real machine's, its
%% axes at their full speed (a speed override of 100 %). The inspection at the
%% unloading exit is switched off: these cells run without the inspection application
%% that answers its block (the block has a bench of its own), and an unanswered block
%% would hold each panel for the inspection's timeout.
-spec settings(#{scale := float(), dual_lane := boolean()}) -> #{atom() => map()}.
settings(#{scale := Scale, dual_lane := Dual}) ->
    #{machine => #{dual_lane => Dual, speed_override => 100},
      router => #{inspection => false},
      router_sim => #{time_scale => Scale, arrival_ms => 0, product_lost_rate => 0.0,
                      jam_rate => 0.0, no_read_rate => 0.0, magazine_low_s => 0}}.

%% Figures and tables, not the cell's log.
quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).
