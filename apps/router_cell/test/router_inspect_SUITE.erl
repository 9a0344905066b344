%% The router as the PLC program of its inspection blocks (seed 004): the unloading
%% segment has the modules at its exit inspected through the block's tags, and the
%% result joins the product's history; a failed inspection marks the product failed;
%% the inspection application crashing during the flow does not stop the cell, whose
%% modules then leave marked failed, not inspected.
%%
%% Every wait is for an event with a deadline.
-module(router_inspect_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([routed_modules_inspected/1, forced_failure/1, inspection_app_crash/1]).

-define(DEADLINE_MS, 60000).
-define(EVENTS, [item_transfer_out, alarm_raised, cell_state]).


all() ->
    [routed_modules_inspected, forced_failure, inspection_app_crash].

init_per_testcase(Case, Config) ->
    %% The router declares its own inspection blocks only where none are configured: an
    %% inspection application an earlier suite of this run left with its blocks goes.
    _ = application:stop(cell_inspect),
    [ok = application:set_env(cell_inspect, K, []) || K <- [blocks, connections]],
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = router_test_settings:start_quiet(Root, #{inspection_timeout_ms => 2000}, #{}),
    %% The demo's camera shows no bad part unless told to.
    ok = cell_settings:put(inspect, #{blocks => [B#{clients => [C#{fail_rate => 0.0} || C <- Cs]}
                                                 || #{clients := Cs} = B
                                                        <- cell_settings:get(inspect, blocks)]},
                           <<"suite">>),
    {ok, _} = application:ensure_all_started(cell_inspect),
    ok = await_camera(router_camera:camera(front)),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell_inspect),
    _ = application:unset_env(cell, shutdown_wait_ms),
    _ = application:unset_env(cell_inspect, blocks),
    cell_testkit:stop(router_cell, [router_plc]).

%% -------------------------------------------------------------------------------------

%% Modules leave inspected: the block's record (PASS, the point, the serial) in the
%% inspection's traceability and in the product's history; the product good.
routed_modules_inspected(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Serials = collect_out(2),
    ok = cell_stats:flush(),
    [begin
         {ok, #{inspections := Ins}} = cell_inspect:traceability(S),
         ?assertMatch([#{result := pass, point := <<"MODULES">>}], Ins),
         {ok, Product} = cell_stats:product(S),
         ?assertEqual([pass], history(Product)),
         ?assertNotMatch(#{failed := true}, Product)
     end || S <- Serials],
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% The camera's next image shows a bad part: that product leaves marked failed, its
%% FAIL in its history; the next one passes.
forced_failure(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = router_camera:fail_next(front),
    ok = cell_controller:start(<<"suite">>),
    [First, Second] = collect_out(2),
    ok = cell_stats:flush(),
    {ok, #{inspections := [#{result := fail}]}} = cell_inspect:traceability(First),
    {ok, #{inspections := [#{result := pass}]}} = cell_inspect:traceability(Second),
    {ok, P1} = cell_stats:product(First),
    ?assertEqual([fail], history(P1)),
    ?assertMatch(#{failed := true}, P1),
    {ok, P2} = cell_stats:product(Second),
    ?assertNotMatch(#{failed := true}, P2),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% The inspection application dies during the flow (its top supervisor killed): the
%% cell runs on; modules not inspected leave marked failed, with a warning, never an
%% error.
inspection_app_crash(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    _ = collect_out(1),
    Sup = whereis(cell_inspect_sup),
    Mon = erlang:monitor(process, Sup),
    exit(Sup, kill),
    receive {'DOWN', Mon, process, Sup, _} -> ok after ?DEADLINE_MS -> ct:fail(sup_alive) end,
    ok = cell_testkit:await_event(fun(#{type := alarm_raised, alarm := A}) ->
                                          maps:get(local_id, A, undefined)
                                              =:= <<"not_inspected">>;
                                     (_) -> false
                                  end, ?DEADLINE_MS),
    [Later] = collect_out(1),
    _ = collect_out(1),
    ok = cell_stats:flush(),
    {ok, P} = cell_stats:product(Later),
    ?assertMatch(#{failed := true}, P),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% -------------------------------------------------------------------------------------

collect_out(N) ->
    router_test_settings:collect_out(N, ?DEADLINE_MS).

never_answer(A) ->
    router_test_settings:never_answer(A).

%% The results of the block's inspections in the product's history.
history(#{events := Events}) ->
    [R || #{event := inspection, detail := #{result := R}} <- Events].

%% The block's view lists the camera among its connected clients.
await_camera(Camera) ->
    ok = cell_inspect:subscribe(),
    {ok, View} = cell_inspect:block(inspect_front),
    await_camera(Camera, View, erlang:monotonic_time(millisecond) + ?DEADLINE_MS).

await_camera(Camera, #{clients := Cs} = View, Deadline) ->
    case lists:member(Camera, Cs) of
        true -> ok;
        false ->
            receive
                {cell_inspect, view, #{id := inspect_front} = V} -> await_camera(Camera, V, Deadline);
                {cell_inspect, view, _} -> await_camera(Camera, View, Deadline)
            after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                ct:fail({camera_not_connected, View})
            end
    end.
