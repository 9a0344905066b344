%% The device task the runtime benchmarks use. `wait': each step waits for a reply
%% that never comes (an idle task). `tick': each step counts and waits 10 ms (a task
%% watching its machine). `spin': each step counts and never waits. uninit tells the
%% benchmark when the task secured its outputs.
-module(cell_bench_task).
-behaviour(cell_task).

-export([init/1, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, T}.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    case cell_task:arg(T, mode, wait) of
        wait ->
            {wait, {reply, cell_task:arg(T, never, undefined)}, T};
        tick ->
            counters:add(cell_task:arg(T, counter, undefined), 1, 1),
            {wait, {timer, 10}, T};
        spin ->
            counters:add(cell_task:arg(T, counter, undefined), 1, 1),
            {continue, T}
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    cell_task:arg(T, notify, self()) ! {secured, cell_task:id(T), erlang:monotonic_time(microsecond)},
    T.
