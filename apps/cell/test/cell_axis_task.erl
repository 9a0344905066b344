%% A device task that moves axes as seed 000's robot tasks do (`LowerRobotTask.Axes'):
%% it powers and homes its axes (each a step, waited for as IO is), then cycles: a point-to-point move of its
%% first axis to a taught position, a cut along a path by its interpolation channel, and
%% back. Without a channel (axes of an NC reached over ADS) the cycle is two
%% point-to-point moves of its first axis, to the taught position and to `far'. Every move is started in one step and waited for in the next, as IO is; an
%% axis's fault becomes the task's error, its text naming the axis and the code, with
%% Retry (the axis is reset and the move made again).
%%
%% Args: #{axes => [X, Y], channel => C, path => cell_hal_path:path(), notify => Pid}, or
%% #{axes => [X, ...], far => Position, notify => Pid}.
%% `notify' gets `{axis_task, Id, cycle, N}' after each cycle and `{axis_task, Id,
%% fault, Axis, Code}' when one is raised.
-module(cell_axis_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).
-export([await_cycles/3, await_error/1]).

-define(PTP, #{velocity => 2000, acceleration => 20000, deceleration => 20000}).
-define(CUT, #{velocity => 1000, acceleration => 10000, deceleration => 10000}).
-define(WAIT_MS, 10000).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, cell_task:put(T, phase, prepare)}.

-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    %% No product: the axes made ready, the cycle starts over from the taught start
    %% position.
    {ok, cell_task:put(T, phase, prepare)}.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    %% Stop or emergency stop: whatever moves is halted, a path the channel follows
    %% first (an NC's channel runs its program until told).
    _ = [cell_hal_channel:halt(C, 20000) || C <- [arg(T, channel)], C =/= undefined],
    _ = [cell_hal_axis:halt(A, 20000) || A <- arg(T, axes)],
    T.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_task:get(T, phase), cell_task:woken_by(T), T).

%% Each axis reset if in error, powered and homed, one command at a time.
step(prepare, {reply, _, {error, _} = Failed}, T) ->
    [X | _] = arg(T, axes),
    move(prepare, X, Failed, T);
step(prepare, _Woken, T) ->
    case next_preparation(arg(T, axes)) of
        ready -> {continue, cell_task:put(T, phase, start)};
        {A, Command} -> move(prepare, A, Command, T)
    end;
step(start, _Woken, T) ->
    [X | _] = arg(T, axes),
    move(to_start, X, cell_hal_axis:move_absolute(X, 0.0, ?PTP), T);
step(to_start, {reply, _, done}, T) ->
    case arg(T, channel) of
        undefined ->
            [X | _] = arg(T, axes),
            move(cutting, X, cell_hal_axis:move_absolute(X, arg(T, far), ?PTP), T);
        C ->
            move(cutting, C, cell_hal_channel:follow(C, arg(T, path), ?CUT), T)
    end;
step(cutting, {reply, _, done}, T) ->
    N = cell_task:get(T, cycles, 0) + 1,
    notify(T, {axis_task, cell_task:id(T), cycle, N}),
    {continue, cell_task:put(cell_task:put(T, cycles, N), phase, start)};
step(Phase, {reply, _, {error, {Axis, Code}}}, T) when Phase =:= cutting ->
    fault(Axis, Code, T);
step(_Phase, {reply, _, {error, Code}}, T) ->
    [X | _] = arg(T, axes),
    fault(X, Code, T);
step(_Phase, {reply, _, aborted}, T) ->
    %% Commanded elsewhere (the service technician's jog): the cycle starts over.
    {continue, cell_task:put(T, phase, start)};
step(_Phase, {timer, _}, T) ->
    {error, cell_task:error_spec(<<"axis_timeout">>, "Axis move not done",
                                 "The move did not end in time. RETRY starts the cycle "
                                 "again.", [retry]), cell_task:put(T, phase, start)};
step(recovering, _Woken, T) ->
    %% The operator's Retry: the axes made ready again (the faulted one reset), the
    %% cycle made again.
    {continue, cell_task:put(T, phase, prepare)}.

next_preparation([]) ->
    ready;
next_preparation([A | Rest]) ->
    case cell_hal_axis:status(A) of
        {ok, #{state := error_stop}} -> {A, cell_hal_axis:reset(A)};
        {ok, #{powered := false}} -> {A, cell_hal_axis:power(A, true)};
        {ok, #{homed := false}} -> {A, cell_hal_axis:home(A, 0.0)};
        {ok, #{}} -> next_preparation(Rest);
        {error, _} = Error -> {A, Error}
    end.

move(Next, _Who, {ok, Ref}, T) ->
    {wait, [{reply, Ref}, {timer, ?WAIT_MS}], cell_task:put(T, phase, Next)};
move(_Next, Who, {error, Why}, T) ->
    fault(Who, Why, T).

fault(Axis, Why, T) ->
    notify(T, {axis_task, cell_task:id(T), fault, Axis, Why}),
    {error, fault_spec(Axis, Why), cell_task:put(T, phase, recovering)}.

fault_spec(Axis, Why) ->
    cell_task:error_spec(<<"axis">>, "Axis fault",
                         io_lib:format("Axis ~ts stopped: ~ts. RETRY resets the axis and "
                                       "makes the move again.", [Axis, words(Why)]),
                         [retry]).

words(Code) when is_integer(Code) -> io_lib:format("NC error 16#~.16B", [Code]);
words({error_stop, Code}) -> io_lib:format("it is in error (16#~.16B)", [Code]);
words(Why) -> io_lib:format("~tp", [Why]).

notify(T, Msg) ->
    case arg(T, notify) of
        undefined -> ok;
        Pid -> Pid ! Msg, ok
    end.

arg(T, Key) ->
    cell_task:arg(T, Key, undefined).

%% -- for the suites that run it --------------------------------------------------------

%% @doc Returns once task `Id' (notifying the caller) has done `N' more cycles; fails
%% the case after `Ms' without one.
-spec await_cycles(atom(), non_neg_integer(), pos_integer()) -> ok.
await_cycles(_Id, 0, _Ms) ->
    ok;
await_cycles(Id, N, Ms) ->
    receive {axis_task, Id, cycle, _} -> await_cycles(Id, N - 1, Ms)
    after Ms -> ct:fail({no_cycle, Id, cell_alarms:list()})
    end.

%% @doc The first error raised in the cell, waited for (the caller subscribed to the
%% cell's events and log) at most `Ms' between two of them.
-spec await_error(pos_integer()) -> cell_alarms:alarm().
await_error(Ms) ->
    case [A || #{kind := error} = A <- cell_alarms:list()] of
        [A | _] -> A;
        [] ->
            receive {cell_event, _} -> await_error(Ms);
                    {cell_log, _} -> await_error(Ms)
            after Ms -> ct:fail(no_alarm)
            end
    end.
