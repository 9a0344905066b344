%% @doc The loading conveyor segment (seed 000 §2.3): takes panels from the previous
%% machine over SMEMA, reads each panel's code at the stopper, and hands the panel to
%% the work segment over the handshake of §2.3.6 as the "previous device".
%%
%% <pre>
%%  phase       waits for                                   then
%%  idle        a panel at the previous machine, or one     belt on, ready to receive → intake
%%              at the stopper already (STARVED)
%%  intake      the panel at the stopper, or the watchdog   belt off; the code reader triggered
%%                                                          → reading
%%  reading     the code reader's answer, or its deadline   the code: the product (ItemIdentifierRead,
%%              (the operator's answer after a no-read)     ItemTransferIn) → full; none: the
%%                                                          operator is asked (below)
%%  full        -                                           offer it to the work segment (phase 1,
%%                                                          BLOCKED) → offered
%%  offered     the work segment's NotBusy                  belt on (phase 2) → leaving
%%  leaving     the panel past the stopper, or the watchdog release (phase 3) → released;
%%              (or the work segment gone: NotBusy off)     belt off → full, offered again
%%  released    the work segment's NotBusy off (phase 4)    belt off; ItemTransferOut → idle
%%  in_transit  the operator, after a transfer was cut off  Ignore: it is here → full;
%%              while the panel moved                        Reset: it is not → idle
%% </pre>
%%
%% Restarted (reconcile), the product file is held against the stopper sensor: a panel
%% held and seen is offered again (full); held but not seen, the operator says where it
%% is: back at the stopper (RETRY, the sensor read again), between the stopper and the
%% work segment (IGNORE: offered, handed over as it is), taken out (RESET: forgotten).
%% Holding none, a panel at the stopper is in no record: its code is read and it is
%% taken as it would be after an intake (the stopper is where a panel is identified).
%%
%% The code reader (the hardware object `reader' of the task's args, {@link
%% cell_hal_code_reader}) is asked without waiting: the step returns and the task waits
%% for its answer. A panel enters the cell's records only with the code its reader
%% read, or, when the reader finds none ("Code not read"), as the operator says:
%% RETRY reads again; IGNORE takes the panel as it is, under a serial the cell makes
%% for it (`NOREAD-<task>-<n>', from a counter retained across restarts, so never
%% made twice), the product marked `no_read' and its identifier read by the operator;
%% RESET is for a panel the operator took off the conveyor: the segment starts again
%% (a panel still at the stopper is read again). A reader that loses its connection
%% with the read (the PLC's, shared with the task's IO, whose loss the engine reports)
%% is asked again once the task's IO reads again; not connected then, it is the
%% "Code reader fault" error. A crash between the trigger and the
%% answer leaves no record: restarted, the task reads the panel at the stopper again,
%% and the reader's object clears the trigger left on, so the answer of before is
%% never taken for a panel.
%%
%% A watchdog that runs out is a "Conveyor jam" error: the belt stops until the
%% operator has freed the panel and chosen Retry. The previous machine's magazine
%% running low is a warning, set and reset as its input changes (the seed's feeder).
-module(router_loading_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

%% How much longer than the reader's own deadline (`reader_deadline_ms') the task waits
%% for its answer: the wait is for a reader object that went away with the question.
-define(READ_MARGIN_MS, 5000).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T0) ->
    T = cell_handover:after_reset(T0),
    %% The warning follows the magazine input from the first step on.
    {ok, cell_task:put(cell_task:out(T, upstream_ready, false), magazine_low, undefined)}.

%% The record against the stopper's sensor: a panel held and seen goes on (full); held
%% but not seen, the operator says where it is.
-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(_Held, T0) ->
    case cell_handover:reconcile(T0, fun(T) -> cell_task:in(T, panel_at_stop) end, fun where/2) of
        {empty, T} ->
            {ok, phase(cell_task:out(T, belt_run, false), idle)};
        %% A panel waits at the stopper, as its product file says.
        {here, sensor, T} ->
            {ok, phase(cell_task:out(T, belt_run, false), full)};
        {here, operator, T} ->
            #{serial := S} = cell_task:product(T),
            cell_task:log(T, brief, "panel ~ts on its way to the work segment (operator)", [S]),
            {ok, phase(cell_task:out(T, belt_run, false), full)};
        {gone, S, T} ->
            cell_task:log(T, brief, "panel ~ts taken out of the machine (operator): forgotten",
                          [S]),
            {ok, phase(cell_task:out(T, belt_run, false), idle)};
        {error, _, _} = Ask ->
            Ask
    end.

where(T, S) ->
    {error, cell_task:error_spec(
              <<"where">>, "Panel not at the stopper",
              io_lib:format("Records say panel ~ts is at the stopper of the loading conveyor; "
                            "the stopper sensor sees no panel. Where is it?~n"
                            "Select RETRY once it is back at the stopper: the sensor is read "
                            "again.~n"
                            "Select IGNORE if it is between the stopper and the work segment: "
                            "it is handed over as it is.~n"
                            "Select RESET if it was taken out of the machine: the product is "
                            "forgotten.", [S]),
              [retry, ignore, reset]),
     T}.

