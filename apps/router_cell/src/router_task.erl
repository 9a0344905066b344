%% @doc What the router's device tasks share: their phase, the IPC-2541 events they
%% raise when they start or stop waiting, watchdogs, and errors whose Reset forgets
%% something.
%%
%% The engine answers Reset by re-initialising the task (the seed's ResetException:
%% uninit, then init). The seed lets the task catch it first, to forget its product
%% ("Select RESET to delete product data"); here a task says with {@link error/6} what
%% Reset is to mean, and its `init' asks {@link reset_chosen/1} whether Reset was the
%% answer (the registry of errors records every answer before the task hears it). A
%% task that re-initialises for another reason (a Stop, then Start) finds no Reset and
%% keeps what it holds.
-module(router_task).

-export([phase/2, phase/1, starved/1, unstarved/1, blocked/1, unblocked/1]).
-export([watch/5, watchdog/3, error/6, reset_chosen/1, interrupted/3, lane/1]).

%% @doc Sets the task's phase (its own state within its IPC-2541 state).
-spec phase(cell_task:task(), atom()) -> cell_task:task().
phase(T, Phase) ->
    cell_task:put(T, phase, Phase).

-spec phase(cell_task:task()) -> atom().
phase(T) ->
    cell_task:get(T, phase, undefined).

%% @doc EquipmentStarved, unless the task is already STARVED.
-spec starved(cell_task:task()) -> cell_task:task().
starved(T) ->
    case cell_task:state(T) of
        {ready, idle, starved} -> T;
        _ -> cell_task:starved(T)
    end.

%% @doc EquipmentUnstarved, if the task is STARVED.
-spec unstarved(cell_task:task()) -> cell_task:task().
unstarved(T) ->
    case cell_task:state(T) of
        {ready, idle, starved} -> cell_task:unstarved(T);
        _ -> T
    end.

%% @doc EquipmentBlocked, unless the task is already BLOCKED.
-spec blocked(cell_task:task()) -> cell_task:task().
blocked(T) ->
    case cell_task:state(T) of
        {ready, idle, blocked} -> T;
        _ -> cell_task:blocked(T)
    end.

%% @doc EquipmentUnblocked, if the task is BLOCKED.
-spec unblocked(cell_task:task()) -> cell_task:task().
unblocked(T) ->
    case cell_task:state(T) of
        {ready, idle, blocked} -> cell_task:unblocked(T);
        _ -> T
    end.

%% @doc Waits in a phase for an IO point to take a value, or for a watchdog (a setting
%% in milliseconds) to run out: the step is woken by `{timer, _}' then.
-spec watch(cell_task:task(), atom(), atom(), cell_hal_type:value(), atom()) ->
          cell_task:step_result().
watch(T, Phase, Point, Value, Watchdog) ->
    {wait, [{io, Point, {eq, Value}}, watchdog(T, Watchdog, 10000)], phase(T, Phase)}.

%% @doc The watchdog wait of a setting.
-spec watchdog(cell_task:task(), atom(), pos_integer()) -> cell_task:wait().
watchdog(T, Setting, Default) ->
    {timer, cell_task:setting(T, Setting, Default)}.

%% @doc An error for the operator; `OnReset' is what the task is to do if the answer
%% is Reset (its `init' learns it from {@link reset_chosen/1}).
-spec error(cell_task:task(), binary(), iodata(), iodata(), [cell_alarms:solution()], atom()) ->
          {error, cell_alarms:spec(), cell_task:task()}.
error(T, Id, Caption, Text, Solutions, OnReset) ->
    Pending = {Id, os:system_time(millisecond), OnReset},
    {error, cell_task:error_spec(Id, Caption, Text, Solutions),
     cell_task:put(T, on_reset, Pending)}.

%% @doc In `init': what the task said Reset would mean, if the operator answered its
%% last error with Reset; `none' otherwise. Either way the question is settled.
-spec reset_chosen(cell_task:task()) -> {atom(), cell_task:task()}.
reset_chosen(T) ->
    case cell_task:get(T, on_reset, undefined) of
        undefined ->
            {none, T};
        {Id, Since, OnReset} ->
            Global = <<(atom_to_binary(cell_task:id(T), utf8))/binary, ":", Id/binary>>,
            Chosen = lists:any(fun(#{id := I, what := reset, time := At}) ->
                                       I =:= Global andalso At >= Since;
                                  (_) ->
                                       false
                               end, cell_alarms:history()),
            T1 = cell_task:put(T, on_reset, undefined),
            case Chosen of
                true -> {OnReset, T1};
                false -> {none, T1}
            end
    end.

%% @doc After a transfer ended early (seed §2.3.6): a product that had not moved stays
%% with the task (`Have' phase), one that was moving is the operator's to settle:
%% Ignore, it is here (`Have'); Reset, it is not (forgotten: `init' takes `forget').
-spec interrupted(cell_task:task(), atom(), atom()) -> cell_task:step_result().
interrupted(T, Have, Empty) ->
    case {cell_task:product(T), cell_handshake:in_transit(T)} of
        {undefined, _} ->
            {continue, phase(T, Empty)};
        {_, false} ->
            {continue, phase(T, Have)};
        {#{serial := S}, true} ->
            error(phase(T, in_transit), <<"transfer">>, "Transfer interrupted",
                  io_lib:format("Product ~ts was moving when its transfer was interrupted.~n"
                                "Check where it is. Select IGNORE if it is at this station, "
                                "RESET if it is not (the station forgets it).", [S]),
                  [ignore, reset], forget)
    end.

%% @doc The task's lane: `front' or `rear'.
-spec lane(cell_task:task()) -> front | rear.
lane(T) ->
    cell_task:arg(T, lane, front).
