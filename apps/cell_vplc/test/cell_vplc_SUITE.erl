%% The virtual PLC of the router cell in an OS process of its own (scripts/vplc, port
%% 0), and the router's real-mode HAL (the Modbus driver, the groups at the addresses
%% router_cell:hal/2 gives them) connected to it from this node: outputs written move
%% the physics and its inputs come back; killing the virtual PLC's process takes the
%% connection down and starting it again brings it back; bad frames get exceptions or
%% a closed connection while the PLC stays up; a pymodbus client reads the same
%% registers.
-module(cell_vplc_SUITE).

-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([outputs_move_the_physics/1, killed_and_started_again/1, bad_input/1,
         pymodbus_reads_the_same_registers/1, the_physics_settings_of_its_root/1,
         the_router_cell_in_real_mode/1]).

%% A node's start on a busy machine.
-define(WAIT, 60000).
-define(CONN, router_plc).

all() ->
    [outputs_move_the_physics, killed_and_started_again, bad_input,
     pymodbus_reads_the_same_registers, the_physics_settings_of_its_root,
     %% Last: it starts the whole cell in this node.
     the_router_cell_in_real_mode].

init_per_suite(Config) ->
    Priv = ?config(priv_dir, Config),
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(Priv, "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_testcase(the_router_cell_in_real_mode = Case, Config) ->
    %% The router declares its own inspection blocks only where none are configured: an
    %% inspection application an earlier suite of this run left with its blocks goes.
    _ = application:stop(cell_inspect),
    [ok = application:set_env(cell_inspect, K, []) || K <- [blocks, connections]],
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    VplcRoot = filename:join(Root, "vplc"),
    ok = cell_testkit:write_settings(VplcRoot, #{router_sim => #{time_scale => 0.02,
                                                                 arrival_ms => 0,
                                                                 product_lost_rate => 0.0,
                                                                 jam_rate => 0.0, no_read_rate => 0.0,
                                                                 magazine_low_s => 0}}),
    #{tcp := Port} = Vplc = start_vplc(VplcRoot, 0),
    CellRoot = filename:join(Root, "cell"),
    %% The lower robot's simulated NC runs in the cell, at the physics' pace.
    ok = cell_testkit:write_settings(CellRoot, #{machine => #{simulation_mode => false},
                                                 router_sim => #{time_scale => 0.02},
                                                 router => #{plc_host => <<"127.0.0.1">>,
                                                             plc_port => Port,
                                                             hal_poll_ms => 5,
                                                             transfer_timeout_ms => 5000,
                                                             motion_timeout_ms => 5000}}),
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    ok = cell_testkit:start(CellRoot, router_cell, router_cell),
    ok = cell_testkit:await_connection(?CONN, ?WAIT),
    %% The inspection block on the virtual PLC's UDT, its camera showing no bad part.
    ok = cell_settings:put(inspect, #{blocks => [B#{clients => [C#{fail_rate => 0.0} || C <- Cs]}
                                                 || #{clients := Cs} = B
                                                        <- cell_settings:get(inspect, blocks)]},
                           <<"suite">>),
    {ok, _} = application:ensure_all_started(cell_inspect),
    [{vplc, Vplc}, {root, Root} | Config];
init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = settings(Case, Root),
    Vplc = start_vplc(Root, 0),
    ok = connect(maps:get(tcp, Vplc)),
    [{vplc, Vplc}, {root, Root} | Config].

end_per_testcase(the_router_cell_in_real_mode, Config) ->
    _ = application:stop(cell_inspect),
    _ = application:unset_env(cell_inspect, blocks),
    ok = cell_testkit:stop(router_cell, []),
    _ = application:unset_env(cell, shutdown_wait_ms),
    stop_vplc(?config(vplc, Config));
