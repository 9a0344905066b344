%% @doc ADS reads per second: cellrt's client beside pyads' client (Beckhoff's AdsLib)
%% against the same ADS server in the same run.
%%
%% The server is `bench/ads_responder.c', compiled here: a minimal ADS server in C that
%% answers each request in a few microseconds, so the figures show what the clients
%% cost rather than what the server costs. Both clients talk AMS/TCP to it on
%% 127.0.0.1, one request at a time, each waiting for its answer:
%%
%% <ul>
%% <li>a 4-byte variable (DINT) read by handle (pyads: `read_by_name' with a handle,
%%     AdsSyncReadReqEx2; ours: `read_vars/2' of one variable);</li>
%% <li>a 200-point IO group read in one sum command (pyads: `read_list_by_name' with
%%     its symbol information cached, one 0xF080 request by index group and offset;
%%     ours: `read_vars/2', one 0xF080 request by handles);</li>
%% <li>the same group read one point at a time, by handle.</li>
%% </ul>
%%
%% Beside them, the group read without sum commands by cellrt, whose reads of a group
%% are in flight together. The VM measures on one scheduler (see run/0).
%% `make bench BENCH=cell_hal_ads_bench' runs it.
-module(cell_hal_ads_bench).

-export([run/0]).

%% Rounds alternate between the two clients, and each figure is the median of its
%% rounds: on a shared machine the load moves, and both sides then see the same load.
-define(ROUNDS, 11).
-define(SECONDS, 0.2).
-define(POINTS, 200).
-define(NET, "127.0.0.1.1.1").
-define(WAIT, 60000).

-spec run() -> [cell_bench:result()].
run() ->
    %% cell_base is not started: its logger would write into the working folder, and
    %% the client's log lines are not wanted here (cell_log without it drops them).
    {Responder, Port} = start_responder(build()),
    Names = [point(I) || I <- lists:seq(0, ?POINTS - 1)],
    AdsLib = peer("pyads_client.py", ["--port", integer_to_list(Port), "--target", ?NET,
                                      "--local", "10.11.12.13.1.1"]),
    {ready, _} = hello(AdsLib),
    %% The responder has no notifications: the symbol version is not watched.
    Opts = #{host => "127.0.0.1", port => Port, target_net_id => ?NET, name => ads_bench,
             symbol_version => ignore},
    C = client(Opts),
    %% the same group on a client without sum commands: 200 reads, all in flight
    Pipelined = client(Opts#{sum_commands => false}),
    %% One scheduler while measuring: an idle scheduler spins a while before it sleeps,
    %% and on a two-core machine that takes the core the server needs (a cell's PLC
    %% is another machine). AdsLib's threads block instead of spinning.
    Schedulers = erlang:system_flag(schedulers_online, 1),
    try
        Counter = {<<"MAIN.counter">>, int32},
        Group = [{list_to_binary(N), int32} || N <- Names],
        {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Counter]),
        [begin
             {ok, Resolved} = cell_hal_ads_client:resolve(Client, Group, 30000),
             ?POINTS = length([ok || {ok, _} <- Resolved])
         end || Client <- [C, Pipelined]],
        Expected = [{ok, I} || I <- lists:seq(0, ?POINTS - 1)],
        Seconds = float_to_list(?SECONDS, [{decimals, 2}]),
        {Ours1, Peer1} =
            rounds(fun() -> {ok, [{ok, 42}]} = cell_hal_ads_client:read_vars(C, [Counter]) end,
                   AdsLib, ["bench_handle ", Seconds, " MAIN.counter DINT"]),
        {Ours2, Peer2} =
            rounds(fun() -> {ok, Expected} = cell_hal_ads_client:read_vars(C, Group) end,
                   AdsLib, ["bench_sum ", Seconds, [[" ", N] || N <- Names]]),
        {Ours3, Peer3} =
            rounds(fun() ->
                           [{ok, [{ok, _}]} = cell_hal_ads_client:read_vars(C, [V]) || V <- Group]
                   end,
                   AdsLib, ["bench_single ", Seconds, " DINT", [[" ", N] || N <- Names]]),
        InFlight = median([rate(fun() -> {ok, Expected} = cell_hal_ads_client:read_vars(
                                                            Pipelined, Group)
                                end) || _ <- lists:seq(1, ?ROUNDS)]),
        {Bare, Peer4} = bare(Port, AdsLib, Seconds),
        PeerName = "pyads 3.6 (Beckhoff AdsLib), same C responder",
        [#{title => "4-byte variable (DINT) read by handle", unit => "reads/s",
           ours => Ours1, peer => Peer1, peer_name => PeerName, better => higher,
           goal => "faster than pyads"},
         #{title => "4-byte variable read by handle, by a bare gen_tcp loop ({active, once}, "
                    "a frame built once, no decoding): the platform's ceiling",
           unit => "reads/s", ours => Bare, peer => Peer4, peer_name => PeerName,
           better => higher,
           note => "What any Erlang client reading over an {active, once} socket can reach "
                   "here, beside pyads again in the same rounds. cellrt's client costs the "
                   "difference: the caller's call to the connection's process and back, "
                   "and encoding, matching and decoding each frame. pyads pays a Python "
                   "call into AdsLib, whose receive thread wakes the calling thread."},
         #{title => "200-point IO group, one sum command (0xF080)", unit => "group reads/s",
           ours => Ours2, peer => Peer2, peer_name => PeerName, better => higher,
           goal => "faster than pyads"},
         #{title => "200-point IO group, one point at a time", unit => "group reads/s",
           ours => Ours3, peer => Peer3, peer_name => PeerName, better => higher,
           goal => "faster than pyads",
           note => io_lib:format(
                     "All figures over 127.0.0.1 to a minimal ADS server in C "
                     "(bench/ads_responder.c, a few microseconds a request), medians of ~b "
                     "alternating rounds of ~s s, one request at a time on both sides, the "
                     "Erlang VM on one scheduler (an idle one would spin on the core the "
                     "server needs). One sum command instead of 200 single reads: ~.1fx "
                     "more group reads/s for cellrt, ~.1fx for pyads. Without sum commands "
                     "cellrt keeps the 200 reads of a group in flight together: ~b group "
                     "reads/s (pyads' calls wait for each answer).",
                     [?ROUNDS, Seconds, Ours2 / Ours3, Peer2 / Peer3, InFlight])}]
    after
        _ = erlang:system_flag(schedulers_online, Schedulers),
        _ = cell_hal_ads_client:stop(C),
        _ = cell_hal_ads_client:stop(Pipelined),
        stop(AdsLib),
        stop_responder(Responder)
    end.

