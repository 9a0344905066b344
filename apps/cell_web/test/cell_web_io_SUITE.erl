%% The panel's picture of the machine, IO view and forcing over real HTTP on 127.0.0.1:
%% the layout drawn from the spec, the IO points, who may force and when, the value a
%% forced output keeps for its release, the ends of forces (emergency stop, service
%% mode, logout) and their audit, the camera's image, the live messages.
-module(cell_web_io_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-compile([export_all, nowarn_export_all]).

-define(TASKS, [{loader, <<"Loading">>}, {router, <<"Routing">>}, {unloader, <<"Unloading">>}]).

all() ->
    [layout_from_the_spec, io_points_and_connections, force_needs_role_and_service_mode,
     bad_force_requests_change_nothing, forced_output_keeps_task_writes,
     forced_simulated_input, forces_end_on_estop_service_mode_and_logout,
     forces_end_when_the_io_service_restarts,
     camera_image, websocket_carries_forces_io_and_links, websocket_carries_axes].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    %% A root of its own: in a run of the whole folder the suites share one priv_dir,
    %% and the API suite's root holds its users' changed passwords and its products.
    Root = filename:join(?config(priv_dir, Config), "cell_web_io_root"),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    _ = [application:stop(A) || A <- [cell_web, cell, cell_hal, mnesia, cell_base]],
    _ = [application:load(A) || A <- [cell_base, cell, cell_web]],
    ok = application:set_env(cell_base, root, Root),
    Specs = [cell_web_demo_task:spec(Id, Z, <<"Front">>, self()) || {Id, Z} <- ?TASKS],
    Monitor = #{io => maps:from_list([{R, {general, R}} || R <- cell_monitor_spec:outputs()])},
    ok = application:set_env(
           cell, cell_spec,
           #{name => <<"suite">>, tasks => Specs,
             links => [#{id => load_route, from => loader, to => router},
                       #{id => route_unload, from => router, to => unloader}],
             hal => #{connections => [#{id => plc, driver => cell_hal_sim, opts => #{}}],
                      groups => [#{id => general, module => cell_web_demo, connection => plc,
                                   opts => #{kind => general}},
                                 #{id => line, module => cell_web_demo, connection => plc,
                                   opts => #{kind => line}}],
                      hardware => [#{id => camera, kind => camera, type => sim,
                                     opts => #{width => 8, height => 4}},
                                   #{id => x, kind => axis, type => sim,
                                     opts => #{position => 12.5}},
                                   #{id => y, kind => axis, type => sim},
                                   #{id => xy, kind => channel, type => sim,
                                     opts => #{axes => [x, y]}}]},
             monitor => Monitor}),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = up(plc, 10000),
    [{specs, Specs} | Config].

end_per_suite(_Config) ->
    _ = [application:stop(A) || A <- [cell_web, cell, cell_hal, mnesia, cell_base]],
    ok = application:unset_env(cell, cell_spec),
    ok.

init_per_testcase(_Case, Config) ->
    [{port, cell_web:port()} | Config].

end_per_testcase(_Case, _Config) ->
    ok = cell_controller:estop(false),
    ok = cell_controller:service_mode(false),
    ok = cell_controller:stop(),
    ok = cell_controller:sync(),
    %% Whatever a case left forced ended with service mode.
    released().

%% -------------------------------------------------------------------------------------
%% Helpers

anon(Config) -> cell_web_client:new(?config(port, Config)).

as(Role, Config) ->
    Name = atom_to_list(Role),
    {ok, C} = cell_web_client:login(anon(Config), Name, Name),
    C.

req(C, M, P) -> cell_web_client:req(C, M, P).
req(C, M, P, B) -> cell_web_client:req(C, M, P, B).

assert_error(Status, Code, {Status, #{<<"error">> := Code, <<"message">> := M}, _}) ->
    ?assert(is_binary(M) andalso M =/= <<>>);
assert_error(Status, Code, Other) ->
    ct:fail("expected ~p ~s, got ~p", [Status, Code, Other]).

force(C, G, P, V) ->
    req(C, post, "/api/forces", #{group => G, point => P, value => V}).

%% The connection up, waited for by its subscription (no polling).
up(Conn, Timeout) ->
    {ok, Status} = cell_hal:subscribe_connection(Conn),
    Result = case Status of
                 up -> ok;
                 down -> receive {cell_hal_conn, Conn, up} -> ok after Timeout -> timeout end
             end,
    ok = cell_hal:unsubscribe_connection(Conn),
    Result.

%% The point's value as the HAL reads it, waited for by a watch.
value_becomes(G, P, V) ->
    {ok, Ref} = cell_hal:watch(G, P, {eq, V}),
    receive {cell_hal_watch, Ref, V} -> ok
    after 5000 -> ct:fail({value_not_reached, G, P, V, cell_hal:read(G, P)})
    end.

%% What the simulated PLC holds of an output, once the HAL's write reached it: a
%% write_sync of the same point behind it is confirmed after it.
device(G, P) ->
    {ok, V} = cell_hal_sim:get({G, P}),
    V.

audit(C) ->
    {200, #{<<"entries">> := Es}, _} = req(C, get, "/api/audit?limit=1000"),
    Es.

%% -------------------------------------------------------------------------------------

layout_from_the_spec(Config) ->
    {200, L, _} = req(anon(Config), get, "/api/layout"),
    #{<<"zones">> := Zones, <<"tasks">> := Tasks, <<"links">> := Links,
      <<"beacon">> := Beacon, <<"counters">> := Counters} = L,
    ?assertEqual([<<"Loading">>, <<"Routing">>, <<"Unloading">>],
                 [Z || #{<<"name">> := Z} <- Zones]),
    ?assertEqual([{<<"loader">>, 0}, {<<"router">>, 1}, {<<"unloader">>, 2}],
                 [{I, C} || #{<<"id">> := I, <<"column">> := C} <- Tasks]),
    ?assertEqual([{<<"load_route">>, <<"idle">>}, {<<"route_unload">>, <<"idle">>}],
                 [{I, P} || #{<<"id">> := I, <<"phase">> := P} <- Links]),
    ?assertEqual([<<"beacon_red">>, <<"beacon_yellow">>, <<"beacon_green">>, <<"beacon_blue">>],
                 [B || #{<<"lamp">> := B} <- Beacon]),
    ?assertMatch(#{<<"in">> := 0, <<"out">> := 0, <<"good">> := 0, <<"scrapped">> := 0},
                 Counters),
    assert_error(405, <<"method_not_allowed">>, req(as(admin, Config), delete, "/api/layout")).

io_points_and_connections(Config) ->
    {200, Io, _} = req(anon(Config), get, "/api/io"),
    #{<<"connections">> := [Conn], <<"groups">> := Groups, <<"hardware">> := Hw,
      <<"forces">> := []} = Io,
    ?assertMatch(#{<<"id">> := <<"plc">>, <<"status">> := <<"up">>, <<"reconnects">> := 0}, Conn),
    ?assertEqual([<<"general">>, <<"line">>], [G || #{<<"id">> := G} <- Groups]),
    [General, Line] = Groups,
    %% In the order the group's module lists them.
    ?assertEqual([<<"beacon_red">>, <<"beacon_yellow">>, <<"beacon_green">>, <<"beacon_blue">>,
                  <<"service_key">>, <<"air_pressure">>],
                 [P || #{<<"point">> := P} <- maps:get(<<"points">>, General)]),
    [Speed] = [P || #{<<"point">> := <<"conveyor_speed">>} = P <- maps:get(<<"points">>, Line)],
    ?assertMatch(#{<<"dir">> := <<"out">>, <<"type">> := <<"INT">>, <<"unit">> := <<"mm/s">>,
                   <<"address">> := <<"A2.40.01">>, <<"caption">> := <<"Conveyor speed">>,
                   <<"quality">> := <<"good">>, <<"value">> := 0, <<"forced">> := false,
                   <<"forceable">> := true}, Speed),
    %% An axis with its state and position, a channel with its progress.
    ?assertEqual([#{<<"id">> => <<"camera">>, <<"kind">> => <<"camera">>, <<"status">> => <<"up">>},
                  #{<<"id">> => <<"x">>, <<"kind">> => <<"axis">>, <<"status">> => <<"up">>,
                    <<"axis">> => #{<<"state">> => <<"disabled">>, <<"position">> => 12.5,
                                    <<"velocity">> => 0.0, <<"error">> => 0,
                                    <<"homed">> => false, <<"powered">> => false}},
                  #{<<"id">> => <<"xy">>, <<"kind">> => <<"channel">>, <<"status">> => <<"up">>,
                    <<"channel">> => #{<<"state">> => <<"idle">>, <<"along">> => 0.0,
                                       <<"length">> => 0.0, <<"segment">> => 0,
                                       <<"segments">> => 0}}],
                 %% (The override is the monitor's to set: its own suites check it.)
                 [case H of
                      #{<<"axis">> := A} -> H#{<<"axis">> := maps:remove(<<"override">>, A)};
                      _ -> H
                  end || #{<<"id">> := Id} = H <- Hw, Id =/= <<"y">>]).

force_needs_role_and_service_mode(Config) ->
    Op = as(operator, Config),
    Svc = as(service, Config),
    assert_error(401, <<"login_required">>, force(anon(Config), line, clamp, true)),
    assert_error(403, <<"forbidden">>, force(Op, line, clamp, true)),
    assert_error(409, <<"not_service_mode">>, force(Svc, line, clamp, true)),
    ok = cell_controller:service_mode(true),
    assert_error(403, <<"forbidden">>, force(Op, line, clamp, true)),
    {200, [#{<<"group">> := <<"line">>, <<"point">> := <<"clamp">>, <<"value">> := true,
             <<"who">> := <<"service">>}], _} = force(Svc, line, clamp, true),
    ?assert(cell_hal_force:forced(line, clamp)),
    ?assertEqual(true, device(line, clamp)),
    %% An admin may as well; an operator may not release.
    {200, _, _} = force(as(admin, Config), line, conveyor_motor, true),
    assert_error(403, <<"forbidden">>, req(Op, delete, "/api/forces/line/clamp")),
    assert_error(403, <<"forbidden">>, req(Op, delete, "/api/forces")),
    {200, [_], _} = req(Svc, delete, "/api/forces/line/clamp"),
    ?assertEqual(false, device(line, clamp)),
    {200, #{<<"released">> := 1}, _} = req(Svc, delete, "/api/forces"),
    {200, [], _} = req(anon(Config), get, "/api/forces"),
    Audit = [{W, A, T, D} || #{<<"who">> := W, <<"action">> := A, <<"target">> := T,
                               <<"outcome">> := <<"200">>, <<"detail">> := D} <- audit(Svc),
                             binary:match(T, <<"/api/forces">>) =/= nomatch],
    ?assertEqual([{<<"service">>, <<"POST">>, <<"/api/forces">>, <<"forced line.clamp = true">>},
                  {<<"admin">>, <<"POST">>, <<"/api/forces">>,
                   <<"forced line.conveyor_motor = true">>},
                  {<<"service">>, <<"DELETE">>, <<"/api/forces/line/clamp">>,
                   <<"released line.clamp">>},
                  {<<"service">>, <<"DELETE">>, <<"/api/forces">>,
                   <<"released 1 forced point(s)">>}], Audit).

bad_force_requests_change_nothing(Config) ->
    Svc = as(service, Config),
    ok = cell_controller:service_mode(true),
    assert_error(404, <<"not_found">>, force(Svc, line, no_such_point, true)),
    assert_error(404, <<"not_found">>, force(Svc, nowhere, clamp, true)),
    assert_error(400, <<"bad_value">>, force(Svc, line, conveyor_speed, <<"fast">>)),
    assert_error(400, <<"bad_value">>, force(Svc, line, conveyor_speed, 100000)),
    assert_error(400, <<"bad_value">>, force(Svc, line, clamp, 1)),
    assert_error(400, <<"bad_request">>, req(Svc, post, "/api/forces", #{group => line})),
    assert_error(400, <<"bad_request">>, req(Svc, post, "/api/forces", #{group => 1, point => 2, value => 3})),
    assert_error(400, <<"bad_json">>, req(Svc, post, "/api/forces", {"application/json", <<"{">>})),
    assert_error(404, <<"not_forced">>, req(Svc, delete, "/api/forces/line/clamp")),
    assert_error(404, <<"not_found">>, req(Svc, delete, "/api/forces/line/nope")),
    assert_error(405, <<"method_not_allowed">>, req(Svc, put, "/api/forces", #{})),
    ?assertEqual([], cell_hal_force:forces()).

forced_output_keeps_task_writes(Config) ->
    Svc = as(service, Config),
    ok = cell_controller:service_mode(true),
    ok = cell_hal:write_sync(line, conveyor_speed, 100, 5000),
    {200, _, _} = force(Svc, line, conveyor_speed, 250),
    ?assertEqual(250, device(line, conveyor_speed)),
    %% A task's writes while forced are kept, not sent.
    ok = cell_hal:write(line, conveyor_speed, 120),
    ok = cell_hal:write_sync(line, conveyor_speed, 130, 5000),
    ?assertEqual(250, device(line, conveyor_speed)),
    ?assertEqual({ok, 250}, cell_hal:read(line, conveyor_speed)),
    %% Released, the output has the task's last value.
    {200, [], _} = req(Svc, delete, "/api/forces/line/conveyor_speed"),
    ?assertEqual(130, device(line, conveyor_speed)),
    %% With no write meanwhile, the value it had before the force.
    {200, _, _} = force(Svc, line, conveyor_speed, 7),
    {200, _, _} = req(Svc, delete, "/api/forces"),
    ?assertEqual(130, device(line, conveyor_speed)).

forced_simulated_input(Config) ->
    Svc = as(service, Config),
    ok = cell_controller:service_mode(true),
    ok = cell_hal_sim:set({line, board_present}, false),
    {200, _, _} = force(Svc, line, board_present, true),
    ok = value_becomes(line, board_present, true),
    %% The simulation's own value does not show through the force.
    ok = cell_hal_sim:set({line, clamp_closed}, true),
    ok = value_becomes(line, clamp_closed, true),
    ?assertEqual({ok, true}, cell_hal:read(line, board_present)),
    {200, _, _} = req(Svc, delete, "/api/forces/line/board_present"),
    ok = value_becomes(line, board_present, false),
    %% A real PLC's input is not forceable.
    ?assertEqual({error, not_forceable}, cell_hal_force:forceable(in, cell_hal_modbus)).

forces_end_on_estop_service_mode_and_logout(Config) ->
    Svc = as(service, Config),
    Admin = as(admin, Config),
    ok = cell_controller:service_mode(true),
    {200, _, _} = force(Svc, line, clamp, true),
    ok = cell_controller:estop(true),
    ok = released(),
    ?assertEqual(false, device(line, clamp)),
    assert_error(409, <<"estop_active">>, force(Svc, line, clamp, true)),
    ok = cell_controller:estop(false),
    {200, _, _} = force(Svc, line, clamp, true),
    ok = cell_controller:service_mode(false),
    ok = released(),
    ok = cell_controller:service_mode(true),
    {200, _, _} = force(Svc, line, clamp, true),
    {200, _, _} = force(Admin, line, conveyor_motor, true),
    {200, _, _} = req(Svc, delete, "/api/session"),
    ?assertEqual([#{group => line, point => conveyor_motor}],
                 [maps:with([group, point], F) || F <- cell_hal_force:forces()]),
    {200, _, _} = req(Admin, delete, "/api/session"),
    ?assertEqual([], cell_hal_force:forces()),
    Released = [{T, D} || #{<<"action">> := <<"RELEASE">>, <<"who">> := <<"cell">>,
                            <<"target">> := T, <<"detail">> := D} <- audit(as(admin, Config))],
    ?assertEqual([{<<"/api/forces/line/clamp">>, <<"emergency stop">>},
                  {<<"/api/forces/line/clamp">>, <<"service mode ended">>},
                  {<<"/api/forces/line/clamp">>, <<"service logged out">>},
                  {<<"/api/forces/line/conveyor_motor">>, <<"admin logged out">>}], Released).

%% The HAL's server crashes (and with it, rest_for_one, every connection's worker): the
%% forces end with it. The forced output is written back to the task's last value as
%% its connection comes up again, and a forced simulated input answers the PLC's own
%% value; no force is reported, the keeper records each end in the audit trail.
forces_end_when_the_io_service_restarts(Config) ->
    Svc = as(service, Config),
    ok = cell_controller:service_mode(true),
    ok = cell_hal:write_sync(line, conveyor_speed, 100, 5000),
    {200, _, _} = force(Svc, line, conveyor_speed, 250),
    ok = cell_hal_sim:set({line, board_present}, false),
    {200, _, _} = force(Svc, line, board_present, true),
    ok = value_becomes(line, board_present, true),
    ?assertEqual(250, device(line, conveyor_speed)),
    %% The task writes while forced: kept, not sent.
    ok = cell_hal:write(line, conveyor_speed, 140),
    ?assertEqual(250, device(line, conveyor_speed)),
    ok = cell_log:subscribe(),
    {ok, up} = cell_hal:subscribe_connection(plc),
    exit(whereis(cell_hal_server), kill),
    receive {cell_hal_conn, plc, down} -> ok after 10000 -> ct:fail(no_down) end,
    receive {cell_hal_conn, plc, up} -> ok after 10000 -> ct:fail(no_up) end,
    ok = cell_hal:unsubscribe_connection(plc),
    %% The worker, once up, wrote the output back before taking any other write: one
    %% confirmed behind it means the simulated PLC holds it.
    {ok, Clamp} = cell_hal:read(line, clamp),
    ok = cell_hal:write_sync(line, clamp, Clamp, 5000),
    ?assertEqual(140, device(line, conveyor_speed)),
    ?assertEqual({ok, 140}, cell_hal:read(line, conveyor_speed)),
    ok = value_becomes(line, board_present, false),
    ?assertEqual([], cell_hal_force:forces()),
    ?assertNot(cell_hal_force:forced(line, conveyor_speed)),
    ?assertNot(cell_hal_force:forced(line, board_present)),
    {200, [], _} = req(anon(Config), get, "/api/forces"),
    %% Said by the connection and by the keeper (which has audited by then).
    ok = logged([<<"force of line.conveyor_speed ended: the IO service restarted">>,
                 <<"2 forced IO point(s) released: the IO service restarted">>]),
    ok = cell_log:unsubscribe(),
    Released = [T || #{<<"action">> := <<"RELEASE">>, <<"who">> := <<"cell">>, <<"target">> := T,
                       <<"detail">> := <<"forces ended: the IO service restarted">>}
                         <- audit(as(admin, Config))],
    ?assertEqual([<<"/api/forces/line/board_present">>, <<"/api/forces/line/conveyor_speed">>],
                 lists:sort(Released)),
    %% The new server's forces are forces again.
    {200, _, _} = force(Svc, line, conveyor_speed, 77),
    ?assert(cell_hal_force:forced(line, conveyor_speed)),
    ?assertEqual(77, device(line, conveyor_speed)),
    {200, _, _} = req(Svc, delete, "/api/forces"),
    ?assertEqual(140, device(line, conveyor_speed)).

%% Log lines (as cell_log sends them) holding each of these words, in any order.
logged([]) ->
    ok;
logged(Words) ->
    receive
        {cell_log, #{text := T}} when is_binary(T) ->
            logged([W || W <- Words, binary:match(T, W) =:= nomatch]);
        {cell_log, _} ->
            logged(Words)
    after 10000 ->
        ct:fail({not_logged, Words})
    end.

%% The forces keeper has taken the cell's event (a call behind it is answered after).
released() ->
    _ = sys:get_state(cell_web_forces),
    [] = cell_hal_force:forces(),
    ok.

camera_image(Config) ->
    Svc = as(service, Config),
    {200, Png, H} = req(Svc, get, "/api/io/hardware/camera/image"),
    ?assertEqual({"content-type", "image/png"}, lists:keyfind("content-type", 1, H)),
    <<137, "PNG", 13, 10, 26, 10, 13:32, "IHDR", 8:32, 4:32, _/binary>> = Png,
    assert_error(403, <<"forbidden">>, req(as(operator, Config), get, "/api/io/hardware/camera/image")),
    assert_error(404, <<"not_found">>, req(Svc, get, "/api/io/hardware/scanner/image")).

websocket_carries_forces_io_and_links(Config) ->
    Svc = as(service, Config),
    Origin = "http://127.0.0.1:" ++ integer_to_list(?config(port, Config)),
    {ok, Ws} = cell_web_client:ws_connect(Svc, Origin),
    {[Snapshot], Ws0} = cell_web_client:ws_next(Ws, 10000),
    ?assertMatch(#{<<"type">> := <<"snapshot">>, <<"forces">> := []}, Snapshot),
    ok = cell_controller:service_mode(true),
    {200, _, _} = force(Svc, line, clamp, true),
    {_, Ws1} = next_of(<<"forces">>, Ws0),
    ok = cell_hal_sim:set({line, board_present}, true),
    {#{<<"points">> := Points}, Ws2} = next_io(<<"board_present">>, Ws1),
    ?assertMatch([#{<<"group">> := <<"line">>, <<"value">> := true, <<"quality">> := <<"good">>}],
                 [P || #{<<"point">> := <<"board_present">>} = P <- Points]),
    ok = cell_hal_sim:set({line, board_present}, false),
    %% A link's phase: the loader offers its product.
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    [Loader] = [S || #{id := loader} = S <- ?config(specs, Config)],
    ok = cell_web_demo_task:command(Loader, loader, {product, <<"P-1">>}),
    ok = cell_web_demo_task:command(Loader, loader, {offer, load_route}),
    {#{<<"link">> := Link}, Ws3} = next_of(<<"link">>, Ws2),
    ?assertEqual(#{<<"link">> => <<"load_route">>, <<"phase">> => <<"offered">>,
                   <<"serial">> => <<"P-1">>}, Link),
    ok = cell_web_client:ws_close(Ws3).

%% An axis's moves reach the pages as they happen: its state as a move begins, where
%% it stands when done. Nothing is asked by the page.
websocket_carries_axes(Config) ->
    Svc = as(service, Config),
    Origin = "http://127.0.0.1:" ++ integer_to_list(?config(port, Config)),
    {ok, Ws} = cell_web_client:ws_connect(Svc, Origin),
    {[_Snapshot], Ws0} = cell_web_client:ws_next(Ws, 10000),
    %% The page's watch is asked as it connects (a cast before the snapshot); a call
    %% after the snapshot comes after it.
    _ = cell_web_io:connections(),
    {ok, _} = cell_hal_axis:power(x, true),
    {_, Ws1} = next_axis(<<"x">>, fun(#{<<"state">> := S}) -> S =:= <<"standstill">> end, Ws0),
    {ok, H} = cell_hal_axis:home(x, 0.0),
    ok = await_reply(H),
    Slow = #{velocity => 20, acceleration => 200, deceleration => 200},
    {ok, M} = cell_hal_axis:move_absolute(x, 30.0, Slow),
    {_, Ws1a} = next_axis(<<"x">>, fun(#{<<"state">> := S}) -> S =:= <<"discrete_motion">> end,
                          Ws1),
    %% On its way: read again while it moves, though it publishes nothing (a move of
    %% 1.6 s, read every 50 ms).
    {_, Ws2} = next_axis(<<"x">>, fun(#{<<"state">> := S, <<"position">> := P}) ->
                                          S =:= <<"discrete_motion">> andalso P > 0
                                              andalso P < 30
                                  end, Ws1a),
    ok = await_reply(M),
    {#{<<"axis">> := Done}, Ws3} =
        next_axis(<<"x">>, fun(#{<<"state">> := S, <<"position">> := P}) ->
                                   S =:= <<"standstill">> andalso P == 30.0
                           end, Ws2),
    ?assertMatch(#{<<"homed">> := true, <<"velocity">> := 0.0, <<"error">> := 0}, Done),
    ok = cell_web_client:ws_close(Ws3).

await_reply(Ref) ->
    receive {Ref, done} -> ok;
            {Ref, Other} -> ct:fail({axis_job, Other})
    after 10000 -> ct:fail({no_end_of_job, Ref})
    end.

%% The next `hardware' message whose axis `Id' satisfies `Pred'.
next_axis(Id, Pred, Ws) ->
    {#{<<"hardware">> := Hw}, Ws1} = next_of(<<"hardware">>, Ws),
    case [H || #{<<"id">> := I, <<"axis">> := A} = H <- Hw, I =:= Id, Pred(A)] of
        [H | _] -> {H, Ws1};
        [] -> next_axis(Id, Pred, Ws1)
    end.

next_of(Type, Ws) ->
    {Msgs, Ws1} = cell_web_client:ws_next(Ws, 5000),
    case [M || #{<<"type">> := T} = M <- Msgs, T =:= Type] of
        [M | _] -> {M, Ws1};
        [] -> next_of(Type, Ws1)
    end.

next_io(Point, Ws) ->
    {#{<<"points">> := Ps} = M, Ws1} = next_of(<<"io">>, Ws),
    case [P || #{<<"point">> := P} <- Ps, P =:= Point] of
        [_] -> {M, Ws1};
        [] -> next_io(Point, Ws1)
    end.
