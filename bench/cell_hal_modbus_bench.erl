%% @doc The Modbus TCP client against libmodbus's own client, both talking to the same
%% libmodbus server in the same run:
%% <ul>
%% <li>read holding registers (10): round trips a second and p99 latency, one request
%%   at a time and pipelined (libmodbus has no pipelining: its figure is sequential);</li>
%% <li>one full poll of an IO image of 2000 mixed points: requests a poll (beside one
%%   request a point, what reading tag by tag costs) and time a poll (beside libmodbus
%%   sending the same requests).</li>
%% </ul>
%% The C server and client are compiled here from the test peer and `bench/'. Ours is
%% measured at the driver, hosted by the benchmark process as a HAL worker hosts it,
%% and once through the HAL's worker (`cell_hal:request/3').
-module(cell_hal_modbus_bench).

-export([run/0]).

-define(ROUNDS, 7).
-define(SEQ_N, 4000).
-define(PIPE_N, 12000).
-define(WINDOW, 64).        %% requests in flight when pipelining
-define(POLL_WINDOW, 32).   %% more than one poll's requests: all of them at once
-define(POLLS, 60).
-define(POINTS, 2000).

-spec run() -> [cell_bench:result()].
run() ->
    Server = cell_bench:build_c("apps/cell_hal/test/cell_hal_modbus_SUITE_data/modbus_server.c",
                                "modbus_server"),
    Client = cell_bench:build_c("bench/modbus_client.c", "modbus_client"),
    Peer = cell_bench:start_c_server(Server),
    try
        Port = maps:get(tcp, Peer),
        Requests = poll_requests(),
        Plan = [[integer_to_list(Fc), $\s, integer_to_list(A), $\s, integer_to_list(N), $\n]
                || {Fc, A, N} <- Requests],
        %% Warm both up (connections, caches, the server's pages).
        _ = libmodbus(Client, Port, ["seq", "2000"]),
        _ = ours_sequential(Port, 2000),
        %% The other programs on the machine come and go: each round measures both
        %% sides one right after the other, and each figure is the median of rounds.
        Rounds = [#{lib => libmodbus(Client, Port, ["seq", integer_to_list(?SEQ_N)]),
                    seq => ours_sequential(Port, ?SEQ_N),
                    bare => bare_gen_tcp(Port, ?SEQ_N),
                    pipe => ours_pipelined(Port, ?PIPE_N, ?WINDOW),
                    lib_poll => libmodbus(Client, Port, ["poll", integer_to_list(?POLLS)], Plan),
                    poll => ours_poll(Port, ?POLLS, 1),
                    poll_pipe => ours_poll(Port, ?POLLS, ?POLL_WINDOW)}
                  || _ <- lists:seq(1, ?ROUNDS)],
        M = fun(Side, Key) -> median([maps:get(Key, maps:get(Side, R)) || R <- Rounds]) end,
        Hal = through_hal(Port, ?SEQ_N),
        Lib = #{rps => M(lib, rps), p99_us => M(lib, p99_us)},
        Rhr = "read holding registers (10)",
        Note = io_lib:format("Medians of ~b rounds, each measuring libmodbus and cellrt one "
                             "right after the other on the same libmodbus server.", [?ROUNDS]),
        [#{title => [Rhr, ", one at a time"], unit => "round trips/s",
           ours => M(seq, rps), peer => maps:get(rps, Lib),
           peer_name => "libmodbus 3.1 C client", better => higher,
           goal => "at least 0.8 of libmodbus", note => Note},
         #{title => [Rhr, ", one at a time: p99 latency"], unit => "µs",
           ours => M(seq, p99_us), peer => maps:get(p99_us, Lib),
           peer_name => "libmodbus 3.1 C client", better => lower},
         #{title => [Rhr, ", one at a time, by a bare gen_tcp loop (a passive receive, a "
                     "frame built once, no decoding): the platform's ceiling"],
           unit => "round trips/s", ours => M(bare, rps), peer => maps:get(rps, Lib),
           peer_name => "libmodbus 3.1 C client", better => higher,
           note => "What any Erlang client with an {active, once} socket can reach here: "
                   "a blocked C client is woken by the kernel directly, a BEAM process "
                   "through the VM's poll thread and a scheduler."},
         #{title => [Rhr, ", ", integer_to_list(?WINDOW), " in flight"], unit => "round trips/s",
           ours => M(pipe, rps), peer => maps:get(rps, Lib),
           peer_name => "libmodbus 3.1 C client (one at a time: it cannot pipeline)",
           better => higher, goal => "at least 2 × libmodbus"},
         #{title => [Rhr, ", ", integer_to_list(?WINDOW), " in flight: p99 latency"],
           unit => "µs", ours => M(pipe, p99_us), peer => maps:get(p99_us, Lib),
           peer_name => "libmodbus 3.1 C client (one at a time)", better => lower,
           note => "With requests in flight a request also waits for those ahead of it."},
         #{title => [Rhr, " through the HAL worker (cell_hal:request/3), one at a time"],
           unit => "round trips/s", ours => maps:get(rps, Hal), peer => maps:get(rps, Lib),
           peer_name => "libmodbus 3.1 C client", better => higher,
           note => "The caller's process hop to the connection's worker included; one round."},
         #{title => ["poll of ", integer_to_list(?POINTS), " mixed points: requests"],
           unit => "requests/poll", ours => length(Requests), peer => ?POINTS,
           peer_name => "one request a point", better => lower},
         #{title => ["poll of ", integer_to_list(?POINTS), " mixed points, decoded, one request at a time"],
           unit => "ms/poll", ours => M(poll, p50_us) / 1000, peer => M(lib_poll, p50_us) / 1000,
           peer_name => "libmodbus 3.1 C client, same requests, raw registers", better => lower,
           note => "Ours decodes every point to its type."},
         #{title => ["poll of ", integer_to_list(?POINTS), " mixed points, decoded, ",
                     "all requests in flight"],
           unit => "ms/poll", ours => M(poll_pipe, p50_us) / 1000,
           peer => M(lib_poll, p50_us) / 1000,
           peer_name => "libmodbus 3.1 C client, same requests one at a time", better => lower}]
    after
        cell_bench:stop_c_server(Peer)
    end.