%% Reads of the counter by its handle (1 in the responder) in a loop of this process
%% alone, beside pyads' reads by handle.
bare(Port, AdsLib, Seconds) ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}, {nodelay, true}]),
    Frame = iolist_to_binary(cell_hal_ads_codec:encode_frame({{127, 0, 0, 1, 1, 1}, 851},
                                                             {{127, 0, 0, 1, 1, 1}, 32905}, 1,
                                                             {read, 16#F005, 1, 4})),
    Read = fun() ->
                   ok = gen_tcp:send(S, Frame),
                   ok = inet:setopts(S, [{active, once}]),
                   receive {tcp, S, <<_:38/binary, 0:32, 4:32/little, 42:32/little>>} -> ok
                   after ?WAIT -> error(no_answer)
                   end
           end,
    try
        rounds(Read, AdsLib, ["bench_handle ", Seconds, " MAIN.counter DINT"])
    after
        ok = gen_tcp:close(S)
    end.

%% The C responder, compiled into _build/bench.
build() ->
    Top = top(),
    Out = filename:join([Top, "_build", "bench"]),
    ok = filelib:ensure_path(Out),
    Exe = filename:join(Out, "ads_responder"),
    Src = filename:join([Top, "bench", "ads_responder.c"]),
    case os:cmd("gcc -O2 -Wall -o '" ++ Exe ++ "' '" ++ Src ++ "' 2>&1 && echo built") of
        "built\n" -> Exe;
        Err -> error({cannot_compile, Src, Err})
    end.

start_responder(Exe) ->
    P = open_port({spawn_executable, Exe}, [{args, ["0"]}, {line, 256}, exit_status, binary]),
    receive
        {P, {data, {eol, <<"port ", N/binary>>}}} -> {P, binary_to_integer(N)}
    after 10000 -> error(ads_responder_did_not_start)
    end.

%% Closing its stdin ends it.
stop_responder(P) ->
    catch port_close(P),
    ok.

top() ->
    case os:getenv("CELLRT_TOP") of
        false -> ".";
        T -> T
    end.

client(Opts) ->
    {ok, C} = cell_hal_ads_client:start_link(Opts),
    ok = cell_hal_ads_client:subscribe_status(C),
    ok = await_up(C),
    C.

%% Our rate and the peer's, each the median of rounds taken in turn (who goes first
%% alternates too).
rounds(Ours, Peer, PeerCommand) ->
    Pairs = [case I rem 2 of
                 0 -> O = rate(Ours), {O, peer_rate(ask(Peer, PeerCommand))};
                 1 -> P = peer_rate(ask(Peer, PeerCommand)), {rate(Ours), P}
             end || I <- lists:seq(1, ?ROUNDS)],
    {median([O || {O, _} <- Pairs]), median([P || {_, P} <- Pairs])}.

median(Xs) ->
    lists:nth((length(Xs) + 1) div 2, lists:sort(Xs)).

point(I) ->
    lists:flatten(io_lib:format("GVL.Io.P~3..0b", [I])).

%% Calls per second of `Fun' over ?SECONDS, after a short warm-up.
rate(Fun) ->
    _ = [Fun() || _ <- lists:seq(1, 5)],
    Start = erlang:monotonic_time(microsecond),
    Until = Start + round(?SECONDS * 1000000),
    N = loop(Fun, Until, 0),
    round(N / ((erlang:monotonic_time(microsecond) - Start) / 1000000)).

loop(Fun, Until, N) ->
    case erlang:monotonic_time(microsecond) < Until of
        true -> Fun(), loop(Fun, Until, N + 1);
        false -> N
    end.

peer_rate({ok, Count, Micros}) ->
    round(Count / (Micros / 1000000)).

await_up(C) ->
    receive
        {cell_hal_ads, C, up} -> ok;
        {cell_hal_ads, C, {down, _}} -> await_up(C)
    after ?WAIT -> error(plc_not_up)
    end.

%% The peers: Python scripts taking one command a line, answering one Erlang term a line.

peer(Script, Args) ->
    Top = top(),
    Python = filename:join([Top, "_pyenv", "bin", "python"]),
    Path = filename:join([Top, "apps", "cell_hal_ads", "test", "peers", Script]),
    open_port({spawn_executable, Python},
              [{args, [Path | Args]}, {line, 1 bsl 20}, binary, exit_status, use_stdio]).

hello(Port) ->
    answer(Port).

ask(Port, Line) ->
    true = port_command(Port, [Line, $\n]),
    answer(Port).

answer(Port) ->
    answer(Port, <<>>).

answer(Port, Acc) ->
    receive
        {Port, {data, {noeol, Part}}} ->
            answer(Port, <<Acc/binary, Part/binary>>);
        {Port, {data, {eol, Part}}} ->
            {ok, Tokens, _} = erl_scan:string(binary_to_list(<<Acc/binary, Part/binary>>) ++ "."),
            {ok, Term} = erl_parse:parse_term(Tokens),
            Term;
        {Port, {exit_status, Status}} ->
            error({peer_exited, Status})
    after ?WAIT ->
            error(peer_silent)
    end.

stop(Port) ->
    true = port_command(Port, <<"quit\n">>),
    receive
        {Port, {exit_status, _}} -> ok
    after 5000 ->
            catch port_close(Port),
            ok
    end.
