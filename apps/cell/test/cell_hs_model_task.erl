%% A device task at one end of a handshake link, driven step by step by its test
%% (prop_cell_handshake): each step waits for `{Ref, {Command, From}}' (Ref is the
%% task's `ref' argument), makes the handshake call the seed's examples make at that
%% point (seed 000 §2.3.6) on its link `link' as `role' and answers `{hs_reply, Id,
%% Reply, Snapshot}'. It tells `notify' `{hs_ready, Id, self(), Snapshot}' at its
%% first wait after each init, and writes `{Role, Id, self()}' into the table
%% `tab', where the test finds the incarnation to command.
%%
%% Snapshot: `#{phase, product (serial or none), in_transit}', the task's view.
%%
%% Upstream commands: `{new, Serial}', `offer', `try_abort_offering', `release',
%% `finish', `confirm', `look'. Downstream: `peek', `commit' (the seed's formal check
%% of Available that locks the handshake), `complete', `abort', `ship' (the product
%% leaves the line), `confirm', `look'.
-module(cell_hs_model_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, cell_task:put(T, fresh, true)}.

-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    {ok, T}.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    T.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    Ref = arg(T, ref),
    case cell_task:woken_by(T) of
        {reply, Ref, {Command, From}} ->
            {Reply, T1} = case guard(Command, T) of
                              ok -> do(Command, T);
                              Refused -> {Refused, T}
                          end,
            From ! {hs_reply, cell_task:id(T), Reply, snapshot(T1)},
            {wait, {reply, Ref}, T1};
        _ ->
            T1 = case cell_task:get(T, fresh, false) of
                     true ->
                         true = ets:insert(arg(T, tab), {arg(T, role), cell_task:id(T), self()}),
                         arg(T, notify) ! {hs_ready, cell_task:id(T), self(), snapshot(T)},
                         cell_task:put(T, fresh, false);
                     false ->
                         T
                 end,
            {wait, {reply, Ref}, T1}
    end.

%% A task acts on what it sees, as the seed's loops do: a command whose moment has not
%% come (or has passed: the partner stopped meanwhile) is refused, `{not_now, Phase}'.
guard(Command, T) ->
    Phase = cell_handshake:phase(T, arg(T, link)),
    Have = cell_task:product(T) =/= undefined,
    Ok = case Command of
             %% The seed's previous device is in its transfer until phase 4.
             {new, _} -> not Have andalso Phase =:= idle;
             offer -> Have andalso Phase =:= idle andalso not cell_handshake:in_transit(T);
             release -> Phase =:= committed;
             commit -> not Have;
             complete -> Phase =:= released;
             abort -> Phase =:= committed orelse Phase =:= released;
             ship -> Have andalso Phase =:= idle andalso not cell_handshake:in_transit(T);
             _ -> true
         end,
    case Ok of
        true -> ok;
        false -> {not_now, Phase}
    end.

%% -- upstream (previous device) ---------------------------------------------------------
do({new, Serial}, T) ->
    {ok, cell_task:set_product(T, cell_product:new(Serial, <<"model">>))};
do(offer, T) ->
    %% Phase 1: Data and Available.
    {ok, cell_handshake:offer(T, arg(T, link))};
do(try_abort_offering, T) ->
    cell_handshake:try_abort_offering(T, arg(T, link));
do(release, T) ->
    %% Phase 3: the product has left this device's sensor.
    {ok, cell_handshake:release(T, arg(T, link))};
do(finish, T) ->
    cell_handshake:finish(T, arg(T, link));
%% -- downstream (next device) -----------------------------------------------------------
do(peek, T) ->
    case cell_handshake:peek(T, arg(T, link)) of
        {ok, #{serial := S}} -> {{ok, S}, T};
        none -> {none, T}
    end;
do(commit, T) ->
    %% Phase 2: the formal check of Available, which locks the handshake, and NotBusy.
    case cell_handshake:commit(T, arg(T, link)) of
        {ok, T1} -> {ok, T1};
        {not_available, T1} -> {not_available, T1}
    end;
do(complete, T) ->
    %% Phase 4: the product has arrived.
    {ok, cell_handshake:complete(T, arg(T, link))};
do(abort, T) ->
    {ok, cell_handshake:abort(T, arg(T, link))};
do(ship, T) ->
    #{serial := S} = cell_task:product(T),
    {{ok, S}, cell_task:clear_product(T)};
%% -- either -----------------------------------------------------------------------------
do(confirm, T) ->
    {ok, cell_handshake:confirm_here(T)};
do(look, T) ->
    {ok, T}.

snapshot(T) ->
    #{phase => cell_handshake:phase(T, arg(T, link)),
      product => case cell_task:product(T) of
                     #{serial := S} -> S;
                     undefined -> none
                 end,
      in_transit => cell_handshake:in_transit(T)}.

arg(T, Key) ->
    cell_task:arg(T, Key, undefined).