median(L) ->
    figure(cell_bench:percentile(lists:sort(L), 50)).

%%--------------------------------------------------------------------
%% The peers
%%--------------------------------------------------------------------

libmodbus(Client, Port, Args) ->
    libmodbus(Client, Port, Args, []).

%% Runs the C client (its plan on stdin) and reads its one line of figures.
libmodbus(Client, Port, Args, Stdin) ->
    Plan = filename:join(filename:dirname(Client), "poll_plan.txt"),
    ok = file:write_file(Plan, Stdin),
    Cmd = io_lib:format("'~s' ~b ~s < '~s'", [Client, Port, lists:join(" ", Args), Plan]),
    Line = string:trim(os:cmd(lists:flatten(Cmd))),
    case string:lexemes(Line, " ") of
        [K1, V1, K2, V2, K3, V3] ->
            maps:from_list([{list_to_atom(K), figure(number(V))}
                            || {K, V} <- [{K1, V1}, {K2, V2}, {K3, V3}]]);
        _ ->
            error({libmodbus_client_failed, Line})
    end.

number(S) ->
    case string:to_float(S) of
        {F, []} -> F;
        _ -> list_to_integer(S)
    end.

%%--------------------------------------------------------------------
%% Ours, at the driver
%%--------------------------------------------------------------------

connect(Port, Window) ->
    {ok, Opts} = cell_hal_modbus:check_opts(#{host => "127.0.0.1", port => Port,
                                              max_in_flight => Window}),
    {ok, S} = cell_hal_modbus:connect(cell_hal_modbus:init(bench, Opts)),
    {[connected], S1} = events(S),
    S1.

%% The next message for the driver, turned into its events.
events(S) ->
    receive
        Msg ->
            case cell_hal_modbus:handle_info(Msg, S) of
                {ok, [], S1} -> events(S1);
                {ok, Events, S1} -> {Events, S1};
                unknown -> events(S)
            end
    after 10000 ->
            error(no_answer)
    end.

