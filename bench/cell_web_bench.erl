%% @doc Operator panel benchmarks:
%% <ul>
%% <li>API request latency, `GET /api/cell' from 100 concurrent keep-alive clients,
%%     beside a bare cowboy handler answering the same JSON bytes on the same node;</li>
%% <li>websocket fan-out: events published in the cell reach 100 connected pages,
%%     beside bare cowboy websockets subscribed to the same events, one frame an event:
%%     events delivered per second when published as fast as the publisher can (and
%%     what publishing costs the publisher, a device task in the cell), and the delay
%%     from publish to the client's decode at a rate both sides keep up with.</li>
%% </ul>
-module(cell_web_bench).
-behaviour(cowboy_handler).

-export([run/0, ws_open/2, frame/2]).
-export([init/2, websocket_init/1, websocket_handle/2, websocket_info/2]).

-define(CLIENTS, 100).
-define(REQUESTS, 50).          %% per client
-define(EVENTS, 3000).          %% per throughput run, published at once
-define(PACED, 600).            %% per delay run, paced below
-define(BURST, 3).
-define(BURST_MS, 10).

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    start_cell(),
    Body = jsx:encode(cell_web_cell_h:cell()),
    PeerPort = start_peer(Body),
    OursPort = cell_web:port(),
    %% A round each first: the modules load on their first call here, as they never
    %% do in the release, which loads them all at boot.
    _ = latencies(OursPort),
    _ = latencies(PeerPort),
    Ours = latencies(OursPort),
    Peer = latencies(PeerPort),
    {OurRate, OurCost, _} = fanout(OursPort, "/api/ws", ?EVENTS, ?EVENTS),
    {PeerRate, PeerCost, _} = fanout(PeerPort, "/ws", ?EVENTS, ?EVENTS),
    {_, _, OurDelays} = fanout(OursPort, "/api/ws", ?PACED, ?BURST),
    {_, _, PeerDelays} = fanout(PeerPort, "/ws", ?PACED, ?BURST),
    ok = cowboy:stop_listener(cell_web_bench_peer),
    #{median := OM, p99 := OP} = cell_bench:stats(Ours),
    #{median := PM, p99 := PP} = cell_bench:stats(Peer),
    #{p99 := ODP, median := ODM} = cell_bench:stats(OurDelays),
    #{p99 := PDP, median := PDM} = cell_bench:stats(PeerDelays),
    Api = "GET /api/cell, 100 concurrent clients",
    Fan = "websocket fan-out of events to 100 pages",
    [#{title => [Api, ", median"], unit => "ms", ours => OM / 1000, peer => PM / 1000,
       peer_name => "bare cowboy handler, same JSON", better => lower},
     #{title => [Api, ", p99"], unit => "ms", ours => OP / 1000, peer => PP / 1000,
       peer_name => "bare cowboy handler, same JSON", better => lower},
     #{title => [Fan, ", events delivered"], unit => "events/s", ours => OurRate,
       peer => PeerRate, peer_name => "bare cowboy websockets, a frame an event",
       better => higher},
     #{title => [Fan, ", the publisher's time an event"], unit => "µs", ours => OurCost,
       peer => PeerCost, peer_name => "bare cowboy websockets, a frame an event",
       better => lower},
     #{title => [Fan, ", median delay"], unit => "ms", ours => ODM / 1000, peer => PDM / 1000,
       peer_name => "bare cowboy websockets, a frame an event", better => lower},
     #{title => [Fan, ", p99 delay"], unit => "ms", ours => ODP / 1000, peer => PDP / 1000,
       peer_name => "bare cowboy websockets, a frame an event", better => lower,
       note => io_lib:format("Fan-out: ~p events published at once for the rate and the "
                             "publisher's time; for the delay ~p events in bursts of ~p "
                             "every ~p ms, from publish to the page's decode of the frame.",
                             [?EVENTS, ?PACED, ?BURST, ?BURST_MS])}].

%% -------------------------------------------------------------------------------------
%% API latency

latencies(Port) ->
    Self = self(),
    Pids = [spawn_link(fun() -> Self ! {lat, self(), client(Port)} end)
            || _ <- lists:seq(1, ?CLIENTS)],
    lists:append([receive {lat, P, L} -> L end || P <- Pids]).

client(Port) ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}, {nodelay, true}]),
    Req = ["GET /api/cell HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"],
    L = [begin
             T0 = erlang:monotonic_time(microsecond),
             ok = gen_tcp:send(S, Req),
             {200, _} = response(S, <<>>),
             erlang:monotonic_time(microsecond) - T0
         end || _ <- lists:seq(1, ?REQUESTS)],
    gen_tcp:close(S),
    L.

response(S, Buf) ->
    case binary:split(Buf, <<"\r\n\r\n">>) of
        [Head, Rest] ->
            <<"HTTP/1.1 ", Code:3/binary, _/binary>> = Head,
            {match, [Len]} = re:run(Head, "(?i)content-length: *([0-9]+)",
                                    [{capture, all_but_first, binary}]),
            body(S, Rest, binary_to_integer(Len), binary_to_integer(Code));
        [_] ->
            {ok, More} = gen_tcp:recv(S, 0, 10000),
            response(S, <<Buf/binary, More/binary>>)
    end.

body(_S, Buf, Len, Code) when byte_size(Buf) >= Len -> {Code, Buf};
body(S, Buf, Len, Code) ->
    {ok, More} = gen_tcp:recv(S, 0, 10000),
    body(S, <<Buf/binary, More/binary>>, Len, Code).

%% -------------------------------------------------------------------------------------
%% Websocket fan-out

%% `Events' published in bursts of `Burst' every ?BURST_MS: events delivered per
%% second, the publisher's microseconds an event, every delay.
fanout(Port, Path, Events, Burst) ->
    Self = self(),
    Clients = [spawn_link(fun() -> ws_client(Port, Path, Self, Events) end)
               || _ <- lists:seq(1, ?CLIENTS)],
    _ = [receive {ready, C} -> ok end || C <- Clients],
    T0 = erlang:monotonic_time(microsecond),
    Spent = publish(Events, Burst, 0),
    Delays = lists:append([receive {done, C, D} -> D end || C <- Clients]),
    T1 = erlang:monotonic_time(microsecond),
    {?CLIENTS * Events / ((T1 - T0) / 1000000), Spent / Events, Delays}.

