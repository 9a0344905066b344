%% Loaded by router_release_SUITE into the running release, to wait there for what the
%% cell does: waiting is done on the cell's events, never by asking again and again.
-module(router_release_probe).

-export([await/2, await_state/2, await_state_or_error/2, snapshot/0, time_check/0,
         await_left/2, await_committed/1, await_alarm/2, await_gone/2, books/0,
         estop_by_hand/2, forward/2, await_point/4]).

%% Returns as soon as an error waits for the operator (`{error, Alarm}'), or the
%% simulated machine has delivered `Target' products (`{out, N}'), within `Timeout' ms.
-spec await(non_neg_integer(), pos_integer()) ->
          {error, map()} | {out, non_neg_integer()} | timeout.
await(Target, Timeout) ->
    ok = cell_events:subscribe([alarm_raised, item_transfer_out]),
    loop(Target, erlang:monotonic_time(millisecond) + Timeout).

loop(Target, Deadline) ->
    case [A || #{kind := error} = A <- cell_alarms:list()] of
        [A | _] ->
            {error, maps:with([id, caption, solutions, task], A)};
        [] ->
            #{counters := #{delivered := N}} = router_sim:world(),
            case N >= Target of
                true ->
                    {out, N};
                false ->
                    receive
                        {cell_event, _} -> loop(Target, Deadline)
                    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                        timeout
                    end
            end
    end.

%% Returns when the cell's state is `State', or with the first error waiting for an
%% answer (or `timeout').
-spec await_state_or_error(cell_ipc:state(), pos_integer()) -> ok | {error, map()} | timeout.
await_state_or_error(State, Timeout) ->
    ok = cell_events:subscribe([cell_state, alarm_raised]),
    case {cell_controller:state(), [A || #{kind := error} = A <- cell_alarms:list()]} of
        {State, _} ->
            ok;
        {_, [Error | _]} ->
            {error, Error};
        _ ->
            receive
                {cell_event, #{type := cell_state, state := State}} -> ok;
                {cell_event, #{type := alarm_raised}} -> await_state_or_error(State, Timeout)
            after Timeout ->
                timeout
            end
    end.

%% Returns when the cell's state is `State' (or `timeout').
-spec await_state(cell_ipc:state(), pos_integer()) -> ok | timeout.
await_state(State, Timeout) ->
    ok = cell_events:subscribe([cell_state]),
    case cell_controller:state() of
        State ->
            ok;
        _ ->
            receive
                {cell_event, #{type := cell_state, state := State}} -> ok
            after Timeout ->
                timeout
            end
    end.

%% What the machine and the books say now.
-spec snapshot() -> map().
snapshot() ->
    ok = cell_stats:flush(),
    ok = cell_stats:flush(),
    ok = cell_stats:flush(),
    #{world => router_sim:world(), total => cell_stats:summary(total),
      held => lists:sort([S || #{serial := S} <- cell_controller:tasks(), is_binary(S)])}.

%% For every task of the cell: the time in its states and the time since it was first
%% seen to the last write, in microseconds.
-spec time_check() -> [{atom(), integer(), integer()}].
time_check() ->
    ok = cell_stats:flush(),
    Checks = cell_stats:time_check(),
    [begin {Sum, Span} = maps:get(T, Checks), {T, Sum, Span} end
     || #{id := T} <- cell_controller:tasks()].

%% As await/2, for a cell whose machine is not in this node (real mode): returns as
%% soon as an error waits for the operator, or `Target' products have left the cell by
%% its own books (`{out, N}'), within `Timeout' ms.
-spec await_left(non_neg_integer(), pos_integer()) ->
          {error, map()} | {out, non_neg_integer()} | timeout.
await_left(Target, Timeout) ->
    ok = cell_events:subscribe([alarm_raised, item_transfer_out]),
    left_loop(Target, erlang:monotonic_time(millisecond) + Timeout).

left_loop(Target, Deadline) ->
    case [A || #{kind := error} = A <- cell_alarms:list()] of
        [A | _] ->
            {error, maps:with([id, caption, solutions, task], A)};
        [] ->
            ok = cell_stats:flush(),
            #{cell := #{out := N}} = cell_stats:summary(total),
            case N >= Target of
                true ->
                    {out, N};
                false ->
                    receive
                        {cell_event, _} -> left_loop(Target, Deadline)
                    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                        timeout
                    end
            end
    end.

%% Returns once a handshake link commits a transfer (the product on its way from one
%% task to the next): `{committed, Link, Serial}', or `timeout'.
-spec await_committed(pos_integer()) -> {committed, atom(), term()} | timeout.
await_committed(Timeout) ->
    ok = cell_events:subscribe([link_phase]),
    receive
        {cell_event, #{type := link_phase, phase := committed, link := Link, serial := S}} ->
            {committed, Link, S}
    after Timeout ->
        timeout
    end.

%% Returns the first active alarm with the caption `Caption', as soon as there is one.
-spec await_alarm(binary(), pos_integer()) -> {alarm, map()} | timeout.
await_alarm(Caption, Timeout) ->
    ok = cell_events:subscribe([alarm_raised]),
    case [A || #{caption := C} = A <- cell_alarms:list(), iolist_to_binary(C) =:= Caption] of
        [A | _] ->
            {alarm, A};
        [] ->
            receive
                {cell_event, #{type := alarm_raised}} -> await_alarm(Caption, Timeout)
            after Timeout ->
                timeout
            end
    end.

%% Returns once no active alarm has the id `Id' (answered, cleared or withdrawn).
-spec await_gone(binary(), pos_integer()) -> ok | timeout.
await_gone(Id, Timeout) ->
    ok = cell_events:subscribe([alarm_cleared]),
    case lists:any(fun(#{id := I}) -> I =:= Id end, cell_alarms:list()) of
        false ->
            ok;
        true ->
            receive
                {cell_event, #{type := alarm_cleared}} -> await_gone(Id, Timeout)
            after Timeout ->
                timeout
            end
    end.

%% The operator's hand on the machine's emergency stop (`<<"press">>' or
%% `<<"release">>'), carried out where the machine's physics runs, as the panel's
%% button does; returns once the cell's emergency stop follows (`{estop, Active}'), or
%% why the action was not carried out, or `timeout'.
-spec estop_by_hand(binary(), pos_integer()) -> {estop, boolean()} | {error, term()} | timeout.
estop_by_hand(Choice, Timeout) ->
    ok = cell_events:subscribe([estop]),
    Want = Choice =:= <<"press">>,
    case cell_machine_actions:run(<<"estop">>, Choice, Timeout) of
        {ok, _, _} ->
            receive
                {cell_event, #{type := estop, active := Want}} -> {estop, Want}
            after Timeout ->
                timeout
            end;
        {error, _} = Error ->
            Error
    end.

%% The cell's own books: its totals and the serials its tasks hold.
-spec books() -> map().
books() ->
    ok = cell_stats:flush(),
    #{total => cell_stats:summary(total),
      held => lists:sort([S || #{serial := S} <- cell_controller:tasks(), is_binary(S)])}.

%% @doc Forwards the cell's events of these types to `To' (a process of the suite's
%% node) as `{probe_event, Event}', from a process subscribed before this returns, so
%% that what the suite does next cannot be missed; the process ends when `To' does.
-spec forward([atom()], pid()) -> ok.
forward(Types, To) ->
    Self = self(),
    Ref = make_ref(),
    {Pid, Started} = spawn_monitor(fun() ->
                                           ok = cell_events:subscribe(Types),
                                           Mon = monitor(process, To),
                                           Self ! Ref,
                                           forward_loop(To, Mon)
                                   end),
    receive
        Ref -> demonitor(Started, [flush]), ok;
        {'DOWN', Started, process, Pid, Why} -> error({no_forwarder, Why})
    end.

forward_loop(To, Mon) ->
    receive
        {cell_event, Event} ->
            To ! {probe_event, Event},
            forward_loop(To, Mon);
        {'DOWN', Mon, process, _, _} ->
            ok
    end.

%% @doc Returns once the HAL reads `Value' at the point `Point' of `Group' (or `timeout').
-spec await_point(atom(), atom(), term(), pos_integer()) -> ok | timeout.
await_point(Group, Point, Value, Timeout) ->
    {ok, Ref} = cell_hal:watch(Group, Point, {eq, Value}),
    receive
        {cell_hal_watch, Ref, _} -> ok
    after Timeout ->
        _ = cell_hal:cancel_watch(Ref),
        timeout
    end.
