%% A PropEr state-machine model of the SHDR adapter's cache and protocol, as the
%% MTConnect standard documents an adapter (Part 1, the SHDR protocol; seed 003), run
%% against the adapter over real TCP with a scripted HAL (cell_shdr_prop_SUITE):
%%
%% - a client that connects first gets a snapshot: every data item's current value and
%%   every condition's state (each active code at its level, or one NORMAL with no
%%   code when none is active), and only changes after it;
%% - a value equal to the one last sent is not sent again (duplicate filtering);
%% - a condition is marked and swept: a new code goes out at its level, a code that
%%   goes away goes out NORMAL for that code, and when the last one goes away one
%%   NORMAL with no code clears the item;
%% - `* PING' is answered `* PONG <heartbeat ms>', after every change sent before it;
%% - a client that stops reading costs the others nothing;
%% - a connection killed on the adapter's side closes that client's socket and nothing
%%   else; a client that closes its socket is let go.
%%
%% The model is the standard's, written from the list above: item values, active
%% codes, and the clients that read. It never asks the adapter what it thinks.
-module(prop_cell_shdr).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([connect/0, set/3, raise/2, clear/2, ping/1, stall/1, kill/1, close/1]).
-export([setup/0, reset/0, cleanup/1, prop_sequential/1]).
-export([points/0, snapshot_matches/2, session/0, session_matches/2]).

-define(WAIT, 15000).
-define(HEARTBEAT, <<"* PONG 10000">>).
-define(KEYS, [<<"prop_a">>, <<"prop_b">>]).
-define(VALUES, [<<"OPEN">>, <<"CLOSED">>, <<"UNLATCHED">>]).
-define(INITIAL, <<"OPEN">>).
-define(CODES, [<<"c1">>, <<"c2">>, <<"c3">>]).

-record(m, {values = #{} :: #{binary() => binary()},
            active = [] :: [binary()],
            clients = [] :: [{term(), reading | stalled}]}).

%%--------------------------------------------------------------------
%% The property
%%--------------------------------------------------------------------

prop_sequential(NumTests) ->
    proper:quickcheck(
      ?FORALL(Cmds, commands(?MODULE),
              begin
                  ok = reset(),
                  Cache = whereis(cell_shdr_cache),
                  {History, State, Result} = run_commands(?MODULE, Cmds),
                  ok = cleanup(State),
                  ?WHENFAIL(io:format(user, "History: ~p~nState: ~p~nResult: ~p~n",
                                      [History, State, Result]),
                            aggregate(command_names(Cmds),
                                      Result =:= ok andalso
                                      %% No client's end ever took the adapter down.
                                      whereis(cell_shdr_cache) =:= Cache))
              end),
      [{to_file, user}, {numtests, NumTests}, {max_size, 20}]).

%%--------------------------------------------------------------------
%% The model
%%--------------------------------------------------------------------

initial_state() ->
    #m{values = maps:from_list([{K, ?INITIAL} || K <- ?KEYS])}.

