%% A conveyor task for the device-task IO suite: it runs its belt until the sensor sees
%% a panel, stops it, waits for the panel to go, and counts. Each wake-up is recorded
%% in the `tab' argument as {woke, Id, N, Woken}. With a `serial' argument the task
%% holds that product from its first init; a `mid_step' argument (a fun) runs inside
%% the step that sees a panel, before it touches its IO: what happens to the HAL
%% under a task in the middle of a step. A `before_run' argument (a fun) runs in the
%% first step before it commands the belt on: what happens to a write in flight. With
%% `stop_first' the step that sees a panel stops the belt before `mid_step' runs.
-module(cell_io_test_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    T1 = case {cell_task:arg(T, serial, undefined), cell_task:product(T)} of
             {undefined, _} -> T;
             {Serial, undefined} ->
                 cell_task:set_product(T, #{serial => Serial, recipe => <<"R">>,
                                            failed => false});
             {_, _} -> T
         end,
    {ok, cell_task:put(cell_task:out(T1, motor, false), n, 0)}.

%% The belt starts off whatever it was; each step looks at the sensor itself.
-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    {ok, T}.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    cell_task:out(T, motor, false).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    record(T),
    case cell_task:woken_by(T) of
        undefined ->
            _ = (cell_task:arg(T, before_run, fun() -> ok end))(),
            {wait, {io, sensor, {eq, true}}, cell_task:out(T, motor, true)};
        {answer, _} ->
            {wait, {io, sensor, {eq, true}}, cell_task:out(T, motor, true)};
        {io, _, sensor, true} ->
            %% A panel: stop the belt, read the counter (a lost connection here is the
            %% engine's to report), wait until the panel is taken away. With
            %% `stop_first' the belt is stopped before `mid_step' too.
            T0 = case cell_task:arg(T, stop_first, false) of
                     true -> cell_task:out(T, motor, false);
                     false -> T
                 end,
            _ = (cell_task:arg(T0, mid_step, fun() -> ok end))(),
            Count = cell_task:in(T0, count),
            T1 = cell_task:put(cell_task:out(T0, motor, false), count, Count),
            {wait, {io, sensor, {eq, false}}, T1};
        {io, _, sensor, false} ->
            {wait, {io, sensor, {eq, true}}, cell_task:out(T, motor, true)}
    end.

record(T) ->
    N = cell_task:get(T, n, 0) + 1,
    Tab = cell_task:arg(T, tab, undefined),
    true = ets:insert(Tab, {{woke, cell_task:id(T), N}, cell_task:woken_by(T)}),
    cell_task:arg(T, notify, self()) ! {woke, cell_task:id(T), cell_task:woken_by(T)},
    ok.
