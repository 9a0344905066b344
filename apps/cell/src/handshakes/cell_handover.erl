%% @doc The hand-over patterns every device task writes alike around {@link
%% cell_handshake} (seed 000 §2.3.6), and the restart reconciliation they need: public
%% API for task modules.
%%
%% A task keeps its own state within its IPC-2541 state as a phase ({@link phase/2},
%% {@link phase/1}); the functions here take the phases to go to and return a step
%% result, so a task's step reads as its state table. What they get right, which a
%% task written from the bare handshake easily gets wrong:
%%
%% <ul>
%% <li>{@link take/3}: downstream commits only to an offer that still stands (the seed's
%%     TryAbortOffering may withdraw it in between) and otherwise waits for one.</li>
%% <li>{@link offered/3}: an offer that is gone (the link restarted, a Pause withdrew
%%     it) is made again, never waited on for ever.</li>
%% <li>{@link finish/4}: the end of the transfer (phase 4) answers `pending' until the
%%     partner's NotBusy is off: the task waits, it does not decide.</li>
%% <li>{@link interrupted/3}: a transfer that ended early leaves a product that had
%%     not moved with its task; one that was moving is the operator's to settle
%%     (Ignore: here; Reset: not here, forgotten), unless the task's own sensors show
%%     it at its station.</li>
%% <li>{@link error/6} and {@link after_reset/1}: an error whose Reset forgets the
%%     product. The engine answers Reset by re-initialising the task; its `init' asks
%%     {@link reset_chosen/1} or {@link after_reset/1} what the Reset meant.</li>
%% <li>{@link reconcile/3}: the record held against the station's sensor after a
%%     restart, with the operator's question where they disagree, and {@link
%%     unheld/3} / {@link unheld_error/4} for what a sensor sees that no record
%%     holds.</li>
%% </ul>
%%
%% A conveyor segment written with them (its sensor `part_here', its belt `belt'):
%% ```
%% init(T) -> {ok, cell_task:out(cell_handover:after_reset(T), belt, false)}.
%%
%% reconcile(_Held, T0) ->
%%     case cell_handover:reconcile(T0, fun(T) -> cell_task:in(T, part_here) end,
%%                                  fun where/2) of
%%         {empty, T} -> {ok, cell_handover:phase(T, idle)};
%%         {here, _By, T} -> {ok, cell_handover:phase(T, full)};
%%         {gone, _Serial, T} -> {ok, cell_handover:phase(T, idle)};
%%         {error, _, _} = Ask -> Ask
%%     end.
%%
%% step(T) -> step(cell_handover:phase(T), cell_task:woken_by(T), T).
%%
%% step(idle, _, T) ->                                      % downstream: take
%%     cell_handover:take(T, prev, moving_in, fun(T1) -> cell_task:out(T1, belt, true) end);
%% step(moving_in, {handshake, _, interrupted}, T) ->
%%     cell_handover:interrupted(cell_task:out(T, belt, false), arriving, idle);
%% step(moving_in, {handshake, _, available, false}, T) ->
%%     {wait, {io, part_here, {eq, true}}, cell_handover:phase(T, arriving)};
%% step(moving_in, _, T) ->
%%     {wait, {handshake, prev, available, false}, T};
%% step(arriving, _, T) ->
%%     T1 = cell_handshake:complete(cell_task:out(T, belt, false), prev),
%%     {continue, cell_handover:phase(T1, full)};
%% step(full, _, T) ->                                      % upstream: offer
%%     {wait, {handshake, next, not_busy, true},
%%      cell_handover:phase(cell_handshake:offer(T, next), offered)};
%% step(offered, {handshake, _, not_busy, true}, T) ->
%%     T1 = cell_handshake:release(T, next),
%%     {wait, {handshake, next, not_busy, false}, cell_handover:phase(T1, released)};
%% step(offered, _, T) ->
%%     cell_handover:offered(T, next, full);
%% step(released, {handshake, _, interrupted}, T) ->
%%     cell_handover:interrupted(T, full, idle);
%% step(released, _, T) ->
%%     cell_handover:finish(T, next, idle, full);
%% step(in_transit, _, T) ->                                % the operator's Ignore
%%     {continue, cell_handover:phase(cell_handshake:confirm_here(T), full)}.
%% '''
%% A task whose transfer was interrupted while the product moved is asked "Transfer
%% interrupted" in its `in_transit' phase: Ignore runs that phase's step (the product
%% is here), Reset re-initialises the task and `after_reset/1' forgets the product.
%%
%% `apps/cell/test/cell_handover_task.erl' is a whole segment written so, which
%% `prop_cell_handover' runs in a line through kills, link restarts, emergency stops and
%% the operator's answers.
%%
%% The task's data keys `phase', `on_reset' and `transit_have' belong to this module.
-module(cell_handover).

-export([phase/1, phase/2]).
-export([take/3, take/4, offered/3, finish/4, finish/5, finish/6,
         interrupted/3, interrupted/4, transit_have/1]).
-export([error/6, reset_chosen/1, after_reset/1, drop_reset/1]).
-export([reconcile/3, here/1, forget/2, unheld/3, unheld_anywhere/2, unheld_error/4]).

-export_type([located/0, outcome/0]).

%% Whether the task's own sensors show the product of an interrupted transfer at its
%% station (see interrupted/4).
-type located() :: fun((cell_task:task()) -> boolean()).
-type outcome() :: completed | aborted | interrupted.

%%--------------------------------------------------------------------
%% The task's phase
%%--------------------------------------------------------------------

%% @doc Sets the task's phase (its own state within its IPC-2541 state).
-spec phase(cell_task:task(), atom()) -> cell_task:task().
phase(T, Phase) ->
    cell_task:put(T, phase, Phase).

%% @doc The task's phase; `undefined' before it set one.
-spec phase(cell_task:task()) -> atom().
phase(T) ->
    cell_task:get(T, phase, undefined).

%%--------------------------------------------------------------------
%% The steps of a hand-over (seed §2.3.6)
%%--------------------------------------------------------------------

%% @doc Downstream, empty: commits to the partner's offer on `Prev' if it makes one
%% (phase 2), then waits in `Phase' for it to let go (phase 3); else waits for an
%% offer, in the phase it is in.
-spec take(cell_task:task(), atom(), atom()) -> cell_task:step_result().
take(T, Prev, Phase) ->
    take(T, Prev, Phase, fun(T1) -> T1 end).

%% @doc As {@link take/3}, `OnCommit' applied once committed (a belt started).
-spec take(cell_task:task(), atom(), atom(), fun((cell_task:task()) -> cell_task:task())) ->
          cell_task:step_result().
take(T, Prev, Phase, OnCommit) ->
    Available = cell_handshake:available(T, Prev),
    case cell_handover_core:take(Available, none) of
        commit ->
            {Reply, T1} = cell_handshake:commit(T, Prev),
            case cell_handover_core:take(Available, Reply) of
                committed ->
                    {wait, {handshake, Prev, available, false}, phase(OnCommit(T1), Phase)};
                wait_offer ->
                    {wait, {handshake, Prev, available, true}, T1}
            end;
        wait_offer ->
            {wait, {handshake, Prev, available, true}, T}
    end.

%% @doc Upstream, offered: an offer still open on `Next' waits for the partner's
%% commit; one that is gone (the link restarted) is made again from `Again'.
-spec offered(cell_task:task(), atom(), atom()) -> cell_task:step_result().
offered(T, Next, Again) ->
    case cell_handover_core:offered(cell_handshake:phase(T, Next)) of
        wait -> {wait, {handshake, Next, not_busy, true}, T};
        again -> {continue, phase(T, Again)}
    end.

%% @doc Upstream, released: the end of the transfer (phase 4). Completed: on in
%% `Done'; aborted (the partner gave the product back): again from `Again';
%% interrupted: {@link interrupted/3}; pending: it waits for the partner's NotBusy off.
-spec finish(cell_task:task(), atom(), atom(), atom()) -> cell_task:step_result().
finish(T, Next, Done, Again) ->
    finish(T, Next, Done, Again, fun(_, T1) -> T1 end).

%% @doc As {@link finish/4}, `Settle(Outcome, T)' applied first once it has ended (a
%% belt stopped).
-spec finish(cell_task:task(), atom(), atom(), atom(),
             fun((outcome(), cell_task:task()) -> cell_task:task())) ->
          cell_task:step_result().
finish(T, Next, Done, Again, Settle) ->
    finish(T, Next, Done, Again, Settle, fun(_) -> false end).

%% @doc As {@link finish/5}; an interruption is settled by {@link interrupted/4} with
%% `Here'.
-spec finish(cell_task:task(), atom(), atom(), atom(),
             fun((outcome(), cell_task:task()) -> cell_task:task()), located()) ->
          cell_task:step_result().
finish(T, Next, Done, Again, Settle, Here) ->
    {Outcome, T1} = cell_handshake:finish(T, Next),
    case cell_handover_core:finished(Outcome) of
        done -> {continue, phase(Settle(completed, T1), Done)};
        again -> {continue, phase(Settle(aborted, T1), Again)};
        interrupted -> interrupted(Settle(interrupted, T1), Again, Done, Here);
        wait -> {wait, {handshake, Next, not_busy, false}, T1}
    end.

%% @doc After a transfer ended early (seed §2.3.6): a product that had not moved stays
%% with the task (`Have' phase), one that was moving is the operator's to settle: the
%% task goes to its `in_transit' phase with the error "Transfer interrupted"; Ignore,
%% it is here (the `in_transit' step runs, see {@link transit_have/1}); Reset, it is
%% not (forgotten by {@link after_reset/1} in `init'). No product: `Empty'.
-spec interrupted(cell_task:task(), atom(), atom()) -> cell_task:step_result().
interrupted(T, Have, Empty) ->
    interrupted(T, Have, Empty, fun(_) -> false end).

%% @doc As {@link interrupted/3}, but a product that was moving and that the task's own
%% sensors show at its station (`Here') is confirmed here without a question.
-spec interrupted(cell_task:task(), atom(), atom(), located()) -> cell_task:step_result().
interrupted(T0, Have, Empty, Here) ->
    T = cell_task:put(T0, transit_have, Have),
    Product = cell_task:product(T),
    case cell_handover_core:interrupted(Product =/= undefined, cell_handshake:in_transit(T)) of
        empty ->
            {continue, phase(T, Empty)};
        have ->
            {continue, phase(T, Have)};
        moving ->
            #{serial := S} = Product,
            case Here(T) of
                true ->
                    cell_task:log(T, brief, "the transfer of product ~ts was interrupted; "
                                  "this station's sensors show where it is: it goes on from here",
                                  [S]),
                    {continue, phase(cell_handshake:confirm_here(T), Have)};
                false ->
                    transfer_question(T, S)
            end
    end.

%% @doc In the `in_transit' step after the operator's Ignore: the phase the task was to
%% go on in with the product ({@link interrupted/3}'s `Have'), `undefined' if none.
-spec transit_have(cell_task:task()) -> atom().
transit_have(T) ->
    cell_task:get(T, transit_have, undefined).

transfer_question(T, S) ->
    error(phase(T, in_transit), <<"transfer">>, "Transfer interrupted",
          io_lib:format("Product ~ts was moving when its transfer was interrupted.~n"
                        "Check where it is. Select IGNORE if it is at this station, "
                        "RESET if it is not (the station forgets it).", [S]),
          [ignore, reset], forget).

%%--------------------------------------------------------------------
%% Errors whose Reset means something
%%--------------------------------------------------------------------

%% @doc An error for the operator; `OnReset' is what the task is to do if the answer
%% is Reset (its `init' learns it from {@link reset_chosen/1}; `forget' is what
%% {@link after_reset/1} acts on).
-spec error(cell_task:task(), binary(), iodata(), iodata(), [cell_alarms:solution()], atom()) ->
          {error, cell_alarms:spec(), cell_task:task()}.
error(T, Id, Caption, Text, Solutions, OnReset) ->
    Pending = {Id, os:system_time(millisecond), OnReset},
    {error, cell_task:error_spec(Id, Caption, Text, Solutions),
     cell_task:put(T, on_reset, Pending)}.

%% @doc In `init': what the task said Reset would mean, if the operator answered its
%% last error with Reset; `none' otherwise. Either way the question is settled. (The
%% registry of errors records every answer before the task hears it.) A task that
%% re-initialises for another reason (a Stop, then Start) finds no Reset.
-spec reset_chosen(cell_task:task()) -> {atom(), cell_task:task()}.
reset_chosen(T) ->
    case cell_task:get(T, on_reset, undefined) of
        undefined ->
            {none, T};
        {Id, _Since, OnReset} = Pending ->
            Global = <<(atom_to_binary(cell_task:id(T), utf8))/binary, ":", Id/binary>>,
            T1 = drop_reset(T),
            case cell_handover_core:reset_chosen(Pending, Global, cell_alarms:history()) of
                true -> {OnReset, T1};
                false -> {none, T1}
            end
    end.

%% @doc In `init': the task as it is, or without its product if the operator answered
%% its last error with a Reset that forgets it (`forget').
-spec after_reset(cell_task:task()) -> cell_task:task().
after_reset(T0) ->
    case reset_chosen(T0) of
        {forget, T} -> cell_task:clear_product(T);
        {_, T} -> T
    end.

%% @doc The task settled its last error itself (its `reconcile' acted on the answer):
%% what it said Reset would mean no longer stands.
-spec drop_reset(cell_task:task()) -> cell_task:task().
drop_reset(T) ->
    cell_task:put(T, on_reset, undefined).

%%--------------------------------------------------------------------
%% Restart reconciliation
%%--------------------------------------------------------------------

%% @doc In `reconcile': the product record held against what the station's sensor
%% says (`Seen'). Holding none: `{empty, T}'. Holding one the sensor sees: `{here,
%% sensor, T}', its in-transit mark cleared ({@link here/1}). Not seen: `Ask(T,
%% Serial)', the task's question to the operator, with RETRY (the sensor is read
%% again), IGNORE (it is here after all: `{here, operator, T}') and RESET (it was taken
%% out of the machine: `{gone, Serial, T}', the product forgotten, ItemWorkAbort). The
%% answer comes back to `reconcile', which calls this again.
-spec reconcile(cell_task:task(), located(),
                fun((cell_task:task(), binary()) -> {error, cell_alarms:spec(), cell_task:task()})) ->
          {empty, cell_task:task()} | {here, sensor | operator, cell_task:task()} |
          {gone, binary(), cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(T, Seen, Ask) ->
    Product = cell_task:product(T),
    case cell_handover_core:reconcile(Product =/= undefined, cell_task:answer(T)) of
        empty ->
            {empty, T};
        look ->
            #{serial := S} = Product,
            case Seen(T) of
                true -> {here, sensor, here(T)};
                false -> Ask(T, S)
            end;
        here ->
            {here, operator, here(T)};
        gone ->
            #{serial := S} = Product,
            {gone, S, forget(T, <<"taken out of the machine">>)}
    end.

%% @doc The product is this task's, whatever transfer brought it (the operator or a
%% sensor said so): an in-transit mark is cleared, durably; without one nothing is
%% written.
-spec here(cell_task:task()) -> cell_task:task().
here(T) ->
    case cell_handshake:in_transit(T) of
        true -> cell_handshake:confirm_here(T);
        false -> T
    end.

%% @doc The task forgets its product (ItemWorkAbort with `Why', then the file goes).
-spec forget(cell_task:task(), binary()) -> cell_task:task().
forget(T, Why) ->
    cell_task:clear_product(cell_task:work_abort(T, Why)).

%% @doc Whether what a station's sensor sees, its own task holding no product, is in
%% no record: none of the tasks `Takers' (those whose product may lie there: a robot
%% that took charge of it in place, say) holds a product of `Lane' (a product without
%% a lane counts as of every lane). `Others' is what the other tasks hold ({@link
%% cell_task:others_products/1}). A taker whose own sensor sees its product elsewhere
%% is left out of `Takers' by the caller.
-spec unheld(term(), [atom()], [{atom(), cell_product:product()}]) -> boolean().
unheld(Lane, Takers, Others) ->
    cell_handover_core:unheld(Lane, Takers, Others).

%% @doc As {@link unheld/3}, for a station any lane's products may reach: none of the
%% tasks `Takers' holds a product.
-spec unheld_anywhere([atom()], [{atom(), cell_product:product()}]) -> boolean().
unheld_anywhere(Takers, Others) ->
    cell_handover_core:unheld_anywhere(Takers, Others).

%% @doc The operator's error for it (id `unheld'): `Where' (a format, with `Args') says
%% what lies where ("a panel lies in the work fixture of lane front"); the operator
%% takes it out of the machine and selects RETRY, and the task looks again.
-spec unheld_error(cell_task:task(), iodata(), io:format(), [term()]) ->
          {error, cell_alarms:spec(), cell_task:task()}.
unheld_error(T, Caption, Where, Args) ->
    {error, cell_task:error_spec(
              <<"unheld">>, Caption,
              [io_lib:format(Where, Args),
               " and no record holds it: take it out of the machine, then select RETRY."],
              [retry]),
     T}.