command(#m{clients = Cs} = M) ->
    Readers = readers(M),
    frequency(
      [{3, {call, ?MODULE, connect, []}},
       {5, {call, ?MODULE, set, [oneof(?KEYS), oneof(?VALUES), Readers]}},
       {2, {call, ?MODULE, raise, [oneof(?CODES), Readers]}},
       {2, {call, ?MODULE, clear, [oneof(?CODES), Readers]}}]
      ++ [{2, {call, ?MODULE, ping, [oneof(Readers)]}} || Readers =/= []]
      ++ [{1, {call, ?MODULE, stall, [oneof(Readers)]}} || Readers =/= []]
      ++ [{2, {call, ?MODULE, kill, [elements([C || {C, _} <- Cs])]}} || Cs =/= []]
      ++ [{1, {call, ?MODULE, close, [elements([C || {C, _} <- Cs])]}} || Cs =/= []]).

readers(#m{clients = Cs}) ->
    [C || {C, reading} <- Cs].

precondition(#m{clients = Cs}, {call, _, connect, []}) ->
    length(Cs) < 4;
precondition(M, {call, _, F, [_, _, Readers]}) when F =:= set ->
    Readers =:= readers(M);
precondition(M, {call, _, F, [_, Readers]}) when F =:= raise; F =:= clear ->
    Readers =:= readers(M);
precondition(M, {call, _, F, [C]}) when F =:= ping; F =:= stall ->
    lists:member(C, readers(M));
precondition(#m{clients = Cs}, {call, _, F, [C]}) when F =:= kill; F =:= close ->
    lists:keymember(C, 1, Cs).

next_state(#m{clients = Cs} = M, Res, {call, _, connect, []}) ->
    M#m{clients = Cs ++ [{Res, reading}]};
next_state(#m{values = V} = M, _Res, {call, _, set, [K, X, _]}) ->
    M#m{values = V#{K => X}};
next_state(#m{active = A} = M, _Res, {call, _, raise, [Code, _]}) ->
    M#m{active = lists:usort([Code | A])};
next_state(#m{active = A} = M, _Res, {call, _, clear, [Code, _]}) ->
    M#m{active = A -- [Code]};
next_state(M, _Res, {call, _, ping, [_]}) ->
    M;
next_state(#m{clients = Cs} = M, _Res, {call, _, stall, [C]}) ->
    M#m{clients = lists:keyreplace(C, 1, Cs, {C, stalled})};
next_state(#m{clients = Cs} = M, _Res, {call, _, F, [C]}) when F =:= kill; F =:= close ->
    M#m{clients = lists:keydelete(C, 1, Cs)}.

postcondition(M, {call, _, connect, []}, #{snapshot := Snap, pong := Pong}) ->
    Pong =:= ?HEARTBEAT andalso snapshot_matches(M, Snap);
postcondition(#m{values = V}, {call, _, set, [K, X, _]}, Deltas) ->
    Expected = case maps:get(K, V) of
                   X -> [];                       %% the same value: not sent again
                   _ -> [{K, X}]
               end,
    lists:all(fun(#{pairs := P, conditions := C}) -> P =:= Expected andalso C =:= [] end,
              Deltas);
postcondition(#m{active = A}, {call, _, raise, [Code, _]}, Deltas) ->
    Expected = case lists:member(Code, A) of
                   true -> [];                    %% active already, the same text
                   false -> [{<<"WARNING">>, Code}]
               end,
    lists:all(fun(#{pairs := P, conditions := C}) -> P =:= [] andalso C =:= Expected end,
              Deltas);
postcondition(#m{active = A}, {call, _, clear, [Code, _]}, Deltas) ->
    Expected = case {lists:member(Code, A), A -- [Code]} of
                   {false, _} -> [];
                   {true, []} -> [{<<"NORMAL">>, <<>>}];   %% the last: the item cleared
                   {true, _} -> [{<<"NORMAL">>, Code}]
               end,
    lists:all(fun(#{pairs := P, conditions := C}) -> P =:= [] andalso C =:= Expected end,
              Deltas);
postcondition(_M, {call, _, ping, [_]}, {#{pairs := P, conditions := C}, Pong}) ->
    P =:= [] andalso C =:= [] andalso Pong =:= ?HEARTBEAT;
postcondition(_M, {call, _, stall, [_]}, Res) ->
    Res =:= ok;
postcondition(_M, {call, _, kill, [_]}, Res) ->
    Res =:= closed;
postcondition(_M, {call, _, close, [_]}, Res) ->
    Res =:= gone;
postcondition(_M, _Call, _Res) ->
    false.

%% A snapshot holds every item's value the model has, and each condition as the model
%% has it: the active codes at their level, or one NORMAL with no code.
snapshot_matches(#m{values = V, active = A}, #{pairs := P, conditions := C}) ->
    Expected = case A of
                   [] -> [{<<"NORMAL">>, <<>>}];
                   _ -> [{<<"WARNING">>, Code} || Code <- lists:sort(A)]
               end,
    maps:from_list(P) =:= V andalso length(P) =:= map_size(V)
        andalso lists:sort(C) =:= Expected.

%% A session's view: what it read up to its PONG, the snapshot and the changes after
%% it, applied in order, is the model's state at one moment.
session_matches(#m{values = V, active = A}, #{values := SV, active := SA}) ->
    SV =:= V andalso SA =:= lists:sort(A).

%%--------------------------------------------------------------------
%% The adapter, as clients see it
%%--------------------------------------------------------------------

%% The suite's settings: two HAL points of the scripted HAL, as events.
points() ->
    [#{name => K, group => <<"prop">>, point => K, category => event,
       type => <<"DOOR_STATE">>, units => <<>>} || K <- ?KEYS].

setup() ->
    _ = [ok = cell_shdr_test_hal:set(prop, binary_to_atom(K), ?INITIAL) || K <- ?KEYS],
    ok = cell_settings:put(shdr, #{points => points()}, <<"suite">>),
    ok = cell_shdr_cache:sync(),
    _ = sys:get_state(cell_shdr_sampler),
    ok.

%% Before each run: no client, every item at its initial value, no code active.
reset() ->
    Pids = cell_shdr_cache:clients(),
    Refs = [monitor(process, P) || P <- Pids],
    _ = [exit(P, kill) || P <- Pids],
    ok = await_down(Refs, deadline()),
    _ = [ok = cell_shdr_test_hal:set(prop, binary_to_atom(K), ?INITIAL) || K <- ?KEYS],
    _ = [ok = cell_alarms:reset_warning(cell, C) || C <- ?CODES],
    barrier(),
    [] = cell_alarms:list(),
    ok.

%% After each run: the clients' sockets closed.
cleanup(#m{clients = Cs}) ->
    _ = [gen_tcp:close(S) || {#{socket := S}, _} <- Cs],
    ok;
cleanup(_) ->
    ok.

connect() ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, cell_shdr:port(),
                              [binary, {active, false}, {packet, line}, {buffer, 1 bsl 16}]),
    {Snap, Pong} = ping_read(S),
    #{socket => S, server => server_of(S), snapshot => Snap, pong => Pong}.

%% A client that connects, reads up to the PONG to its first PING and leaves (for the
%% parallel model): the items and active codes it was told, the snapshot and the
%% changes after it applied in order; `killed' when its connection was killed
%% meanwhile.
session() ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, cell_shdr:port(),
                              [binary, {active, false}, {packet, line}, {buffer, 1 bsl 16}]),
    try ping_read(S) of
        {Read, ?HEARTBEAT} -> applied(Read);
        {_, Other} -> {bad_pong, Other}
    catch
        throw:{closed, _} -> killed
    after
        ok = gen_tcp:close(S)
    end.

set(K, X, Readers) ->
    ok = cell_shdr_test_hal:set(prop, binary_to_atom(K), X),
    deltas(Readers).

raise(Code, Readers) ->
    ok = cell_alarms:warning(cell, Code, ["Check ", Code], ""),
    deltas(Readers).

clear(Code, Readers) ->
    ok = cell_alarms:reset_warning(cell, Code),
    deltas(Readers).

ping(#{socket := S}) ->
    ping_read(S).

stall(_C) ->
    ok.

kill(#{socket := S, server := Pid}) ->
    exit(Pid, kill),
    drain(S, deadline()).

close(#{socket := S, server := Pid}) ->
    Ref = monitor(process, Pid),
    ok = gen_tcp:close(S),
    receive {'DOWN', Ref, process, Pid, _} -> gone
    after ?WAIT -> still_there
    end.

%% What each reading client got since it last read, once the adapter has taken the
%% change: the lines before the PONG to a PING.
deltas(Readers) ->
    barrier(),
    [element(1, ping_read(S)) || #{socket := S} <- Readers].

barrier() ->
    ok = cell_alarms:sync(),
    ok = cell_shdr_cache:sync().

ping_read(S) ->
    ok = gen_tcp:send(S, <<"* PING\n">>),
    read_until_pong(S, deadline(), []).

read_until_pong(S, Deadline, Acc) ->
    case gen_tcp:recv(S, 0, left(Deadline)) of
        {ok, Line0} ->
            Line = string:trim(Line0, trailing, "\r\n"),
            case Line of
                <<"* PONG", _/binary>> -> {parse(lists:reverse(Acc)), Line};
                _ -> read_until_pong(S, Deadline, [Line | Acc])
            end;
        {error, Why} ->
            throw({closed, Why})
    end.

drain(S, Deadline) ->
    case gen_tcp:recv(S, 0, left(Deadline)) of
        {ok, _} -> drain(S, Deadline);
        {error, closed} -> closed;
        {error, Why} -> Why
    end.

%% The connection's process on the adapter's side: the one whose peer is this socket
%% (it has just answered this socket's PING). The cache may still list connections
%% that ended a moment ago (their 'DOWN' on its way): those are not it.
server_of(S) ->
    {ok, Me} = inet:sockname(S),
    [Pid] = [P || P <- cell_shdr_cache:clients(), {ok, Me} =:= peer_of(P)],
    Pid.

peer_of(Pid) ->
    try sys:get_state(Pid) of
        State -> inet:peername(element(2, State))
    catch
        exit:{noproc, _} -> gone
    end.

%% What a client was told, applied in order: each item's last value, and the codes
%% active (a code NORMAL leaves, a NORMAL with no code clears them all).
applied(#{pairs := P, conditions := C}) ->
    Active = lists:foldl(fun({<<"NORMAL">>, <<>>}, _) -> [];
                            ({<<"NORMAL">>, Code}, Acc) -> Acc -- [Code];
                            ({_, Code}, Acc) -> lists:usort([Code | Acc])
                         end, [], C),
    #{values => maps:from_list(P), active => Active}.

%% The model's items in data lines, and the `system' condition's level and code.
parse(Lines) ->
    Fields = [binary:split(L, <<"|">>, [global]) || L <- Lines],
    #{pairs => [{K, V} || [_Ts | KVs] <- Fields, {K, V} <- kv(KVs), lists:member(K, ?KEYS)],
      conditions => [{Level, code(Code)} || [_Ts, <<"system">>, Level, Code | _] <- Fields]}.

kv([K, V | Rest]) -> [{K, V} | kv(Rest)];
kv(_) -> [].

%% The native code names the alarm by its task and id: the model's code is its id.
code(<<>>) -> <<>>;
code(Native) ->
    case binary:split(Native, <<".">>, [global]) of
        [_ | _] = Parts -> lists:last(Parts)
    end.

await_down([], _Deadline) ->
    ok;
await_down([Ref | Refs], Deadline) ->
    receive {'DOWN', Ref, process, _, _} -> await_down(Refs, Deadline)
    after left(Deadline) -> {still_running, length(Refs) + 1}
    end.

deadline() ->
    erlang:monotonic_time(millisecond) + ?WAIT.

left(Deadline) ->
    max(0, Deadline - erlang:monotonic_time(millisecond)).
