%% A PropEr state-machine model of an ADS connection to a TwinCAT PLC, written from
%% what Beckhoff documents of ADS over AMS/TCP, not from the client's code:
%%
%% - a PLC variable is read and written by name through a handle the client takes
%%   (ADSIGRP_SYM_HNDBYNAME); a value written is what the PLC holds until the PLC
%%   program or someone else changes it;
%% - device notifications (on change) bring a variable's present value once added,
%%   then every change of it;
%% - when the PLC runtime restarts with its program loaded again, every handle and
%%   every notification on a symbol is invalid, the variables start from their initial
%%   values, and the symbol version moves on: a client watching the symbol version
%%   takes new handles and adds its notifications again, its callers never resolve
%%   anything again;
%% - a notification lives as long as the connection: across a restart of the PLC too,
%%   where the client adds it again, and the subscriber is told the value the PLC
%%   starts with;
%% - when the connection is lost (cut, or the client's process killed), nothing more
%%   is answered on it, and a write whose answer was lost may or may not have reached
%%   the PLC; the PLC keeps its values; a new connection (the HAL worker reconnects,
%%   the client is one connection and no more) reads what the PLC holds.
%%
%% The PLC is the suite's fake TwinCAT PLC (test/peers/fake_plc.py), which keeps
%% running between the runs; the client is started as {@link cell_hal_ads} starts it.
%% The model keeps, for each variable, the values the PLC may hold (more than one
%% after a write whose answer was lost); a read narrows them to what it found.
%%
%% {@link prop_sequential/0} runs every command; {@link prop_parallel/0} runs reads,
%% writes, notifications, kills and cuts in two parallel branches (a PLC restart
%% makes any handle fail while it lasts, which no serial order explains, so it stays
%% in the sequential property). The commands run in {@link cell_hal_ads_model_SUITE}.
-module(prop_cell_hal_ads_conn).
-include_lib("proper/include/proper.hrl").

-export([prop_sequential/0, prop_parallel/0, setup/1, teardown/0]).
-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([connect/0, kill/0, cut/0, restart/0, read/1, write/2, sub_read/1, notify/2,
         watched/1]).

-define(TAB, cell_hal_ads_model).
-define(NET, "127.0.0.1.1.1").
%% How long a command waits for what it expects: far more than any answer takes on a
%% busy machine, so a miss is a fault, not a slow run.
-define(WAIT, 10000).
%% The PLC's variables (DINT) and their initial values.
-define(VARS, [{<<"MAIN.m1">>, 1}, {<<"MAIN.m2">>, 2}, {<<"MAIN.m3">>, 3}]).

%%--------------------------------------------------------------------
%% Properties
%%--------------------------------------------------------------------

%% @doc Every command, one after the other.
prop_sequential() ->
    ?FORALL(Cmds, commands(?MODULE),
            begin
                ok = reset(),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                ok = reset(),
                ?WHENFAIL(io:format("history: ~p~nstate: ~p~nresult: ~p~n",
                                    [History, State, Result]),
                          Result =:= ok)
            end).

%% @doc Reads, writes, notifications, kills and cuts racing each other.
prop_parallel() ->
    ?FORALL(Cmds, parallel_commands(prop_cell_hal_ads_conn_par),
            begin
                ok = reset(),
                {Seq, Par, Result} = run_parallel_commands(prop_cell_hal_ads_conn_par, Cmds),
                ok = reset(),
                ?WHENFAIL(io:format("sequential: ~p~nparallel: ~p~nresult: ~p~n",
                                    [Seq, Par, Result]),
                          Result =:= ok)
            end).

%% @doc Where the fake PLC listens: its variables are added; the table that tells the
%% commands of the present client is made (owned by the caller, for the properties'
%% runs).
-spec setup(#{fake := pid(), port := inet:port_number()}) -> ok.
setup(#{fake := Fake, port := Port}) ->
    ?TAB = ets:new(?TAB, [named_table, public]),
    true = ets:insert(?TAB, [{fake, Fake}, {port, Port}]),
    [{ok, _, _} = cell_hal_ads_peer:cmd(Fake, ["add ", Name, " DINT 3 4 ", hex(Init)])
     || {Name, Init} <- ?VARS],
    ok.

-spec teardown() -> ok.
teardown() ->
    ok = stop_client(),
    true = ets:delete(?TAB),
    ok.

%% Between runs: no client, the PLC's variables at their initial values, no message
%% of an earlier run left.
reset() ->
    ok = stop_client(),
    ok = fake(["restart"]),
    flush().

flush() ->
    receive
        {cell_hal_ads, _, _} -> flush()
    after 0 -> ok
    end.

%%--------------------------------------------------------------------
%% The model
%%--------------------------------------------------------------------

initial_state() ->
    #{conn => down, values => initial()}.

initial() ->
    maps:from_list([{Name, [Init]} || {Name, Init} <- ?VARS]).

var() ->
    elements([Name || {Name, _} <- ?VARS]).

value() ->
    integer(-100000, 100000).

command(#{conn := down}) ->
    frequency([{6, {call, ?MODULE, connect, []}},
               {1, {call, ?MODULE, read, [var()]}},
               {1, {call, ?MODULE, write, [var(), value()]}},
               {1, {call, ?MODULE, restart, []}}]);
command(#{conn := up}) ->
    frequency([{6, {call, ?MODULE, read, [var()]}},
               {6, {call, ?MODULE, write, [var(), value()]}},
               %% a notification added costs a PLC task cycle: fewer of these
               {1, {call, ?MODULE, sub_read, [var()]}},
               {1, {call, ?MODULE, notify, [var(), value()]}},
               {2, {call, ?MODULE, watched, [var()]}},
               {1, {call, ?MODULE, restart, []}},
               {1, {call, ?MODULE, kill, []}},
               {1, {call, ?MODULE, cut, []}}]).

precondition(#{conn := Conn}, {call, _, F, _}) when F =:= kill; F =:= cut ->
    Conn =:= up;
precondition(#{conn := Conn}, {call, _, connect, _}) ->
    Conn =:= down;
precondition(_, _) ->
    true.

next_state(S, _, {call, _, connect, _}) ->
    S#{conn := up};
next_state(S, _, {call, _, F, _}) when F =:= kill; F =:= cut ->
    S#{conn := down};
next_state(S, _, {call, _, restart, _}) ->
    S#{values := initial()};
next_state(#{values := Vs} = S, Res, {call, _, F, [Var]})
  when F =:= read; F =:= sub_read; F =:= watched ->
    case Res of
        {ok, V} when is_integer(V) -> S#{values := Vs#{Var := [V]}};
        _ -> S
    end;
next_state(#{values := Vs} = S, Res, {call, _, F, [Var, V]}) when F =:= write; F =:= notify ->
    case is_error(Res) of
        %% the answer lost, not the write: the PLC may or may not hold the value now
        true -> S#{values := Vs#{Var := lists:usort([V | maps:get(Var, Vs)])}};
        false -> S#{values := Vs#{Var := [V]}}
    end.

postcondition(#{conn := down}, {call, _, F, _}, Res)
  when F =:= read; F =:= write; F =:= sub_read; F =:= notify; F =:= watched ->
    is_error(Res);
postcondition(#{values := Vs}, {call, _, F, [Var]}, Res)
  when F =:= read; F =:= sub_read; F =:= watched ->
    case Res of
        {ok, V} -> lists:member(V, maps:get(Var, Vs));
        _ -> false
    end;
postcondition(_, {call, _, write, _}, Res) ->
    Res =:= ok;
postcondition(_, {call, _, notify, [_, V]}, Res) ->
    Res =:= {ok, V};
postcondition(_, {call, _, _, _}, Res) ->
    Res =:= ok.

is_error({error, _}) -> true;
is_error(_) -> false.

%%--------------------------------------------------------------------
%% Commands
%%--------------------------------------------------------------------

%% @doc A new connection, as the HAL worker makes one: the earlier client is gone
%% first (a cut one ends on its own).
connect() ->
    case ets:lookup(?TAB, client) of
        [{client, Old}] ->
            await_down(Old);
        [] ->
            ok
    end,
    [{port, Port}] = ets:lookup(?TAB, port),
    {ok, C} = cell_hal_ads_client:start(#{host => {127, 0, 0, 1}, port => Port,
                                          target_net_id => ?NET,
                                          log_variables => false, name => <<"ads_model">>,
                                          handle_idle => 1000, request_timeout => ?WAIT}),
    true = ets:insert(?TAB, {client, C}),
    Result = case with_status(C, fun() -> ok end, up) of
                 ok -> start_watcher(C);
                 Other -> Other
             end,
    flush(),
    Result.

%% @doc The connection's process killed.
kill() ->
    [{client, C}] = ets:lookup(?TAB, client),
    exit(C, kill),
    await_down(C).

%% @doc The connection cut by the PLC's side.
cut() ->
    fake(["drop"]).

%% @doc The PLC runtime restarted; a client that is up has taken new handles when
%% this returns.
restart() ->
    case ets:lookup(?TAB, client) of
        [{client, C}] ->
            Mon = monitor(process, C),
            Watching = try cell_hal_ads_client:subscribe_status(C)
                       catch exit:_ -> down
                       end,
            Result = case {fake(["restart"]), Watching} of
                         {ok, ok} ->
                             case await_status(Mon, C, symbols_changed) of
                                 {error, down} -> ok;     % a cut client, ended now
                                 Other -> Other
                             end;
                         {Restarted, _} ->
                             Restarted
                     end,
            catch cell_hal_ads_client:unsubscribe_status(C),
            demonitor(Mon, [flush]),
            flush(),
            Result;
        [] ->
            fake(["restart"])
    end.

%% @doc A variable read by name.
read(Name) ->
    client(fun(C) -> cell_hal_ads_client:read_by_name(C, Name, int32, ?WAIT) end).

%% @doc A variable written by name.
write(Name, V) ->
    client(fun(C) -> cell_hal_ads_client:write_by_name(C, Name, int32, V, ?WAIT) end).

%% @doc A variable's value as its notification brings it when added.
sub_read(Name) ->
    client(fun(C) ->
                   with_sub(C, Name, fun(_Ref, First) -> {ok, First} end)
           end).

%% @doc The PLC program sets a variable; the caller's notification brings the value.
notify(Name, V) ->
    client(fun(C) ->
                   with_sub(C, Name,
                            fun(Ref, First) ->
                                    ok = fake(["set ", Name, " ", hex(V)]),
                                    case First of
                                        V -> {ok, V};
                                        _ -> await_value(C, Ref, V)
                                    end
                            end)
           end).

%% @doc A variable read by name; then the notification that the connection's watcher
%% has had since it connected brings the same value.
watched(Name) ->
    case read(Name) of
        {ok, V} ->
            [{watcher, W}] = ets:lookup(?TAB, watcher),
            Mon = monitor(process, W),
            W ! {await, self(), Name, V},
            Result = receive
                         {watched, W, Name, V} -> {ok, V};
                         {'DOWN', Mon, process, W, _} -> {error, down}
                     after ?WAIT -> {error, {not_notified, V}}
                     end,
            demonitor(Mon, [flush]),
            Result;
        Other ->
            Other
    end.

%%--------------------------------------------------------------------
%% The watcher: a subscriber to every variable for as long as a connection lasts
%%--------------------------------------------------------------------

start_watcher(C) ->
    Test = self(),
    W = spawn(fun() -> watcher(Test, C) end),
    Mon = monitor(process, W),
    receive
        {watching, W} ->
            demonitor(Mon, [flush]),
            true = ets:insert(?TAB, {watcher, W}),
            ok;
        {'DOWN', Mon, process, W, Why} ->
            {error, {watcher, Why}}
    after ?WAIT ->
            {error, watcher_not_started}
    end.

watcher(Test, C) ->
    Mon = monitor(process, C),
    {ok, Results} = cell_hal_ads_client:subscribe(
                      C, [{{Name, int32}, #{cycle_us => 1000}} || {Name, _} <- ?VARS], ?WAIT),
    Refs = maps:from_list(lists:zip([R || {ok, R} <- Results], [N || {N, _} <- ?VARS])),
    3 = map_size(Refs),
    Test ! {watching, self()},
    watch(Mon, Refs, #{}, []).

%% Keeps the latest value of each variable; answers who waits for one.
watch(Mon, Refs, Latest, Waiting) ->
    receive
        {cell_hal_ads, Ref, {samples, Samples}} when is_map_key(Ref, Refs) ->
            {_, V} = lists:last(Samples),
            Latest1 = Latest#{maps:get(Ref, Refs) => V},
            watch(Mon, Refs, Latest1, answer(Waiting, Latest1));
        {await, From, Name, V} ->
            watch(Mon, Refs, Latest, answer([{From, Name, V} | Waiting], Latest));
        {'DOWN', Mon, process, _, _} ->
            ok
    end.

answer(Waiting, Latest) ->
    [W || {From, Name, V} = W <- Waiting,
          case Latest of
              #{Name := V} -> From ! {watched, self(), Name, V}, false;
              _ -> true
          end].

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

client(Fun) ->
    case ets:lookup(?TAB, client) of
        [{client, C}] ->
            try Fun(C) of
                {ok, _} = Ok -> Ok;
                ok -> ok;
                {error, _} = E -> E
            catch
                exit:_ -> {error, down}
            end;
        [] ->
            {error, no_client}
    end.

%% Subscribes to a variable, hands its first sample's value to `Fun', unsubscribes.
with_sub(C, Name, Fun) ->
    case cell_hal_ads_client:subscribe(C, [{{Name, int32}, #{cycle_us => 1000}}], ?WAIT) of
        {ok, [{ok, Ref}]} ->
            Result = case await_sample(C, Ref) of
                         {ok, First} -> Fun(Ref, First);
                         {error, _} = E -> E
                     end,
            _ = cell_hal_ads_client:unsubscribe(C, [Ref]),
            Result;
        {ok, [{error, _} = E]} ->
            E;
        {error, _} = E ->
            E
    end.

%% The value of the next sample of a subscription: the last of its message.
await_sample(C, Ref) ->
    Mon = monitor(process, C),
    Result = receive
                 {cell_hal_ads, Ref, {samples, Samples}} ->
                     {_, V} = lists:last(Samples),
                     {ok, V};
                 {'DOWN', Mon, process, C, _} ->
                     {error, down}
             after ?WAIT ->
                     {error, no_sample}
             end,
    demonitor(Mon, [flush]),
    Result.

%% Samples until one brings `V'.
await_value(C, Ref, V) ->
    Mon = monitor(process, C),
    Result = await_value(Mon, C, Ref, V, erlang:monotonic_time(millisecond) + ?WAIT),
    demonitor(Mon, [flush]),
    Result.

await_value(Mon, C, Ref, V, Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {cell_hal_ads, Ref, {samples, Samples}} ->
            case lists:keymember(V, 2, Samples) of
                true -> {ok, V};
                false -> await_value(Mon, C, Ref, V, Deadline)
            end;
        {'DOWN', Mon, process, C, _} ->
            {error, down}
    after Left ->
            {error, {no_sample_of, V}}
    end.

%% Runs `Fun' with the client's status messages on; then waits for `Status'.
with_status(C, Fun, Status) ->
    Mon = monitor(process, C),
    Result = try cell_hal_ads_client:subscribe_status(C) of
                 ok ->
                     case Fun() of
                         ok -> await_status(Mon, C, Status);
                         Other -> Other
                     end
             catch
                 exit:_ -> {error, down}
             end,
    catch cell_hal_ads_client:unsubscribe_status(C),
    demonitor(Mon, [flush]),
    Result.

await_status(Mon, C, Status) ->
    receive
        {cell_hal_ads, C, Status} -> ok;
        {'DOWN', Mon, process, C, _} -> {error, down}
    after ?WAIT -> {error, {no_status, Status}}
    end.

await_down(C) ->
    Mon = monitor(process, C),
    receive
        {'DOWN', Mon, process, C, _} -> ok
    after ?WAIT -> {error, {still_running, C}}
    end.

stop_client() ->
    case ets:lookup(?TAB, client) of
        [{client, C}] ->
            exit(C, kill),
            ok = await_down(C),
            true = ets:delete(?TAB, client),
            ok;
        [] ->
            ok
    end.

fake(Line) ->
    [{fake, Fake}] = ets:lookup(?TAB, fake),
    cell_hal_ads_peer:cmd(Fake, Line).

hex(V) when is_integer(V) ->
    binary:encode_hex(<<V:32/little-signed>>).
