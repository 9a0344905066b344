%% The device task the runtime benchmarks use. `wait': each step waits for a reply
%% that never comes (an idle task). `tick': each step counts and waits 10 ms (a task
%% watching its machine). `spin': each step counts and never waits. uninit tells the
%% benchmark (`notify') when the task secured its outputs.
-module(cell_bench_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, T}.

%% No machine behind it: nothing to hold the record against.
-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    {ok, T}.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    case cell_task:args(T) of
        #{mode := spin, counter := Counter} ->
            counters:add(Counter, 1, 1),
            {continue, T};
        #{mode := tick, counter := Counter} ->
            counters:add(Counter, 1, 1),
            {wait, {timer, 10}, T};
        #{never := Never} ->
            {wait, {reply, Never}, T}
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    case cell_task:arg(T, notify, undefined) of
        undefined -> ok;
        Bench -> Bench ! {secured, cell_task:id(T), erlang:monotonic_time(microsecond)}
    end,
    T.
