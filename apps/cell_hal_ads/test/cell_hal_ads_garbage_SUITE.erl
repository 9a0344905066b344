%% Random garbage from the network: a peer that answers the client's first request
%% with random bytes (or a frame whose AMS/TCP header is right and whose content is
%% random). Whatever it sends, the client closes that connection (or waits for an
%% answer that never comes, and then closes it) and ends with the reason, never with
%% a crash; the HAL's worker, whose job connecting again is, takes each new connection
%% and its garbage and stays the same process.
-module(cell_hal_ads_garbage_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("proper/include/proper.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([garbage_never_crashes_the_client/1, hal_worker_reconnects_through_garbage/1]).

-define(WAIT, 10000).
-define(NET, "127.0.0.1.1.1").

all() ->
    [garbage_never_crashes_the_client, hal_worker_reconnects_through_garbage].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

%% A client is one connection: each garbage gets a new one, which ends with
%% `{shutdown, Reason}' (a reason that reads as words), never with a crash.
garbage_never_crashes_the_client(_Config) ->
    {Listen, Port} = listen(),
    Property = ?FORALL(Garbage, garbage(), client_ends_cleanly(Listen, Port, Garbage)),
    ?assert(proper:quickcheck(Property, [{to_file, user}, {numtests, 60}])),
    ok = gen_tcp:close(Listen).

client_ends_cleanly(Listen, Port, Garbage) ->
    {ok, C} = cell_hal_ads_client:start(#{host => "127.0.0.1", port => Port,
                                          target_net_id => ?NET, request_timeout => 200,
                                          link_check => infinity}),
    %% set before the client has its garbage: it cannot have ended yet
    Mon = monitor(process, C),
    Closed = answered_with(Listen, Garbage),
    receive
        {'DOWN', Mon, process, C, {shutdown, Why}} ->
            ct:log("~ts", [cell_hal_ads_client:format_error(Why)]),
            Closed andalso byte_size(cell_hal_ads_client:format_error(Why)) > 0;
        {'DOWN', Mon, process, C, Crash} ->
            ct:log("the client crashed: ~p", [Crash]),
            false
    after ?WAIT ->
            ct:log("the client still runs after closing its connection"),
            false
    end.

%% Through the HAL: its worker starts a client for each connection, and whatever
%% garbage ends it, connects again after its back-off with a new one. The worker is
%% the same process all along, and no client ended otherwise than with a reason.
hal_worker_reconnects_through_garbage(_Config) ->
    {Listen, Port} = listen(),
    ok = cell_log:subscribe(),
    ok = cell_hal:add_connection(#{id => garbage, driver => cell_hal_ads,
                                   opts => #{host => "127.0.0.1", port => Port,
                                             target_net_id => ?NET, timeout_ms => 200,
                                             link_check => infinity, reconnect_ms => 1,
                                             max_reconnect_ms => 5}}),
    Worker = worker(garbage),
    Property = ?FORALL(Garbage, garbage(), answered_with(Listen, Garbage)),
    ?assert(proper:quickcheck(Property, [{to_file, user}, {numtests, 60}])),
    ?assertEqual(Worker, worker(garbage)),
    ?assertEqual(down, cell_hal:status(garbage)),
    ok = cell_hal:remove_connection(garbage),
    ok = cell_log:unsubscribe(),
    Crashes = [T || {cell_log, #{text := T}} <- lines(),
                    binary:match(T, <<"ended unexpectedly">>) =/= nomatch],
    ?assertEqual([], Crashes),
    ok = gen_tcp:close(Listen).

listen() ->
    {ok, Listen} = gen_tcp:listen(0, [binary, {ip, {127, 0, 0, 1}}, {active, false},
                                      {reuseaddr, true}]),
    {ok, Port} = inet:port(Listen),
    {Listen, Port}.

worker(Conn) ->
    [Pid] = [P || {Id, P, _, _} <- supervisor:which_children(cell_hal_conn_sup), Id =:= Conn],
    Pid.

lines() ->
    receive {cell_log, _} = L -> [L | lines()]
    after 0 -> []
    end.

garbage() ->
    oneof([binary(),
           %% a frame that holds together, with a random AMS header and data
           ?LET(Body, binary(), <<0:16, (byte_size(Body)):32/little, Body/binary>>),
           %% an AMS header addressed to the client's port, random command and data
           ?LET({Cmd, Flags, Err, Invoke, Data}, {integer(0, 12), integer(0, 7), integer(0, 2000),
                                                  integer(0, 3), binary()},
                frame(Cmd, Flags, Err, Invoke, Data)),
           %% a length the client must refuse
           ?LET(Len, integer(16#1000001, 16#FFFFFFFF), <<0:16, Len:32/little>>)]).

frame(Cmd, Flags, Err, Invoke, Data) ->
    Body = <<127, 0, 0, 1, 1, 1, 16#89, 16#80, 127, 0, 0, 1, 1, 1, 16#53, 16#03,
             Cmd:16/little, Flags:16/little, (byte_size(Data)):32/little, Err:32/little,
             Invoke:32/little, Data/binary>>,
    <<0:16, (byte_size(Body)):32/little, Body/binary>>.

%% A client connects, sends its first request and gets the garbage; whatever it makes
%% of it, it closes the connection within its request timeout.
answered_with(Listen, Garbage) ->
    {ok, S} = gen_tcp:accept(Listen, ?WAIT),
    {ok, _First} = gen_tcp:recv(S, 0, ?WAIT),
    ok = gen_tcp:send(S, Garbage),
    Closed = drain(S, erlang:monotonic_time(millisecond) + ?WAIT),
    _ = gen_tcp:close(S),
    Closed.

%% Reads whatever else the client sends until it closes the connection.
drain(S, Deadline) ->
    Left = Deadline - erlang:monotonic_time(millisecond),
    case Left > 0 andalso gen_tcp:recv(S, 0, Left) of
        {ok, _} -> drain(S, Deadline);
        {error, closed} -> true;
        _ -> false
    end.
