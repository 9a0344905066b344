%% The operator's hand on the simulated machine over real HTTP on 127.0.0.1
%% (`/api/machine/actions'): who may, bad requests refused, and the default cell
%% reacting, with its physics in this VM (simulation mode) and in a virtual PLC's OS
%% process (scripts/vplc with a node name), which the cell reaches by its node.
-module(cell_web_machine_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-compile([export_all, nowarn_export_all]).

-define(WAIT_MS, 60000).
-define(EVENTS, [estop, service_mode, alarm_raised, alarm_cleared]).

all() ->
    [{group, in_vm}, {group, vplc}].

groups() ->
    [{in_vm, [sequence], [roles_refused, lists_the_machine_actions, bad_actions_refused,
                          estop_and_key_from_the_panel, drive_fault_from_the_panel,
                          from_the_shell]},
     {vplc, [sequence], [actions_reach_the_virtual_plc]}].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    _ = [application:stop(A) || A <- [cell_web, router_cell, cell, cell_hal, mnesia, cell_base]],
    Config.

end_per_suite(_Config) ->
    ok.

%% The default cell with its physics in this VM.
init_per_group(in_vm, Config) ->
    Root = filename:join(?config(priv_dir, Config), "cell_web_machine_vm"),
    ok = cell_testkit:write_settings(Root, settings(#{simulation_mode => true}, #{})),
    start_cell(Root),
    ok = router_sim:ready(?WAIT_MS),
    [{root, Root} | Config];
%% The default cell in real mode over Modbus TCP against a virtual PLC in an OS
%% process of its own: both started by the case (the port of the OS process belongs to
%% the case's process).
init_per_group(vplc, Config) ->
    Config.

end_per_group(in_vm, _Config) ->
    _ = application:stop(cell_web),
    cell_testkit:stop(router_cell, [router_plc]);
end_per_group(vplc, _Config) ->
    ok.

%% The virtual PLC's case starts (and stops) its cell itself.
init_per_testcase(actions_reach_the_virtual_plc, Config) ->
    Config;
init_per_testcase(_Case, Config) ->
    ok = cell_events:subscribe(?EVENTS),
    [{port, cell_web:port()} | Config].

end_per_testcase(actions_reach_the_virtual_plc, _Config) ->
    ok;
end_per_testcase(_Case, _Config) ->
    ok = cell_events:unsubscribe(),
    ok.

%% A fast machine that makes no mistakes of its own, no panels arriving: what
%% happens is the operator's doing.
sim() ->
    #{time_scale => 0.02, arrival_ms => 0, upstream_capacity => 0, product_lost_rate => 0.0,
      jam_rate => 0.0, magazine_low_s => 0}.

settings(Machine, Router) ->
    #{machine => Machine, router_sim => sim(),
      router => Router#{hal_poll_ms => 10},
      monitor => #{drive_reset_pulse_ms => 20, drive_reset_wait_ms => 100}}.

start_cell(Root) ->
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = cell_testkit:await_connection(router_plc, ?WAIT_MS).

%% -------------------------------------------------------------------------------------
%% Helpers

anon(Config) -> cell_web_client:new(?config(port, Config)).

as(Role, Config) ->
    Name = atom_to_list(Role),
    {ok, C} = cell_web_client:login(anon(Config), Name, Name),
    C.

act(C, Action, Choice) ->
    cell_web_client:req(C, post, "/api/machine/actions", #{action => Action, choice => Choice}).

assert_error(Status, Code, {Status, #{<<"error">> := Code, <<"message">> := M}, _}) ->
    ?assert(is_binary(M) andalso M =/= <<>>);
assert_error(Status, Code, Other) ->
    ct:fail("expected ~p ~s, got ~p", [Status, Code, Other]).

await(Match) ->
    cell_testkit:await_event(Match, ?WAIT_MS).

estop(Active) ->
    await(fun(#{type := estop, active := A}) -> A =:= Active; (_) -> false end).

service_mode(Active) ->
    await(fun(#{type := service_mode, active := A}) -> A =:= Active; (_) -> false end).

%% -------------------------------------------------------------------------------------

%% Nobody but a service user (or an admin) sees or carries out the machine's actions;
%% a refused action leaves the machine as it was.
roles_refused(Config) ->
    assert_error(401, <<"login_required">>, cell_web_client:req(anon(Config), get, "/api/machine/actions")),
    Op = as(operator, Config),
    assert_error(403, <<"forbidden">>, cell_web_client:req(Op, get, "/api/machine/actions")),
    assert_error(403, <<"forbidden">>, act(Op, <<"estop">>, <<"press">>)),
    ?assertMatch(#{estop := false}, cell_controller:flags()),
    ?assertEqual({ok, true}, cell_hal:read(general_io, estop_ok)),
    {200, _, _} = cell_web_client:req(as(admin, Config), get, "/api/machine/actions"),
    %% The refusal is in the audit trail.
    Audit = audit(Config),
    ?assert(lists:any(fun(#{<<"who">> := <<"operator">>, <<"outcome">> := <<"403">>,
                            <<"target">> := <<"/api/machine/actions">>}) -> true;
                         (_) -> false
                      end, Audit)).

%% The router's actions, where its physics runs.
lists_the_machine_actions(Config) ->
    {200, #{<<"where">> := Where, <<"actions">> := Actions}, _} =
        cell_web_client:req(as(service, Config), get, "/api/machine/actions"),
    ?assertEqual(#{<<"kind">> => <<"local">>}, Where),
    Ids = [I || #{<<"id">> := I} <- Actions],
    ?assertEqual([<<"estop">>, <<"service_key">>, <<"door_loading">>, <<"door_unloading">>,
                  <<"air">>, <<"drive_conveyor_front">>, <<"drive_lower">>, <<"drive_upper">>],
                 Ids),
    [Estop | _] = Actions,
    ?assertMatch(#{<<"caption">> := <<"Emergency stop">>, <<"group">> := <<"Safety">>,
                   <<"choices">> := [#{<<"id">> := <<"press">>, <<"caption">> := <<"Press">>},
                                     #{<<"id">> := <<"release">>}]}, Estop),
    %% What carries an action out stays in the cell.
    ?assertNot(lists:any(fun(#{<<"choices">> := Cs}) ->
                                 lists:any(fun(C) -> maps:is_key(<<"run">>, C) end, Cs)
                         end, Actions)).

%% Unknown actions and choices, and malformed bodies, are refused with a 4xx and
%% change nothing on the machine.
bad_actions_refused(Config) ->
    Svc = as(service, Config),
    assert_error(404, <<"not_found">>, act(Svc, <<"self_destruct">>, <<"now">>)),
    assert_error(400, <<"bad_request">>, act(Svc, <<"estop">>, <<"smash">>)),
    assert_error(400, <<"bad_request">>, act(Svc, <<"estop">>, 1)),
    assert_error(400, <<"bad_request">>,
                 cell_web_client:req(Svc, post, "/api/machine/actions", #{action => <<"estop">>})),
    %% One lane: no rear conveyors.
    assert_error(404, <<"not_found">>, act(Svc, <<"drive_conveyor_rear">>, <<"fault">>)),
    assert_error(405, <<"method_not_allowed">>,
                 cell_web_client:req(Svc, delete, "/api/machine/actions")),
    ?assertMatch(#{estop := false, service_mode := false}, cell_controller:flags()),
    ?assertEqual({ok, true}, cell_hal:read(general_io, estop_ok)).

%% A service user presses the emergency stop on the panel: the cell's emergency stop
%% follows (seed 000 §2.4); released, it ends. The key switch turns service mode on
%% and off. Each action is in the audit trail in the operator's words.
estop_and_key_from_the_panel(Config) ->
    Svc = as(service, Config),
    {200, #{<<"done">> := <<"Emergency stop: Press">>}, _} = act(Svc, <<"estop">>, <<"press">>),
    estop(true),
    ?assertMatch(#{estop := true}, cell_controller:flags()),
    ?assertEqual({error, estop_active}, cell_controller:start(<<"suite">>)),
    {200, _, _} = act(Svc, <<"estop">>, <<"release">>),
    estop(false),
    {200, _, _} = act(Svc, <<"service_key">>, <<"service">>),
    service_mode(true),
    {200, _, _} = act(Svc, <<"service_key">>, <<"production">>),
    service_mode(false),
    Details = [D || #{<<"who">> := <<"service">>, <<"target">> := <<"/api/machine/actions">>,
                      <<"outcome">> := <<"200">>, <<"detail">> := D} <- audit(Config)],
    [?assert(lists:member(D, Details), D)
     || D <- [<<"Emergency stop: Press">>, <<"Emergency stop: Release">>,
              <<"Service key switch: Service">>, <<"Service key switch: Production">>]].

%% A door opened and the air dropped are warnings; a drive that no reset clears is
%% reset three times by the monitor, then handed to the operator (seed 000 §2.4).
drive_fault_from_the_panel(Config) ->
    Svc = as(service, Config),
    {200, _, _} = act(Svc, <<"door_loading">>, <<"open">>),
    await_alarm(raised, warning, <<"cell:door">>),
    {200, _, _} = act(Svc, <<"door_loading">>, <<"close">>),
    await_alarm(cleared, warning, <<"cell:door">>),
    {200, _, _} = act(Svc, <<"air">>, <<"drop">>),
    await_alarm(raised, warning, <<"cell:air">>),
    {200, _, _} = act(Svc, <<"air">>, <<"restore">>),
    await_alarm(cleared, warning, <<"cell:air">>),
    %% One reset clears it.
    {200, _, _} = act(Svc, <<"drive_lower">>, <<"fault">>),
    await_alarm(raised, warning, <<"cell:drive.lower">>),
    await_alarm(cleared, warning, <<"cell:drive.lower">>),
    %% No reset does: the operator is asked after three.
    {200, _, _} = act(Svc, <<"drive_upper">>, <<"fault_stuck">>),
    await_alarm(raised, error, <<"cell:drive.upper.failed">>),
    ?assertMatch(#{upper := #{error := true, attempt := 3}}, maps:get(drives, cell_monitor:info())).

await_alarm(How, Kind, Id) ->
    Type = case How of raised -> alarm_raised; cleared -> alarm_cleared end,
    await(fun(#{type := T, alarm := #{id := I, kind := K}}) ->
                  T =:= Type andalso I =:= Id andalso K =:= Kind;
             (_) -> false
          end).

%% The same actions from the remote shell, by their names.
from_the_shell(_Config) ->
    ok = cell_diag:machine(),
    ok = cell_diag:machine(service_key, service),
    service_mode(true),
    ok = cell_diag:machine(<<"service_key">>, <<"production">>),
    service_mode(false),
    ?assertEqual({error, {unknown_action, <<"nope">>}}, cell_diag:machine(nope, x)),
    ?assertEqual({error, {unknown_choice, <<"air">>, <<"x">>}}, cell_diag:machine(air, x)).

%% The machine's physics in the virtual PLC's own OS process: the panel's action
%% reaches it, and the cell reacts to what the PLC then shows over Modbus TCP. Once the
%% virtual PLC is gone, an action is refused at once, saying so.
actions_reach_the_virtual_plc(Config0) ->
    Priv = ?config(priv_dir, Config0),
    VRoot = filename:join(Priv, "cell_web_machine_vplc"),
    Root = filename:join(Priv, "cell_web_machine_real"),
    VName = "machine_actions_vplc_" ++ os:getpid() ++ "@localhost",
    VNode = list_to_atom(VName),
    ok = cell_testkit:write_settings(VRoot, #{router_sim => sim(), router => #{hal_poll_ms => 10}}),
    {Vplc, Port} = start_vplc(VRoot, VName),
    %% This node reaches the virtual PLC by the distribution (whose epmd the virtual
    %% PLC's node started).
    Dist = case node() of
               nonode@nohost ->
                   {ok, _} = net_kernel:start(
                               list_to_atom("machine_actions_ct_" ++ os:getpid() ++ "@localhost"),
                               #{name_domain => shortnames}),
                   true;
               _ ->
                   false
           end,
    try
        true = os:putenv("CELLRT_VPLC_NODE", VName),
        true = os:putenv("CELLRT_VPLC_COOKIE", filename:join([VRoot, "Distribution", "cookie"])),
        ok = cell_testkit:write_settings(
               Root, settings(#{simulation_mode => false},
                              #{plc_host => <<"127.0.0.1">>, plc_port => Port})),
        start_cell(Root),
        ok = cell_events:subscribe(?EVENTS),
        Config = [{port, cell_web:port()} | Config0],
        Svc = as(service, Config),
        {200, #{<<"where">> := Where, <<"actions">> := [_ | _]}, _} =
            cell_web_client:req(Svc, get, "/api/machine/actions"),
        ?assertEqual(#{<<"kind">> => <<"vplc">>, <<"node">> => atom_to_binary(VNode, utf8)},
                     Where),
        %% Nothing of the physics runs in this VM.
        ?assertEqual(undefined, whereis(router_sim)),
        {200, _, _} = act(Svc, <<"estop">>, <<"press">>),
        estop(true),
        ?assertMatch(#{estop := true}, cell_controller:flags()),
        {200, _, _} = act(Svc, <<"estop">>, <<"release">>),
        estop(false),
        assert_error(400, <<"bad_request">>, act(Svc, <<"estop">>, <<"smash">>)),
        %% The virtual PLC gone: refused at once, saying so.
        ok = net_kernel:monitor_nodes(true),
        kill_vplc(Vplc),
        receive {nodedown, VNode} -> ok after ?WAIT_MS -> ct:fail(vplc_node_not_down) end,
        T0 = erlang:monotonic_time(millisecond),
        assert_error(503, <<"unreachable">>, act(Svc, <<"estop">>, <<"press">>)),
        ?assert(erlang:monotonic_time(millisecond) - T0 < 10000),
        %% A real PLC (no virtual PLC named): nothing to act on.
        true = os:unsetenv("CELLRT_VPLC_NODE"),
        {200, #{<<"where">> := #{<<"kind">> := <<"none">>}, <<"actions">> := []}, _} =
            cell_web_client:req(Svc, get, "/api/machine/actions"),
        assert_error(409, <<"no_simulation">>, act(Svc, <<"estop">>, <<"press">>))
    after
        _ = application:stop(cell_web),
        cell_testkit:stop(router_cell, []),
        kill_vplc(Vplc),
        true = os:unsetenv("CELLRT_VPLC_NODE"),
        true = os:unsetenv("CELLRT_VPLC_COOKIE"),
        _ = Dist andalso net_kernel:stop()
    end.

audit(Config) ->
    {200, #{<<"entries">> := Es}, _} =
        cell_web_client:req(as(admin, Config), get, "/api/audit?limit=1000"),
    Es.

%% -------------------------------------------------------------------------------------
%% The virtual PLC's OS process

%% scripts/vplc for the router on a port the OS picks, with a node name; returns once
%% it listens: the port of its OS process, the port it listens on.
start_vplc(Root, Name) ->
    Top = os:getenv("CELLRT_TOP"),
    Script = filename:join([Top, "scripts", "vplc"]),
    %% The apps as this run built them.
    Build = filename:dirname(filename:dirname(code:lib_dir(cell_vplc))),
    P = open_port({spawn_executable, Script},
                  [{args, ["--port", "0", "--root", Root, "--node", Name]},
                   {env, [{"CELLRT_BUILD", Build}]},
                   {line, 4096}, exit_status, stderr_to_stdout, binary]),
    {P, cell_vplc_os:await_listening(P, erlang:monotonic_time(millisecond) + ?WAIT_MS)}.

%% Kills the virtual PLC's OS process outright, and waits for its end.
kill_vplc(P) ->
    cell_vplc_os:kill(P, ?WAIT_MS).