%% Stop the belt and tell the previous machine to hold; the panel stays where it is.
-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    cell_task:out(cell_task:out(T, belt_run, false), upstream_ready, false).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    T1 = magazine(T),
    step(cell_handover:phase(T1), cell_task:woken_by(T1), T1).

%% -- empty: a panel from the previous machine ---------------------------------------
step(idle, _Woken, T) ->
    %% A panel already at the stopper (one no record holds any more) is read like one
    %% that just arrived, even when the previous machine offers none.
    case cell_task:in(T, upstream_available) orelse cell_task:in(T, panel_at_stop) of
        true ->
            T1 = cell_task:out(cell_task:out(T, belt_run, true), upstream_ready, true),
            watch(intake, panel_at_stop, true, router_task:unstarved(T1));
        false ->
            {wait, [{io, upstream_available, {eq, true}} | magazine_wait(T)],
             router_task:starved(T)}
    end;
step(intake, {timer, _}, T) ->
    jam(T, "did not reach the stopper");
step(intake, _Woken, T) ->
    case cell_task:in(T, panel_at_stop) of
        true ->
            T1 = cell_task:out(cell_task:out(T, belt_run, false), upstream_ready, false),
            read_code(T1);
        false ->
            %% After Retry: the belt runs again.
            watch(intake, panel_at_stop, true, cell_task:out(T, belt_run, true))
    end;
%% -- reading: the code reader's answer ----------------------------------------------
step(reading, {reply, _Ref, {error, not_connected}}, T) ->
    case cell_task:get(T, lost_read, false) of
        false ->
            %% The reader's connection went with the read: here the PLC's, which the
            %% task's own IO shares, and the engine tells the operator of that one.
            %% Once the task's IO reads again, the stopper is looked at and the panel
            %% read anew; a reader not connected then is a fault of its own.
            {wait, [{io, panel_at_stop, {eq, true}}, {io, panel_at_stop, {eq, false}}],
             phase(cell_task:put(T, lost_read, true), intake)};
        true ->
            reader_fault(io_lib:format("it answered ~ts", [why(not_connected)]),
                         cell_task:put(T, lost_read, false))
    end;
step(reading, {reply, _Ref, Answer}, T) ->
    read(Answer, cell_task:put(T, lost_read, false));
step(reading, {timer, _}, T) ->
    reader_fault(io_lib:format("it did not answer within ~.1f s", [read_wait(T) / 1000]), T);
step(reading, _Woken, T) ->
    %% The operator's answer to a read that failed.
    case {cell_task:answer(T), cell_task:get(T, read_failed, undefined)} of
        {ignore, no_read} -> no_read_product(T);
        _ -> read_code(T)
    end;
%% -- full: hand it to the work segment ----------------------------------------------
step(full, _Woken, T) ->
    {wait, {handshake, next(T), not_busy, true}, phase(cell_handshake:offer(T, next(T)), offered)};
step(offered, {handshake, _Next, not_busy, true}, T) ->
    leave(cell_task:out(T, belt_run, true));
step(offered, _Woken, T) ->
    cell_handover:offered(T, next(T), full);
step(leaving, {timer, _}, T) ->
    jam(T, "did not leave the stopper");
step(leaving, _Woken, T) ->
    case {cell_handshake:phase(T, next(T)), cell_task:in(T, panel_at_stop)} of
        {committed, false} ->
            T1 = cell_handshake:release(T, next(T)),
            {wait, {handshake, next(T), not_busy, false}, phase(T1, released)};
        {committed, true} ->
            leave(cell_task:out(T, belt_run, true));
        {_, _} ->
            %% The work segment stopped taking it (it restarted): the panel stays
            %% with this task, wherever the belts left it, and is offered again.
            {continue, phase(cell_task:out(T, belt_run, false), full)}
    end;
step(released, {handshake, _Next, interrupted}, T) ->
    cell_handover:interrupted(cell_task:out(T, belt_run, false), full, idle);
step(released, _Woken, T) ->
    cell_handover:finish(T, next(T), idle, full, fun(_, T1) -> cell_task:out(T1, belt_run, false) end);
%% -- the operator said the panel of an interrupted transfer is here ------------------
step(in_transit, _Woken, T) ->
    {continue, phase(cell_handshake:confirm_here(T), full)}.

read({ok, Serial}, T) -> identified(Serial, T);
read({error, no_read}, T) -> no_code(T);
read({error, Why}, T) -> reader_fault(io_lib:format("it answered ~ts", [why(Why)]), T).

%% The panel at the stopper: its reader triggered, its answer waited for.
read_code(T) ->
    Ref = cell_hal_code_reader:read_async(cell_task:arg(T, reader, undefined)),
    {wait, [{reply, Ref}, {timer, read_wait(T)}],
     phase(cell_task:put(T, read_failed, undefined), reading)}.

