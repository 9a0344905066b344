%% A device task that makes serial numbers from a retained counter, for
%% cell_retain_SUITE: each step takes the next serial (durable before the task goes
%% on), tells the `notify' process `{made, Pid, N}' and waits for a timer of 0 ms. Its
%% reconcile tells `{reconciled, Pid, Cause, Counter}'. With `refuse_at => N' the step
%% that made serial N then tries to retain its own pid, which is refused.
-module(cell_retain_test_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, T}.

-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(#{cause := Cause}, T) ->
    notify(T, {reconciled, self(), Cause, cell_task:retained(T, serial, 0)}),
    {ok, T}.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T0) ->
    {N, T} = cell_task:retain_update(T0, serial, fun(S) -> S + 1 end, 0),
    T1 = case cell_task:arg(T, refuse_at, undefined) of
             N -> cell_task:retain(T, owner, self());
             _ -> T
         end,
    notify(T1, {made, self(), N}),
    {wait, {timer, 0}, T1}.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    T.

notify(T, Msg) ->
    cell_task:arg(T, notify, self()) ! Msg.
