%% Random garbage from the network, at the level of the client process: a peer that
%% answers the client's first request with random bytes (or a frame whose AMS/TCP
%% header is right and whose content is random). Whatever it sends, the client closes
%% that connection (or waits for an answer that never comes, and then closes it) and
%% connects again; the client process never crashes.
-module(cell_hal_ads_garbage_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("proper/include/proper.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([garbage_never_crashes_the_client/1]).

-define(WAIT, 10000).

all() ->
    [garbage_never_crashes_the_client].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, _} = application:ensure_all_started(cell_base),
    Config.

end_per_suite(Config) ->
    Config.

garbage_never_crashes_the_client(_Config) ->
    {ok, Listen} = gen_tcp:listen(0, [binary, {ip, {127, 0, 0, 1}}, {active, false},
                                      {reuseaddr, true}]),
    {ok, Port} = inet:port(Listen),
    {ok, C} = cell_hal_ads_client:start(#{host => "127.0.0.1", port => Port,
                                          target_net_id => "127.0.0.1.1.1",
                                          backoff => {1, 5}, request_timeout => 200,
                                          link_check => infinity}),
    Ref = monitor(process, C),
    Property = ?FORALL(Garbage, garbage(), answered_with(Listen, Garbage, C)),
    ?assert(proper:quickcheck(Property, [{to_file, user}, {numtests, 60}])),
    receive {'DOWN', Ref, process, C, Why} -> ct:fail("the client died: ~p", [Why])
    after 0 -> ok
    end,
    #{state := State} = cell_hal_ads_client:status(C),
    ct:log("after the garbage the client is ~p", [State]),
    ok = cell_hal_ads_client:stop(C),
    ok = gen_tcp:close(Listen).

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

%% The client connects, sends its first request and gets the garbage; whatever it
%% makes of it, it closes the connection within its request timeout and stays alive.
answered_with(Listen, Garbage, C) ->
    {ok, S} = gen_tcp:accept(Listen, ?WAIT),
    {ok, _First} = gen_tcp:recv(S, 0, ?WAIT),
    ok = gen_tcp:send(S, Garbage),
    Closed = drain(S, erlang:monotonic_time(millisecond) + ?WAIT),
    _ = gen_tcp:close(S),
    Closed andalso is_process_alive(C).

%% Reads whatever else the client sends until it closes the connection.
drain(S, Deadline) ->
    Left = Deadline - erlang:monotonic_time(millisecond),
    case Left > 0 andalso gen_tcp:recv(S, 0, Left) of
        {ok, _} -> drain(S, Deadline);
        {error, closed} -> true;
        _ -> false
    end.
