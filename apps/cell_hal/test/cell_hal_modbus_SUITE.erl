%% The Modbus TCP driver against servers written by others, started by this suite on
%% 127.0.0.1 with ports the OS picks: Debian's pymodbus and a small server on Debian's
%% libmodbus (both in this suite's data folder, each with a control channel on its
%% stdin to set and read its tables, stop answering, or send faulty frames).
-module(cell_hal_modbus_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, groups/0, init_per_suite/1, end_per_suite/1, init_per_group/2,
         end_per_group/2, init_per_testcase/2, end_per_testcase/2]).
-export([every_type_in_both_word_orders/1, all_four_tables/1, raw_functions/1,
         exceptions/1, refused_poll_faults_its_points/1, refused_write/1,
         refused_address_faults_its_request/1, exception_every_fifth_request/1,
         refused_write_keeps_the_connection/1, whole_group_refused_faults_it/1,
         whole_group_refused_disconnects/1,
         server_killed_mid_poll/1, server_stops_answering/1, per_request_timeout/1,
         pipelined_requests/1, malformed_frames_close_the_connection/1,
         transaction_ids_wrap_around/1, connection_refused/1]).

-define(WAIT, 10000).

all() ->
    [{group, pymodbus}, {group, libmodbus}].

groups() ->
    Common = [every_type_in_both_word_orders, all_four_tables, raw_functions, exceptions,
              refused_poll_faults_its_points, refused_write, server_killed_mid_poll,
              server_stops_answering, per_request_timeout, pipelined_requests,
              connection_refused],
    [{pymodbus, [], Common},
     {libmodbus, [], Common ++ [malformed_frames_close_the_connection,
                                transaction_ids_wrap_around,
                                refused_address_faults_its_request,
                                exception_every_fifth_request,
                                refused_write_keeps_the_connection,
                                whole_group_refused_faults_it,
                                whole_group_refused_disconnects]}].

init_per_suite(Config) ->
    Priv = ?config(priv_dir, Config),
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(Priv, "root")),
    Server = filename:join(Priv, "modbus_server"),
    Src = filename:join(?config(data_dir, Config), "modbus_server.c"),
    case os:cmd("gcc -O2 -Wall -o '" ++ Server ++ "' '" ++ Src ++ "' -lmodbus 2>&1 && echo built") of
        "built\n" -> ok;
        Out -> ct:fail({cannot_build_the_libmodbus_server, Out})
    end,
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps}, {libmodbus_server, Server} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_group(Kind, Config) ->
    [{kind, Kind} | Config].

end_per_group(_, _Config) ->
    ok.

init_per_testcase(_Case, Config) ->
    Peer = start_peer(Config, 0),
    [{peer, Peer} | Config].

end_per_testcase(_Case, Config) ->
    _ = cell_log:unsubscribe(),
    [ok = cell_hal:remove_group(G) || G <- cell_hal:groups()],
    [ok = cell_hal:remove_connection(C) || C <- cell_hal:connections()],
    stop_peer(?config(peer, Config)).

%%--------------------------------------------------------------------
%% The peers
%%--------------------------------------------------------------------

start_peer(Config, Port) ->
    Kind = ?config(kind, Config),
    {Exe, Args} = case Kind of
                      pymodbus ->
                          {"/usr/bin/python3",
                           [filename:join(?config(data_dir, Config), "pymodbus_server.py")]};
                      libmodbus ->
                          {?config(libmodbus_server, Config), []}
                  end,
    Log = filename:join(?config(priv_dir, Config), atom_to_list(Kind) ++ ".stderr"),
    %% The peer's own diagnostics go to a file, its answers to us.
    P = open_port({spawn_executable, "/bin/sh"},
                  [{args, ["-c", "exec \"$0\" \"$@\" 2>>\"$PEER_LOG\"", Exe
                           | Args ++ [integer_to_list(Port)]]},
                   {env, [{"PEER_LOG", Log}]}, {line, 1 bsl 16}, exit_status, use_stdio,
                   binary]),
    receive
        {P, {data, {eol, <<"port ", N/binary>>}}} ->
            {os_pid, OsPid} = erlang:port_info(P, os_pid),
            #{port => P, tcp => binary_to_integer(N), os_pid => OsPid, kind => Kind}
    after ?WAIT ->
            ct:fail({peer_did_not_start, Kind, file:read_file(Log)})
    end.