end_per_testcase(_Case, Config) ->
    _ = cell_hal:unsubscribe_connection(?CONN),
    [ok = cell_hal:remove_group(G) || G <- cell_hal:groups()],
    [ok = cell_hal:remove_connection(C) || C <- cell_hal:connections()],
    stop_vplc(?config(vplc, Config)).

%%--------------------------------------------------------------------
%% Cases
%%--------------------------------------------------------------------

%% The upper robot's axes told to stand over the front module nest (their positions
%% written over Modbus as an NC writes them, 32-bit floats over two holding registers
%% each) bring up the machine's in-position signal for the nest; the spindle's coil
%% brings up its at-speed input; the air pressure reads as a 64-bit float over four
%% input registers.
outputs_move_the_physics(_Config) ->
    place(250.0, 150.0, at_nest_front),
    {ok, false} = cell_hal:read(upper_io, at_home),
    {ok, 6.0} = cell_hal:read(general_io, air_pressure),
    ok = cell_hal:write(lower_io, spindle_run, true),
    wait(lower_io, spindle_at_speed, {eq, true}),
    ok = cell_hal:write(lower_io, spindle_run, false),
    wait(lower_io, spindle_at_speed, {eq, false}).

%% The virtual PLC's process killed as a power cut would: the HAL says the connection
%% is down; the virtual PLC started again on the same port: the HAL is back on its
%% own and the physics answers again.
killed_and_started_again(Config) ->
    place(250.0, 150.0, at_nest_front),
    #{tcp := Port} = Vplc = ?config(vplc, Config),
    ok = kill_vplc(Vplc),
    receive {cell_hal_conn, ?CONN, down} -> ok after ?WAIT -> ct:fail(connection_not_down) end,
    ?assertMatch({error, _}, cell_hal:read(upper_io, at_nest_front)),
    Again = start_vplc(?config(root, Config), Port),
    receive {cell_hal_conn, ?CONN, up} -> ok after ?WAIT -> ct:fail(connection_not_back) end,
    place(1100.0, 150.0, at_unloading_front),
    stop_vplc(Again).