ours_sequential(Port, N) ->
    S = connect(Port, 1),
    T0 = erlang:monotonic_time(),
    {Lat, S1} = sequential(N, S, []),
    Total = erlang:monotonic_time() - T0,
    _ = cell_hal_modbus:disconnect(S1),
    summary(N, Total, Lat).

sequential(0, S, Lat) ->
    {Lat, S};
sequential(N, S, Lat) ->
    T0 = erlang:monotonic_time(),
    {ok, S1} = cell_hal_modbus:request(N, {read_holding_registers, 0, 10}, 5000, S),
    {[{reply, N, {ok, <<_:20/binary>>}}], S2} = events(S1),
    sequential(N - 1, S2, [erlang:monotonic_time() - T0 | Lat]).

%% Keeps `Window' requests in flight until N were answered.
ours_pipelined(Port, N, Window) ->
    S = connect(Port, Window),
    T0 = erlang:monotonic_time(),
    {S1, Sent} = send_many(lists:seq(1, min(N, Window)), S, #{}),
    {Lat, S2} = pipelined(N, min(N, Window), S1, Sent, []),
    Total = erlang:monotonic_time() - T0,
    _ = cell_hal_modbus:disconnect(S2),
    summary(N, Total, Lat).

send_many(Tags, S, Sent) ->
    lists:foldl(fun(Tag, {Si, Acc}) ->
                        {ok, Si1} = cell_hal_modbus:request(Tag, {read_holding_registers, 0, 10},
                                                            5000, Si),
                        {Si1, Acc#{Tag => erlang:monotonic_time()}}
                end, {S, Sent}, Tags).

pipelined(N, _Issued, S, Sent, Lat) when map_size(Sent) =:= 0, length(Lat) =:= N ->
    {Lat, S};
pipelined(N, Issued, S, Sent, Lat) ->
    {Events, S1} = events(S),
    Now = erlang:monotonic_time(),
    Done = [Tag || {reply, Tag, {ok, <<_:20/binary>>}} <- Events],
    length(Done) =:= length(Events) orelse error({unexpected, Events}),
    Lat1 = [Now - maps:get(Tag, Sent) || Tag <- Done] ++ Lat,
    Sent1 = maps:without(Done, Sent),
    More = lists:seq(Issued + 1, min(N, Issued + length(Done))),
    {S2, Sent2} = send_many(More, S1, Sent1),
    pipelined(N, Issued + length(More), S2, Sent2, Lat1).

summary(N, Total, Lat) ->
    Us = [erlang:convert_time_unit(L, native, nanosecond) / 1000 || L <- Lat],
    #{median := M, p99 := P} = cell_bench:stats(Us),
    #{rps => figure(N / (erlang:convert_time_unit(Total, native, microsecond) / 1.0e6)),
      p50_us => figure(M), p99_us => figure(P)}.

%% Figures of 100 and more are whole numbers (the runner prints them so).
figure(X) when X >= 100 -> round(X);
figure(X) -> X.

%% The leanest round trip an {active, once} socket allows: no driver at all.
bare_gen_tcp(Port, N) ->
    {ok, Sock} = gen_tcp:connect("127.0.0.1", Port, [binary, {active, false}, {nodelay, true}]),
    Frame = cell_hal_modbus_codec:adu(1, 1, cell_hal_modbus_codec:request_pdu(
                                              {read_holding_registers, 0, 10})),
    T0 = erlang:monotonic_time(),
    Lat = bare_loop(N, Sock, Frame, []),
    Total = erlang:monotonic_time() - T0,
    ok = gen_tcp:close(Sock),
    summary(N, Total, Lat).

bare_loop(0, _, _, Lat) ->
    Lat;
bare_loop(N, Sock, Frame, Lat) ->
    T0 = erlang:monotonic_time(),
    ok = gen_tcp:send(Sock, Frame),
    {ok, <<_:9/binary, _:20/binary>>} = gen_tcp:recv(Sock, 29, 5000),
    bare_loop(N - 1, Sock, Frame, [erlang:monotonic_time() - T0 | Lat]).

%%--------------------------------------------------------------------
%% Through the HAL
%%--------------------------------------------------------------------

through_hal(Port, N) ->
    %% The HAL logs through cell_log into the benchmark's root folder; lager's own
    %% default handlers would write into the working directory.
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, []),
    ok = application:set_env(lager, crash_log, false),
    {ok, _} = application:ensure_all_started(cell_hal),
    ok = cell_hal:add_connection(#{id => bench_plc, driver => cell_hal_modbus,
                                   opts => #{host => "127.0.0.1", port => Port}}),
    try
        {ok, Status} = cell_hal:subscribe_connection(bench_plc),
        Status =:= up orelse receive {cell_hal_conn, bench_plc, up} -> ok
                             after 10000 -> error(hal_not_up)
                             end,
        T0 = erlang:monotonic_time(),
        Lat = [begin
                   T = erlang:monotonic_time(),
                   {ok, <<_:20/binary>>} = cell_hal:request(bench_plc, {read_holding_registers, 0, 10}, 5000),
                   erlang:monotonic_time() - T
               end || _ <- lists:seq(1, N)],
        summary(N, erlang:monotonic_time() - T0, Lat)
    after
        ok = cell_hal:remove_connection(bench_plc)
    end.

%%--------------------------------------------------------------------
%% A poll of 2000 mixed points
%%--------------------------------------------------------------------

%% 2000 inputs as a machine has them: discrete inputs and coils, bits packed in input
%% registers, and values of every type in input and holding registers.
image() ->
    Types = [bool, byte, sbyte, char, int16, uint16, int32, uint32, int64, uint64, real,
             lreal, {string, 10}, date, time, decimal],
    Discrete = [{{di, I}, bool, {discrete_input, I}} || I <- lists:seq(0, 599)],
    Coils = [{{co, I}, bool, {coil, I}} || I <- lists:seq(0, 199)],
    Bits = [{{bit, I}, bool, {input_register, 5000 + I div 16, I rem 16}} || I <- lists:seq(0, 199)],
    {Typed, _} = lists:mapfoldl(
                   fun(I, A) ->
                           T = lists:nth(I rem length(Types) + 1, Types),
                           Table = case I < 700 of true -> input_register; false -> holding_register end,
                           Addr = case I =:= 700 of true -> 0; false -> A end,
                           {{{reg, I}, T, {Table, Addr}}, Addr + cell_hal_type_codec:registers(T)}
                   end, 0, lists:seq(0, 999)),
    Points = Discrete ++ Coils ++ Bits ++ Typed,
    ?POINTS = length(Points),
    [begin
         {ok, F} = cell_hal_modbus_plan:field(in, T, Field, #{unit => 1, word_order => big}),
         #{key => K, dir => in, type => T, field => F}
     end || {K, T, Field} <- Points].

%% The requests of one poll, as libmodbus is given them.
poll_requests() ->
    {{Plan, _Outputs}, _} = cell_hal_modbus:plan(image(), cell_hal_modbus:init(bench, #{host => "", port => 1,
                                                                          unit => 1, word_order => big,
                                                                          timeout_ms => 1000,
                                                                          max_in_flight => 1,
                                                                          max_gap => 0})),
    [{fc(R), element(2, R), element(3, R)} || {_, R} <- cell_hal_modbus_plan:requests(Plan)].

ours_poll(Port, Polls, Window) ->
    S = connect(Port, Window),
    {Plan, _} = cell_hal_modbus:plan(image(), S),
    {Lat, S1} = polls(Polls, Plan, S, []),
    _ = cell_hal_modbus:disconnect(S1),
    summary(Polls, lists:sum(Lat), Lat).

polls(0, _Plan, S, Lat) ->
    {Lat, S};
polls(N, Plan, S, Lat) ->
    T0 = erlang:monotonic_time(),
    {ok, S1} = cell_hal_modbus:read(N, Plan, S),
    {[{reply, N, {ok, Values}}], S2} = events(S1),
    ?POINTS = length(Values),
    polls(N - 1, Plan, S2, [erlang:monotonic_time() - T0 | Lat]).

fc({read_coils, _, _}) -> 1;
fc({read_discrete_inputs, _, _}) -> 2;
fc({read_holding_registers, _, _}) -> 3;
fc({read_input_registers, _, _}) -> 4.