publish(0, _Burst, Spent) ->
    Spent;
publish(N, Burst, Spent) ->
    T0 = erlang:monotonic_time(microsecond),
    _ = [cell_events:publish(cell_events:new(item_transfer_in, bench_task,
                                             #{item => integer_to_binary(
                                                          erlang:monotonic_time(microsecond))}))
         || _ <- lists:seq(1, min(N, Burst))],
    T1 = erlang:monotonic_time(microsecond),
    case N > Burst of
        true -> receive after ?BURST_MS -> ok end;
        false -> ok
    end,
    publish(max(0, N - Burst), Burst, Spent + T1 - T0).

ws_client(Port, Path, Parent, Events) ->
    {S, Rest} = ws_open(Port, Path),
    %% The first frame (our snapshot, or the peer's hello) says the socket is live.
    {_, Rest1} = frame(S, Rest),
    Parent ! {ready, self()},
    Delays = collect(S, Rest1, Events, []),
    Parent ! {done, self(), Delays},
    gen_tcp:close(S).

%% @doc A websocket client's socket once upgraded, and what came after the answer's head.
-spec ws_open(inet:port_number(), iodata()) -> {gen_tcp:socket(), binary()}.
ws_open(Port, Path) ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}, {nodelay, true}]),
    ok = gen_tcp:send(S, ["GET ", Path, " HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
                          "Connection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
                          "Sec-WebSocket-Key: ", base64:encode(crypto:strong_rand_bytes(16)),
                          "\r\n\r\n"]),
    {S, upgraded(S, <<>>)}.

