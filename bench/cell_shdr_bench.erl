%% @doc MTConnect SHDR adapter benchmarks:
%% <ul>
%% <li>observations per second delivered to 1, 10 and 100 clients: value changes in
%%     the cell (controller mode flips, published as the cell publishes them) until
%%     every client has read every line, beside the same lines written straight to
%%     the same number of sockets by one process (no cache, no duplicate filtering,
%%     no log);</li>
%% <li>the delay from a value change in the cell to its bytes on a client's socket
%%     (median, p99), one change at a time, beside writing the same line straight to
%%     the socket; ours holds each value until its millisecond is over (a value that
%%     lasted no time is not sent), up to 2 ms.</li>
%% </ul>
%% Readers count newlines on plain loopback sockets, the same readers for both.
-module(cell_shdr_bench).

-export([run/0]).

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    ok = start(),
    Rates = lists:append([rate(N, Changes) || {N, Changes} <- [{1, 20000}, {10, 10000},
                                                                {100, 3000}]]),
    Delay = delay(2000),
    stop(),
    Rates ++ Delay.

%% -------------------------------------------------------------------------------------
%% Throughput
%% -------------------------------------------------------------------------------------

rate(N, Changes) ->
    Ours = ours_rate(N, Changes),
    Peer = peer_rate(N, Changes),
    [#{title => io_lib:format("Observations delivered per second, ~p client~s", [N, plural(N)]),
       unit => "obs/s", ours => Ours, peer => Peer,
       peer_name => "same lines written straight to the sockets", better => higher}].

ours_rate(N, Changes) ->
    Readers = [reader(connect()) || _ <- lists:seq(1, N)],
    T0 = erlang:monotonic_time(microsecond),
    flips(Changes),
    [await_lines(R, Changes) || R <- Readers],
    Us = erlang:monotonic_time(microsecond) - T0,
    [close(R) || R <- Readers],
    N * Changes / (Us / 1.0e6).

peer_rate(N, Changes) ->
    {ok, L} = gen_tcp:listen(0, [binary, {active, false}, {reuseaddr, true}, {nodelay, true},
                                  {ip, {127, 0, 0, 1}}]),
    {ok, Port} = inet:port(L),
    Pairs = [begin
                 {ok, C} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}]),
                 {ok, S} = gen_tcp:accept(L),
                 ok = inet:setopts(S, [{nodelay, true}]),
                 {S, reader(C)}
             end || _ <- lists:seq(1, N)],
    Socks = [S || {S, _} <- Pairs],
    T0 = erlang:monotonic_time(microsecond),
    lists:foreach(fun(I) ->
                          Line = line(I),
                          [ok = gen_tcp:send(S, Line) || S <- Socks]
                  end, lists:seq(1, Changes)),
    [await_lines(R, Changes) || {_, R} <- Pairs],
    Us = erlang:monotonic_time(microsecond) - T0,
    [begin gen_tcp:close(S), close(R) end || {S, R} <- Pairs],
    gen_tcp:close(L),
    N * Changes / (Us / 1.0e6).

%% The line the adapter writes for the I-th flip, built the same way.
line(I) ->
    cell_shdr_codec:data_line({utc, os:system_time(millisecond)},
                              [{<<"mode">>, mode(I)}]).

mode(I) when I rem 2 =:= 1 -> <<"MANUAL">>;
mode(_) -> <<"AUTOMATIC">>.

%% Value changes as the controller publishes them: service mode on, off, on ... Each
%% stamped a millisecond after the one before: the adapter sends no value that lasted
%% no time, and a loop flips many times a millisecond.
flips(Changes) ->
    Base = os:system_time(millisecond) - Changes,
    lists:foreach(fun(I) ->
                          Ev = cell_events:new(service_mode, cell,
                                               #{active => I rem 2 =:= 1, who => <<"bench">>}),
                          cell_events:publish(Ev#{time => Base + I})
                  end, lists:seq(1, Changes)).

flip(I) ->
    cell_events:publish(cell_events:new(service_mode, cell, #{active => I rem 2 =:= 1,
                                                              who => <<"bench">>})).

%% -------------------------------------------------------------------------------------
%% Delay
%% -------------------------------------------------------------------------------------

delay(Reps) ->
    R = reader(connect()),
    R ! {notify, self()},
    Ours = [begin
                T0 = erlang:monotonic_time(microsecond),
                %% Every run leaves the mode AUTOMATIC, so flip 1 is a change.
                flip(I),
                receive {line, R, T1} -> T1 - T0 after 10000 -> erlang:error(no_line) end
            end || I <- lists:seq(1, Reps)],
    close(R),
    {ok, L} = gen_tcp:listen(0, [binary, {active, false}, {reuseaddr, true}, {nodelay, true},
                                  {ip, {127, 0, 0, 1}}]),
    {ok, Port} = inet:port(L),
    {ok, C} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}]),
    {ok, S} = gen_tcp:accept(L),
    ok = inet:setopts(S, [{nodelay, true}]),
    PR = reader(C),
    PR ! {notify, self()},
    Peer = [begin
                T0 = erlang:monotonic_time(microsecond),
                ok = gen_tcp:send(S, line(I)),
                receive {line, PR, T1} -> T1 - T0 after 10000 -> erlang:error(no_line) end
            end || I <- lists:seq(1, Reps)],
    gen_tcp:close(S),
    close(PR),
    gen_tcp:close(L),
    #{median := OM, p99 := OP} = cell_bench:stats(Ours),
    #{median := PM, p99 := PP} = cell_bench:stats(Peer),
    [#{title => "Delay from a value change to its bytes on a client's socket, median",
       unit => "µs", ours => OM, peer => PM, better => lower,
       peer_name => "same line written straight to the socket",
       note => "The adapter holds a value until the millisecond of its timestamp is "
               "over (1 to 2 ms after the change), so that of an item's changes "
               "within one millisecond only the last goes out and a value that lasted "
               "no time is never sent: the delay is that hold, the peer sends at once."},
     #{title => "Delay from a value change to its bytes on a client's socket, p99",
       unit => "µs", ours => OP, peer => PP, better => lower,
       peer_name => "same line written straight to the socket"}].

