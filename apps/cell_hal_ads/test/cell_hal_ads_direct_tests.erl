%% Unit tests of direct reads: the test plays the connection (a helper process owns
%% the tables and a real loopback socket) and the PLC (the other end of that socket),
%% so every answer, its timing and its epoch are the test's to choose.
-module(cell_hal_ads_direct_tests).
-include_lib("eunit/include/eunit.hrl").

-define(D, cell_hal_ads_direct).
-define(WAIT, 5000).
-define(X, {<<"MAIN.x">>, int32}).
-define(Y, {<<"MAIN.y">>, int32}).
-define(READ_X, <<16#F005:32/little, 7:32/little, 4:32/little>>).

%%--------------------------------------------------------------------
%% A connection and a PLC
%%--------------------------------------------------------------------

-record(env, {conn :: pid(), tables :: ?D:tables(), counters :: ?D:counters(),
              socket :: gen_tcp:socket(), plc :: gen_tcp:socket()}).

-define(MAX_IN_FLIGHT, 3).

setup() ->
    %% small kernel buffers on both ends: a PLC that stops reading fills them soon
    {ok, L} = gen_tcp:listen(0, [binary, {active, false}, {ip, loopback}, {recbuf, 4096}]),
    {ok, Port} = inet:port(L),
    Test = self(),
    Conn = spawn(fun() -> conn(Test, Port) end),
    {ok, Plc} = gen_tcp:accept(L, ?WAIT),
    ok = gen_tcp:close(L),
    receive
        {Conn, ready, T, Counters, S} ->
            #env{conn = Conn, tables = T, counters = Counters, socket = S, plc = Plc}
    after ?WAIT -> error(no_connection)
    end.

cleanup(#env{conn = Conn, plc = Plc}) ->
    exit(Conn, kill),
    gen_tcp:close(Plc).

%% The connection: owns the tables and the socket, publishes two variables, forwards
%% what callers tell it to the test, and runs what the test asks of it.
conn(Test, Port) ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false},
                                                     {sndbuf, 4096}]),
    T = ?D:new(),
    Counters = ?D:counters(),
    ok = ?D:announce(self(), T),
    ok = ?D:open(T, #{pid => self(), socket => S, target => {{1, 2, 3, 4, 1, 1}, 851},
                      source => {{5, 6, 7, 8, 1, 1}, 32905}, epoch => 1,
                      mode => #{sum => true, max_sum => 2}, counters => Counters,
                      max_in_flight => ?MAX_IN_FLIGHT},
                 [{<<"MAIN.x">>, int32, {<<"MAIN.X">>, int32}, {16#F005, 7, 4}},
                  {<<"MAIN.y">>, int32, {<<"MAIN.Y">>, int32}, {16#F005, 8, 4}}]),
    Test ! {self(), ready, T, Counters, S},
    conn_loop(Test).

conn_loop(To) ->
    receive
        {run, From, Fun} -> From ! {self(), Fun()}, conn_loop(From);
        Cast -> To ! {conn_got, Cast}, conn_loop(To)
    end.

%% Runs `Fun' in the connection, which from then on forwards what it gets to the
%% caller.
run(#env{conn = Conn}, Fun) ->
    Conn ! {run, self(), Fun},
    receive {Conn, Result} -> Result after ?WAIT -> error(conn_silent) end.

%% A caller reading in a process of its own: its result, and what else it received.
reader(E, Vars, Timeout) ->
    reader(E, Vars, Timeout, []).

%% ... with these messages waiting when it reads.
reader(#env{conn = Conn}, Vars, Timeout, Waiting) ->
    Test = self(),
    spawn(fun() ->
                  [self() ! M || M <- Waiting],
                  Result = ?D:read_vars(Conn, Vars, Timeout),
                  {messages, Left} = process_info(self(), messages),
                  Test ! {read, self(), Result, Left}
          end).

read_result(Reader) ->
    receive {read, Reader, Result, Left} -> {Result, Left}
    after ?WAIT -> error(no_result)
    end.

%% The frame the PLC received, and its invoke id.
request(#env{plc = Plc}) ->
    {ok, <<0:16, Len:32/little>>} = gen_tcp:recv(Plc, 6, ?WAIT),
    {ok, <<_:16/binary, Cmd:16/little, 4:16/little, DLen:32/little, 0:32, Invoke:32/little,
           Data:DLen/binary>>} = gen_tcp:recv(Plc, Len, ?WAIT),
    {Cmd, Invoke, Data}.

value(V) -> <<0:32, 4:32/little, V:32/little>>.

%% The connection's side of an answer.
answer(#env{tables = T, counters = Counters}, Invoke, Cmd, Error, Data, Epoch) ->
    ?D:answer(T, Counters, Invoke, Cmd, Error, Data, Epoch).

in_flight(#env{counters = Counters}) ->
    ?D:in_flight(Counters).

%% The PLC stops reading: the kernel's buffers fill, then bytes wait in the socket's
%% own queue. How many bytes were sent in all.
fill(#env{socket = S}) ->
    %% chunks shorter than the high watermark, so that what is left of one is too
    fill(S, binary:copy(<<0>>, 1024), 0).

fill(S, Chunk, Sent) ->
    case erlang:port_info(S, queue_size) of
        {queue_size, 0} ->
            ok = gen_tcp:send(S, Chunk),
            fill(S, Chunk, Sent + byte_size(Chunk));
        {queue_size, _} ->
            Sent
    end.

%% The socket's queue this short of its high watermark: the next frame fills it.
top_up(#env{socket = S}, Short) ->
    {ok, [{high_watermark, High}]} = inet:getopts(S, [high_watermark]),
    {queue_size, Queued} = erlang:port_info(S, queue_size),
    Top = High - Queued - Short,
    ok = gen_tcp:send(S, binary:copy(<<0>>, Top)),
    Top.

%% The PLC reads again, `N' bytes of filling first.
skip(#env{plc = Plc}, N) when N > 0 ->
    {ok, Bin} = gen_tcp:recv(Plc, min(N, 1 bsl 20), ?WAIT),
    skip(#env{plc = Plc}, N - byte_size(Bin));
skip(_, 0) ->
    ok.

%%--------------------------------------------------------------------
%% Tests
%%--------------------------------------------------------------------

direct_test_() ->
    {foreach, fun setup/0, fun cleanup/1,
     [fun(E) -> {name(F), ?_test(F(E))} end
      || F <- [fun answered/1, fun group_in_one_sum/1, fun ads_error_asks_for_the_version/1,
               fun older_epoch_goes_the_slow_way/1, fun other_command_goes_the_slow_way/1,
               fun timeout_leaves_nothing_behind/1,
               fun answer_claimed_before_timeout_is_given/1, fun caller_exits_mid_read/1,
               fun exited_callers_swept/1, fun disconnect_answers_all/1,
               fun closed_socket_goes_the_slow_way/1, fun connection_exits/1,
               fun what_the_tables_cannot_answer/1, fun withdrawn_variable/1,
               fun slots_shared_with_the_connection/1, fun queued_socket_goes_the_slow_way/1,
               fun full_socket_waits_for_the_plc/1,
               fun full_socket_waits_no_longer_than_send_timeout/1,
               fun full_socket_closed_ends_the_wait/1, fun busy_caller_goes_the_slow_way/1]]}.

name(F) ->
    {name, Name} = erlang:fun_info(F, name),
    atom_to_list(Name).

%% One variable: one Read by handle with an even invoke id; the answer decoded.
answered(E) ->
    R = reader(E, [?X], ?WAIT),
    {2, Invoke, ?READ_X} = request(E),
    ?assertEqual(0, Invoke band 1),
    ?assertEqual(1, in_flight(E)),
    ?assertEqual(ok, answer(E, Invoke, read, 0, value(42), 1)),
    ?assertEqual({{ok, [{ok, 42}]}, []}, read_result(R)),
    ?assertEqual(0, in_flight(E)),
    %% the next read takes the next id
    R2 = reader(E, [?X], ?WAIT),
    {2, Invoke2, _} = request(E),
    ?assertEqual(Invoke + 2, Invoke2),
    ok = answer(E, Invoke2, read, 0, value(-1), 1),
    ?assertEqual({{ok, [{ok, -1}]}, []}, read_result(R2)).

%% Two variables: one sum read (0xF080), answered per variable.
group_in_one_sum(E) ->
    R = reader(E, [?X, ?Y], ?WAIT),
    {9, Invoke, <<16#F080:32/little, 2:32/little, 16:32/little, 24:32/little, Items/binary>>} =
        request(E),
    ?assertEqual(<<16#F005:32/little, 7:32/little, 4:32/little,
                   16#F005:32/little, 8:32/little, 4:32/little>>, Items),
    Answer = <<0:32, 16:32/little, 0:32, 16#710:32/little, 42:32/little, 0:32>>,
    ok = answer(E, Invoke, read_write, 0, Answer, 1),
    ?assertMatch({{ok, [{ok, 42}, {error, {ads_error, 16#710, _}}]}, []}, read_result(R)).

%% An error a stale handle gives: the read says so, and the connection is told to
%% look at the symbol version.
ads_error_asks_for_the_version(E) ->
    ok = run(E, fun() -> ok end),
    R = reader(E, [?X], ?WAIT),
    {2, Invoke, _} = request(E),
    ok = answer(E, Invoke, read, 16#710, <<>>, 1),
    ?assertMatch({{ok, [{error, {ads_error, 16#710, _}}]}, []}, read_result(R)),
    S = E#env.socket,
    receive {conn_got, {'$gen_cast', {?D, stale, S}}} -> ok
    after ?WAIT -> error(no_stale_notice)
    end.

%% Handles were given back since the read was sent: its answer is not used.
older_epoch_goes_the_slow_way(E) ->
    R = reader(E, [?X], 3000),
    {2, Invoke, _} = request(E),
    ok = answer(E, Invoke, read, 0, value(42), 2),
    {{slow, Left}, []} = read_result(R),
    ?assertEqual(0, in_flight(E)),
    ?assert(Left =< 3000 andalso Left > 1000).

%% An answer to another command: the caller goes the slow way, the connection is
%% told not to trust its peer.
other_command_goes_the_slow_way(E) ->
    R = reader(E, [?X], ?WAIT),
    {2, Invoke, _} = request(E),
    ?assertEqual({unexpected, read}, answer(E, Invoke, write, 0, <<0:32>>, 1)),
    ?assertMatch({{slow, _}, []}, read_result(R)).

%% No answer in time: `{error, timeout}', the connection told when the read was sent;
%% an answer after that reaches nobody and leaves no message behind.
timeout_leaves_nothing_behind(E) ->
    ok = run(E, fun() -> ok end),
    Before = erlang:monotonic_time(),
    R = reader(E, [?X], 50),
    {2, Invoke, _} = request(E),
    ?assertEqual({{error, timeout}, []}, read_result(R)),
    S = E#env.socket,
    receive {conn_got, {'$gen_cast', {?D, expired, S, Sent}}} -> ?assert(Sent >= Before)
    after ?WAIT -> error(no_expired_notice)
    end,
    ?assertEqual(0, in_flight(E)),
    ?assertEqual(unknown, answer(E, Invoke, read, 0, value(42), 1)),
    ?assertEqual(0, in_flight(E)).

%% The connection took the registration before the caller's timeout and answers after
%% it: the caller waits for that answer, which is neither lost nor left behind.
answer_claimed_before_timeout_is_given(E) ->
    R = reader(E, [?X], 500),
    {2, Invoke, _} = request(E),
    %% held while its registration is taken, so that its timeout comes after
    true = erlang:suspend_process(R),
    Claim = ?D:claim(E#env.tables, E#env.counters, Invoke),
    1 = erlang:trace(R, true, [running]),
    true = erlang:resume_process(R),
    %% its timeout passed: it found its registration gone, and waits for the answer
    ok = await_out(R, {?D, await, 2}),
    ?assertEqual({messages, []}, process_info(R, messages)),
    ok = ?D:settle(Claim, read, 0, value(42), 1),
    ?assertEqual({{ok, [{ok, 42}]}, []}, read_result(R)).

await_out(Pid, MFA) ->
    receive
        {trace, Pid, out, MFA} -> ok;
        {trace, Pid, _, _} -> await_out(Pid, MFA)
    after ?WAIT -> error({not_waiting, MFA})
    end.

%% A caller that exits with a read in flight: its answer goes nowhere, nothing breaks.
caller_exits_mid_read(E) ->
    R = reader(E, [?X], ?WAIT),
    {2, Invoke, _} = request(E),
    exit(R, kill),
    ?assertEqual(ok, answer(E, Invoke, read, 0, value(42), 1)),
    ?assertEqual(0, in_flight(E)).

%% A caller that exits and whose answer never comes: swept.
exited_callers_swept(E) ->
    R = reader(E, [?X], ?WAIT),
    Alive = reader(E, [?Y], ?WAIT),
    {2, _, _} = request(E),
    {2, _, _} = request(E),
    Ref = monitor(process, R),
    exit(R, kill),
    receive {'DOWN', Ref, process, R, _} -> ok end,
    ?assertEqual(2, in_flight(E)),
    ?assertEqual(1, ?D:sweep(E#env.tables, E#env.counters)),
    ?assertEqual(1, in_flight(E)),
    exit(Alive, kill).

%% A lost connection answers every read in flight; nothing waits for answers after.
disconnect_answers_all(E) ->
    Rs = [reader(E, [V], ?WAIT) || V <- [?X, ?Y]],
    Invokes = [element(2, request(E)) || _ <- Rs],
    ok = ?D:fail_all(E#env.tables, disconnected),
    [?assertEqual({{error, disconnected}, []}, read_result(R)) || R <- Rs],
    [?assertEqual(unknown, answer(E, I, read, 0, value(1), 1)) || I <- Invokes].

%% The connection closed its socket and is about to withdraw it: a read that still
%% finds it goes the slow way, registering nothing.
closed_socket_goes_the_slow_way(E) ->
    ok = run(E, fun() -> gen_tcp:close(E#env.socket) end),
    ?assertMatch({{slow, _}, []}, read_result(reader(E, [?X], ?WAIT))),
    ?assertEqual(0, in_flight(E)).

%% The client exits with a read in flight: its monitor says so, at once, leaving
%% nothing behind. The reason is the monitor's: the client's exit reason if the client
%% took the monitor before it began to exit, `noproc' if after. Which comes first is
%% not ordered: the monitor is the reader's signal to the client, the exit the test's,
%% and the runtime orders signals only between one sender and one receiver, not along
%% a chain of causes (the PLC having the frame orders nothing between them): a loop of
%% this case alone saw `noproc' in 1 run in 300 to 63 in 300, with the reader's monitor
%% taken before its frame went out. A call to a process that exits at that moment has
%% the same two outcomes. What is ordered is the test's own signals: when the client
%% shows the reader's monitor to the test before the test's exit, the reason is the
%% client's.
connection_exits(E) ->
    R = reader(E, [?X], ?WAIT),
    {2, _, _} = request(E),
    {monitored_by, By} = process_info(E#env.conn, monitored_by),
    exit(E#env.conn, stopped),
    {{down, Reason}, []} = read_result(R),
    case lists:member(R, By) of
        true -> ?assertEqual(stopped, Reason);
        false -> ?assert(lists:member(Reason, [stopped, noproc]))
    end.

%% What the tables cannot answer at once goes the slow way, untouched: a variable not
%% published, a bad argument, a group beyond one sum command, no time, a client that
%% publishes nothing, a connection not ready.
what_the_tables_cannot_answer(E) ->
    Conn = E#env.conn,
    Cases = [{[{<<"MAIN.z">>, int32}], 100}, {[?X, {<<"MAIN.z">>, int32}], 100},
             {[?X, bad], 100}, {not_a_list, 100}, {[?X, ?Y, ?X], 100}, {[?X], 0}],
    ?assertEqual([{slow, T} || {_, T} <- Cases],
                 [?D:read_vars(Conn, Vars, T) || {Vars, T} <- Cases]),
    ?assertEqual({slow, 100}, ?D:read_vars(self(), [?X], 100)),
    ?assertEqual({slow, 100}, ?D:read_vars(no_such_client, [?X], 100)),
    ok = run(E, fun() -> ?D:close(E#env.tables) end),
    ?assertEqual({slow, 100}, ?D:read_vars(Conn, [?X], 100)),
    ?assertEqual(0, in_flight(E)).

%% A variable whose handle goes back is read the slow way; a read of it already in
%% flight gets its answer only if the epoch is still the one it read.
withdrawn_variable(E) ->
    R = reader(E, [?X], ?WAIT),
    {2, Invoke, _} = request(E),
    ok = run(E, fun() -> ?D:drop(E#env.tables, {<<"MAIN.X">>, int32}, 2) end),
    ok = answer(E, Invoke, read, 0, value(42), 2),
    ?assertMatch({{slow, _}, []}, read_result(R)),
    ?assertEqual({slow, 100}, ?D:read_vars(E#env.conn, [?X], 100)),
    %% the other variable is still read directly, in the new epoch
    R2 = reader(E, [?Y], ?WAIT),
    {2, Invoke2, _} = request(E),
    ok = answer(E, Invoke2, read, 0, value(7), 2),
    ?assertEqual({{ok, [{ok, 7}]}, []}, read_result(R2)).

%% `max_in_flight' counts the connection's requests and direct reads alike: with every
%% slot taken a read goes through the connection (which queues it), and a slot given
%% back is there for the next.
slots_shared_with_the_connection(E) ->
    Counters = E#env.counters,
    %% the connection's own requests
    [true = ?D:take_slot(Counters, ?MAX_IN_FLIGHT) || _ <- lists:seq(1, ?MAX_IN_FLIGHT - 1)],
    R = reader(E, [?X], ?WAIT),
    {2, Invoke, _} = request(E),
    ?assertEqual(?MAX_IN_FLIGHT, in_flight(E)),
    ?assertNot(?D:take_slot(Counters, ?MAX_IN_FLIGHT)),
    ?assertMatch({{slow, _}, []}, read_result(reader(E, [?Y], ?WAIT))),
    ?assertEqual(?MAX_IN_FLIGHT, in_flight(E)),
    ok = answer(E, Invoke, read, 0, value(1), 1),
    ?assertEqual({{ok, [{ok, 1}]}, []}, read_result(R)),
    %% an answer to the connection's own request frees its slot
    ok = ?D:free_slots(Counters, 1),
    ?assertEqual(?MAX_IN_FLIGHT - 2, in_flight(E)),
    R2 = reader(E, [?Y], ?WAIT),
    {2, Invoke2, _} = request(E),
    ok = answer(E, Invoke2, read, 0, value(2), 1),
    ?assertEqual({{ok, [{ok, 2}]}, []}, read_result(R2)).

%% Bytes wait in the socket's queue (the PLC reads slowly): a direct frame would wait
%% behind them, so the read goes through the connection, taking nothing.
queued_socket_goes_the_slow_way(E) ->
    _ = fill(E),
    ?assertMatch({{slow, _}, []}, read_result(reader(E, [?X], ?WAIT))),
    ?assertEqual(0, in_flight(E)).

%% The instant between the look at the socket's queue and the write cannot be staged
%% here; what the caller does after a write that filled the queue can: it waits for
%% the PLC to read, and is answered as usual.
full_socket_waits_for_the_plc(E) ->
    Sent = fill(E) + top_up(E, 10),
    W = writer(E),
    ok = await_out(start(W), {?D, sent, 1}),
    ok = skip(E, Sent),
    ?assertEqual(ok, writer_result(W)),
    ?assertMatch({2, 0, ?READ_X}, request(E)).

%% ... or for the socket's send timeout, the client's request timeout.
full_socket_waits_no_longer_than_send_timeout(E) ->
    ok = inet:setopts(E#env.socket, [{send_timeout, 100}]),
    _ = fill(E) + top_up(E, 10),
    T0 = erlang:monotonic_time(millisecond),
    ?assertEqual(error, writer_result(start(writer(E)))),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 100).

%% ... or for the connection to close the socket (as the client gives a connection
%% up: at once, dropping what is queued).
full_socket_closed_ends_the_wait(E) ->
    _ = fill(E) + top_up(E, 10),
    W = writer(E),
    ok = await_out(start(W), {?D, sent, 1}),
    S = E#env.socket,
    ok = run(E, fun() -> ok = inet:setopts(S, [{linger, {true, 0}}]), gen_tcp:close(S) end),
    ?assertEqual(error, writer_result(W)).

%% A caller's write of a direct read's frame (a Read of MAIN.x, invoke id 0), as the
%% direct read does it once it found the socket's queue empty; it starts when told,
%% traced.
writer(#env{socket = S}) ->
    Test = self(),
    Frame = cell_hal_ads_codec:encode_frame({{1, 2, 3, 4, 1, 1}, 851},
                                            {{5, 6, 7, 8, 1, 1}, 32905}, 0,
                                            {read, 16#F005, 7, 4}),
    spawn(fun() ->
                  receive go -> ok end,
                  true = erlang:port_command(S, Frame, [nosuspend]),
                  Test ! {written, self(), ?D:sent(S)}
          end).

start(W) ->
    1 = erlang:trace(W, true, [running]),
    W ! go,
    W.

writer_result(W) ->
    receive {written, W, Result} -> Result after ?WAIT -> error(writer_stuck) end.

%% A caller with many messages waiting goes through the connection, whose call does
%% not look through them; its messages stay as they were.
busy_caller_goes_the_slow_way(E) ->
    Many = [{other, I} || I <- lists:seq(1, 101)],
    ?assertEqual({{slow, ?WAIT}, Many}, read_result(reader(E, [?X], ?WAIT, Many))),
    ?assertEqual(0, in_flight(E)),
    %% with one fewer it reads directly
    Fewer = tl(Many),
    R = reader(E, [?X], ?WAIT, Fewer),
    {2, Invoke, _} = request(E),
    ok = answer(E, Invoke, read, 0, value(5), 1),
    ?assertEqual({{ok, [{ok, 5}]}, Fewer}, read_result(R)).
