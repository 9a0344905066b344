%% A conveyor segment of a line written with the framework's hand-over patterns only
%% (cell_handover, around the bare offer, release and complete of cell_handshake): the
%% way a cell of one's own writes its tasks. It takes a product from the previous
%% segment, moves it along and hands it to the next; the first takes new serials from
%% a feed table, the last sends them out.
%%
%% <pre>
%%  phase      waits for                                  then
%%  idle       the previous segment's offer (STARVED)     commit (phase 2) → moving_in
%%  moving_in  its Available off (phase 3)                → arriving
%%  arriving   `delay' (the move), the link watched       complete (phase 4) → full; cut off
%%                                                        meanwhile: see below
%%  full       -                                          offer (phase 1) → offered; the last
%%                                                        segment sends the product out → idle
%%  offered    the next segment's NotBusy                 → leaving; the offer gone (link
%%                                                        restarted): → full
%%  leaving    `delay' (the move), or the next segment's  release (phase 3) → released; the
%%             NotBusy off                                next segment gone: → full
%%  released   the next segment's NotBusy off             completed → idle; given back → full;
%%                                                        interrupted: see below
%%
%% A transfer cut off while the product moved (cell_handover:interrupted/4): the
%% segment's sensor seeing it, it goes on (full); else the operator is asked.
%%  in_transit the operator's Ignore after "Transfer      → full (Reset: forgotten at init)
%%             interrupted"
%% </pre>
%%
%% Restarted (reconcile), the record is held against the segment's sensor: a simulated
%% one that sees the product unless the test made it blind (`{blind, Task}' in the
%% `sensors' table); not seen, the operator is asked where the product is.
%%
%% Args: #{prev => Link, next => Link, feed => Tab, out => Tab, ref => Ref,
%%         delay => Ms, notify => Pid, sensors => Tab}. The feed is an ordered_set of
%% {N, Serial}; when it runs dry the first segment waits for `{Ref, fed}'. The out
%% table gets {Serial, Task}; a serial sent out twice (not the hand-out of one already
%% begun) is put in `sensors' as `{{duplicate_out, Serial}, Task}'. `notify' gets
%% `{line_out, Task, Serial}', and `{line_arriving, Task}' as a product starts to move in.
-module(cell_handover_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, cell_handover:after_reset(T)}.

-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(_Held, T0) ->
    case cell_handover:reconcile(T0, fun seen/1, fun where/2) of
        {empty, T} ->
            {ok, phase(T, idle)};
        {here, _By, T} ->
            %% A take from the feed cut short after the product was saved: finish it.
            #{serial := S} = cell_task:product(T),
            forget_fed(T, S),
            {ok, phase(T, full)};
        {gone, _Serial, T} ->
            {ok, phase(T, idle)};
        {error, _, _} = Ask ->
            Ask
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    T.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

%% -- empty: take a product -------------------------------------------------------------
step(idle, _Woken, T) ->
    case arg(T, prev) of
        undefined -> take_new(T);
        Prev -> cell_handover:take(T, Prev, moving_in)
    end;
step(moving_in, {handshake, _Prev, interrupted}, T) ->
    cell_handover:interrupted(T, full, idle);
step(moving_in, {handshake, Prev, available, false}, T) ->
    %% On its way in, the link watched: a transfer cut off meanwhile ends the wait.
    notify(T, {line_arriving, cell_task:id(T)}),
    {wait, [{timer, delay(T)}, {handshake, Prev, available, true}], phase(T, arriving)};
step(moving_in, _Woken, T) ->
    {wait, {handshake, arg(T, prev), available, false}, T};
step(arriving, {handshake, _Prev, interrupted}, T) ->
    cell_handover:interrupted(T, full, idle, fun seen/1);
step(arriving, _Woken, T) ->
    %% Interrupted meanwhile, the link has moved on; the product arrived all the same.
    {continue, phase(cell_handshake:complete(T, arg(T, prev)), full)};
