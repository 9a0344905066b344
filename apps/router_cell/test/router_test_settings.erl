%% Settings files for the router's tests: each object as `Settings/<name>.json' in a
%% root folder, before the cell starts there; and the cell started on them.
-module(router_test_settings).

-export([write/2, start_cell/3, start_quiet/3, collect_out/2, never_answer/1]).

write(Root, Objects) ->
    cell_testkit:write_settings(Root, Objects).

%% Writes the settings, starts the router cell on them and returns once its PLC is
%% connected and the physics has set every input (or fails after `Timeout' ms).
start_cell(Root, Objects, Timeout) ->
    ok = write(Root, Objects),
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = cell_testkit:await_connection(router_plc, Timeout),
    ok = router_sim:ready(Timeout).

%% The router cell started in `Root' on a quiet simulated machine (one lane, panels
%% always waiting, no faults, a fast physics), `Router' over the short watchdogs,
%% `Others' more settings objects; returns once its PLC is connected and its physics
%% runs.
start_quiet(Root, Router, Others) ->
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    ok = write(Root, Others#{machine => #{},
                             router_sim => #{time_scale => 0.02, arrival_ms => 0,
                                             product_lost_rate => 0.0, jam_rate => 0.0,
                                             no_read_rate => 0.0, magazine_low_s => 0},
                             router => maps:merge(#{hal_poll_ms => 5,
                                                    transfer_timeout_ms => 3000,
                                                    motion_timeout_ms => 3000}, Router)}),
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = cell_testkit:await_connection(router_plc, 60000),
    router_sim:ready(60000).

%% The serials of the next `N' products out of the front lane; an error raised meanwhile
%% fails the case (warnings do not).
collect_out(N, Timeout) ->
    cell_testkit:collect(N, fun(#{type := item_transfer_out, task := unloading_front,
                                  item := S}) -> {true, S};
                               (_) -> false
                            end, fun never_answer/1, Timeout).

never_answer(#{kind := error} = A) -> ct:fail({unexpected_error, A});
never_answer(_) -> ok.