read_wait(T) ->
    cell_task:setting(T, reader_deadline_ms, 2000) + ?READ_MARGIN_MS.

%% The code reader read the panel at the stopper: it is the cell's from now on.
identified(Serial, T) ->
    T1 = enter(Serial, #{}, <<"code reader">>, T),
    #{recipe := Recipe} = cell_task:product(T1),
    cell_task:log(T1, brief, "panel ~ts (~ts) at the stopper", [Serial, Recipe]),
    {continue, phase(T1, full)}.

%% The operator took the unread panel as it is: a serial of the cell's, never made
%% twice (the counter is durable before the serial is used), and marked as such.
no_read_product(T) ->
    {N, T1} = cell_task:retain_update(T, no_read_serial, fun(I) -> I + 1 end, 0),
    Serial = iolist_to_binary(io_lib:format("NOREAD-~s-~6..0b", [cell_task:id(T1), N])),
    cell_task:log(T1, brief, "panel at the stopper taken without a code (operator): serial ~ts",
                  [Serial]),
    {continue, phase(enter(Serial, #{no_read => true}, <<"operator (no read)">>, T1), full)}.

enter(Serial, Fields, Source, T) ->
    Lane = router_task:lane(T),
    Recipe = cell_task:setting(T, recipe_key(Lane), <<"demo-2x2">>),
    T1 = cell_task:set_product(T, cell_product:new(Serial, Recipe, Fields#{lane => Lane})),
    cell_task:transfer_in(cell_task:identifier_read(T1, Serial, Source), Serial).

no_code(T) ->
    {error, cell_task:error_spec(
              <<"no_code">>, "Code not read",
              io_lib:format("The code reader found no code on the panel at the stopper of "
                            "the loading conveyor.~n"
                            "Select RETRY to read it again (clean the label or the reader's "
                            "window first).~n"
                            "Select IGNORE to take the panel without its code: it gets a "
                            "serial NOREAD-..., marked in its history as not read.~n"
                            "Select RESET once you have taken the panel off the conveyor: "
                            "it never enters the records (a panel left at the stopper is "
                            "read again).", []),
              [retry, ignore, reset]),
     cell_task:put(T, read_failed, no_read)}.

reader_fault(What, T) ->
    {error, cell_task:error_spec(
              <<"reader">>, "Code reader fault",
              io_lib:format("The code reader of the loading conveyor was triggered for the "
                            "panel at the stopper, but ~ts.~nCheck the reader and its "
                            "cable, then select RETRY to read again.", [What]),
              [retry]),
     cell_task:put(T, read_failed, fault)}.

why(not_connected) -> "that it is not connected";
why(timeout) -> "no code in time";
why(not_present) -> "that it is not there (not configured, or restarting)";
why({unavailable, Why}) -> ["that its IO cannot be used: ", Why];
why(Other) -> io_lib:format("~tp", [Other]).

recipe_key(front) -> recipe_front;
recipe_key(rear) -> recipe_rear.

jam(T, What) ->
    Serial = case cell_task:product(T) of
                 undefined -> <<"from the previous machine">>;
                 #{serial := S} -> S
             end,
    Ms = cell_task:setting(T, transfer_timeout_ms, 10000),
    {error, cell_task:error_spec(
              <<"jam">>, "Conveyor jam",
              io_lib:format("Panel ~ts ~ts within ~.1f s: the belt is stopped.~nFree the "
                            "panel on the loading conveyor, then select RETRY to run the "
                            "belt again.", [Serial, What, Ms / 1000]),
              [retry]),
     cell_task:out(T, belt_run, false)}.

%% Phase 2: the belt runs the panel out, as long as the work segment takes it.
leave(T) ->
    {wait, [{io, panel_at_stop, {eq, false}}, {handshake, next(T), not_busy, false},
            router_task:watchdog(T, transfer_timeout_ms, 10000)], phase(T, leaving)}.

watch(Phase, Point, Value, T) ->
    router_task:watch(T, Phase, Point, Value, transfer_timeout_ms).

%% The seed's feeder: a warning while the previous machine's magazine is low.
magazine(T) ->
    Low = cell_task:in(T, magazine_low),
    case {Low, cell_task:get(T, magazine_low, false)} of
        {Same, Same} ->
            T;
        {true, _} ->
            cell_task:put(cell_task:warning(T, <<"magazine_low">>, "Panel magazine low",
                                            "The previous machine's panel magazine is nearly "
                                            "empty: refill it."), magazine_low, true);
        {false, _} ->
            cell_task:put(cell_task:reset_warning(T, <<"magazine_low">>), magazine_low, false)
    end.

magazine_wait(T) ->
    [{io, magazine_low, {ne, cell_task:get(T, magazine_low, false)}}].

next(T) ->
    cell_task:arg(T, next, undefined).

phase(T, Phase) ->
    cell_handover:phase(T, Phase).