%% Frames that are not Modbus close their connection, refused requests get their
%% exceptions; the virtual PLC and the HAL's connection stay up throughout.
bad_input(Config) ->
    #{tcp := Port} = ?config(vplc, Config),
    %% A protocol id other than Modbus's 0: the connection is closed.
    S1 = open(Port),
    ok = gen_tcp:send(S1, <<1:16, 7:16, 6:16, 1, 1, 0:16, 1:16>>),
    {error, closed} = gen_tcp:recv(S1, 0, ?WAIT),
    %% A length field beyond Modbus TCP's 254: closed too.
    S2 = open(Port),
    ok = gen_tcp:send(S2, <<2:16, 0:16, 900:16, 1, 1>>),
    {error, closed} = gen_tcp:recv(S2, 0, ?WAIT),
    S = open(Port),
    %% No point at discrete input 5000: illegal data address.
    ?assertEqual(<<16#82, 2>>, ask(S, 1, <<2, 5000:16, 1:16>>)),
    %% A span running past the last point of the loading segment's inputs.
    ?assertEqual(<<16#82, 2>>, ask(S, 1, <<2, 0:16, 100:16>>)),
    %% The high word of the Y position's 32-bit float written alone is a position (the
    %% low word kept: 150.0); a quantity of 0 coils is refused.
    ?assertEqual(<<6, 262:16, 16#4316:16>>, ask(S, 1, <<6, 262:16, 16#4316:16>>)),
    ?assertEqual(<<16#81, 3>>, ask(S, 1, <<1, 0:16, 0:16>>)),
    %% A function the PLC does not offer, a unit it does not serve.
    ?assertEqual(<<16#C1, 1>>, ask(S, 1, <<16#41, 1, 2, 3>>)),
    ?assertEqual(<<16#83, 11>>, ask(S, 9, <<3, 200:16, 2:16>>)),
    %% A coil written with a value other than on or off.
    ?assertEqual(<<16#85, 3>>, ask(S, 1, <<5, 200:16, 16#1234:16>>)),
    %% Still up, for this client and for the HAL.
    ?assertEqual(<<3, 4, 16#4316:16, 0:16>>, ask(S, 1, <<3, 262:16, 2:16>>)),
    ok = gen_tcp:close(S),
    up = cell_hal:status(?CONN),
    place(250.0, 150.0, at_nest_front).

%% pymodbus, a client written by others, reads what the HAL wrote and what the physics
%% set at the same addresses.
pymodbus_reads_the_same_registers(Config) ->
    place(1100.0, 150.0, at_unloading_front),
    ok = cell_hal:write(lower_io, spindle_run, true),
    wait(lower_io, spindle_at_speed, {eq, true}),
    #{tcp := Port} = ?config(vplc, Config),
    Script = filename:join(?config(data_dir, Config), "pymodbus_client.py"),
    P = open_port({spawn_executable, "/usr/bin/python3"},
                  [{args, [Script, integer_to_list(Port)]}, {line, 1024}, exit_status,
                   use_stdio, binary, stderr_to_stdout]),
    Lines = lines(P, []),
    ?assertEqual([<<"x_actual 1100.0">>, <<"y_actual 150.0">>, <<"spindle_run 1">>,
                  <<"at_unloading_front 1">>, <<"air_pressure 6.0">>, <<"end">>], Lines).

%% The physics runs on the settings saved in the virtual PLC's root: a panel always
%% waiting at the previous machine (arrival_ms 0) is offered before the first read,
%% where the default rhythm offers the first one some ten seconds after the start.
the_physics_settings_of_its_root(_Config) ->
    %% The first value read, whichever it is (a group added after the connection came
    %% up may not have been read yet when the connection says up).
    {ok, T} = cell_hal:watch(loading_front_io, upstream_available, {eq, true}),
    {ok, F} = cell_hal:watch(loading_front_io, upstream_available, {eq, false}),
    First = receive {cell_hal_watch, R, V} when R =:= T; R =:= F -> V
            after ?WAIT -> ct:fail(never_read)
            end,
    ?assertEqual(true, First).

%% The router cell itself with simulation_mode off, its HAL on the Modbus driver: panels
%% pass the whole line through the virtual PLC, each serial once, no error or warning
%% raised. Each is inspected at the unloading exit by the inspection block on the
%% virtual PLC's UDT, whose camera sees no bad part: each passes.
the_router_cell_in_real_mode(_Config) ->
    {ok, #{driver := cell_hal_modbus}} = cell_hal:info(?CONN),
    ok = cell_events:subscribe([item_transfer_out, alarm_raised, cell_state]),
    ok = cell_controller:start(<<"suite">>),
    Out = cell_testkit:collect(5, fun(#{type := item_transfer_out, task := unloading_front,
                                        item := S}) -> {true, S};
                                     (_) -> false
                                  end, fun never_answer/1, ?WAIT),
    ?assertEqual(5, length(lists:usort(Out))),
    ok = cell_stats:flush(),
    [?assertEqual([<<"pass">>], inspections(S), S) || S <- Out],
    ok = cell_testkit:stop_cell(fun never_answer/1, ?WAIT).

%% The inspection verdicts a product's history records.
inspections(Serial) ->
    {ok, #{events := Events}} = cell_stats:product(Serial),
    [V || #{event := changed, changes := #{inspection := V}} <- Events].

never_answer(Alarm) ->
    ct:fail({unexpected_error, Alarm}).

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

settings(the_physics_settings_of_its_root, Root) ->
    cell_testkit:write_settings(Root, #{router_sim => #{arrival_ms => 0, magazine_low_s => 0}});
settings(_, _) ->
    ok.

%% The router's HAL in real mode, as router_cell builds it, on the virtual PLC's port.
connect(Port) ->
    Router = maps:merge(cell_settings_schema:defaults(router_settings),
                        #{plc_host => <<"127.0.0.1">>, plc_port => Port}),
    #{connections := [Conn], groups := Groups} =
        router_cell:hal(#{simulation_mode => false, dual_lane => false}, Router),
    #{driver := cell_hal_modbus} = Conn,
    ok = cell_hal:add_connection(Conn),
    [ok = cell_hal:add_group(G) || G <- Groups],
    {ok, _} = cell_hal:subscribe_connection(?CONN),
    case cell_hal:status(?CONN) of
        up -> ok;
        down -> receive {cell_hal_conn, ?CONN, up} -> ok after ?WAIT -> ct:fail(not_up) end
    end.

%% The upper robot's NC tells the PLC its axes stand at X, Y (mm), a station of the
%% machine: its in-position signal `At' comes up.
place(X, Y, At) ->
    ok = cell_hal:write(upper_io, x_actual, X),
    ok = cell_hal:write(upper_io, y_actual, Y),
    wait(upper_io, At, {eq, true}).

wait(G, P, Cond) ->
    {ok, Ref} = cell_hal:watch(G, P, Cond),
    receive {cell_hal_watch, Ref, _} -> ok
    after ?WAIT -> ct:fail({not_seen, G, P, Cond, cell_hal:read(G, P)})
    end.

start_vplc(Root, Port) ->
    Top = os:getenv("CELLRT_TOP"),
    %% The build this suite runs from (the test profile's), not the default one.
    Build = filename:dirname(filename:dirname(code:lib_dir(cell_vplc))),
    P = open_port({spawn_executable, filename:join([Top, "scripts", "vplc"])},
                  [{args, ["--port", integer_to_list(Port), "--root", Root]},
                   {env, [{"CELLRT_BUILD", Build}]}, {line, 1 bsl 16}, exit_status,
                   use_stdio, stderr_to_stdout, binary]),
    {os_pid, OsPid} = erlang:port_info(P, os_pid),
    #{port => P, os_pid => OsPid, tcp => listening(P)}.

listening(P) ->
    receive
        {P, {data, {eol, <<"virtual PLC of router_cell listening on 127.0.0.1 port ",
                           N/binary>>}}} ->
            binary_to_integer(N);
        {P, {data, _}} ->
            listening(P);
        {P, {exit_status, S}} ->
            ct:fail({vplc_exited, S})
    after ?WAIT ->
            ct:fail(vplc_not_listening)
    end.

%% SIGTERM: the node stops in order (a process already gone is left as it is).
stop_vplc(#{port := P, os_pid := OsPid}) ->
    case erlang:port_info(P) of
        undefined ->
            ok;
        _ ->
            _ = os:cmd("kill -TERM " ++ integer_to_list(OsPid)),
            receive {P, {exit_status, 0}} -> ok after ?WAIT -> ct:fail(vplc_not_stopped) end
    end.

kill_vplc(#{port := P, os_pid := OsPid}) ->
    _ = os:cmd("kill -9 " ++ integer_to_list(OsPid)),
    receive {P, {exit_status, _}} -> ok after ?WAIT -> ct:fail(vplc_not_killed) end.

open(Port) ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}], ?WAIT),
    S.

ask(S, Unit, Pdu) ->
    ok = gen_tcp:send(S, cell_hal_modbus_codec:adu(77, Unit, Pdu)),
    {ok, <<77:16, 0:16, Len:16, Unit>>} = gen_tcp:recv(S, 7, ?WAIT),
    {ok, Reply} = gen_tcp:recv(S, Len - 1, ?WAIT),
    Reply.

lines(P, Acc) ->
    receive
        {P, {data, {eol, Line}}} -> lines(P, [Line | Acc]);
        {P, {exit_status, _}} -> lists:reverse(Acc)
    after ?WAIT ->
            ct:fail({pymodbus_client_silent, lists:reverse(Acc)})
    end.
