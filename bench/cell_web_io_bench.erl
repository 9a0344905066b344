%% @doc The panel's IO view under load: 20 pages open on the IO view of a cell with 500
%% IO points on a simulated PLC, every point changing 10 times a second. Measured: the
%% delay from a value set in the PLC to its decode on a page (p99 and median), and the
%% node's CPU (the schedulers' busy share) while it runs. Beside it, in the same run and
%% node: 20 bare cowboy websockets sending the same frames (the panel's feed's `io'
%% messages, as they are made), one frame a message, no snapshot, batching or session;
%% so the difference is what the panel's own websocket adds. The delay includes the HAL's
%% poll (every 20 ms) and the panel's gathering of changes (at most every 50 ms), on
%% both sides.
-module(cell_web_io_bench).
-behaviour(cell_hal_group).
-behaviour(cowboy_handler).

-export([run/0, points/1]).
-export([init/2, websocket_init/1, websocket_handle/2, websocket_info/2]).

-define(PAGES, 20).
-define(GROUPS, 5).
-define(PER_GROUP, 100).        %% 500 points
-define(PERIOD_MS, 100).        %% each point changes 10 times a second
-define(TICKS, 100).            %% 10 s a side
-define(WARM_UP, 10).
-define(POLL_MS, 20).

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    start_cell(),
    ok = cell_web_io:watch(),
    _ = sys:get_state(cell_web_io),
    PeerPort = start_peer(),
    T0 = erlang:monotonic_time(millisecond),
    %% A short round each first: the modules load on their first call here, as they
    %% never do in the release, which loads them all at boot.
    _ = side(cell_web:port(), "/api/ws", T0, ?WARM_UP),
    _ = side(PeerPort, "/ws", T0, ?WARM_UP),
    {OurDelays, OurCpu} = side(cell_web:port(), "/api/ws", T0, ?TICKS),
    {PeerDelays, PeerCpu} = side(PeerPort, "/ws", T0, ?TICKS),
    ok = cowboy:stop_listener(cell_web_io_bench_peer),
    #{median := OM, p99 := OP} = cell_bench:stats(OurDelays),
    #{median := PM, p99 := PP} = cell_bench:stats(PeerDelays),
    Title = "IO view, 20 pages, 500 points changing 10 times a second",
    Peer = "bare cowboy websockets, the same frames",
    [#{title => [Title, ", median update delay"], unit => "ms", ours => OM, peer => PM,
       peer_name => Peer, better => lower},
     #{title => [Title, ", p99 update delay"], unit => "ms", ours => OP, peer => PP,
       peer_name => Peer, better => lower},
     #{title => [Title, ", node CPU"], unit => "% of the schedulers", ours => OurCpu,
       peer => PeerCpu, peer_name => Peer, better => lower,
       note => io_lib:format("~p pages, ~p points in ~p groups on a simulated PLC polled every "
                             "~p ms, all set every ~p ms for ~p s a side; delay from the set to "
                             "the page's decode (the HAL's poll and the panel's 50 ms "
                             "gathering included on both sides); CPU the schedulers' busy "
                             "share over the side's run, the pages' clients in the same node.",
                             [?PAGES, ?GROUPS * ?PER_GROUP, ?GROUPS, ?POLL_MS, ?PERIOD_MS,
                              ?TICKS * ?PERIOD_MS div 1000])}].

%% One side: the pages connect, every point is set ?TICKS times, each page reads until
%% it has seen the last value of every point; the delays of all pages and the CPU.
side(Port, Path, T0, Last) ->
    Self = self(),
    Clients = [spawn_link(fun() -> client(Port, Path, Self, T0) end)
               || _ <- lists:seq(1, ?PAGES)],
    _ = [receive {ready, C} -> ok end || C <- Clients],
    erlang:system_flag(scheduler_wall_time, true),
    W0 = lists:sort(erlang:statistics(scheduler_wall_time)),
    ok = tick(1, Last, T0),
    Delays = lists:append([receive {done, C, D} -> D end || C <- Clients]),
    W1 = lists:sort(erlang:statistics(scheduler_wall_time)),
    erlang:system_flag(scheduler_wall_time, false),
    {Delays, cpu(W0, W1)}.

%% The normal schedulers' busy share, in percent.
cpu(W0, W1) ->
    N = erlang:system_info(schedulers),
    {Active, Total} = lists:foldl(fun({{I, A0, T0}, {I, A1, T1}}, {A, T}) when I =< N ->
                                          {A + A1 - A0, T + T1 - T0};
                                     (_, Acc) -> Acc
                                  end, {0, 0}, lists:zip(W0, W1)),
    round(1000 * Active / max(Total, 1)) / 10.

%% Every point set at once, to the time since T0 in ms, and at the last tick to the
%% marker the pages wait for.
tick(N, Last, _T0) when N > Last ->
    ok;
tick(N, Last, T0) ->
    Now = erlang:monotonic_time(millisecond) - T0,
    Value = case N of Last -> -Now; _ -> Now end,
    ok = cell_hal_sim:preset(bench_plc, maps:from_list([{K, Value} || K <- keys()])),
    receive after ?PERIOD_MS -> ok end,
    tick(N + 1, Last, T0).

keys() ->
    [{group(G), point(P)} || G <- lists:seq(1, ?GROUPS), P <- lists:seq(1, ?PER_GROUP)].

group(G) -> list_to_atom("bench_io_" ++ integer_to_list(G)).
point(P) -> list_to_atom("p" ++ integer_to_list(P)).

%% -------------------------------------------------------------------------------------
%% A page: reads frames, keeps the delay of every value, stops once every point has
%% shown the last tick's marker (a negative value).

client(Port, Path, Parent, T0) ->
    {S, Rest} = cell_web_bench:ws_open(Port, Path),
    {_, Rest1} = cell_web_bench:frame(S, Rest),
    Parent ! {ready, self()},
    Delays = collect(S, Rest1, T0, ?GROUPS * ?PER_GROUP, []),
    Parent ! {done, self(), Delays},
    gen_tcp:close(S).

collect(_S, _Buf, _T0, 0, Acc) ->
    Acc;
collect(S, Buf, T0, Left, Acc) ->
    {Payload, Rest} = cell_web_bench:frame(S, Buf),
    Now = erlang:monotonic_time(millisecond) - T0,
    Values = [V || #{<<"type">> := <<"io">>, <<"points">> := Ps} <- jsx:decode(Payload, [return_maps]),
                   #{<<"value">> := V} <- Ps, is_integer(V)],
    Done = length([V || V <- Values, V < 0]),
    collect(S, Rest, T0, Left - Done, [Now - abs(V) || V <- Values] ++ Acc).

%% -------------------------------------------------------------------------------------
%% The peer: a bare cowboy websocket that sends each of the feed's messages as it comes

start_peer() ->
    Dispatch = cowboy_router:compile([{'_', [{"/ws", ?MODULE, ws}]}]),
    {ok, _} = cowboy:start_clear(cell_web_io_bench_peer, [{ip, {127, 0, 0, 1}}, {port, 0}],
                                 #{env => #{dispatch => Dispatch}}),
    ranch:get_port(cell_web_io_bench_peer).

-spec init(cowboy_req:req(), ws) -> {cowboy_websocket, cowboy_req:req(), ws}.
init(Req, ws) ->
    {cowboy_websocket, Req, ws}.

-spec websocket_init(ws) -> {[cow_ws:frame()], ws}.
websocket_init(State) ->
    ok = cell_web_feed:join(self()),
    {[{text, <<"[]">>}], State}.

-spec websocket_handle(term(), ws) -> {[], ws}.
websocket_handle(_Frame, State) ->
    {[], State}.

-spec websocket_info(term(), ws) -> {[cow_ws:frame()], ws}.
websocket_info({cell_web_feed, Json}, State) ->
    {[{text, [$[, Json, $]]}], State};
websocket_info(_, State) ->
    {[], State}.

%% -------------------------------------------------------------------------------------
%% The cell: no task, 500 points on a simulated PLC

%% The points of a group (cell_hal_group): ?PER_GROUP DINT inputs.
-spec points(map()) -> [cell_hal_group:point_def()].
points(#{}) ->
    [#{name => point(P), dir => in, type => int32,
       address => iolist_to_binary(io_lib:format("B1.~3..0b", [P])),
       caption => iolist_to_binary(["Bench input ", integer_to_list(P)]), field => point(P)}
     || P <- lists:seq(1, ?PER_GROUP)].

start_cell() ->
    _ = [application:load(A) || A <- [cell, cell_web]],
    Hal = #{connections => [#{id => bench_plc, driver => cell_hal_sim,
                              opts => #{poll_ms => ?POLL_MS}}],
            groups => [#{id => group(G), module => ?MODULE, connection => bench_plc}
                       || G <- lists:seq(1, ?GROUPS)]},
    ok = application:set_env(cell, cell_spec, #{name => <<"bench">>, tasks => [], hal => Hal}),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    {ok, Status} = cell_hal:subscribe_connection(bench_plc),
    ok = case Status of
             up -> ok;
             down -> receive {cell_hal_conn, bench_plc, up} -> ok after 30000 -> timeout end
         end,
    ok = cell_hal:unsubscribe_connection(bench_plc).

quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).