stop_peer(#{port := P}) ->
    catch port_close(P),
    ok.

%% Kills the peer the hard way, as a power cut would.
kill_peer(#{port := P, os_pid := OsPid}) ->
    _ = os:cmd("kill -9 " ++ integer_to_list(OsPid)),
    receive {P, {exit_status, _}} -> ok after ?WAIT -> ct:fail(peer_not_killed) end.

cmd(#{port := P}, Fmt, Args) ->
    true = port_command(P, [io_lib:format(Fmt, Args), $\n]),
    receive
        {P, {data, {eol, <<"ok", Rest/binary>>}}} ->
            [binary_to_integer(W) || W <- binary:split(Rest, <<" ">>, [global, trim_all])];
        {P, {data, {eol, Other}}} -> ct:fail({peer_said, Other})
    after ?WAIT -> ct:fail({peer_silent, Fmt})
    end.

set(Peer, Table, Addr, Values) ->
    [] = cmd(Peer, "set ~s ~b~s", [Table, Addr, [[$\s, integer_to_list(V)] || V <- Values]]),
    ok.

get(Peer, Table, Addr, N) ->
    cmd(Peer, "get ~s ~b ~b", [Table, Addr, N]).

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

connect(Config) -> connect(Config, #{}).

connect(Config, Opts) ->
    #{tcp := Port} = ?config(peer, Config),
    ok = cell_hal:add_connection(#{id => plc, driver => cell_hal_modbus,
                                   opts => maps:merge(#{host => "127.0.0.1", port => Port,
                                                        poll_ms => 20, reconnect_ms => 50,
                                                        max_reconnect_ms => 400,
                                                        timeout_ms => 1000}, Opts)}),
    {ok, _} = cell_hal:subscribe_connection(plc),
    ok.

group(Id, Opts) ->
    ok = cell_hal:add_group(#{id => Id, module => cell_hal_test_io, connection => plc,
                              opts => Opts}).

await_status(Status) ->
    case cell_hal:status(plc) of
        Status -> flush_conn(), ok;
        _ -> receive {cell_hal_conn, plc, Status} -> ok
             after ?WAIT -> ct:fail({not_reached, Status, cell_hal:info(plc)})
             end
    end.

flush_conn() ->
    receive {cell_hal_conn, plc, _} -> flush_conn() after 0 -> ok end.

%% A point refused for a moment ends the watch: it is placed again once the point
%% is usable again (its subscribers are told its value then).
await_value(G, Point, V) ->
    ok = cell_hal:subscribe(G, Point),
    Got = await_value(G, Point, V, erlang:monotonic_time(millisecond) + ?WAIT),
    ok = cell_hal:unsubscribe(G, Point),
    Got.

await_value(G, Point, V, Deadline) ->
    {ok, Ref} = cell_hal:watch(G, Point, {eq, V}),
    Left = fun() -> max(0, Deadline - erlang:monotonic_time(millisecond)) end,
    receive
        {cell_hal_watch, Ref, Got} -> Got;
        {cell_hal_unavailable, Ref, _} ->
            receive {cell_hal, {G, Point}, _} -> await_value(G, Point, V, Deadline)
            after Left() -> ct:fail({never_usable, G, Point, V, cell_hal:read(G, Point)})
            end
    after Left() -> ct:fail({never, G, Point, V, cell_hal:read(G, Point)})
    end.

address(G, Point) ->
    {ok, #{field := Field}} = cell_hal:describe(G, Point),
    element(2, Field).

words(T, V, Order) ->
    [W || <<W:16>> <= cell_hal_type_codec:encode_registers(T, V, Order)].

name(T, Dir) ->
    N = case T of
            {string, L} -> "string" ++ integer_to_list(L);
            _ -> atom_to_list(T)
        end,
    list_to_atom(N ++ "_" ++ atom_to_list(Dir)).

%%--------------------------------------------------------------------
%% Cases
%%--------------------------------------------------------------------

every_type_in_both_word_orders(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config),
    ok = group(big, #{base => 0}),
    ok = group(little, #{base => 100, word_order => little}),
    ok = await_status(up),
    [begin
         V = cell_hal_test_io:sample(T, N),
         In = name(T, in),
         Out = name(T, out),
         ok = set(Peer, ir, address(G, In), words(T, V, Order)),
         ?assertEqual(V, await_value(G, In, V)),
         ok = cell_hal:write_sync(G, Out, V, ?WAIT),
         Words = words(T, V, Order),
         ?assertEqual(Words, get(Peer, hr, address(G, Out), length(Words)))
     end || {G, Order} <- [{big, big}, {little, little}], {T, _, _} <- cell_hal_test_io:types(),
            N <- [1, 2]],
    %% The layouts, word by word, as a PLC programmer writes them down.
    Check = fun(G, Point, V, Expected) ->
                    ok = cell_hal:write_sync(G, Point, V, ?WAIT),
                    ?assertEqual(Expected, get(Peer, hr, address(G, Point), length(Expected)))
            end,
    Check(big, int32_out, 16#12345678, [16#1234, 16#5678]),
    Check(little, int32_out, 16#12345678, [16#5678, 16#1234]),
    Check(big, int64_out, 16#0102030405060708, [16#0102, 16#0304, 16#0506, 16#0708]),
    Check(little, int64_out, 16#0102030405060708, [16#0708, 16#0506, 16#0304, 16#0102]),
    Check(big, real_out, 1.0, [16#3F80, 0]),
    Check(little, real_out, -2.5, [0, 16#C020]),
    Check(big, lreal_out, 1.0, [16#3FF0, 0, 0, 0]),
    Check(big, string10_out, <<"cellrt">>, [$c * 256 + $e, $l * 256 + $l, $r * 256 + $t, 0, 0]),
    Check(big, sbyte_out, -1, [16#FFFF]),
    Check(big, date_out, {1970, 1, 2}, [1, 16#5180]),
    Check(big, time_out, 1500, [0, 1500]).

all_four_tables(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config),
    ok = group(io, #{base => 10}),
    ok = await_status(up),
    %% Coils: written by the HAL, read as inputs too.
    ok = cell_hal:write_sync(io, coil_out, true, ?WAIT),
    ?assertEqual([1], get(Peer, co, 10, 1)),
    ok = set(Peer, co, 11, [1]),
    true = await_value(io, coil_in, true),
    %% Discrete inputs.
    ok = set(Peer, di, 10, [1]),
    true = await_value(io, discrete_in, true),
    ok = set(Peer, di, 10, [0]),
    false = await_value(io, discrete_in, false),
    %% A bit of a holding register: the other bits stay as the device has them.
    ok = set(Peer, hr, 210, [16#F0F0]),
    ok = cell_hal:write_sync(io, bit_out, true, ?WAIT),
    ?assertEqual([16#F0F8], get(Peer, hr, 210, 1)),
    ok = set(Peer, hr, 210, [16#FFFF]),
    ok = cell_hal:write_sync(io, bit_out, false, ?WAIT),
    ?assertEqual([16#FFF7], get(Peer, hr, 210, 1)),
    %% A bit of an input register.
    ok = set(Peer, ir, 210, [1 bsl 12]),
    true = await_value(io, bit_in, true),
    ok = set(Peer, ir, 210, [16#EFFF]),
    false = await_value(io, bit_in, false),
    %% The whole image is read in few requests: inputs on input registers, coils and
    %% discrete inputs, and the input register bit beyond a gap.
    {ok, #{status := up}} = cell_hal:info(plc).

raw_functions(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config),
    ok = await_status(up),
    R = fun(Req) -> cell_hal:request(plc, Req, 2000) end,
    ok = set(Peer, co, 20, [1, 0, 1]),
    ?assertEqual({ok, [true, false, true]}, R({read_coils, 20, 3})),
    ok = set(Peer, di, 30, [0, 1]),
    ?assertEqual({ok, [false, true]}, R({read_discrete_inputs, 30, 2})),
    ok = set(Peer, hr, 40, [7, 65535]),
    ?assertEqual({ok, <<7:16, 65535:16>>}, R({read_holding_registers, 40, 2})),
    ok = set(Peer, ir, 50, [9]),
    ?assertEqual({ok, <<9:16>>}, R({read_input_registers, 50, 1})),
    ?assertEqual({ok, ok}, R({write_single_coil, 60, true})),
    ?assertEqual([1], get(Peer, co, 60, 1)),
    ?assertEqual({ok, ok}, R({write_single_register, 61, 4242})),
    ?assertEqual([4242], get(Peer, hr, 61, 1)),
    ?assertEqual({ok, ok}, R({write_multiple_coils, 70, [true, true, false, true]})),
    ?assertEqual([1, 1, 0, 1], get(Peer, co, 70, 4)),
    ?assertEqual({ok, ok}, R({write_multiple_registers, 80, <<1:16, 2:16, 3:16>>})),
    ?assertEqual([1, 2, 3], get(Peer, hr, 80, 3)),
    ok = set(Peer, hr, 90, [16#0012]),
    ?assertEqual({ok, ok}, R({mask_write_register, 90, 16#F2, 16#25})),
    ?assertEqual([16#0017], get(Peer, hr, 90, 1)),
    ok = set(Peer, hr, 100, [5, 6]),
    ?assertEqual({ok, <<5:16, 6:16>>},
                 R({read_write_registers, 100, 2, 110, <<11:16, 12:16>>})),
    ?assertEqual([11, 12], get(Peer, hr, 110, 2)),
    %% Both sides of the protocol's limits, against the device.
    ?assertMatch({ok, <<_:250/binary>>}, R({read_holding_registers, 0, 125})),
    ?assertEqual({error, {bad_request, quantity}}, R({read_holding_registers, 0, 126})),
    ?assertMatch({ok, L} when length(L) =:= 2000, R({read_coils, 0, 2000})),
    ?assertEqual({error, {bad_request, quantity}}, R({read_coils, 0, 2001})),
    ?assertEqual({ok, ok}, R({write_multiple_registers, 200, <<0:(123 * 16)>>})),
    ?assertEqual({error, {bad_request, quantity}},
                 R({write_multiple_registers, 200, <<0:(124 * 16)>>})),
    ?assertEqual({ok, ok}, R({write_multiple_coils, 0, lists:duplicate(1968, false)})),
    ?assertEqual({error, {bad_request, quantity}},
                 R({write_multiple_coils, 0, lists:duplicate(1969, false)})),
    ?assertEqual({error, {bad_request, request}}, R(hello)).

exceptions(Config) ->
    Peer = ?config(peer, Config),
    Kind = ?config(kind, Config),
    ok = connect(Config),
    ok = await_status(up),
    R = fun(Req, T) -> cell_hal:request(plc, Req, T) end,
    Beyond = case Kind of pymodbus -> 2000; libmodbus -> 10000 end,
    ?assertEqual({error, {modbus_exception, 2, illegal_data_address}},
                 R({read_holding_registers, Beyond - 1, 2}, 2000)),
    ?assertEqual({error, {modbus_exception, 1, illegal_function}},
                 R({user_function, 65, <<>>}, 2000)),
    case Kind of
        libmodbus ->
            [] = cmd(Peer, "reject 6", []),
            ?assertEqual({error, {modbus_exception, 1, illegal_function}},
                         R({write_single_register, 0, 1}, 2000)),
            ?assertEqual({error, {modbus_exception, 11, gateway_target_failed_to_respond}},
                         R({7, {read_holding_registers, 0, 1}}, 2000));
        pymodbus ->
            %% pymodbus answers nothing for a unit it does not serve.
            ?assertEqual({error, timeout}, R({7, {read_holding_registers, 0, 1}}, 300))
    end,
    %% None of this took the connection down.
    ?assertEqual(up, cell_hal:status(plc)),
    ?assertEqual({ok, <<0:16>>}, R({read_holding_registers, 0, 1}, 2000)).

%% A group placed where the device has no registers: its point reads unavailable, with
%% the exception in words; the other group and the connection go on.
refused_poll_faults_its_points(Config) ->
    Kind = ?config(kind, Config),
    Peer = ?config(peer, Config),
    ok = cell_log:subscribe(),
    ok = connect(Config),
    ok = await_status(up),
    Beyond = case Kind of pymodbus -> 2000; libmodbus -> 10000 end,
    ok = group(io, #{base => Beyond, only => [int16_in]}),
    ok = group(io2, #{base => 0, only => [int16_in]}),
    %% Placed before or after the point is found refused, the watch ends with why.
    {ok, Ref} = cell_hal:watch(io, int16_in, {eq, 1}),
    #{{io, int16_in} := Logged} = await_logs(error, [{io, int16_in}]),
    {error, {unavailable, Why}} = cell_hal:read(io, int16_in),
    receive {cell_hal_unavailable, Ref, Ended} -> ?assertEqual(Why, Ended)
    after ?WAIT -> ct:fail(watch_not_ended) end,
    ct:log("~s", [Why]),
    ?assertEqual(Logged, Why),
    ?assertEqual(iolist_to_binary(["the PLC refuses this address (illegal data address, "
                                   "Modbus exception 2): read input registers ",
                                   integer_to_list(Beyond + 4), " (unit 1)"]), Why),
    ok = set(Peer, ir, 4, [321]),
    321 = await_value(io2, int16_in, 321),
    {ok, #{status := up, faults := [#{point := {io, int16_in}, reason := Why}]}} =
        cell_hal:info(plc),
    never_down(),
    ok = cell_hal:remove_group(io),
    {ok, #{status := up, faults := []}} = cell_hal:info(plc),
    ok = set(Peer, ir, 4, [322]),
    322 = await_value(io2, int16_in, 322),
    %% Added again, still refused: unavailable again.
    ok = group(io, #{base => Beyond, only => [int16_in]}),
    #{{io, int16_in} := Why} = await_logs(error, [{io, int16_in}]),
    ?assertEqual({error, {unavailable, Why}}, cell_hal:read(io, int16_in)),
    never_down().

refused_write(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config),
    ok = group(io, #{base => 0}),
    ok = await_status(up),
    case ?config(kind, Config) of
        libmodbus ->
            [] = cmd(Peer, "reject 5", []),
            ok = cell_log:subscribe(),
            ?assertEqual({error, {modbus_exception, 1, illegal_function}},
                         cell_hal:write_sync(io, coil_out, true, ?WAIT)),
            %% An asynchronous write the device refuses is logged for the operator.
            ok = cell_hal:write(io, coil_out, false),
            {cell_log, #{text := Text, level := error}} =
                receive {cell_log, #{source := <<"hal/plc">>, level := error}} = M -> M
                after ?WAIT -> ct:fail(not_logged) end,
            ?assertEqual(<<"writing io.coil_out := false on plc failed: the PLC does not offer "
                           "this function (illegal function, Modbus exception 1)">>, Text),
            ok = cell_log:unsubscribe();
        pymodbus ->
            ok
    end,
    ?assertEqual(up, cell_hal:status(plc)).

%% The server dies while being polled and comes back on the same port with another
%% image: the HAL goes down, presents nothing while down, and publishes only values
%% the server really held.
server_killed_mid_poll(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config, #{poll_ms => 5}),
    ok = group(io, #{base => 0}),
    ok = await_status(up),
    Old = 1111111, New = 2222222,
    ok = set(Peer, ir, address(io, int32_in), words(int32, Old, big)),
    ok = set(Peer, ir, address(io, uint32_in), words(uint32, Old, big)),
    Old = await_value(io, int32_in, Old),
    Old = await_value(io, uint32_in, Old),
    ok = cell_hal:subscribe(io, int32_in),
    ok = cell_hal:subscribe(io, uint32_in),
    kill_peer(Peer),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    ?assertEqual({error, disconnected}, cell_hal:read(io, int32_in)),
    ?assertEqual({error, disconnected}, cell_hal:write(io, int32_out, 1)),
    Peer2 = start_peer(Config, maps:get(tcp, Peer)),
    try
        ok = set(Peer2, ir, address(io, int32_in), words(int32, New, big)),
        ok = set(Peer2, ir, address(io, uint32_in), words(uint32, New, big)),
        receive {cell_hal_conn, plc, up} -> ok after ?WAIT -> ct:fail(not_up) end,
        New = await_value(io, int32_in, New),
        New = await_value(io, uint32_in, New),
        %% Everything published until the new image was read is in the mailbox now.
        Published = drain_values([]),
        ct:log("published ~p", [Published]),
        %% The restarted server may answer a poll before the suite set its image:
        %% then zero is what it held. Nothing else may ever appear.
        [?assert(lists:member(V, [Old, New, 0])) || {_, V} <- Published],
        ?assertEqual(New, element(2, lists:last([P || {int32_in, _} = P <- Published])))
    after
        stop_peer(Peer2)
    end.

drain_values(Acc) ->
    receive {cell_hal, {io, P}, V} -> drain_values([{P, V} | Acc])
    after 0 -> lists:reverse(Acc)
    end.

server_stops_answering(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config, #{timeout_ms => 300}),
    ok = group(io, #{base => 0, only => [int16_in, int16_out]}),
    ok = await_status(up),
    T0 = erlang:monotonic_time(millisecond),
    [] = cmd(Peer, "silent 1", []),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    ct:log("down after ~b ms", [erlang:monotonic_time(millisecond) - T0]),
    {ok, #{reason := Reason}} = cell_hal:info(plc),
    ct:log("~s", [Reason]),
    ?assertNotEqual(nomatch, binary:match(Reason, <<"no answer within 300 ms">>)),
    ?assertEqual({error, disconnected}, cell_hal:read(io, int16_in)),
    ?assertEqual({error, disconnected}, cell_hal:write_sync(io, int16_out, 1, 1000)),
    [] = cmd(Peer, "silent 0", []),
    answering_again(erlang:monotonic_time(millisecond) + ?WAIT).

%% The connection comes back once the server answers. A reconnection made while it was
%% still silent may have reported `up' and gone down again: the write that counts is
%% one made after an `up', within the deadline.
answering_again(Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive {cell_hal_conn, plc, up} -> ok after Left -> ct:fail(not_up) end,
    case cell_hal:write_sync(io, int16_out, 3, ?WAIT) of
        ok -> ok;
        {error, disconnected} -> answering_again(Deadline)
    end.

%% A caller's deadline holds even when the device takes longer; the request that
%% timed out leaves the connection usable.
per_request_timeout(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config, #{timeout_ms => 5000}),
    ok = await_status(up),
    [] = cmd(Peer, "silent 1", []),
    T0 = erlang:monotonic_time(millisecond),
    ?assertEqual({error, timeout}, cell_hal:request(plc, {read_holding_registers, 0, 1}, 200)),
    Elapsed = erlang:monotonic_time(millisecond) - T0,
    ?assert(Elapsed >= 200 andalso Elapsed < 2000),
    [] = cmd(Peer, "silent 0", []),
    ?assertEqual(up, cell_hal:status(plc)),
    ok = set(Peer, hr, 0, [5]),
    ?assertEqual({ok, <<5:16>>}, cell_hal:request(plc, {read_holding_registers, 0, 1}, 2000)).

%% Many requests in flight on one connection, from many callers: each gets its own
%% answer.
pipelined_requests(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config, #{max_in_flight => 16}),
    ok = await_status(up),
    ok = set(Peer, hr, 0, lists:seq(1000, 1099)),
    Self = self(),
    Pids = [spawn_link(fun() ->
                               Results = [cell_hal:request(plc, {read_holding_registers, A, 1}, 5000)
                                          || _ <- lists:seq(1, 20), A <- [I, I + 50]],
                               Self ! {done, I, Results}
                       end) || I <- lists:seq(0, 49)],
    [receive {done, I, Results} ->
         ?assertEqual(lists:append(lists:duplicate(20, [{ok, <<(1000 + I):16>>},
                                                        {ok, <<(1050 + I):16>>}])), Results)
     after ?WAIT * 3 -> ct:fail(no_answers)
     end || I <- lists:seq(0, length(Pids) - 1)].

connection_refused(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config),
    ok = await_status(up),
    ok = cell_log:subscribe(),
    kill_peer(Peer),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    {cell_log, #{text := Text}} =
        receive {cell_log, #{source := <<"hal/plc">>, text := <<"cannot connect", _/binary>>}} = M -> M
        after ?WAIT -> ct:fail(no_log) end,
    Expected = iolist_to_binary(io_lib:format("cannot connect to plc (127.0.0.1:~b): connection "
                                              "refused; retrying in", [maps:get(tcp, Peer)])),
    ?assertEqual(Expected, binary:part(Text, 0, byte_size(Expected))),
    ok = cell_log:unsubscribe().

%% One address refused: the points of the request that reads it are unavailable with
%% the exception in words, every other point goes on, and the connection stays up.
%% Readable again, they are usable again with the value the PLC holds.
refused_address_faults_its_request(Config) ->
    Peer = ?config(peer, Config),
    %% b.int16_in (input register 24) is refused; b.uint16_in (25) is read by the
    %% same request.
    [] = cmd(Peer, "refuse ir 24 2", []),
    ok = set(Peer, ir, 4, [11]),
    ok = set(Peer, ir, 24, [22, 33]),
    ok = set(Peer, co, 1, [1]),
    ok = cell_log:subscribe(),
    ok = connect(Config, #{refused_retry_ms => 20, max_refused_retry_ms => 100}),
    ok = group(a, #{base => 0, only => [int16_in, coil_in, discrete_in]}),
    ok = group(b, #{base => 20, only => [int16_in, uint16_in]}),
    ok = await_status(up),
    Logged = await_logs(error, [{b, int16_in}, {b, uint16_in}]),
    Words = <<"the PLC refuses this address (illegal data address, Modbus exception 2): "
              "read input registers 24..25 (unit 1)">>,
    ?assertEqual(#{{b, int16_in} => Words, {b, uint16_in} => Words}, Logged),
    ?assertEqual({error, {unavailable, Words}}, cell_hal:read(b, int16_in)),
    ?assertEqual({error, {unavailable, Words}}, cell_hal:read(b, uint16_in)),
    %% A task waiting for a refused point is told at once, not left waiting.
    {ok, Ref} = cell_hal:watch(b, int16_in, {eq, 22}),
    receive {cell_hal_unavailable, Ref, Words} -> ok after ?WAIT -> ct:fail(watch_not_ended) end,
    %% The rest of the image is read, and keeps being read.
    11 = await_value(a, int16_in, 11),
    true = await_value(a, coil_in, true),
    ?assertEqual({ok, false}, cell_hal:read(a, discrete_in)),
    ok = set(Peer, ir, 4, [12]),
    12 = await_value(a, int16_in, 12),
    {ok, #{status := up, faults := Faults}} = cell_hal:info(plc),
    ?assertEqual([{b, int16_in}, {b, uint16_in}], [K || #{point := K} <- Faults]),
    never_down(),
    %% The PLC answers for the address again: both points come back.
    ok = set(Peer, ir, 24, [44]),
    [] = cmd(Peer, "refuse ir 24 0", []),
    _ = await_logs(silent, [{b, int16_in}, {b, uint16_in}]),
    ?assertEqual({ok, 44}, cell_hal:read(b, int16_in)),
    ?assertEqual({ok, 33}, cell_hal:read(b, uint16_in)),
    {ok, #{status := up, faults := []}} = cell_hal:info(plc),
    never_down().

%% A PLC that refuses each request every fifth time it is asked (busy) still lets the
%% connection come up, and every point keeps being read: a refused request only costs
%% its points one read. (Counted across requests, the refusals could land on the same
%% request at every ask: the HAL asks a refused request again one poll later, and with
%% three requests a poll that cycle is five requests long.)
exception_every_fifth_request(Config) ->
    Peer = ?config(peer, Config),
    [] = cmd(Peer, "fail_every 5 6", []),
    ok = connect(Config, #{refused_retry_ms => 20, max_refused_retry_ms => 40}),
    ok = group(a, #{base => 0, only => [int16_in, coil_in, discrete_in]}),
    ok = await_status(up),
    [begin
         ok = set(Peer, ir, 4, [V]),
         V = await_value(a, int16_in, V),
         ok = set(Peer, co, 1, [V rem 2]),
         _ = await_value(a, coil_in, V rem 2 =:= 1)
     end || V <- lists:seq(1, 10)],
    ?assert(hd(cmd(Peer, "count ir 4", [])) >= 10),
    never_down().

%% A write to an address the PLC refuses: the caller is told, in a term and in the log,
%% and the connection stays up (the read-back of that output at connect, refused too,
%% did not take it down either).
refused_write_keeps_the_connection(Config) ->
    Peer = ?config(peer, Config),
    [] = cmd(Peer, "refuse hr 4 2", []),
    ok = connect(Config),
    ok = group(a, #{base => 0, only => [int16_in, int16_out]}),
    ok = await_status(up),
    ?assertEqual({error, {modbus_exception, 2, illegal_data_address}},
                 cell_hal:write_sync(a, int16_out, 5, ?WAIT)),
    ok = cell_log:subscribe(),
    ok = cell_hal:write(a, int16_out, 6),
    {cell_log, #{text := Text}} =
        receive {cell_log, #{source := <<"hal/plc">>, level := error}} = M -> M
        after ?WAIT -> ct:fail(not_logged) end,
    ?assertEqual(<<"writing a.int16_out := 6 on plc failed: the PLC refuses this address "
                   "(illegal data address, Modbus exception 2)">>, Text),
    ok = set(Peer, ir, 4, [9]),
    9 = await_value(a, int16_in, 9),
    {ok, #{status := up, faults := []}} = cell_hal:info(plc),
    never_down().

%% Every request of a group refused, by default: its points are unavailable, the other
%% group goes on, and the refused requests rest (here longer than the test) instead of
%% going out at every poll.
whole_group_refused_faults_it(Config) ->
    Peer = ?config(peer, Config),
    [] = cmd(Peer, "refuse ir 44 2", []),
    [] = cmd(Peer, "refuse co 41 11", []),
    ok = cell_log:subscribe(),
    ok = connect(Config, #{refused_retry_ms => 60000, max_refused_retry_ms => 60000}),
    ok = group(a, #{base => 0, only => [int16_in]}),
    ok = group(c, #{base => 40, only => [int16_in, coil_in]}),
    ok = await_status(up),
    #{{c, coil_in} := CoilWhy} = await_logs(error, [{c, int16_in}, {c, coil_in}]),
    ?assertEqual(<<"the device behind the gateway did not answer (gateway target failed to "
                   "respond, Modbus exception 11): read coils 41 (unit 1)">>, CoilWhy),
    ok = set(Peer, ir, 4, [5]),
    5 = await_value(a, int16_in, 5),
    %% Thirty more reads of a: c's requests went out once each.
    [] = cmd(Peer, "notify_after ir 4 ~b", [hd(cmd(Peer, "count ir 4", [])) + 30]),
    #{port := P} = Peer,
    receive {P, {data, {eol, <<"reached">>}}} -> ok after ?WAIT -> ct:fail(not_polled) end,
    ?assertEqual([1], cmd(Peer, "count ir 44", [])),
    ?assertEqual([1], cmd(Peer, "count co 41", [])),
    {error, {unavailable, _}} = cell_hal:read(c, int16_in),
    never_down().

%% `refused_group => disconnect': one refused request of a group leaves the connection
%% up; every request of the group refused is a lost connection, retried at the
%% reconnect backoff until the PLC answers for the group again.
whole_group_refused_disconnects(Config) ->
    Peer = ?config(peer, Config),
    [] = cmd(Peer, "refuse ir 44 2", []),
    ok = cell_log:subscribe(),
    ok = connect(Config, #{refused_group => disconnect, refused_retry_ms => 20,
                           max_refused_retry_ms => 40}),
    ok = group(a, #{base => 0, only => [int16_in]}),
    ok = group(c, #{base => 40, only => [int16_in, coil_in]}),
    ok = await_status(up),
    _ = await_logs(error, [{c, int16_in}]),
    ok = set(Peer, co, 41, [1]),
    true = await_value(c, coil_in, true),
    never_down(),
    [] = cmd(Peer, "refuse co 41 2", []),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    {ok, #{reason := Reason}} = cell_hal:info(plc),
    ct:log("~s", [Reason]),
    ?assertNotEqual(nomatch, binary:match(Reason, <<"the PLC refuses every request of IO group c">>)),
    ?assertEqual({error, disconnected}, cell_hal:read(a, int16_in)),
    [] = cmd(Peer, "refuse ir 44 0", []),
    [] = cmd(Peer, "refuse co 41 0", []),
    ok = set(Peer, ir, 44, [7]),
    ok = await_status(up),
    7 = await_value(c, int16_in, 7),
    {ok, #{faults := []}} = cell_hal:info(plc).

%% The connection went down at no point so far.
never_down() ->
    receive {cell_hal_conn, plc, down} -> ct:fail(went_down) after 0 -> ok end,
    ?assertEqual(up, cell_hal:status(plc)).

%% The worker's log lines, one per point, that it cannot be used (`error') or can be
%% used again (`silent', a notice): point => what the line says after the point.
await_logs(Level, Points) ->
    await_logs(Level, Points, #{}, erlang:monotonic_time(millisecond) + ?WAIT).

await_logs(_Level, [], Got, _Deadline) ->
    Got;
await_logs(Level, Points, Got, Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {cell_log, #{source := <<"hal/plc">>, level := Level, text := Text}} ->
            case [P || {G, N} = P <- Points, is_point_line(Text, G, N)] of
                [P] ->
                    After = case binary:split(Text, <<"cannot be used: ">>) of
                                [_, Why] -> Why;
                                [_] -> Text
                            end,
                    await_logs(Level, Points -- [P], Got#{P => After}, Deadline);
                [] ->
                    await_logs(Level, Points, Got, Deadline)
            end
    after Left ->
            ct:fail({not_logged, Level, Points, cell_hal:info(plc)})
    end.

is_point_line(Text, G, N) ->
    Name = iolist_to_binary([atom_to_list(G), $., atom_to_list(N), " ("]),
    binary:longest_common_prefix([Text, Name]) =:= byte_size(Name).

%% Faulty frames from the device close only that connection, with the reason in words,
%% and never put a value in front of a task.
malformed_frames_close_the_connection(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config, #{poll_ms => 50}),
    ok = group(io, #{base => 0, only => [int16_in]}),
    ok = await_status(up),
    0 = await_value(io, int16_in, 0),
    ok = cell_hal:subscribe(io, int16_in),
    Reasons = [{tid, <<"answered transaction">>}, {unit, <<"answered for unit">>},
               {proto, <<"protocol id 1">>}, {oversize, <<"announced 300 bytes">>},
               {fc, <<"answered function">>}, {count, <<"counted 7 data bytes">>}],
    [begin
         [] = cmd(Peer, "mangle ~s", [Kind]),
         receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail({not_down, Kind}) end,
         {ok, #{reason := Reason}} = cell_hal:info(plc),
         ct:log("~s: ~s", [Kind, Reason]),
         ?assertNotEqual(nomatch, binary:match(Reason, Words), Kind),
         receive {cell_hal_conn, plc, up} -> ok after ?WAIT -> ct:fail({not_up, Kind}) end
     end || {Kind, Words} <- Reasons],
    %% The faulty frames carried 42; it was never published.
    receive {cell_hal, {io, int16_in}, V} -> ct:fail({published, V}) after 0 -> ok end,
    ?assertEqual({ok, 0}, cell_hal:read(io, int16_in)).

%% Transaction ids wrap around after 65535 without confusing answers.
transaction_ids_wrap_around(Config) ->
    Peer = ?config(peer, Config),
    ok = connect(Config, #{max_in_flight => 32}),
    ok = await_status(up),
    ok = set(Peer, hr, 0, lists:seq(0, 99)),
    Self = self(),
    N = 70000,
    Workers = 16,
    [spawn_link(fun() ->
                        Bad = [A || I <- lists:seq(1, N div Workers),
                                    A <- [(I + W) rem 100],
                                    cell_hal:request(plc, {read_holding_registers, A, 1}, 5000)
                                        =/= {ok, <<A:16>>}],
                        Self ! {done, W, Bad}
                end) || W <- lists:seq(1, Workers)],
    [receive {done, W, Bad} -> ?assertEqual({W, []}, {W, Bad})
     after 120000 -> ct:fail(too_slow)
     end || W <- lists:seq(1, Workers)],
    ?assertEqual(up, cell_hal:status(plc)).