upgraded(S, Buf) ->
    case binary:split(Buf, <<"\r\n\r\n">>) of
        [<<"HTTP/1.1 101", _/binary>>, Rest] -> Rest;
        [_] -> {ok, More} = gen_tcp:recv(S, 0, 10000), upgraded(S, <<Buf/binary, More/binary>>)
    end.

collect(_S, _Buf, N, Acc) when N =< 0 ->
    Acc;
collect(S, Buf, N, Acc) ->
    {Payload, Rest} = frame(S, Buf),
    Now = erlang:monotonic_time(microsecond),
    Sent = sent_times(jsx:decode(Payload, [return_maps])),
    collect(S, Rest, N - length(Sent), [Now - T || T <- Sent] ++ Acc).

%% Our frames are arrays of messages; the peer's are one event each.
sent_times(Msgs) when is_list(Msgs) ->
    [binary_to_integer(I) || #{<<"type">> := <<"event">>,
                               <<"event">> := #{<<"item">> := I}} <- Msgs];
sent_times(#{<<"item">> := I}) ->
    [binary_to_integer(I)];
sent_times(_) ->
    [].

%% @doc The payload of the next text frame (others skipped), and what follows it.
-spec frame(gen_tcp:socket(), binary()) -> {binary(), binary()}.
frame(S, Buf) ->
    case Buf of
        <<_:4, Op:4, 0:1, 127:7, Len:64, P:Len/binary, Rest/binary>> -> text(S, Op, P, Rest);
        <<_:4, Op:4, 0:1, 126:7, Len:16, P:Len/binary, Rest/binary>> -> text(S, Op, P, Rest);
        <<_:4, Op:4, 0:1, Len:7, P:Len/binary, Rest/binary>> when Len < 126 -> text(S, Op, P, Rest);
        _ ->
            {ok, More} = gen_tcp:recv(S, 0, 30000),
            frame(S, <<Buf/binary, More/binary>>)
    end.

text(_S, 1, Payload, Rest) -> {Payload, Rest};
text(S, _Op, _Payload, Rest) -> frame(S, Rest).

%% -------------------------------------------------------------------------------------
%% The peer: a bare cowboy handler and a bare websocket

start_peer(Body) ->
    Dispatch = cowboy_router:compile([{'_', [{"/api/cell", ?MODULE, {json, Body}},
                                             {"/ws", ?MODULE, ws}]}]),
    {ok, _} = cowboy:start_clear(cell_web_bench_peer, [{ip, {127, 0, 0, 1}}, {port, 0}],
                                 #{env => #{dispatch => Dispatch}}),
    ranch:get_port(cell_web_bench_peer).

-spec init(cowboy_req:req(), term()) -> term().
init(Req, {json, Body}) ->
    {ok, cowboy_req:reply(200, #{<<"content-type">> => <<"application/json">>}, Body, Req),
     {json, Body}};
init(Req, ws) ->
    {cowboy_websocket, Req, ws}.

-spec websocket_init(ws) -> {[cow_ws:frame()], ws}.
websocket_init(State) ->
    ok = cell_events:subscribe(),
    {[{text, <<"{}">>}], State}.

-spec websocket_handle(term(), ws) -> {[], ws}.
websocket_handle(_Frame, State) ->
    {[], State}.

-spec websocket_info(term(), ws) -> {[cow_ws:frame()], ws}.
websocket_info({cell_event, E}, State) ->
    {[{text, jsx:encode(cell_web_json:event(E))}], State};
websocket_info(_, State) ->
    {[], State}.

%% -------------------------------------------------------------------------------------

start_cell() ->
    _ = [application:load(A) || A <- [cell, cell_web]],
    Task = #{id => bench_task, module => cell_bench_task, zone => <<"Bench">>,
             lane => <<"1">>, args => #{mode => wait, never => make_ref()}},
    ok = application:set_env(cell, cell_spec, #{name => <<"bench">>, tasks => [Task]}),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    ok.

quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).
