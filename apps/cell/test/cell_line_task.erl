%% A conveyor segment of a line, written the way seed 000 §2.3.6 writes its examples:
%% it takes a product from the previous segment over a handshake, moves it along, and
%% hands it to the next. The first segment (no `prev') takes new serials from a feed
%% table; the last (no `next') sends them out. `delay' milliseconds stand for the
%% physical moves (0: none).
%%
%% Args: #{prev => Link, next => Link, feed => Tab, out => Tab, ref => Ref,
%%         delay => Ms, notify => Pid, jam => true, hold => true, out_log => File}. With `jam' the first
%% product taken sticks before it arrives: an error with Retry. With `hold' a product
%% stops in the middle of its move and stays there (a segment stopped mid-transfer,
%% for a test to kill the node at that moment). The feed is an ordered_set of {N, Serial}; when
%% it runs dry the first segment waits for `{Ref, fed}'. The out table gets
%% {Serial, Task}. With `out_log' the last segment also appends each serial it sends
%% out to that file, on disk before it forgets the product: the log is the sensor that
%% says a product left, so a segment that comes back after a power cut still holding
%% a product the log has does not send it out again. `notify' gets `{line_phase, Task, Phase}' at every phase change
%% (unless `phases => false') and `{line_out, Task, Serial}' for every product sent out.
%%
%% A transfer interrupted while the product moved asks the operator (Ignore: it is here;
%% Reset: it is not). The engine answers Reset by initialising the task again: `init'
%% then forgets the product, as a user's task does (cell_handover:error/6 and
%% after_reset/1), so a product the operator says is gone is never sent on.
-module(cell_line_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, cell_handover:after_reset(T)}.

%% A line of simulated segments has no sensors to hold the record against: the product
%% file is where the product is, and the segment goes on from there.
-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    case cell_task:product(T) of
        undefined ->
            {ok, phase(T, idle)};
        #{serial := S} ->
            case logged_out(T, S) of
                true ->
                    %% Sent out just before the power went: it is gone.
                    {ok, phase(cell_task:clear_product(T), idle)};
                false ->
                    %% A take cut short after the product was saved: finish it.
                    forget_fed(T, S),
                    {ok, phase(T, full)}
            end
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    T.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_task:get(T, phase), cell_task:woken_by(T), T).

%% -- empty: take a product ------------------------------------------------------------
step(idle, _Woken, T) ->
    case arg(T, prev) of
        undefined -> take_new(T);
        Prev -> take_from(Prev, T)
    end;
step(moving_in, {handshake, Prev, available, false}, T) ->
    %% Phase 3 seen: the product left the previous segment; run until it arrives.
    case cell_task:arg(T, hold, false) of
        true -> {wait, {reply, make_ref()}, phase(T, arriving)};
        false -> after_delay(arriving, T, fun() -> arrived(Prev, T) end)
    end;
step(moving_in, {handshake, _Prev, interrupted}, T) ->
    interrupted(T);
step(moving_in, _Woken, T) ->
    {wait, {handshake, arg(T, prev), available, false}, T};
step(arriving, _Woken, T) ->
    case cell_task:arg(T, jam, false) andalso not cell_task:get(T, jammed, false) of
        true ->
            {error, cell_task:error_spec(<<"jam">>, "Jam", "The product sticks.", [retry]),
             cell_task:put(T, jammed, true)};
        false ->
            arrived(arg(T, prev), T)
    end;
%% -- full: hand the product on -----------------------------------------------------------
step(full, _Woken, T) ->
    case arg(T, next) of
        undefined ->
            #{serial := S} = cell_task:product(T),
            ok = log_out(T, S),
            true = ets:insert(arg(T, out), {S, cell_task:id(T)}),
            notify(T, {line_out, cell_task:id(T), S}),
            {continue, phase(cell_task:clear_product(T), idle)};
        Next ->
            T1 = cell_handshake:offer(T, Next),
            {wait, {handshake, Next, not_busy, true}, phase(T1, offered)}
    end;
step(offered, {handshake, Next, not_busy, true}, T) ->
    %% Phase 2 seen: the next segment took it; run until it left our sensor.
    after_delay(leaving, T, fun() -> released(Next, T) end);
step(offered, _Woken, T) ->
    Next = arg(T, next),
    case cell_handshake:phase(T, Next) of
        offered -> {wait, {handshake, Next, not_busy, true}, T};
        %% The offer is gone (the link restarted): offer again.
        _ -> {continue, phase(T, full)}
    end;
step(leaving, _Woken, T) ->
    released(arg(T, next), T);
step(released, {handshake, _Next, interrupted}, T) ->
    interrupted(T);
step(released, _Woken, T) ->
    Next = arg(T, next),
    case cell_handshake:finish(T, Next) of
        {completed, T1} -> {continue, phase(T1, idle)};
        {aborted, T1} -> {continue, phase(T1, full)};
        {interrupted, T1} -> interrupted(T1);
        {pending, T1} -> {wait, {handshake, Next, not_busy, false}, T1}
    end;
%% -- an interrupted transfer the operator answered ---------------------------------------
step(in_transit, _Woken, T) ->
    case {cell_task:answer(T), cell_task:product(T)} of
        %% Meanwhile a newer record elsewhere took the product from this task.
        {_, undefined} -> {continue, phase(T, idle)};
        {ignore, _} -> {continue, phase(cell_handshake:confirm_here(T), full)};
        %% (Reset re-initialises the task: init forgets the product.)
        _ -> {continue, T}
    end.

%% The first segment takes the next serial of the feed the way a panel arrives: the
%% product is saved first, then the feed forgets it, so a crash in between leaves it
%% owned (and init finishes the take), never nowhere.
take_new(T) ->
    Feed = arg(T, feed),
    case ets:first(Feed) of
        '$end_of_table' ->
            T1 = case cell_task:state(T) of
                     {ready, idle, starved} -> T;
                     _ -> cell_task:starved(T)
                 end,
            {wait, {reply, arg(T, ref)}, T1};
        N ->
            [{N, Serial}] = ets:lookup(Feed, N),
            T1 = cell_task:set_product(T, cell_product:new(Serial, <<"line">>)),
            true = ets:delete(Feed, N),
            {continue, phase(T1, full)}
    end.

log_out(T, S) ->
    case arg(T, out_log) of
        undefined -> ok;
        File -> file:write_file(File, [S, $\n], [append, sync])
    end.

logged_out(T, S) ->
    case arg(T, out_log) of
        undefined ->
            false;
        File ->
            case file:read_file(File) of
                {ok, Log} -> lists:member(S, binary:split(Log, <<"\n">>, [global]));
                {error, enoent} -> false
            end
    end.

forget_fed(T, Serial) ->
    case arg(T, feed) of
        undefined -> ok;
        Feed -> true = ets:match_delete(Feed, {'_', Serial}), ok
    end.

take_from(Prev, T) ->
    case cell_handshake:available(T, Prev) of
        true ->
            case cell_handshake:commit(T, Prev) of
                {ok, T1} -> {wait, {handshake, Prev, available, false}, phase(T1, moving_in)};
                {not_available, T1} -> {wait, {handshake, Prev, available, true}, T1}
            end;
        false ->
            {wait, {handshake, Prev, available, true}, T}
    end.

arrived(Prev, T) ->
    {continue, phase(cell_handshake:complete(T, Prev), full)}.

released(Next, T) ->
    T1 = cell_handshake:release(T, Next),
    {wait, {handshake, Next, not_busy, false}, phase(T1, released)}.

%% Seed 000 §2.3.6: a transfer interrupted while the product moved is the operator's
%% to settle; one interrupted before it moved leaves the product where it was.
interrupted(T) ->
    case {cell_task:product(T), cell_handshake:in_transit(T)} of
        {undefined, _} ->
            {continue, phase(T, idle)};
        {_, false} ->
            {continue, phase(T, full)};
        {#{serial := S}, true} ->
            cell_handover:error(
              phase(T, in_transit), <<"transfer">>, "Transfer interrupted",
              io_lib:format("Product ~ts was moving when its transfer was "
                            "interrupted. IGNORE: it is here. RESET: it is not.", [S]),
              [ignore, reset], forget)
    end.

after_delay(Phase, T, Now) ->
    case cell_task:arg(T, delay, 0) of
        0 -> Now();
        Ms -> {wait, {timer, Ms}, phase(T, Phase)}
    end.

phase(T, Phase) ->
    case cell_task:get(T, phase, undefined) of
        Phase -> T;
        _ -> cell_task:arg(T, phases, true)
                 andalso notify(T, {line_phase, cell_task:id(T), Phase}),
             cell_task:put(T, phase, Phase)
    end.

notify(T, Msg) ->
    case arg(T, notify) of
        undefined -> ok;
        Pid -> Pid ! Msg, ok
    end.

arg(T, Key) ->
    cell_task:arg(T, Key, undefined).