%% -- full: hand the product on -----------------------------------------------------------
step(full, _Woken, T) ->
    case arg(T, next) of
        undefined -> send_out(T);
        Next -> {wait, {handshake, Next, not_busy, true}, phase(cell_handshake:offer(T, Next), offered)}
    end;
step(offered, {handshake, Next, not_busy, true}, T) ->
    %% On its way out, as long as the next segment takes it.
    {wait, [{timer, delay(T)}, {handshake, Next, not_busy, false}], phase(T, leaving)};
step(offered, _Woken, T) ->
    cell_handover:offered(T, arg(T, next), full);
step(leaving, _Woken, T) ->
    Next = arg(T, next),
    case cell_handshake:phase(T, Next) of
        committed ->
            {wait, {handshake, Next, not_busy, false},
             phase(cell_handshake:release(T, Next), released)};
        %% The next segment stopped taking it: offered again.
        _ -> {continue, phase(T, full)}
    end;
step(released, {handshake, _Next, interrupted}, T) ->
    cell_handover:interrupted(T, full, idle, fun seen/1);
step(released, _Woken, T) ->
    cell_handover:finish(T, arg(T, next), idle, full, fun(_, T1) -> T1 end, fun seen/1);
%% -- the operator said the product of an interrupted transfer is here --------------------
step(in_transit, _Woken, T) ->
    case cell_task:product(T) of
        %% Meanwhile a newer record elsewhere took the product from this task.
        undefined -> {continue, phase(T, idle)};
        _ -> {continue, phase(cell_handshake:confirm_here(T), cell_handover:transit_have(T))}
    end.

%% The first segment takes the next serial of the feed: the product is saved first,
%% then the feed forgets it, so a crash in between leaves it owned, never nowhere.
take_new(T) ->
    Feed = arg(T, feed),
    case ets:first(Feed) of
        '$end_of_table' ->
            {wait, {reply, arg(T, ref)}, T};
        N ->
            [{N, Serial}] = ets:lookup(Feed, N),
            T1 = cell_task:set_product(T, cell_product:new(Serial, <<"line">>)),
            true = ets:delete(Feed, N),
            {continue, phase(T1, full)}
    end.

%% The hand-out is saved as begun before the product goes: a restart in between finds
%% it gone (in the out table, the exit's "sensor") and does not send it twice.
send_out(T0) ->
    #{serial := S} = P = cell_task:product(T0),
    Id = cell_task:id(T0),
    {Resumed, T} = case P of
                       #{handing_out := true} -> {true, T0};
                       _ -> {false, cell_task:set_product(T0, P#{handing_out => true})}
                   end,
    _ = ets:insert_new(arg(T, out), {S, Id}) orelse Resumed
        orelse ets:insert(arg(T, sensors), {{duplicate_out, S}, Id}),
    notify(T, {line_out, Id, S}),
    {continue, phase(cell_task:clear_product(cell_task:transfer_out(T, S)), idle)}.

forget_fed(T, Serial) ->
    case arg(T, feed) of
        undefined -> ok;
        Feed -> true = ets:match_delete(Feed, {'_', Serial}), ok
    end.

%% The segment's product sensor, simulated: it sees the product unless made blind.
seen(T) ->
    case arg(T, sensors) of
        undefined -> true;
        Tab -> not ets:member(Tab, {blind, cell_task:id(T)})
    end.

where(T, S) ->
    {error, cell_task:error_spec(
              <<"where">>, "Product not on the segment",
              io_lib:format("Records say product ~ts is on this segment; its sensor sees "
                            "none. RETRY: look again. IGNORE: it is here. RESET: it was taken "
                            "out of the machine.", [S]),
              [retry, ignore, reset]),
     T}.

delay(T) ->
    cell_task:arg(T, delay, 0).

phase(T, Phase) ->
    cell_handover:phase(T, Phase).

notify(T, Msg) ->
    case arg(T, notify) of
        undefined -> ok;
        Pid -> Pid ! Msg, ok
    end.

arg(T, Key) ->
    cell_task:arg(T, Key, undefined).
