%% @doc The unloading conveyor segment (seed 000 §2.3): takes the modules the upper
%% robot puts down at its entry, conveys them to the exit and hands them to the next
%% machine over SMEMA. Its transfer out is the product leaving the cell.
%%
%% <pre>
%%  phase      waits for                                       then
%%  idle       the upper robot's offer (STARVED)               commit (phase 2) → receiving
%%  receiving  the robot's Available off (it let go, phase 3)  → landing
%%  landing    the modules at the entry, or the watchdog       complete (phase 4, ItemTransferIn);
%%                                                             belt on → conveying. Put down
%%                                                             before a restart and seen by
%%                                                             neither sensor: belt on → conveying
%%  conveying  the modules at the exit, or the watchdog        belt off → prepare (the
%%                                                             inspection), or when it is off
%%                                                             or done: board available to the
%%                                                             next machine → waiting
%%  prepare,   the inspection block's tags, phase by phase     the verdict in the product
%%  cleared,   ({@link router_inspection}), or the watchdog    (FAIL, Error or no answer:
%%  triggered  (`inspection_timeout_ms': not answered)         failed); board available → waiting
%%  waiting    the next machine ready (BLOCKED)                saved as handed out; belt on → leaving
%%  leaving    the modules gone from the exit, or the watchdog belt off, board available off;
%%                                                             ItemTransferOut → idle
%% </pre>
%%
%% Restarted (reconcile), the record is held against the exit sensor: modules handed
%% out and gone from the exit have left (ItemTransferOut → idle); still there, the
%% hand-out goes on with both signals it needs, belt and board available (leaving);
%% modules not yet handed out at the exit wait for the next machine again (waiting),
%% inspected first if they were not (prepare);
%% elsewhere they are conveyed (landing).
%%
%% Modules at the entry or the exit that no record holds (this task holds no product,
%% nor does the upper robot one of this lane with its gripper empty, as after a
%% hand-out cut off once it let go) would be handed out as the next product, or have the next ones dropped on them:
%% restarted, or idle, the task asks the operator to take them out of the machine
%% (`unheld') and looks again at RETRY.
-module(router_unloading_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, cell_handover:after_reset(T)}.

-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(_Held, T) ->
    case {cell_task:product(T), cell_task:in(T, panel_at_exit)} of
        {undefined, _} ->
            T1 = phase(outputs(T, false, false), idle),
            case unheld_here(T1) of
                true -> unheld_error(T1);
                false -> {ok, T1}
            end;
        %% Handed to the next machine when it stopped: gone meanwhile, they left.
        {#{handing_out := true}, false} ->
            {ok, phase(handed_out(outputs(T, false, false)), idle)};
        %% Still at the exit: the hand-out goes on, the next machine told again.
        {#{handing_out := true}, true} ->
            {ok, phase(outputs(T, true, true), leaving)};
        {P, true} ->
            case to_inspect(T, P) of
                %% Not inspected yet: the inspection from its start, the commands a
                %% predecessor left raised dropped (prepare waits for their echoes).
                true -> {ok, phase(drop_commands(outputs(T, false, false)), prepare)};
                false -> {ok, phase(outputs(T, false, true), waiting)}
            end;
        {_, false} ->
            {ok, phase(outputs(T, false, false), landing)}
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    cell_task:out(cell_task:out(T, belt_run, false), board_available, false).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

%% -- empty: modules from the upper robot -------------------------------------------------
step(idle, _Woken, T) ->
    case unheld_here(T) of
        true -> unheld_error(outputs(T, false, false));
        false -> cell_handover:take(T, prev(T), receiving)
    end;
step(receiving, {handshake, _Prev, interrupted}, T) ->
    cell_handover:interrupted(T, landing, idle);
step(receiving, {handshake, _Prev, available, false}, T) ->
    watch(T, landing, panel_at_entry, true);
step(receiving, _Woken, T) ->
    {wait, {handshake, prev(T), available, false}, T};
step(landing, {timer, _}, T) ->
    fault(T, "are not at the entry");
step(landing, _Woken, T) ->
    case cell_task:in(T, panel_at_entry) orelse cell_task:in(T, panel_at_exit) of
        true ->
            T1 = case cell_handshake:phase(T, prev(T)) of
                     released -> cell_handshake:complete(T, prev(T));
                     _ -> T                        %% after a restart: it is here already
                 end,
            watch(cell_task:out(T1, belt_run, true), conveying, panel_at_exit, true);
        false ->
            case cell_handshake:phase(T, prev(T)) of
                released ->
                    %% Being put down now.
                    watch(T, landing, panel_at_entry, true);
                _ ->
                    %% Put down before a Stop or a restart, and on their way to the
                    %% exit when the belt stopped: between the two sensors.
                    watch(cell_task:out(T, belt_run, true), conveying, panel_at_exit, true)
            end
    end;
step(conveying, {timer, _}, T) ->
    fault(T, "did not reach the exit");
step(conveying, _Woken, T) ->
    case cell_task:in(T, panel_at_exit) of
        true ->
            inspect(cell_task:out(T, belt_run, false));
        false ->
            watch(cell_task:out(T, belt_run, true), conveying, panel_at_exit, true)
    end;
%% -- at the exit: the camera's inspection, as the PLC program drives it ---------------
step(Phase, {timer, _}, T) when Phase =:= prepare; Phase =:= cleared; Phase =:= triggered ->
    {_, Facts} = inspection_facts(T),
    inspected(router_inspection:expired(Phase, Facts), T);
step(Phase, _Woken, T) when Phase =:= prepare; Phase =:= cleared; Phase =:= triggered ->
    {G, Facts} = inspection_facts(T),
    #{serial := S} = cell_task:product(T),
    Ids = [{P, V} || {_, P, V} <- router_inspect_io:string(G, inspection_point_id,
                                                            router_inspection:point())
                                      ++ router_inspect_io:string(G, part_serial, S)],
    case router_inspection:next(Phase, Facts, Ids) of
        {wait, Conds} ->
            {wait, [{io, G, Point, Cond} || {Point, Cond} <- Conds]
                   ++ [router_task:watchdog(T, inspection_timeout_ms, 10000)], phase(T, Phase)};
        {write, Writes, Next} ->
            {continue, phase(lists:foldl(fun({P, V}, Ti) -> cell_task:out(Ti, G, P, V) end,
                                         T, Writes), Next)};
        {done, Verdict} ->
            inspected(Verdict, T)
    end;
%% -- full: the next machine takes them -----------------------------------------------------
step(waiting, _Woken, T) ->
    case cell_task:in(T, downstream_ready) of
        true ->
            %% Saved first: once the belt runs, the next machine may take them even
            %% if this task stops before it sees them go.
            P = cell_task:product(T),
            T1 = cell_task:set_product(router_task:unblocked(T), P#{handing_out => true}),
            watch(cell_task:out(T1, belt_run, true), leaving, panel_at_exit, false);
        false ->
            {wait, {io, downstream_ready, {eq, true}}, router_task:blocked(T)}
    end;
step(leaving, {timer, _}, T) ->
    fault(T, "did not leave to the next machine");
step(leaving, _Woken, T) ->
    case cell_task:in(T, panel_at_exit) of
        false ->
            {continue, phase(handed_out(outputs(T, false, false)), idle)};
        true ->
            %% The hand-out needs both: the belt, and the next machine told a board is
            %% there (after a Retry or a restart it may have been taken away).
            watch(outputs(T, true, true), leaving, panel_at_exit, false)
    end;
step(in_transit, _Woken, T) ->
    {continue, phase(cell_handshake:confirm_here(T), landing)}.

%% At the exit, before the next machine is told: the inspection unless it is done or
%% switched off.
inspect(T) ->
    case to_inspect(T, cell_task:product(T)) of
        true -> {continue, phase(cell_task:out(T, board_available, false), prepare)};
        false -> offer(T)
    end.

%% The inspection on, and no verdict saved with the product yet.
to_inspect(T, P) ->
    cell_task:setting(T, inspection, true) andalso not maps:is_key(inspection, P).

%% The PLC program's commands to the lane's inspection block dropped.
drop_commands(T) ->
    G = router_cell:group(inspect, router_task:lane(T)),
    lists:foldl(fun(Pt, Ti) -> cell_task:out(Ti, G, Pt, false) end, T,
                [trigger_inspection, clear_results]).

offer(T) ->
    T1 = cell_task:out(cell_task:out(T, belt_run, false), board_available, true),
    {continue, phase(router_task:blocked(T1), waiting)}.

%% The verdict in the product (saved), the PLC's commands dropped, then the offer.
%% The lane's inspection group and its tags as read now.
inspection_facts(T) ->
    G = router_cell:group(inspect, router_task:lane(T)),
    {G, maps:from_list([{P, V} || P <- router_inspect_io:mapped(),
                                  {ok, V} <- [cell_task:read(T, G, P)]])}.

inspected(Verdict, T) ->
    #{serial := S} = P = cell_task:product(T),
    {P1, Warning} = router_inspection:product(Verdict, P),
    T2 = drop_commands(cell_task:set_product(T, P1)),
    T3 = case Warning of
             none ->
                 cell_task:log(T2, brief, "modules of panel ~ts inspected: ~ts",
                               [S, maps:get(inspection, P1)]),
                 cell_task:reset_warning(T2, <<"not_inspected">>);
             {Id, Text} ->
                 cell_task:log(T2, brief, "~ts", [Text]),
                 cell_task:warning(T2, Id, "Modules not inspected", Text)
         end,
    offer(T3).

handed_out(T) ->
    #{serial := S} = cell_task:product(T),
    T1 = cell_task:clear_product(cell_task:transfer_out(T, S)),
    cell_task:log(T1, brief, "modules of panel ~ts handed to the next machine", [S]),
    T1.

outputs(T, Belt, Available) ->
    cell_task:out(cell_task:out(T, belt_run, Belt), board_available, Available).

fault(T, What) ->
    #{serial := S} = cell_task:product(T),
    {error, cell_task:error_spec(
              <<"jam">>, "Conveyor jam",
              io_lib:format("The modules of panel ~ts ~ts in time: the belt is stopped.~n"
                            "Free them on the unloading conveyor, then select RETRY.", [S, What]),
              [retry]),
     cell_task:out(T, belt_run, false)}.

watch(T, Phase, Point, Value) ->
    router_task:watch(T, Phase, Point, Value, transfer_timeout_ms).

prev(T) -> cell_task:arg(T, prev, undefined).

%% Modules seen at the entry or the exit while the task holds no product and the upper
%% robot holds none of this lane that can lie here: with modules in its gripper (its
%% sensor sees them), its product is there, not on this conveyor.
unheld_here(T) ->
    cell_task:product(T) =:= undefined
        andalso (cell_task:in(T, panel_at_entry) orelse cell_task:in(T, panel_at_exit))
        andalso cell_handover:unheld(router_task:lane(T),
                                   [upper || not cell_task:in(T, upper_io, product_present)],
                                   cell_task:others_products(T)).

unheld_error(T) ->
    cell_handover:unheld_error(T, "Modules on the unloading conveyor unknown",
                             "Modules lie on the unloading conveyor of lane ~ts",
                             [router_task:lane(T)]).

phase(T, Phase) -> cell_handover:phase(T, Phase).