%% -------------------------------------------------------------------------------------
%% Readers: count the lines arriving on a socket
%% -------------------------------------------------------------------------------------

reader(Sock) ->
    Pid = spawn_link(fun() -> receive go -> ok end, read_loop(Sock, 0, undefined, undefined) end),
    ok = gen_tcp:controlling_process(Sock, Pid),
    ok = inet:setopts(Sock, [{active, once}]),
    Pid ! go,
    Pid.

read_loop(Sock, Count, Waiter, Notify) ->
    receive
        {tcp, Sock, Data} ->
            T = erlang:monotonic_time(microsecond),
            ok = inet:setopts(Sock, [{active, once}]),
            Lines = length(binary:matches(Data, <<"\n">>)),
            case Notify of
                P when is_pid(P), Lines > 0 -> P ! {line, self(), T};
                _ -> ok
            end,
            check(Sock, Count + Lines, Waiter, Notify);
        {tcp_closed, Sock} ->
            ok;
        {notify, P} ->
            read_loop(Sock, Count, Waiter, P);
        {wait, From, Target} ->
            check(Sock, Count, {From, Target}, Notify);
        close ->
            gen_tcp:close(Sock)
    end.

check(Sock, Count, {From, Target}, Notify) when Count >= Target ->
    From ! {count, self(), Count},
    read_loop(Sock, Count - Target, undefined, Notify);
check(Sock, Count, Waiter, Notify) ->
    read_loop(Sock, Count, Waiter, Notify).

await_lines(R, N) ->
    R ! {wait, self(), N},
    receive {count, R, _} -> ok after 120000 -> erlang:error({lines_missing, N}) end.

close(R) ->
    R ! close,
    ok.

connect() ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, cell_shdr:port(), [binary, {active, false}]),
    %% Read the snapshot up to the PONG, so only changes are counted after.
    ok = gen_tcp:send(S, <<"* PING\n">>),
    ok = skip_snapshot(S, <<>>),
    S.

skip_snapshot(S, Buf) ->
    {ok, Data} = gen_tcp:recv(S, 0, 10000),
    All = <<Buf/binary, Data/binary>>,
    case binary:match(All, <<"* PONG ">>) of
        nomatch -> skip_snapshot(S, All);
        {Pos, _} ->
            case binary:match(All, <<"\n">>, [{scope, {Pos, byte_size(All) - Pos}}]) of
                nomatch -> skip_snapshot(S, All);
                {End, 1} when End + 1 =:= byte_size(All) -> ok;
                {_, 1} -> erlang:error(unexpected_data_after_snapshot)
            end
    end.

%% -------------------------------------------------------------------------------------

start() ->
    _ = [application:load(A) || A <- [cell_base, cell, cell_shdr]],
    ok = application:set_env(cell_shdr, port, 0),
    {ok, _} = application:ensure_all_started(cell_shdr),
    %% The adapter admits 64 clients by default (its `max_clients'); the widest round
    %% here has 100.
    ok = cell_settings:put(shdr, #{max_clients => 100}, <<"bench">>),
    ok = cell_shdr_cache:sync(),
    _ = sys:get_state(cell_shdr_listener),
    ok.

stop() ->
    _ = application:stop(cell_shdr),
    _ = application:stop(cell),
    ok.

quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, []),
    ok = application:set_env(lager, error_logger_redirect, false),
    ok.

plural(1) -> "";
plural(_) -> "s".
