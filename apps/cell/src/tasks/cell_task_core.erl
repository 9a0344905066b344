%% @doc The decisions of a device task's engine, without a process: what the task does
%% next, given where it is and what happened. Most are transitions of the engine's
%% data (`cell_task_engine.hrl', shared with {@link cell_task_proc} only): the data as
%% it is after, the effects the engine carries out in order ({@link effect()}: waits
%% cancelled, an error withdrawn, transfers ended, the outputs secured, the state
%% recorded and announced, the next event), and where going on takes more than
%% effects (calls whose answers decide what follows: arming waits, raising an error,
%% resuming), what the engine goes on with ({@link then()}). Everything here is a
%% function of its arguments and tested without processes.
%%
%% <ul>
%% <li>The controller's commands ({@link control/4}): which of Start, Pause, Stop,
%%     service mode and the emergency stop acts in which state (seed 000 §2.2, arrows
%%     0, 5, 6 and 9), and which is only kept for the state that acts on it.</li>
%% <li>Leaving what the task was doing ({@link leave/3}): the emergency stop, Stop,
%%     a pause, an error, a way back into setup.</li>
%% <li>Pause, Stop and service mode at a step boundary ({@link pause/3}): the seed
%%     allows stopping only before downstream commits, so a transfer under way holds
%%     the request back, and open offers are withdrawn first (TryAbortOffering, which
%%     the engine makes and whose answers it tells back) unless downstream has just
%%     begun to take one.</li>
%% <li>Boot and setup: a crash found at boot ({@link crashed/4}), whether an OFF task
%%     starts ({@link start/1}, {@link from_off/3}), what setup does first
%%     ({@link setup/1}, {@link setup_again/1}), what init and reconcile came to
%%     ({@link inited/2}, {@link reconciled/3}: READY by arrow 1 or 5, or DOWN by arrow
%%     7).</li>
%% <li>The task's IO: its connections as the engine found them before init and at
%%     arrow 5 ({@link checked/3}, {@link conn_status/3}), a connection lost or a
%%     point unavailable under a request ({@link io_lost/3}, {@link unavailable/5}),
%%     what arming the waits and setting the outputs again came to ({@link armed/3},
%%     {@link reasserted/3}).</li>
%% <li>Steps: what a step returned ({@link step_result/2}, {@link stepped/2}), what it
%%     is told woke it ({@link woken_by/2}, {@link clean/1}), which armed wait a timer,
%%     a HAL watch or a reply ends ({@link wait_news/2}) and the wait ending
%%     ({@link wake/3}).</li>
%% <li>Errors: whether a crash is the operator's question ({@link ask_after_crash/1});
%%     what the operator's answer leads to ({@link answered/4}).</li>
%% <li>Transfers: a link's news ({@link link_news/3}: which armed wait it ends, what
%%     a transfer that ended while the task was DOWN changes), the IPC-2541 events the
%%     seed raises when a wait on a link ends ({@link wake/3}) or starts
%%     ({@link starves/4}); a copy of a product another task holds in a newer record
%%     ({@link newer_holder/3}), and what the task does once the registry found its
%%     copy old ({@link stale/4}).</li>
%% </ul>
%%
%% It also gives {@link cell_handshake} the task's fields the handshake keeps
%% (product, generation, in-transit mark, links' views), so that only the engine's
%% modules know the task record.
-module(cell_task_core).

-include("cell_task.hrl").
-include("cell_task_engine.hrl").

-export([leave/3, uninit/1, control/4, pause/3, wake/3, link_news/3, stale/4,
         answered/4, stepped/2, inited/2, reconciled/3, resume/1, step_result/2, woken_by/2, clean/1,
         crashed/4, start/1, setup_again/1, checked/3, conn_status/3, io_lost/3, unavailable/5,
         armed/3, reasserted/3, from_off/3, setup/1, ask_after_crash/1, starves/4, newer_holder/3, link_retry_ms/1,
         wait_news/2, serial_text/1]).
%% The task's handshake fields, for cell_handshake.
-export([links/1, set_links/2, gen/1, marker/1, product_path/1, product_file/1,
         take/4, released/1]).

-export_type([why/0, origin/0, down_reason/0, pending/0, engine/0, leave/0, effect/0,
              then/0, control_action/0, answer_action/0, setup_event/0, armed/0, news/0,
              found/0, io_spec/0]).

-define(LINK_RETRY_MIN_MS, 50).
-define(LINK_RETRY_MAX_MS, 1000).

-type why() :: pause | service.
%% Why a DOWN task is there: paused (Pause, Stop, service mode), or an error the
%% operator answers (its alarm's id).
-type down_reason() :: {paused, why()} | {error, binary(), origin()}.
%% What READY does next: a step, told what woke it, or the waits of the last step.
-type pending() :: undefined | {step, term()} | {waits, [cell_task:wait()]}.
%% Where an error the operator answers came from.
-type origin() :: init | reconcile | step | crash | product_file | retain_file | transit | io
                | handed_on.
-type setup_event() :: retain_damaged | in_transit | run_init | product_damaged
                     | {crashed, term()}.
%% The engine's data (cell_task_engine.hrl).
-type engine() :: #engine{}.
%% What the task leaves what it was doing for (see leave/3).
-type leave() :: {secure, cell_member:estop_barrier()} | estop | off | stop | {pause, why()}
               | {error, binary(), origin()} | {setup, cell_task:cause()}
               | {reconcile, 2 | 8} | forget.
%% What the engine carries out for a transition, in order.
-type effect() :: {withdraw_alarm, binary()}   %% the error is no longer the operator's
                | {cancel, [armed()]}          %% waits left: their timers and watches
                | interrupt_links              %% the task's transfers end
                | uninit                       %% the task module secures the outputs
                | forget_product               %% the product is not here: forgotten
                | keep_product                 %% the product is here: kept, its mark cleared
                | {resumed, boolean()}         %% the registry told (see ask_after_crash/1)
                | headroom                     %% the heap collected, entering READY
                | {reoffer, [atom()]}          %% offers a pause withdrew, made again
                | {log, notice | warning, io:format(), [term()]} %% said in the task's log
                | {crashed, term()}            %% the crash recorded and logged
                | {crash_warning, term()}      %% the warning that it goes on by itself
                | predecessor                  %% what reconcile checks, taken now
                | {ipc_event, unblocked | unstarved} %% seed 000 §2.3.4, as a wait ends
                | {estop_secured, cell_member:estop_barrier()} %% the barrier's slot marked
                | {state, cell_ipc:state(), cell_ipc:cause()}  %% recorded and announced
                | {next_event, term()}.        %% what the engine does next
%% What the engine does with a command of the controller (see control/4).
-type control_action() :: start                       %% OFF, Start: from_off/3 decides
                        | boundary                    %% READY: pause/3 decides
                        | resume                      %% paused, Start: arrow 5
                        | reconcile                   %% paused, Start, its product dropped
                        | stop                        %% DOWN, Stop: arrow 9
                        | {secure, cell_member:estop_barrier()}  %% emergency stop
                        | {secured, cell_member:estop_barrier()} %% the same, OFF already
                        | keep.                       %% kept for the state that acts on it
%% What the engine goes on with after a transition's effects, where that takes more
%% than effects (calls whose answers it tells back to the transition named):
%% <ul>
%% <li>`resume': arrow 5, its connections checked first (checked/3);</li>
%% <li>`{reassert, Ready}': the outputs a lost connection may have lost set again
%%     (reasserted/3);</li>
%% <li>`{arm, Waits, After}': the waits armed, after a step or at arrow 5
%%     (armed/3);</li>
%% <li>`start': whether an OFF task starts (start/1); `init': the task's init, its
%%     connections up; `boundary': pause/3 at the step boundary;</li>
%% <li>`{reconcile, Woken}': reconcile at once, woken thus;</li>
%% <li>`{File, set_aside | reload, Who}': a damaged file of the task's record set aside
%%     or read again (the operator's name for the log);</li>
%% <li>`{raise, Spec, Origin, From}': an error raised for the operator, then DOWN
%%     (leave/3) by the arrow from setup or from the READY state named: reconcile's
%%     errors are setup's, also when it runs again from DOWN after an init error was
%%     ignored;</li>
%% <li>`{down_again, Spec}': a DOWN task stays DOWN with this error as its new
%%     one.</li>
%% </ul>
-type then() :: resume | {reconcile, term()}
              | {product_file | retain_file, set_aside | reload, binary()}
              | {arm, [cell_task:wait()], step | resume} | {reassert, cell_ipc:ready()}
              | {raise, cell_alarms:spec() | io_spec(), origin(), setup | cell_ipc:ready()}
              | start | init | boundary | {down_again, io_spec()}.
%% The connections of the task's IO as the engine found them (see checked/3): a
%% connection's status, one whose subscription the HAL's server could not take (it is
%% restarting: down, and asked for again next time), an IO group the HAL does not know.
-type found() :: {conn, atom(), up | down | unsubscribed} | {group, atom(), unconfigured}.
%% An error of the task's IO, which the engine words with what the HAL says of it: a
%% connection down, a group not configured, a point its device cannot serve.
-type io_spec() :: {io, atom()} | {io_config, atom()} | {point, atom(), atom(), term()}.
%% What the engine does with the operator's answer.
-type answer_action() :: reinit                    %% uninit, then init again (arrow 8)
                       | {resume, term()}          %% READY where it was, woken thus
                       | resume                    %% READY where it was, as it was
                       | {paused, term()}          %% stays DOWN, paused, woken thus later
                       | paused                    %% stays DOWN, paused
                       | {setup, term()}           %% setup again with this event (arrow 8)
                       | {reconcile, term()}       %% reconcile at once, woken thus
                       | forget_then_reinit        %% forget the product, then reinit
                       | {forget, term()}          %% forget the product, setup again
                       | {confirm_here, term()}    %% the product is here, setup again
                       | set_aside_product | reload_product
                       | set_aside_retained | reload_retained.
%% What a message means to a READY task's armed waits (see wait_news/2).
-type news() :: {wake, term()}                         %% the step runs, told this woke it
              | {unavailable, atom(), atom(), term()}  %% its point cannot be served
              | late                                   %% a reply nobody waits for
              | none.                                  %% a wait it has since left
-type armed() :: {timer, reference(), non_neg_integer() | {link_down, atom()}}
               | {reply, reference()}
               | {io, reference(), atom(), atom()}
               | {handshake, reference(), atom(), atom(), term()}.

%% -------------------------------------------------------------------------------------
%% Leaving what the task was doing
%% -------------------------------------------------------------------------------------

%% @doc The task leaves what it was doing in `State', for:
%% <ul>
%% <li>`{secure, Barrier}': the controller's emergency stop. The outputs are secured at
%%     once (an error waiting for the operator withdrawn, the transfers ended, uninit)
%%     and the barrier's slot marked; OFF is recorded and announced (`off') once every
%%     task of the fan-out has secured its outputs, so that announcements do not take
%%     the schedulers from tasks still securing theirs.</li>
%% <li>`estop': the emergency stop's flag seen before a step or an init: secured and
%%     OFF at once.</li>
%% <li>`off': the barrier passed: its waits cancelled, OFF.</li>
%% <li>`stop': Stop while DOWN: the same as securing, then OFF (arrow 9).</li>
%% <li>`{pause, Why}': Pause, Stop or service mode at a step boundary: DOWN (arrow 6),
%%     to go back to `State' at Start; for Stop, on to OFF.</li>
%% <li>`{error, AlarmId, Origin}': an error raised for the operator: DOWN (arrow 7
%%     from setup, 6 from READY).</li>
%% <li>`{setup, Cause}': back towards setup for a product it no longer has (a copy
%%     dropped as old): its waits, a pause held back and the offers to make again are
%%     cancelled, its transfers end, and its reconcile starts again from `Cause'. The
%%     state is the caller's to change.</li>
%% <li>`{reconcile, Arrow}': the same, then into setup (arrow 2 from READY, 8 from
%%     DOWN) to reconcile again with what it holds now, its predecessor taken
%%     afresh.</li>
%% <li>`forget': the operator said its product is not here (the product is in two
%%     places, see cell_guard): as a Reset that forgets it, an error it waited on
%%     withdrawn, back to setup (arrow 2 from READY, 8 from DOWN) to init again.</li>
%% </ul>
-spec leave(leave(), cell_ipc:state(), engine()) -> {engine(), [effect()]}.
leave({secure, {Ref, _, _, _} = Barrier}, _State, E) ->
    {E1, Secured} = secure(E),
    {E1#engine{held = Ref}, Secured ++ [{estop_secured, Barrier}]};
leave(estop, State, E) ->
    {E1, Secured} = secure(E),
    {E2, Off} = leave(off, State, E1),
    {E2, Secured ++ Off};
leave(off, _State, E) ->
    {E1, Cancel} = disarm(E#engine{held = undefined}),
    {E2, Off} = to(off, estop, E1),
    {E2, Cancel ++ [Off]};
leave(stop, _State, E) ->
    {E1, Cancel} = disarm(E),
    {E2, Secured} = secure(E1),
    {E3, Off} = to(off, {arrow, 9}, E2),
    {E3, Cancel ++ Secured ++ [Off]};
leave({pause, Why}, State, #engine{request = Request} = E) ->
    {E1, Cancel} = disarm(E),
    {E2, Down} = to(down, {arrow, 6},
                    E1#engine{down = {paused, Why}, resume = State, deferred = undefined}),
    {E2, Cancel ++ [Down | case Request of stop -> [{next_event, stop}]; _ -> [] end]};
leave({error, AlarmId, Origin}, State, E) ->
    {E1, Cancel} = disarm(E),
    {E2, Down} = to(down, {arrow, down_arrow(State)}, E1#engine{down = {error, AlarmId, Origin}}),
    {E2, Cancel ++ [Down]};
leave({setup, Cause}, _State, E) ->
    {E1, Cancel} = disarm(E),
    {clear(E1#engine{cause = Cause, predecessor = undefined}), Cancel ++ [interrupt_links]};
leave({reconcile, Arrow}, State, E) ->
    {E1, Left} = leave({setup, dropped}, State, E),
    {E2, Setup} = to(setup, {arrow, Arrow}, E1),
    {E2, Left ++ [predecessor, Setup, {next_event, {reconcile, undefined}}]};
leave(forget, off, E) ->
    %% OFF: nothing runs, nothing to secure; it starts without the product.
    {E, [forget_product]};
leave(forget, State, E) ->
    {E1, Withdraw} = withdraw(E),
    {E2, Left} = leave({setup, reset}, State, E1),
    {E3, Uninit} = uninit(E2),
    Arrow = case State of {ready, _, _} -> 2; _ -> 8 end,
    {E4, Setup} = to(setup, {arrow, Arrow}, E3),
    {E4, Withdraw ++ Left ++ Uninit ++ [forget_product, Setup, {next_event, run_init}]}.

%% @doc A wait of a READY task in `State' ended (`Woken', what its step is told woke
%% it): the waits left, the step due; where a wait on a link ends, the event the seed
%% raises there (§2.3.4: upstream seeing NotBusy is unblocked, downstream seeing
%% Available unstarved).
-spec wake(term(), cell_ipc:state(), engine()) -> {engine(), [effect()]}.
wake(Woken, State, E) ->
    {E1, Cancel} = disarm(E),
    Event = case wake_event(Woken, State) of
                none -> [];
                Ipc -> [{ipc_event, Ipc}]
            end,
    {E1#engine{pending = {step, Woken}}, Cancel ++ Event ++ [{next_event, step}]}.

%% @doc A link's news reached the task in `State' (`Wakes', from
%% cell_handshake:handle/2; the task's views of its links in `E' already as the news
%% left them). READY, the wait on that link ends (`{wake, Transition}', see wake/3),
%% or, if none does, a transfer that ended may free a Pause it held back: what
%% pause/3 says at a boundary. Paused (or stopped), a transfer on a link the task will
%% wait on again has ended: at resume its step runs and sees that, instead of waiting
%% for something the link can no longer send.
-spec link_news([{wake, atom(), term()}], cell_ipc:state(), engine()) ->
          {wake, {engine(), [effect()]}} | {go_on, engine()} | {withdraw, [atom()]}
        | {pause, {engine(), [effect()]}}.
link_news(Wakes, {ready, _, _} = State, #engine{armed = Armed, task = T} = E) ->
    Signal = fun(Link, S) -> cell_handshake:signal(T, Link, S) end,
    case woken(Wakes, Armed, Signal) of
        undefined -> pause(boundary, State, E);
        Woken -> {wake, wake(Woken, State, E)}
    end;
link_news(Wakes, _State, #engine{pending = Pending} = E) ->
    {go_on, E#engine{pending = ended_while_down(Wakes, Pending)}}.

%% @doc The registry found the task's copy of product `Serial' old (another task took
%% the product on in a newer record), and the engine dropped it (`Dropped': the task
%% held it until now; `E' as after the drop). What follows is stale_copy/4's: READY,
%% it reconciles again (arrow 2, see leave/3); the same serial dropped before is the
%% operator's (`{ask, Transition}': its transfers end and it leaves for setup, the
%% engine raising the error); paused, it reconciles when started; otherwise the copy
%% is simply gone.
-spec stale(binary(), boolean(), cell_ipc:state(), engine()) ->
          {engine(), [effect()]} | {ask, {engine(), [effect()]}}.
stale(Serial, Dropped, State, #engine{handed_on = HandedOn, down = Down} = E) ->
    Why = case Down of
              undefined -> undefined;
              _ -> element(1, Down)
          end,
    case stale_copy(State, Dropped, HandedOn =:= Serial, Why) of
        reconcile -> leave({reconcile, 2}, State, E#engine{handed_on = Serial});
        ask -> {ask, leave({setup, dropped}, State, E)};
        reconcile_at_start -> {E#engine{dropped = true}, []};
        keep -> {E, []}
    end.

%% The outputs secured, whatever the task was doing: an error it waited on withdrawn,
%% what it would do next forgotten, its transfers ended, uninit.
secure(E) ->
    {E1, Withdraw} = withdraw(E),
    {E2, Uninit} = uninit(clear(E1)),
    {E2, Withdraw ++ [interrupt_links | Uninit]}.

%% An error waiting for the operator is no longer the operator's to answer.
withdraw(#engine{down = {error, AlarmId, _}} = E) -> {E, [{withdraw_alarm, AlarmId}]};
withdraw(E) -> {E, []}.

%% Nothing left of where the task was: no pause, no step or wait to go back to.
clear(E) ->
    E#engine{down = undefined, pending = undefined, resume = undefined, deferred = undefined,
             reoffer = []}.

%% The task's waits are left: its timers and HAL watches cancelled (watches on
%% links are not: a watch that fires later is no longer armed, and is ignored), and a
%% new round begun, so that step and timer messages already sent are ignored.
-spec disarm(engine()) -> {engine(), [effect()]}.
disarm(#engine{armed = Armed, gen = Gen} = E) ->
    {E#engine{armed = [], gen = Gen + 1},
     case Armed of
         [] -> [];
         _ -> [{cancel, Armed}]
     end}.

%% @doc uninit, if init ran and uninit has not since: the outputs are secured, and
%% what the task commanded before is not written again after a lost connection.
-spec uninit(engine()) -> {engine(), [effect()]}.
uninit(#engine{initialized = false} = E) -> {E, []};
uninit(E) -> {E#engine{initialized = false, lost = []}, [uninit]}.

%% Into `To', for `Cause': recorded and announced (the effect). A product dropped
%% while paused is remembered only while DOWN.
to(To, Cause, #engine{dropped = Dropped} = E) ->
    {E#engine{dropped = Dropped andalso To =:= down}, {state, To, Cause}}.

%% -------------------------------------------------------------------------------------
%% The controller's commands; Pause, Stop, service mode
%% -------------------------------------------------------------------------------------

%% @doc A command of the controller (`Key', `Value', see
%% {@link cell_task_proc:control/3}) reached a task in `State': the engine's data with
%% the command kept as every member keeps it (the request, the emergency stop, service
%% mode: {@link cell_member:controlled/3}; the settings' snapshot for the next start),
%% and what the engine does now.
%%
%% Seed 000 §2.2: Start takes an OFF task into setup (arrow 0, `start': from_off/3
%% decides) and a paused one back to READY (5, `resume'); Pause, Stop and service mode
%% take a READY task DOWN (6) at a step boundary (`boundary', pause/3), a Start or
%% service mode ending taking back what a transfer was holding back; Stop takes a DOWN
%% task OFF (9, `stop'); the emergency stop secures any task at once (`{secure,
%% Barrier}'; `{secured, Barrier}' for an OFF task, which has nothing to secure). A
%% paused task whose product was dropped meanwhile reconciles instead of going back
%% to where it was, which rested on that product (`reconcile'). An error waiting for
%% the operator is left to the operator's answer; in setup a command is kept for the
%% step boundary after init (`keep').
-spec control(atom(), term(), cell_ipc:state(), engine()) -> {engine(), control_action()}.
control(Key, Value, State, #engine{request = Request, estop = Estop, task = T} = E0) ->
    #{request := Request1, estop := Estop1, service_mode := Service} =
        cell_member:controlled(Key, Value, #{request => Request, estop => Estop,
                                             service_mode => T#task.service_mode}),
    E = E0#engine{request = Request1, estop = Estop1, task = T#task{service_mode = Service}},
    command(Key, Value, State, E).

command(estop, {true, Barrier}, off, E) ->
    {E, {secured, Barrier}};
command(estop, {true, Barrier}, _State, E) ->
    {E, {secure, Barrier}};
command(settings, Settings, _State, E) ->
    {E#engine{settings = Settings}, keep};
command(request, start, off, E) ->
    {E, start};
command(request, start, {ready, _, _}, E) ->
    %% A Start cancels whatever a transfer was still holding back, service mode
    %% included, as Start resumes a task that service mode paused.
    {E#engine{deferred = undefined}, keep};
command(request, _PauseOrStop, {ready, _, _}, E) ->
    {E, boundary};
command(service_mode, true, {ready, _, _}, E) ->
    {E#engine{deferred = service}, boundary};
command(service_mode, false, {ready, _, _}, #engine{deferred = service} = E) ->
    {E#engine{deferred = undefined}, keep};
command(request, stop, down, E) ->
    {E, stop};
command(request, start, down, #engine{down = {paused, _}, dropped = true} = E) ->
    {E, reconcile};
command(request, start, down, #engine{down = {paused, _}} = E) ->
    {E, resume};
command(_Key, _Value, _State, E) ->
    {E, keep}.

%% @doc What a Pause, Stop or service mode asked of a READY task in `State' (the
%% request not Start, or one a transfer held back: `deferred') does, as a transition:
%% at a step boundary or as the request comes (`boundary'), and when the engine tells
%% the answers of the TryAbortOffering it was asked to make (`{withdrawn, Results}',
%% link by link, `true' where the offer was withdrawn).
%%
%% Seed 000 allows stopping only before downstream commits: while a transfer is under
%% way the request is held back (`{go_on, E}', `deferred' naming it: the task goes on,
%% and is asked again at its next boundary), else its open offers are withdrawn first
%% (`{withdraw, Links}'). Then the task pauses (`{pause, Transition}': arrow 6, see
%% leave/3), to offer again at resume what it withdrew; or, if downstream began to
%% take one, that transfer goes on and holds the request back. Nothing asked: `{go_on,
%% E}' as it was.
-spec pause(boundary | {withdrawn, [{atom(), boolean()}]}, cell_ipc:state(), engine()) ->
          {go_on, engine()} | {withdraw, [atom()]} | {pause, {engine(), [effect()]}}.
pause(boundary, _State, #engine{request = start, deferred = undefined} = E) ->
    %% Running, nothing held back: the common case, at every wait.
    {go_on, E};
pause(boundary, State, #engine{request = Request, deferred = Deferred, task = T} = E) ->
    {true, Why} = pause_asked(Request, Deferred),
    case cell_handshake:holding(T) of
        true ->
            {go_on, E#engine{deferred = Why}};
        false ->
            case cell_handshake:active_offers(T) of
                [] -> {pause, leave({pause, Why}, State, E#engine{reoffer = []})};
                Offers -> {withdraw, Offers}
            end
    end;
pause({withdrawn, Results}, State, #engine{request = Request, deferred = Deferred} = E) ->
    %% Told at once, with nothing between: still asked.
    {true, Why} = pause_asked(Request, Deferred),
    case lists:all(fun({_, Ok}) -> Ok end, Results) of
        true -> {pause, leave({pause, Why}, State, E#engine{reoffer = [L || {L, _} <- Results]})};
        false -> {go_on, E#engine{deferred = Why}}
    end.

pause_asked(start, undefined) -> false;
pause_asked(_Request, undefined) -> {true, pause};
pause_asked(_Request, Deferred) -> {true, Deferred}.

%% -------------------------------------------------------------------------------------
%% Steps
%% -------------------------------------------------------------------------------------

%% @doc What a step of `Mod' returned, its waits as a list; anything else is the
%% module's bug.
-spec step_result(module(), term()) ->
          {continue, cell_task:task()} | {wait, [cell_task:wait()], cell_task:task()}
        | {reset, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
step_result(_Mod, {continue, #task{}} = R) -> R;
step_result(_Mod, {wait, Waits, #task{} = T}) when is_list(Waits) -> {wait, Waits, T};
step_result(_Mod, {wait, Wait, #task{} = T}) -> {wait, [Wait], T};
step_result(_Mod, {reset, #task{}} = R) -> R;
step_result(_Mod, {error, _Spec, #task{}} = R) -> R;
step_result(Mod, Other) -> erlang:error({bad_step_result, Mod, Other}).

%% @doc Arrow 5, its connections up: back to the READY sub-state the task left, the
%% offers a pause withdrew made again, the heap collected; then the outputs a lost
%% connection may have lost set again before the task does what it was doing (its
%% step, or its waits armed again: what it waits for may follow what it commanded).
-spec resume(engine()) -> {engine(), [effect()], then()}.
resume(#engine{resume = Ready, reoffer = Offers} = E) ->
    {E1, Enter} = to(Ready, {arrow, 5},
                     E#engine{down = undefined, resume = undefined, reoffer = []}),
    {E1, [headroom, Enter | [{reoffer, Offers} || Offers =/= []]], {reassert, Ready}}.

%% @doc What the task's init came to: `{ok, T}', `{error, Spec, T}' (its own error
%% for the operator), or `{io, Spec}' (it read or wrote a point whose connection is
%% down, or that its device cannot serve). Done, reconcile follows (`{reconcile,
%% undefined}'); otherwise DOWN (arrow 7) with the error. Either way init has run:
%% uninit follows before the next init.
-spec inited({ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}
             | {io, io_spec()}, engine()) -> {engine(), [effect()], then()}.
inited({ok, T}, E) ->
    {E#engine{task = T, initialized = true}, [], {reconcile, undefined}};
inited({error, Spec, T}, E) ->
    {E#engine{task = T, initialized = true}, [], {raise, Spec, init, setup}};
inited({io, Spec}, E) ->
    {E#engine{initialized = true, resume = undefined}, [], {raise, Spec, io, setup}}.

%% @doc What the task's reconcile came to (`{ok, T}', `{error, Spec, T}', `{io,
%% Spec}' as for inited/2), `Woken' being what its first step is told woke it. Agreed,
%% what its predecessor left is settled and the task enters READY (arrow 1, or 5 from
%% DOWN when an init error was ignored): READY-PROCESSING-ACTIVE with a product,
%% READY-IDLE-STARVED without, its first step due; after a crash the log says its
%% record and its sensors agree. Otherwise DOWN with the error, the predecessor kept
%% for the next reconcile.
-spec reconciled({ok | error, _, _} | {io, io_spec()}, term(), engine()) ->
          {engine(), [effect()]} | {engine(), [effect()], then()}.
reconciled({ok, T0}, Woken, #engine{predecessor = Held} = E) ->
    #task{product = P, ipc = From} = T = clean(T0),
    Said = case Held of
               #{cause := crash} ->
                   [{log, notice, "after the crash its record and its sensors agree: it "
                     "goes on (product ~ts)", [serial_text(P)]}];
               _ ->
                   []
           end,
    {Ready, Arrow} = ready(P, From),
    {E1, Enter} = to(Ready, {arrow, Arrow},
                     E#engine{task = T, predecessor = undefined, cause = start,
                              crash_outputs = undefined, pending = {step, Woken},
                              resume = undefined}),
    {E1, Said ++ [headroom, Enter, {next_event, step}]};
reconciled({error, Spec, T}, _Woken, E) ->
    {E#engine{task = clean(T)}, [], {raise, Spec, reconcile, setup}};
reconciled({io, Spec}, _Woken, E) ->
    {E#engine{resume = undefined}, [], {raise, Spec, io, setup}}.

%% @doc What a step returned (step_result/2), other than `continue' (the engine's
%% hot path: the next step runs at once, or behind what came meanwhile): the waits to
%% arm (`{arm, Waits, step}'; the first wait after going on by itself from a crash tells the
%% registry, so that a crash from here on is reconcile's to decide again); the seed's
%% ResetException (uninit, then arrow 2 to init again); an error for the operator
%% (`{raise, Spec, step}', DOWN from where the step left the task, to go back there).
-spec stepped({wait, [cell_task:wait()], cell_task:task()} | {reset, cell_task:task()}
              | {error, cell_alarms:spec(), cell_task:task()}, engine()) ->
          {engine(), [effect()]} | {engine(), [effect()], then()}.
stepped({wait, Waits, T}, E) ->
    E1 = E#engine{task = clean(T), pending = {waits, Waits}},
    case E1 of
        #engine{resumed = true} ->
            {E1#engine{resumed = false}, [{resumed, false}], {arm, Waits, step}};
        #engine{resumed = false} ->
            {E1, [], {arm, Waits, step}}
    end;
stepped({reset, T}, E) ->
    {E1, Uninit} = uninit(E#engine{task = clean(T), cause = reset}),
    {E2, Setup} = to(setup, {arrow, 2}, E1),
    {E2, Uninit ++ [Setup, {next_event, run_init}]};
stepped({error, Spec, #task{ipc = Ipc} = T}, E) ->
    {E#engine{task = clean(T), resume = Ipc}, [], {raise, Spec, step, Ipc}}.

%% @doc The task as its step sees it: what woke it and, if that was the operator, the
%% answer. (A step that follows a continue finds the task as it left it.)
-spec woken_by(term(), cell_task:task()) -> cell_task:task().
woken_by(undefined, #task{woken_by = undefined, answer = undefined} = T) -> T;
woken_by({answer, A} = Woken, T) -> T#task{woken_by = Woken, answer = A};
woken_by(Woken, T) -> T#task{woken_by = Woken, answer = undefined}.

%% @doc The task after its step or reconcile: what woke it is spent.
-spec clean(cell_task:task()) -> cell_task:task().
clean(#task{answer = undefined, woken_by = undefined} = T) -> T;
clean(T) -> T#task{answer = undefined, woken_by = undefined}.

%% -------------------------------------------------------------------------------------
%% Errors and setup
%% -------------------------------------------------------------------------------------

%% @doc What an OFF task does as it boots or is told Start, given the cell's request,
%% whether the emergency stop is active, and whether the task was restarted after a
%% crash: Start leaves OFF for setup (arrow 0), unless the emergency stop is active;
%% a task restarted after a crash while the cell is paused starts too, so that the
%% crash is settled as in a running cell (it then holds at its first step boundary,
%% the request being Pause); otherwise it stays OFF, its product on disk.
-spec from_off(start | pause | stop, boolean(), boolean()) -> estop | start | stay.
from_off(start, true, _Crashed) -> estop;
from_off(start, false, _Crashed) -> start;
from_off(pause, false, true) -> start;
from_off(_Request, _Estop, _Crashed) -> stay.

%% The arrow of seed 000 §2.2 an error takes into DOWN.
-spec down_arrow(setup | cell_ipc:ready()) -> 6 | 7.
down_arrow(setup) -> 7;
down_arrow({ready, _, _}) -> 6.

%% The READY state a task enters after init and reconcile (with a product it
%% processes, without one it is starved), and the arrow: 1 from setup, 5 from DOWN
%% (init's error ignored).
-spec ready(cell_product:product() | undefined, setup | down) -> {cell_ipc:ready(), 1 | 5}.
ready(Product, From) ->
    Ready = case Product of
                undefined -> {ready, idle, starved};
                _ -> {ready, processing, active}
            end,
    {Ready, case From of setup -> 1; down -> 5 end}.

%% @doc What setup does first: the operator's question about a file the task's record
%% cannot be read from (retained data first: nothing runs without them), an
%% interrupted transfer, a crash only the operator can settle; else init. `go_on':
%% the task goes on by itself after a crash (its reconcile decides); `asked': the
%% crash is the operator's question now.
-spec setup(#{retain_error := term(), crash := term(), crash_ask := boolean(),
              load_error := term(), in_transit := boolean()}) ->
          {setup_event(), none | go_on | asked}.
setup(#{retain_error := Why}) when Why =/= undefined ->
    {retain_damaged, none};
setup(#{crash := undefined, load_error := undefined, in_transit := true}) ->
    {in_transit, none};
setup(#{crash := undefined, load_error := undefined}) ->
    {run_init, none};
setup(#{crash := undefined}) ->
    {product_damaged, none};
setup(#{crash := Why, crash_ask := true}) ->
    {{crashed, Why}, asked};
setup(#{load_error := undefined}) ->
    {run_init, go_on};
setup(#{}) ->
    {product_damaged, go_on}.

%% @doc Whether the operator is asked about a crash rather than the task's reconcile,
%% from the crashed task's registry row: it died where reconcile cannot decide (in
%% init or reconcile itself: in setup), or died again after it had gone on by itself
%% from a crash, before its first wait (a fault that restarting does not cure: it
%% would loop).
-spec ask_after_crash(map()) -> boolean().
ask_after_crash(#{crashed_in := setup}) -> true;
ask_after_crash(#{resumed := true}) -> true;
ask_after_crash(#{}) -> false.

%% What the operator's answer to the task's error leads to, by where the error
%% came from. `Request' is the controller's, `Deferred' a pause a transfer held back
%% when the error came, `Resume' the READY state to go back to (`undefined' when the
%% error came in setup).
-spec answer(origin(), cell_alarms:solution(),
             #{request := start | pause | stop, deferred := why() | undefined,
               resume := cell_ipc:ready() | undefined}) -> answer_action().
answer(step, reset, _) -> reinit;
answer(step, Solution, #{request := start}) -> {resume, {step, {answer, Solution}}};
answer(step, Solution, #{deferred := Deferred}) when Deferred =/= undefined ->
    %% The error came while a transfer held a Pause or Stop back: the transfer goes on,
    %% and the request applies once it has ended, as it would have without the error.
    {resume, {step, {answer, Solution}}};
answer(step, Solution, _) -> {paused, {step, {answer, Solution}}};
answer(init, retry, _) -> {setup, run_init};
answer(init, reset, _) -> reinit;
%% Ignore (or Close): go on as if init had succeeded, reconciled first.
answer(init, Solution, _) -> {reconcile, {answer, Solution}};
%% Every answer, Reset too, is the task's to act on: the question was its own.
answer(reconcile, Solution, _) -> {setup, {reconcile, {answer, Solution}}};
answer(crash, reset, _) -> forget_then_reinit;
answer(crash, _Retry, _) -> {setup, run_init};
answer(transit, reset, _) -> {forget, run_init};
answer(transit, _Ignore, _) -> {confirm_here, run_init};
%% Lost while initialising: initialise again; init checks the IO first.
answer(io, _Retry, #{resume := undefined}) -> {setup, run_init};
answer(io, _Retry, #{request := start}) -> resume;
answer(io, _Retry, _) -> paused;
%% A product handed on before came back to the task (its copy dropped again): once the
%% operator has seen to it, the task starts again from what its sensors see.
answer(handed_on, _Reset, _) -> reinit;
answer(product_file, reset, _) -> set_aside_product;
answer(product_file, _Retry, _) -> reload_product;
answer(retain_file, reset, _) -> set_aside_retained;
answer(retain_file, _Retry, _) -> reload_retained.

%% @doc The operator (`Who') answered the task's error with `Solution', the error having
%% come from `Origin' (answer/3 decides what follows): the data as it is after, the
%% effects, and what the engine then goes on with if that takes more than effects
%% (see {@link then()}). Reset after init, reconcile or a step uninitialises and inits
%% again (arrow 8); Retry and Ignore go back to READY (arrow 5) or stay paused if the
%% cell was paused meanwhile; after a crash or an interrupted transfer the product is
%% forgotten or confirmed here, as the operator said, and the log says who did.
-spec answered(origin(), cell_alarms:solution(), binary(), engine()) ->
          {engine(), [effect()]} | {engine(), [effect()], then()}.
answered(Origin, Solution, Who, #engine{request = Request, deferred = Deferred,
                                        resume = Resume, task = #task{product = P}} = E0) ->
    E = E0#engine{down = undefined},
    case answer(Origin, Solution, #{request => Request, deferred => Deferred, resume => Resume}) of
        reinit ->
            reinit(E);
        {resume, Pending} ->
            {E#engine{pending = Pending}, [], resume};
        resume ->
            {E, [], resume};
        {paused, Pending} ->
            {E#engine{down = {paused, pause}, pending = Pending}, []};
        paused ->
            {E#engine{down = {paused, pause}}, []};
        {setup, Event} ->
            again(Event, E);
        {reconcile, Then} ->
            {E, [], {reconcile, Then}};
        forget_then_reinit ->
            {E1, Reinit} = reinit(E),
            {E1, [{log, notice, "~ts chose to forget product ~ts after the crash",
                   [Who, serial_text(P)]}, forget_product | Reinit]};
        {forget, Event} ->
            {E1, Again} = again(Event, E),
            {E1, [{log, notice, "~ts confirmed product ~ts is not here; it is forgotten",
                   [Who, serial_text(P)]}, forget_product | Again]};
        {confirm_here, Event} ->
            {E1, Again} = again(Event, E),
            {E1, [{log, notice, "~ts confirmed product ~ts is here", [Who, serial_text(P)]},
                  keep_product | Again]};
        set_aside_product ->
            {E, [], {product_file, set_aside, Who}};
        reload_product ->
            {E, [], {product_file, reload, Who}};
        set_aside_retained ->
            {E, [], {retain_file, set_aside, Who}};
        reload_retained ->
            {E, [], {retain_file, reload, Who}}
    end.

%% Reset from DOWN: uninit, then arrow 8 to init again, from what the task holds now.
reinit(E) ->
    {E1, Uninit} = uninit(E#engine{cause = reset, predecessor = undefined}),
    {E2, Again} = again(run_init, E1),
    {E2, Uninit ++ Again}.

%% Setup again from DOWN (arrow 8), `Event' first.
again(Event, E) ->
    {E1, Setup} = to(setup, {arrow, 8}, E),
    {E1, [Setup, {next_event, Event}]}.

%% @doc A product's serial as the log and the operator's texts say it.
-spec serial_text(cell_product:product() | undefined) -> unicode:chardata().
serial_text(undefined) -> "none";
serial_text(#{serial := S}) -> S.

%% -------------------------------------------------------------------------------------
%% Boot, start, and the task's IO
%% -------------------------------------------------------------------------------------

%% @doc The task's previous incarnation crashed (`Why'), leaving its outputs as
%% `Outputs'. The crash is recorded; unless the operator is asked (`Ask',
%% ask_after_crash/1) a warning says the task goes on by itself. Its outputs, as it
%% left them, are kept for reconcile, then secured (init ran in that incarnation).
%% Then start/1 decides whether it starts.
-spec crashed(term(), boolean(), #{atom() => map()}, engine()) ->
          {engine(), [effect()], then()}.
crashed(Why, Ask, Outputs, E) ->
    {E1, Uninit} = uninit(E#engine{initialized = true, crash = Why, cause = crash,
                                   crash_ask = Ask, crash_outputs = Outputs}),
    {E1, [{crashed, Why}] ++ [{crash_warning, Why} || not Ask] ++ Uninit, start}.

%% @doc Boot, or Start in OFF (from_off/3): with the emergency stop active it stays
%% OFF and says why; started, setup by arrow 0 with the settings snapshot taken at
%% Start and what setup does first (setup/1); otherwise OFF, its product on disk and a
%% crash of its last incarnation settled when it next starts, as any start settles one.
-spec start(engine()) -> {engine(), [effect()]}.
start(#engine{request = Request, estop = Estop, crash = Crash} = E) ->
    case from_off(Request, Estop, Crash =/= undefined) of
        estop ->
            {E, [{log, warning, "not started: the emergency stop is active", []}]};
        start ->
            #engine{task = T, settings = Settings} = E,
            into_setup({arrow, 0}, E#engine{task = T#task{settings = Settings}});
        stay ->
            {E#engine{crash = undefined, crash_ask = false}, []}
    end.

%% @doc Setup again by arrow 8, a damaged file of the task's record read again or set
%% aside: what setup does first (setup/1), as at any start.
-spec setup_again(engine()) -> {engine(), [effect()]}.
setup_again(E) ->
    into_setup({arrow, 8}, E).

into_setup(Arrow, #engine{task = T} = E) ->
    {Event, E1, Effects} =
        case setup(#{retain_error => E#engine.retain_error, crash => E#engine.crash,
                     crash_ask => E#engine.crash_ask, load_error => E#engine.load_error,
                     in_transit => cell_handshake:in_transit(T)}) of
            {Ev, none} ->
                {Ev, E, []};
            {Ev, asked} ->
                {Ev, E#engine{crash = undefined, crash_ask = false}, []};
            {Ev, go_on} ->
                %% Going on by itself after a crash: the registry remembers it until the
                %% task first waits, so that a crash before then is the operator's to
                %% answer (ask_after_crash/1).
                {Ev, E#engine{crash = undefined, resumed = true}, [{resumed, true}]}
        end,
    {E2, Setup} = to(setup, Arrow, E1),
    {E2, Effects ++ [Setup, {next_event, Event}]}.

%% @doc The task's IO connections as the engine found them (`Found', in the order of
%% its IO groups), before init (`init') or arrow 5 (`resume'). Each status is kept: the
%% task follows its connections from here, and one found down is among those lost
%% since init (reasserted/3). Before init every group must be configured and its
%% connection up, or setup raises the first that is not (arrow 7); all up, init runs.
%% At arrow 5 all must be up, or the task stays DOWN with the first that is not as its
%% error; all up, resume/1.
-spec checked(init | resume, [found()], engine()) -> {engine(), [effect()], then()}.
checked(For, Found, E0) ->
    E = lists:foldl(fun({conn, Conn, Status}, Ex) when Status =/= unsubscribed ->
                            conn_status(Conn, Status, Ex);
                       (_, Ex) ->
                            Ex
                    end, E0, Found),
    case {For, [F || F <- Found, not is_up(F)]} of
        {init, []} ->
            {E, [], init};
        {init, [{group, Group, unconfigured} | _]} ->
            {E#engine{resume = undefined}, [], {raise, {io_config, Group}, io, setup}};
        {init, [{conn, Conn, _} | _]} ->
            {E#engine{resume = undefined}, [], {raise, {io, Conn}, io, setup}};
        {resume, []} ->
            resume(E);
        {resume, [{conn, Conn, _} | _]} ->
            {E, [], {down_again, {io, Conn}}}
    end.

is_up({conn, _, up}) -> true;
is_up(_) -> false.

%% @doc A connection of the task's IO is `up' or `down' (the HAL's news, or the task's
%% own look): kept; one down is among those lost since init (reasserted/3).
-spec conn_status(atom(), up | down, engine()) -> engine().
conn_status(Conn, Status, #engine{conns = Conns, lost = Lost} = E) ->
    E1 = E#engine{conns = Conns#{Conn => Status}},
    case Status of
        down -> E1#engine{lost = lists:usort([Conn | Lost])};
        up -> E1
    end.

%% @doc A request of the task in `State' found the connection `Conn' of its IO lost
%% (down, or its HAL process restarting), or the HAL said it went down: DOWN with the
%% error naming the connection (nothing the task reads from there can be trusted);
%% Retry takes it back to `State' once the connection is up.
-spec io_lost(atom(), cell_ipc:ready(), engine()) -> {engine(), [effect()], then()}.
io_lost(Conn, State, E) ->
    {(conn_status(Conn, down, E))#engine{resume = State}, [], {raise, {io, Conn}, io, State}}.

%% @doc The point `Point' of the IO group `Group' cannot be served by its device
%% (`Why': a PLC refusing its address, a variable renamed), the connection itself up:
%% DOWN with the error naming it; Retry takes the task back to `State'.
-spec unavailable(atom(), atom(), term(), cell_ipc:ready(), engine()) ->
          {engine(), [effect()], then()}.
unavailable(Group, Point, Why, State, E) ->
    {E#engine{resume = State}, [], {raise, {point, Group, Point, Why}, io, State}}.

%% @doc The waits of the task armed (`{ok, Armed}'), or one could not be
%% (`{io_lost, Conn, Armed}': its connection lost; `Armed', those armed before it, are
%% left by the error). After a step, pause/3 has its say at the boundary; at arrow 5
%% the task waits where it was. A wait that could not be armed takes the task DOWN
%% (io_lost/3); the step's work stands, and its waits are armed again after Retry.
-spec armed({ok, [armed()]} | {io_lost, atom(), [armed()]}, step | resume, engine()) ->
          {engine(), [effect()]} | {engine(), [effect()], then()}.
armed({ok, Armed}, step, E) ->
    {E#engine{armed = Armed}, [], boundary};
armed({ok, Armed}, resume, E) ->
    {E#engine{armed = Armed}, []};
armed({io_lost, Conn, Armed}, _After, #engine{task = #task{ipc = State}} = E) ->
    io_lost(Conn, State, E#engine{armed = Armed}).

%% @doc Arrow 5 in `Ready' went on to set again the outputs a lost connection may have
%% lost (resume/1): `{written, Writes}' (none, if the device held them all), or a
%% write found the connection lost again, or its point unavailable. Written, the log
%% says which and the task does what it was doing: its step, or its waits armed
%% again.
-spec reasserted({written, [{atom(), atom(), term()}]} | {io_lost, atom()}
                 | {unavailable, atom(), atom(), term()}, cell_ipc:ready(), engine()) ->
          {engine(), [effect()]} | {engine(), [effect()], then()}.
reasserted({written, Writes}, _Ready, #engine{lost = Lost, pending = Pending} = E) ->
    Said = [{log, notice, "connection ~ts back: outputs set again as the task last "
             "commanded them: ~ts", [lists:join(", ", [atom_to_list(C) || C <- Lost]),
                                     cell_task_outputs:text(Writes)]} || Writes =/= []],
    E1 = E#engine{lost = []},
    case Pending of
        {waits, Waits} -> {E1, Said, {arm, Waits, resume}};
        {step, _} -> {E1, Said ++ [{next_event, step}]}
    end;
reasserted({io_lost, Conn}, Ready, E) ->
    io_lost(Conn, Ready, E);
reasserted({unavailable, Group, Point, Why}, Ready, E) ->
    unavailable(Group, Point, Why, Ready, E).

%% -------------------------------------------------------------------------------------
%% Transfers
%% -------------------------------------------------------------------------------------

%% Which armed wait the news of a link ends (`Wakes', from cell_handshake:handle/2),
%% and what the step is told woke it; `undefined' if none. `Signal' gives a link's
%% signal as the task sees it now.
-spec woken([{wake, atom(), term()}], [armed()],
            fun((atom(), available | not_busy) -> boolean())) -> term() | undefined.
woken([], _Armed, _Signal) ->
    undefined;
woken([{wake, Link, {watch, Ref, Signal, Value}} | Rest], Armed, Sig) ->
    case [A || {handshake, R, _, _, _} = A <- Armed, R =:= Ref] of
        [_ | _] -> {handshake, Link, Signal, Value};
        [] -> woken(Rest, Armed, Sig)
    end;
woken([{wake, Link, {signals, _Seq}} | Rest], Armed, Sig) ->
    %% The link's signals changed: a wait on one of them that holds now ends.
    case [{S, V} || {handshake, _, L, S, V} <- Armed, L =:= Link, Sig(Link, S) =:= V] of
        [{Signal, Value} | _] -> {handshake, Link, Signal, Value};
        [] -> woken(Rest, Armed, Sig)
    end;
woken([{wake, Link, Outcome} | Rest], Armed, Sig) ->
    case [A || {handshake, _, L, _, _} = A <- Armed, L =:= Link]
        ++ [A || {timer, _, {link_down, L}} = A <- Armed, L =:= Link] of
        [_ | _] -> {handshake, Link, Outcome};
        [] -> woken(Rest, Armed, Sig)
    end.

%% @doc What a message that may end one of a READY task's waits means, given what it
%% armed (`Armed'): a timer that elapsed (one armed while a link was down is that
%% link's transfer interrupted), a watched point that took its value, a point
%% waited for that the device cannot serve, an answer waited for. A timer, a watch or
%% an answer of a wait the task has since left is nothing (`none'; an answer the task
%% never waited for is `late').
-spec wait_news(term(), [armed()]) -> news().
wait_news({timeout, TRef, _}, Armed) ->
    case lists:keyfind(TRef, 2, Armed) of
        {timer, TRef, {link_down, Link}} -> {wake, {handshake, Link, interrupted}};
        {timer, TRef, Ms} -> {wake, {timer, Ms}};
        _ -> none
    end;
wait_news({cell_hal_watch, Ref, Value}, Armed) ->
    case lists:keyfind(Ref, 2, Armed) of
        {io, Ref, Group, Point} -> {wake, {io, Group, Point, Value}};
        _ -> none
    end;
wait_news({cell_hal_unavailable, Ref, Why}, Armed) ->
    case lists:keyfind(Ref, 2, Armed) of
        {io, Ref, Group, Point} -> {unavailable, Group, Point, Why};
        _ -> none
    end;
wait_news({Ref, Term}, Armed) when is_reference(Ref) ->
    case lists:member({reply, Ref}, Armed) of
        true -> {wake, {reply, Ref, Term}};
        false -> late
    end.

%% Paused (or stopped), a transfer on a link the task will wait on again has
%% ended: at resume its step runs and sees that, instead of waiting for something the
%% link can no longer send.
-spec ended_while_down([{wake, atom(), term()}], term()) -> term().
ended_while_down([], Pending) ->
    Pending;
ended_while_down([{wake, Link, Outcome} | Rest], {waits, Waits} = Pending) when is_atom(Outcome) ->
    case [W || {handshake, L, _, _} = W <- Waits, L =:= Link] of
        [_ | _] -> {step, {handshake, Link, Outcome}};
        [] -> ended_while_down(Rest, Pending)
    end;
ended_while_down([_ | Rest], Pending) ->
    ended_while_down(Rest, Pending).

%% Seed 000 §2.3.4 and §2.3.6: upstream seeing NotBusy is unblocked; downstream
%% seeing Available is unstarved.
-spec wake_event(term(), cell_ipc:state()) -> unblocked | unstarved | none.
wake_event({handshake, _Link, not_busy, true}, {ready, idle, blocked}) -> unblocked;
wake_event({handshake, _Link, available, true}, {ready, idle, starved}) -> unstarved;
wake_event(_Woken, _State) -> none.

%% @doc Seed 000 §2.3.4: a READY downstream task that waits for an offer while none
%% stands is starved.
-spec starves(available | not_busy, term(), boolean(), cell_ipc:state()) -> boolean().
starves(available, true, false, {ready, _, _} = S) -> S =/= {ready, idle, starved};
starves(_Signal, _Value, _Available, _State) -> false.

%% @doc Another task holding the product `Serial' (of generation `Gen' here) in a newer
%% record, from the registry's holders of the serial: this task's copy is then stale.
-spec newer_holder(atom(), non_neg_integer(), [{atom(), non_neg_integer()}]) ->
          {ok, atom()} | none.
newer_holder(Id, Gen, Holders) ->
    case [Other || {Other, G2} <- Holders, Other =/= Id, G2 > Gen] of
        [] -> none;
        [Other | _] -> {ok, Other}
    end.

%% What a task does once the registry found its copy of a product old (another
%% task took the product on in a newer record) and the copy was dropped (`Dropped':
%% it held it until now). READY, it reconciles again, for what it does rests on a
%% product it no longer holds; unless it dropped the same serial before (`Again': read
%% again on a part its sensors see), when the operator is asked rather than going
%% round for ever. Paused, it reconciles when started. Otherwise (OFF, setup, an error
%% waiting for the operator, nothing dropped) the copy is simply gone.
-spec stale_copy(cell_ipc:state(), boolean(), boolean(), paused | error | undefined) ->
          reconcile | ask | reconcile_at_start | keep.
stale_copy({ready, _, _}, true, false, _Down) -> reconcile;
stale_copy({ready, _, _}, true, true, _Down) -> ask;
stale_copy(down, true, _Again, paused) -> reconcile_at_start;
stale_copy(_State, _Dropped, _Again, _Down) -> keep.

%% -------------------------------------------------------------------------------------
%% The task's handshake fields
%% -------------------------------------------------------------------------------------

%% @doc The task's views of its handshake links.
-spec links(cell_task:task()) -> #{atom() => map()}.
links(#task{links = L}) -> L.

%% @doc The task with new views of its links.
-spec set_links(cell_task:task(), #{atom() => map()}) -> cell_task:task().
set_links(T, L) when is_map(L) -> T#task{links = L}.

%% @doc The generation of the task's product's record (see cell_product).
-spec gen(cell_task:task()) -> non_neg_integer().
gen(#task{gen = G}) -> G.

%% @doc The product's in-transit mark, if a transfer moves it.
-spec marker(cell_task:task()) -> cell_product:marker().
marker(#task{marker = M}) -> M.

%% @doc The task's product file.
-spec product_path(cell_task:task()) -> binary().
product_path(#task{product_path = P}) -> P.

%% @doc The task's product file, as kept open for its writes.
-spec product_file(cell_task:task()) -> cell_file:record_file().
product_file(#task{product_file = F}) -> F.

%% @doc The task holds `Product' (of generation `Gen', with `Marker') in memory only:
%% its file is written by whoever owns the product on disk (a transfer's rules).
-spec take(cell_task:task(), cell_product:product() | undefined, non_neg_integer(),
           cell_product:marker()) -> cell_task:task().
take(T, Product, Gen, Marker) ->
    T#task{product = Product, gen = Gen, marker = Marker}.

%% @doc The product has left the task (released downstream): it holds none, and its
%% serial is no longer the one it traced.
-spec released(cell_task:task()) -> cell_task:task().
released(T) ->
    T#task{product = undefined, gen = 0, marker = undefined, traced = undefined}.

%% @doc The wait before a task looks again at a link that is down, after the one it
%% waited last (`undefined': the first look): 50 ms, doubling up to 1 s. A link that
%% restarts is back within the first few; a neighbour's node out of reach for minutes
%% is asked once a second, not twenty times. The link's greeting when it is back ends
%% the wait at once, whatever is left of it.
-spec link_retry_ms(pos_integer() | undefined) -> pos_integer().
link_retry_ms(undefined) -> ?LINK_RETRY_MIN_MS;
link_retry_ms(Last) -> min(2 * Last, ?LINK_RETRY_MAX_MS).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% Seed 000 §2.2, arrow 6, and §2.3.6: Pause, Stop and service mode are honoured at a
%% step boundary, only before downstream commits, an open offer withdrawn first.
pause_test_() ->
    Ready = {ready, processing, active},
    E = fun(Request, Deferred, Links) ->
                #engine{request = Request, deferred = Deferred, task = #task{links = Links}}
        end,
    Offering = #{out => #{role => up, phase => offered}},
    Link = fun(Role, Phase) -> #{l => #{role => Role, phase => Phase}} end,
    Two = #{a => #{role => up, phase => offered}, b => #{role => up, phase => offered}},
    %% What the pause leaves the engine's data as: why it is DOWN, what it offers again
    %% at resume, what it goes back to.
    Paused = fun({pause, {#engine{down = Down, reoffer = Re, resume = Res, deferred = De},
                          Effects}}) ->
                     {Down, Re, Res, De, Effects}
             end,
    Deferred = fun({go_on, #engine{deferred = D}}) -> D end,
    Fx = [{state, down, {arrow, 6}}],
    [%% Running, nothing asked.
     ?_assertEqual({go_on, E(start, undefined, #{})},
                   pause(boundary, Ready, E(start, undefined, #{}))),
     %% Nothing under way: at once; for Stop, on to OFF.
     ?_assertEqual({{paused, pause}, [], Ready, undefined, Fx},
                   Paused(pause(boundary, Ready, E(pause, undefined, #{})))),
     ?_assertEqual({{paused, pause}, [], Ready, undefined, Fx ++ [{next_event, stop}]},
                   Paused(pause(boundary, Ready, E(stop, undefined, #{})))),
     %% Service mode, held back before, is still asked after a Start.
     ?_assertEqual({{paused, service}, [], Ready, undefined, Fx},
                   Paused(pause(boundary, Ready, E(start, service, #{})))),
     %% A transfer past the commit, either side: held back, asked again next time.
     [?_assertEqual(pause, Deferred(pause(boundary, Ready, E(pause, undefined, Link(Role, Phase)))))
      || {Role, Phase} <- [{up, committed}, {up, released}, {up, aborting},
                           {down, committed}, {down, released}]],
     ?_assertEqual(service,
                   Deferred(pause(boundary, Ready, E(start, service, Link(down, committed))))),
     %% Downstream taking an offer before its commit does not hold the task.
     ?_assertMatch({{paused, pause}, [], _, _, _},
                   Paused(pause(boundary, Ready, E(stop, undefined, Link(down, offered))))),
     %% An open offer: withdrawn first (TryAbortOffering) ...
     ?_assertEqual({withdraw, [out]}, pause(boundary, Ready, E(pause, undefined, Offering))),
     ?_assertEqual({withdraw, [a, b]}, pause(boundary, Ready, E(stop, undefined, Two))),
     %% ... then paused, to offer again at resume; held back if downstream committed.
     ?_assertEqual({{paused, pause}, [a, b], Ready, undefined, Fx},
                   Paused(pause({withdrawn, [{a, true}, {b, true}]}, Ready,
                                E(pause, undefined, Two)))),
     ?_assertEqual({{paused, service}, [a], Ready, undefined, Fx},
                   Paused(pause({withdrawn, [{a, true}]}, Ready, E(start, service, Two)))),
     ?_assertEqual(pause, Deferred(pause({withdrawn, [{a, true}, {b, false}]}, Ready,
                                         E(stop, undefined, Two)))),
     %% The answers come with nothing between: a request gone meanwhile is a bug.
     ?_assertError({badmatch, false},
                   pause({withdrawn, [{a, true}]}, Ready, E(start, undefined, Two)))].

%% Seed 000 §2.2 and §2.3.1: leaving what the task was doing. The emergency stop
%% secures at once, from any state; Stop leaves DOWN for OFF (arrow 9); Pause and
%% errors take READY or setup DOWN (arrows 6, 7); uninit runs only after init.
leave_test_() ->
    Ready = {ready, processing, active},
    R = make_ref(), W = make_ref(),
    Armed = [{timer, R, 500}, {io, W, io, part}],
    Barrier = {b, 1, 2, self()},
    E = #engine{task = #task{ipc = Ready}, initialized = true, armed = Armed, gen = 3,
                pending = {waits, [{timer, 500}]}, resume = undefined, request = start},
    Error = E#engine{down = {error, <<"a1">>, step}, resume = Ready, armed = []},
    Paused = E#engine{down = {paused, pause}, resume = Ready, armed = [], dropped = true,
                      reoffer = [out], request = stop},
    Cleared = fun(#engine{down = D, pending = P, resume = Re, deferred = De, reoffer = Ro}) ->
                      {D, P, Re, De, Ro} =:= {undefined, undefined, undefined, undefined, []}
              end,
    {Secured, SecureFx} = leave({secure, Barrier}, Ready, E),
    {Estopped, EstopFx} = leave(estop, Ready, E),
    {Off, OffFx} = leave(off, Ready, Secured),
    {Stopped, StopFx} = leave(stop, down, Error),
    {PausedE, PauseFx} = leave({pause, service}, Ready, E#engine{deferred = service}),
    {_, PauseStopFx} = leave({pause, pause}, Ready, E#engine{request = stop}),
    {Raised, RaiseFx} = leave({error, <<"a2">>, step}, Ready, E#engine{dropped = true}),
    {_, InitErrorFx} = leave({error, <<"a3">>, init}, setup, E#engine{armed = []}),
    {Dropped, DroppedFx} = leave({setup, dropped}, Ready, E#engine{reoffer = [out]}),
    {Forgot, ForgotFx} = leave(forget, Ready, E),
    {_, ForgotDownFx} = leave(forget, down, Error),
    [%% The controller's emergency stop: outputs secured at once, transfers ended, the
     %% barrier's slot marked; the waits and OFF wait for the barrier.
     ?_assertEqual([interrupt_links, uninit, {estop_secured, Barrier}], SecureFx),
     ?_assertEqual({b, Armed, false}, {Secured#engine.held, Secured#engine.armed,
                                        Secured#engine.initialized}),
     ?_assert(Cleared(Secured)),
     ?_assertEqual([{cancel, Armed}, {state, off, estop}], OffFx),
     ?_assertEqual({undefined, [], 4}, {Off#engine.held, Off#engine.armed, Off#engine.gen}),
     %% The flag seen before a step: the same, at once.
     ?_assertEqual([interrupt_links, uninit, {cancel, Armed}, {state, off, estop}], EstopFx),
     ?_assert(Cleared(Estopped)),
     %% An error the operator had to answer is withdrawn: nobody answers it now.
     ?_assertMatch({_, [{withdraw_alarm, <<"a1">>}, interrupt_links, uninit,
                        {estop_secured, Barrier}]}, leave({secure, Barrier}, down, Error)),
     %% uninit only after init: an OFF task, or one whose init has not run, secures
     %% nothing of its own.
     ?_assertEqual([interrupt_links, {estop_secured, Barrier}],
                   element(2, leave({secure, Barrier}, setup, #engine{}))),
     ?_assertEqual([interrupt_links, {state, off, estop}],
                   element(2, leave(estop, setup, #engine{}))),
     %% Arrow 9: Stop while DOWN, the error withdrawn, the outputs secured.
     ?_assertEqual([{withdraw_alarm, <<"a1">>}, interrupt_links, uninit,
                    {state, off, {arrow, 9}}], StopFx),
     ?_assert(Cleared(Stopped)),
     ?_assertEqual([{cancel, Armed}, interrupt_links, uninit, {state, off, {arrow, 9}}],
                   element(2, leave(stop, down, Paused#engine{armed = Armed}))),
     %% Arrow 6 for Pause or service mode: DOWN, back to where it was at Start; for Stop,
     %% on to OFF.
     ?_assertEqual([{cancel, Armed}, {state, down, {arrow, 6}}], PauseFx),
     ?_assertEqual({{paused, service}, Ready, undefined, undefined},
                   {PausedE#engine.down, PausedE#engine.resume, PausedE#engine.deferred,
                    PausedE#engine.held}),
     ?_assertEqual([{cancel, Armed}, {state, down, {arrow, 6}}, {next_event, stop}],
                   PauseStopFx),
     %% Errors: arrow 6 from READY, 7 from setup; a product dropped while paused is
     %% still remembered while DOWN.
     ?_assertEqual([{cancel, Armed}, {state, down, {arrow, 6}}], RaiseFx),
     ?_assertEqual({{error, <<"a2">>, step}, true}, {Raised#engine.down, Raised#engine.dropped}),
     ?_assertEqual([{state, down, {arrow, 7}}], InitErrorFx),
     %% Back towards setup for a copy dropped as old: nothing to resume, no offer to make
     %% again, the transfers ended; the state is the caller's.
     ?_assertEqual([{cancel, Armed}, interrupt_links], DroppedFx),
     ?_assert(Cleared(Dropped)),
     ?_assertEqual({dropped, undefined, true},
                   {Dropped#engine.cause, Dropped#engine.predecessor, Dropped#engine.initialized}),
     %% The product not here: a Reset that forgets it (arrow 2 from READY, 8 from DOWN).
     ?_assertEqual([{cancel, Armed}, interrupt_links, uninit, forget_product,
                    {state, setup, {arrow, 2}}, {next_event, run_init}], ForgotFx),
     ?_assertEqual({reset, false}, {Forgot#engine.cause, Forgot#engine.initialized}),
     ?_assertEqual([{withdraw_alarm, <<"a1">>}, interrupt_links, uninit, forget_product,
                    {state, setup, {arrow, 8}}, {next_event, run_init}], ForgotDownFx),
     %% OFF: forgotten, nothing else; it starts without it.
     ?_assertEqual({E, [forget_product]}, leave(forget, off, E)),
     %% The dropped product is forgotten once the task leaves DOWN.
     ?_assertEqual({true, false},
                   {(element(1, to(down, {arrow, 6}, Paused)))#engine.dropped,
                    (element(1, to(setup, {arrow, 8}, Paused)))#engine.dropped}),
     ?_assertEqual({E#engine{initialized = false, lost = []}, [uninit]},
                   uninit(E#engine{lost = [c]})),
     ?_assertEqual({#engine{}, []}, uninit(#engine{})),
     ?_assertEqual({#engine{gen = 1}, []}, disarm(#engine{}))].

%% Seed 000 §2.3.4 and §2.3.6: a wait on a link ends with the event the seed raises
%% there; a transfer that ended while the task was DOWN is seen by its step at resume.
link_news_test_() ->
    R = make_ref(), TRef = make_ref(),
    Starved = {ready, idle, starved},
    Armed = [{handshake, R, in, available, true}, {timer, TRef, 500}],
    E = #engine{task = #task{ipc = Starved}, armed = Armed, gen = 3, request = start,
                pending = {waits, [{handshake, in, available, true}, {timer, 500}]}},
    Offer = [{wake, in, {watch, R, available, true}}],
    {wake, {Woken, WokenFx}} = link_news(Offer, Starved, E),
    Down = E#engine{armed = [], down = {paused, pause}},
    [?_assertEqual([{cancel, Armed}, {ipc_event, unstarved}, {next_event, step}], WokenFx),
     ?_assertEqual({{step, {handshake, in, available, true}}, [], 4},
                   {Woken#engine.pending, Woken#engine.armed, Woken#engine.gen}),
     %% Not starved any more by then: no event, the step runs.
     ?_assertMatch({wake, {_, [{cancel, _}, {next_event, step}]}},
                   link_news(Offer, {ready, processing, active}, E)),
     %% News of no armed wait: the task goes on, or pauses if a Pause was held back.
     ?_assertEqual({go_on, E}, link_news([{wake, out, completed}], Starved, E)),
     ?_assertMatch({pause, {#engine{down = {paused, pause}}, _}},
                   link_news([{wake, out, completed}], Starved,
                             E#engine{request = pause, deferred = pause})),
     %% Paused: the step runs at resume, told the transfer was interrupted.
     ?_assertEqual({go_on, Down#engine{pending = {step, {handshake, in, interrupted}}}},
                   link_news([{wake, in, interrupted}], down, Down)),
     ?_assertEqual({go_on, Down}, link_news([{wake, in, {signals, 4}}], down, Down)),
     %% A wait that is no handshake's raises nothing.
     ?_assertEqual([{cancel, Armed}, {next_event, step}],
                   element(2, wake({timer, 500}, {ready, idle, blocked}, E))),
     ?_assertEqual([{ipc_event, unblocked}, {next_event, step}],
                   element(2, wake({handshake, out, not_busy, true}, {ready, idle, blocked},
                                   E#engine{armed = []})))].

%% A copy found old: READY, the task reconciles again (arrow 2); the same serial
%% dropped again is the operator's; paused, it reconciles when started.
stale_test_() ->
    Ready = {ready, processing, active},
    E = #engine{task = #task{ipc = Ready}, initialized = true, gen = 2,
                pending = {step, undefined}},
    {Again, AgainFx} = stale(<<"S1">>, true, Ready, E),
    [?_assertEqual([interrupt_links, predecessor, {state, setup, {arrow, 2}},
                    {next_event, {reconcile, undefined}}], AgainFx),
     ?_assertEqual({<<"S1">>, dropped, undefined, true},
                   {Again#engine.handed_on, Again#engine.cause, Again#engine.pending,
                    Again#engine.initialized}),
     ?_assertMatch({ask, {#engine{cause = dropped}, [interrupt_links]}},
                   stale(<<"S1">>, true, Ready, E#engine{handed_on = <<"S1">>})),
     ?_assertEqual({E#engine{down = {paused, pause}, dropped = true}, []},
                   stale(<<"S1">>, true, down, E#engine{down = {paused, pause}})),
     %% An error waiting for the operator: the answer is acted on without the copy.
     ?_assertEqual({E#engine{down = {error, <<"a">>, step}}, []},
                   stale(<<"S1">>, true, down, E#engine{down = {error, <<"a">>, step}})),
     ?_assertEqual({E, []}, stale(<<"S1">>, false, Ready, E)),
     %% Paused, started: the same, from DOWN (arrow 8).
     ?_assertMatch({_, [interrupt_links, predecessor, {state, setup, {arrow, 8}}, _]},
                   leave({reconcile, 8}, down, E#engine{down = {paused, pause}}))].

%% Seed 000 §2.2: which command acts in which state. Arrow 0 (OFF, Start → setup),
%% 5 (DOWN, Start while paused → READY), 6 (READY, Pause → DOWN, at a step boundary),
%% 9 (DOWN, Stop → OFF); the emergency stop in every state; service mode as a pause.
control_test_() ->
    Ready = [{ready, idle, starved}, {ready, idle, blocked}, {ready, processing, active},
             {ready, processing, executing}],
    All = [off, setup, down | Ready],
    F = #engine{task = #task{}, request = start},
    Paused = F#engine{down = {paused, pause}},
    Error = F#engine{down = {error, <<"a1">>, step}},
    Act = fun(K, V, S, E) -> element(2, control(K, V, S, E)) end,
    Kept = fun(K, V, S, E) ->
                   #engine{request = Rq, estop = Es, deferred = De, settings = Se,
                           task = #task{service_mode = Sm}} = element(1, control(K, V, S, E)),
                   #{request => Rq, estop => Es, deferred => De, settings => Se, service => Sm}
           end,
    [%% Arrow 0.
     ?_assertEqual(start, Act(request, start, off, F)),
     %% Arrow 6: asked at once, honoured at the boundary (pause/3), whatever a
     %% transfer already holds back kept.
     [?_assertEqual(boundary, Act(request, R, S, F)) || R <- [pause, stop], S <- Ready],
     ?_assertMatch(#{request := stop, deferred := service},
                   Kept(request, stop, hd(Ready), F#engine{deferred = service})),
     [?_assertEqual(boundary, Act(service_mode, true, S, F)) || S <- Ready],
     ?_assertMatch(#{service := true, deferred := service}, Kept(service_mode, true, hd(Ready), F)),
     %% Start, or service mode ending, takes back what a transfer held back.
     [?_assertMatch(#{deferred := undefined},
                    Kept(request, start, S, F#engine{deferred = D, request = pause}))
      || S <- Ready, D <- [pause, service]],
     ?_assertEqual(keep, Act(request, start, hd(Ready), F#engine{deferred = pause})),
     ?_assertMatch(#{deferred := undefined, service := false},
                   Kept(service_mode, false, hd(Ready), F#engine{deferred = service})),
     ?_assertMatch(#{deferred := pause},
                   Kept(service_mode, false, hd(Ready), F#engine{deferred = pause})),
     %% Arrow 5, or reconcile again when the product was dropped meanwhile.
     ?_assertEqual(resume, Act(request, start, down, Paused)),
     ?_assertEqual(reconcile, Act(request, start, down, Paused#engine{dropped = true})),
     %% An error waits for the operator's answer, not for Start.
     ?_assertEqual(keep, Act(request, start, down, Error)),
     %% Arrow 9, paused or in error.
     ?_assertEqual(stop, Act(request, stop, down, Paused)),
     ?_assertEqual(stop, Act(request, stop, down, Error)),
     %% Kept, for the state that acts on them: Pause and Stop when OFF, in setup
     %% (honoured at the boundary after init) or paused; service mode outside READY.
     [?_assertEqual(keep, Act(request, R, S, F)) || R <- [pause, stop], S <- [off, setup]],
     [?_assertMatch(#{request := R}, Kept(request, R, S, F))
      || R <- [pause, stop], S <- [off, setup]],
     ?_assertEqual(keep, Act(request, pause, down, Paused)),
     ?_assertEqual(keep, Act(request, start, setup, F)),
     [?_assertEqual(keep, Act(service_mode, On, S, F))
      || On <- [true, false], S <- [off, setup, down]],
     [?_assertMatch(#{service := On}, Kept(service_mode, On, S, F))
      || On <- [true, false], S <- [off, setup, down]],
     %% The emergency stop: secured at once wherever the task is; OFF has nothing to
     %% secure. It is a Stop too. Its release is kept (Start is needed to leave OFF).
     ?_assertEqual({secured, b}, Act(estop, {true, b}, off, F)),
     [?_assertEqual({secure, b}, Act(estop, {true, b}, S, F)) || S <- All -- [off]],
     [?_assertMatch(#{estop := true, request := stop}, Kept(estop, {true, b}, S, F)) || S <- All],
     [?_assertEqual(keep, Act(estop, false, S, F#engine{estop = true})) || S <- All],
     [?_assertMatch(#{estop := false}, Kept(estop, false, S, F#engine{estop = true})) || S <- All],
     %% The settings: a snapshot for the next start, in any state.
     [?_assertMatch({keep, #{settings := #{a := 1}}},
                    {Act(settings, #{a => 1}, S, F), Kept(settings, #{a => 1}, S, F)})
      || S <- All],
     [?_assertEqual({F, keep}, control(estop_settled, b, S, F)) || S <- All]].

step_result_test_() ->
    T = #task{},
    [?_assertEqual({continue, T}, step_result(m, {continue, T})),
     ?_assertEqual({wait, [{timer, 5}], T}, step_result(m, {wait, {timer, 5}, T})),
     ?_assertEqual({wait, [{timer, 5}, {reply, r}], T},
                   step_result(m, {wait, [{timer, 5}, {reply, r}], T})),
     ?_assertEqual({reset, T}, step_result(m, {reset, T})),
     ?_assertEqual({error, #{}, T}, step_result(m, {error, #{}, T})),
     ?_assertError({bad_step_result, m, ok}, step_result(m, ok)),
     ?_assertError({bad_step_result, m, {continue, x}}, step_result(m, {continue, x}))].

%% Seed 000 §2.2 arrow 0: Start takes an OFF task into setup; the emergency stop
%% keeps it OFF.
from_off_test_() ->
    [?_assertEqual(start, from_off(start, false, false)),
     ?_assertEqual(start, from_off(start, false, true)),
     ?_assertEqual(estop, from_off(start, true, false)),
     ?_assertEqual(estop, from_off(start, true, true)),
     ?_assertEqual(start, from_off(pause, false, true)),
     ?_assertEqual(stay, from_off(pause, false, false)),
     ?_assertEqual(stay, from_off(pause, true, true)),
     ?_assertEqual(stay, from_off(stop, false, true)),
     ?_assertEqual(stay, from_off(stop, false, false))].

arrows_test_() ->
    [?_assertEqual(7, down_arrow(setup)),
     ?_assertEqual(6, down_arrow({ready, idle, starved})),
     ?_assertEqual({{ready, idle, starved}, 1}, ready(undefined, setup)),
     ?_assertEqual({{ready, processing, active}, 5}, ready(#{serial => <<"S">>}, down))].

setup_test_() ->
    Base = #{retain_error => undefined, crash => undefined, crash_ask => false,
             load_error => undefined, in_transit => false},
    [?_assertEqual({run_init, none}, setup(Base)),
     ?_assertEqual({retain_damaged, none}, setup(Base#{retain_error := bad, crash := c})),
     ?_assertEqual({in_transit, none}, setup(Base#{in_transit := true})),
     ?_assertEqual({product_damaged, none}, setup(Base#{load_error := bad, in_transit := true})),
     ?_assertEqual({{crashed, c}, asked}, setup(Base#{crash := c, crash_ask := true})),
     %% After a crash the task's reconcile decides, an in-transit mark included.
     ?_assertEqual({run_init, go_on}, setup(Base#{crash := c, in_transit := true})),
     ?_assertEqual({product_damaged, go_on}, setup(Base#{crash := c, load_error := bad}))].

answer_test_() ->
    Running = #{request => start, deferred => undefined, resume => {ready, idle, starved}},
    Paused = Running#{request := pause},
    [?_assertEqual(reinit, answer(step, reset, Running)),
     ?_assertEqual({resume, {step, {answer, retry}}}, answer(step, retry, Running)),
     ?_assertEqual({resume, {step, {answer, ignore}}},
                   answer(step, ignore, Paused#{deferred := pause})),
     ?_assertEqual({paused, {step, {answer, retry}}}, answer(step, retry, Paused)),
     ?_assertEqual({setup, run_init}, answer(init, retry, Running)),
     ?_assertEqual(reinit, answer(init, reset, Running)),
     ?_assertEqual({reconcile, {answer, ignore}}, answer(init, ignore, Running)),
     ?_assertEqual({setup, {reconcile, {answer, reset}}}, answer(reconcile, reset, Running)),
     ?_assertEqual(forget_then_reinit, answer(crash, reset, Running)),
     ?_assertEqual({setup, run_init}, answer(crash, retry, Paused)),
     ?_assertEqual({forget, run_init}, answer(transit, reset, Running)),
     ?_assertEqual({confirm_here, run_init}, answer(transit, ignore, Running)),
     ?_assertEqual({setup, run_init}, answer(io, retry, Running#{resume := undefined})),
     ?_assertEqual(resume, answer(io, retry, Running)),
     ?_assertEqual(paused, answer(io, retry, Paused)),
     ?_assertEqual(set_aside_product, answer(product_file, reset, Running)),
     ?_assertEqual(reload_product, answer(product_file, retry, Running)),
     ?_assertEqual(set_aside_retained, answer(retain_file, reset, Paused)),
     ?_assertEqual(reload_retained, answer(retain_file, retry, Paused))].

%% Seed 000 §2.2: an error cleared goes back to READY (arrow 5) or to setup (arrow 8);
%% Reset initialises again. The log says who decided about a product.
answered_test_() ->
    Ready = {ready, processing, active},
    P = #{serial => <<"S1">>},
    E = #engine{task = #task{ipc = down, product = P}, initialized = true, request = start,
                down = {error, <<"a1">>, step}, resume = Ready, pending = {step, undefined}},
    Setup8 = fun(Event) -> [{state, setup, {arrow, 8}}, {next_event, Event}] end,
    {Reset, ResetFx} = answered(step, reset, <<"op">>, E),
    {Forgot, ForgotFx} = answered(crash, reset, <<"op">>, E),
    [?_assertEqual([uninit | Setup8(run_init)], ResetFx),
     ?_assertEqual({undefined, reset, false},
                   {Reset#engine.down, Reset#engine.cause, Reset#engine.initialized}),
     %% Retry: back where it was, its step told the answer; paused meanwhile, it stays
     %% DOWN, paused, and the step is told at Start.
     ?_assertEqual({E#engine{down = undefined, pending = {step, {answer, retry}}}, [], resume},
                   answered(step, retry, <<"op">>, E)),
     ?_assertEqual({E#engine{request = pause, down = {paused, pause},
                             pending = {step, {answer, ignore}}}, []},
                   answered(step, ignore, <<"op">>, E#engine{request = pause})),
     ?_assertEqual({E#engine{down = undefined}, Setup8(run_init)},
                   answered(init, retry, <<"op">>, E)),
     ?_assertEqual({E#engine{down = undefined}, [], {reconcile, {answer, ignore}}},
                   answered(init, ignore, <<"op">>, E)),
     %% After a crash, Reset forgets the product: the log says who.
     ?_assertEqual([{log, notice, "~ts chose to forget product ~ts after the crash",
                     [<<"op">>, <<"S1">>]}, forget_product, uninit | Setup8(run_init)],
                   ForgotFx),
     ?_assertEqual(reset, Forgot#engine.cause),
     %% An interrupted transfer: the product confirmed here, or not here.
     ?_assertMatch({_, [{log, notice, _, [<<"op">>, <<"S1">>]}, keep_product,
                        {state, setup, {arrow, 8}}, {next_event, run_init}]},
                   answered(transit, ignore, <<"op">>, E)),
     ?_assertMatch({_, [{log, notice, _, [<<"op">>, <<"S1">>]}, forget_product,
                        {state, setup, {arrow, 8}}, {next_event, run_init}]},
                   answered(transit, reset, <<"op">>, E)),
     %% The task's files: set aside or read again, by the engine.
     ?_assertMatch({_, [], {product_file, set_aside, <<"op">>}},
                   answered(product_file, reset, <<"op">>, E)),
     ?_assertMatch({_, [], {retain_file, reload, <<"op">>}},
                   answered(retain_file, retry, <<"op">>, E)),
     ?_assertMatch({_, [], resume}, answered(io, retry, <<"op">>, E))].

%% Seed 000 §2.2 arrow 2 (ResetException) and 6 (an error in a step).
%% Seed 000 §2.2 arrows 1 and 7: init, then reconcile, then READY; an error in
%% either is DOWN with the operator's question.
setup_results_test_() ->
    P = #{serial => <<"S1">>},
    T = #task{ipc = setup, woken_by = {answer, retry}, answer = retry},
    Clean = T#task{woken_by = undefined, answer = undefined},
    E = #engine{task = #task{ipc = setup}, predecessor = #{cause => start}, cause = reset,
                resume = {ready, idle, starved}},
    {Ready, ReadyFx} = reconciled({ok, T#task{product = P}}, {answer, ignore}, E),
    [?_assertEqual({E#engine{task = T, initialized = true}, [], {reconcile, undefined}},
                   inited({ok, T}, E)),
     ?_assertEqual({E#engine{task = T, initialized = true}, [], {raise, #{}, init, setup}},
                   inited({error, #{}, T}, E)),
     ?_assertEqual({E#engine{initialized = true, resume = undefined}, [], {raise, #{}, io, setup}},
                   inited({io, #{}}, E)),
     ?_assertEqual([headroom, {state, {ready, processing, active}, {arrow, 1}},
                    {next_event, step}], ReadyFx),
     ?_assertEqual({undefined, start, {step, {answer, ignore}}, undefined},
                   {Ready#engine.predecessor, Ready#engine.cause, Ready#engine.pending,
                    Ready#engine.resume}),
     %% From DOWN (an init error ignored): arrow 5; without a product: starved.
     ?_assertMatch({_, [headroom, {state, {ready, idle, starved}, {arrow, 5}}, _]},
                   reconciled({ok, T#task{ipc = down}}, undefined, E)),
     %% After a crash, the log says the record and the sensors agree.
     ?_assertMatch({_, [{log, notice, _, [<<"S1">>]}, headroom, _, _]},
                   reconciled({ok, T#task{product = P}}, undefined,
                              E#engine{predecessor = #{cause => crash}})),
     ?_assertEqual({E#engine{task = Clean}, [], {raise, #{}, reconcile, setup}},
                   reconciled({error, #{}, T}, undefined, E)),
     ?_assertEqual({E#engine{resume = undefined}, [], {raise, #{}, io, setup}},
                   reconciled({io, #{}}, undefined, E)),
     %% Run again from DOWN (an init error ignored), its errors are still setup's.
     ?_assertMatch({_, [], {raise, #{}, reconcile, setup}},
                   reconciled({error, #{}, T#task{ipc = down}}, undefined, E))].

%% Seed 000 §2.2 arrow 5: DOWN, Start while paused or the error cleared: READY where
%% the task was, the offers a pause withdrew made again.
resume_test_() ->
    Active = {ready, processing, active},
    E = #engine{task = #task{ipc = down}, down = {paused, pause}, resume = Active,
                reoffer = [out], pending = {waits, [{timer, 5}]}},
    {Resumed, Fx, Then} = resume(E),
    [?_assertEqual([headroom, {state, Active, {arrow, 5}}, {reoffer, [out]}], Fx),
     ?_assertEqual({reassert, Active}, Then),
     ?_assertEqual({undefined, undefined, [], {waits, [{timer, 5}]}},
                   {Resumed#engine.down, Resumed#engine.resume, Resumed#engine.reoffer,
                    Resumed#engine.pending}),
     ?_assertMatch({_, [headroom, {state, Active, {arrow, 5}}], _},
                   resume(E#engine{reoffer = [], down = {error, <<"a">>, io}}))].

%% Boot after a crash, and Start in OFF (seed 000 §2.2, arrow 0): the crash recorded,
%% the outputs as the crashed task left them kept for reconcile and then secured (init
%% ran in it), a warning unless the operator is asked; setup by arrow 0 with the
%% settings taken at Start, unless the emergency stop is active.
start_test_() ->
    Outputs = #{g => #{valve => true}},
    E = #engine{task = #task{ipc = off}, request = start},
    {Crashed, CrashFx, Then} = crashed(boom, false, Outputs, E),
    {Asked, AskedFx, start} = crashed(boom, true, Outputs, E),
    Started = fun(Ex) -> {E1, Fx} = start(Ex),
                         {E1#engine.crash, E1#engine.crash_ask, E1#engine.resumed, Fx}
              end,
    Settings = #{speed => 3},
    {Set, _} = start(E#engine{settings = Settings}),
    [?_assertEqual([{crashed, boom}, {crash_warning, boom}, uninit], CrashFx),
     ?_assertEqual(start, Then),
     ?_assertEqual({boom, false, crash, Outputs, false},
                   {Crashed#engine.crash, Crashed#engine.crash_ask, Crashed#engine.cause,
                    Crashed#engine.crash_outputs, Crashed#engine.initialized}),
     ?_assertEqual([{crashed, boom}, uninit], AskedFx),
     ?_assertEqual(true, Asked#engine.crash_ask),
     %% Started after a crash it goes on by itself: reconcile decides after init.
     ?_assertEqual({undefined, false, true,
                    [{resumed, true}, {state, setup, {arrow, 0}}, {next_event, run_init}]},
                   Started(Crashed)),
     %% The operator is asked: the question is setup's first event.
     ?_assertEqual({undefined, false, false,
                    [{state, setup, {arrow, 0}}, {next_event, {crashed, boom}}]},
                   Started(Asked)),
     ?_assertEqual({undefined, false, false,
                    [{state, setup, {arrow, 0}}, {next_event, run_init}]}, Started(E)),
     ?_assertEqual(Settings, (Set#engine.task)#task.settings),
     %% An emergency stop: OFF, and the log says why.
     ?_assertMatch({boom, false, false, [{log, warning, _, []}]},
                   Started(Crashed#engine{estop = true})),
     %% Paused, a crashed task starts (to settle the crash); a task not crashed stays.
     ?_assertMatch({undefined, false, true, [_, {state, setup, _}, _]},
                   Started(Crashed#engine{request = pause})),
     ?_assertEqual({undefined, false, false, []},
                   Started(Crashed#engine{request = stop})),
     %% A file read again: setup again by arrow 8, its first event as at any start.
     ?_assertEqual({E, [{state, setup, {arrow, 8}}, {next_event, run_init}]},
                   setup_again(E)),
     ?_assertMatch({_, [{state, setup, {arrow, 8}}, {next_event, product_damaged}]},
                   setup_again(E#engine{load_error = enoent}))].

%% The task's IO before init and at arrow 5: every status kept, one down among those
%% lost; init only with every group configured and its connection up; resume only
%% with every connection up, else DOWN again with the connection's error.
checked_test_() ->
    Active = {ready, processing, active},
    E = #engine{task = #task{ipc = setup}, resume = Active},
    Down = #engine{task = #task{ipc = down}, down = {error, <<"a">>, io}, resume = Active,
                   conns = #{plc => down, io2 => up}, lost = [plc],
                   pending = {waits, [{timer, 5}]}},
    {Init, [], init} = checked(init, [{conn, plc, up}, {conn, io2, up}], E),
    [?_assertEqual({#{plc => up, io2 => up}, []}, {Init#engine.conns, Init#engine.lost}),
     ?_assertMatch({#engine{resume = undefined, conns = #{plc := up, io2 := down},
                            lost = [io2]}, [], {raise, {io, io2}, io, setup}},
                   checked(init, [{conn, plc, up}, {conn, io2, down}], E)),
     %% The first group in the task's order that fails is the one the error names.
     ?_assertMatch({_, [], {raise, {io_config, g2}, io, setup}},
                   checked(init, [{conn, plc, up}, {group, g2, unconfigured},
                                  {conn, io2, down}], E)),
     %% A subscription the HAL could not take: down, but not kept (asked again).
     ?_assertMatch({_, [], {raise, {io, plc}, io, setup}},
                   checked(init, [{conn, plc, unsubscribed}], E)),
     ?_assertEqual({#{}, []}, begin
                                 {Unsub, _, _} = checked(init, [{conn, plc, unsubscribed}], E),
                                 {Unsub#engine.conns, Unsub#engine.lost}
                             end),
     %% Arrow 5 with its connections up: resume/1, the connection back kept up.
     ?_assertMatch({#engine{conns = #{plc := up}, lost = [plc], down = undefined},
                    [headroom, {state, Active, {arrow, 5}}], {reassert, Active}},
                   checked(resume, [{conn, plc, up}, {conn, io2, up}], Down)),
     ?_assertEqual({Down, [], {down_again, {io, plc}}},
                   checked(resume, [{conn, plc, down}, {conn, io2, up}], Down))].

%% A connection lost under a request, a point its device cannot serve, waits that
%% could not be armed: DOWN from where the task was, to go back there after Retry.
io_test_() ->
    Ready = {ready, idle, blocked},
    E = #engine{task = #task{ipc = Ready}, conns = #{plc => up}},
    Armed = [{reply, make_ref()}],
    [?_assertEqual({E#engine{conns = #{plc => down}, lost = [plc], resume = Ready}, [],
                    {raise, {io, plc}, io, Ready}},
                   io_lost(plc, Ready, E)),
     ?_assertEqual({E#engine{resume = Ready}, [], {raise, {point, g, p, refused}, io, Ready}},
                   unavailable(g, p, refused, Ready, E)),
     ?_assertEqual({E#engine{armed = Armed}, [], boundary}, armed({ok, Armed}, step, E)),
     ?_assertEqual({E#engine{armed = Armed}, []}, armed({ok, Armed}, resume, E)),
     ?_assertEqual({E#engine{armed = Armed, conns = #{plc => down}, lost = [plc],
                             resume = Ready}, [], {raise, {io, plc}, io, Ready}},
                   armed({io_lost, plc, Armed}, step, E))].

%% Arrow 5 after a lost connection: the outputs set again are logged, then the task
%% does what it was doing (its waits armed again, or its step).
reasserted_test_() ->
    Ready = {ready, processing, active},
    E = #engine{task = #task{ipc = Ready}, lost = [plc], pending = {waits, [{timer, 5}]}},
    [?_assertEqual({E#engine{lost = []}, [], {arm, [{timer, 5}], resume}},
                   reasserted({written, []}, Ready, E)),
     ?_assertMatch({#engine{lost = []}, [{log, notice, _, [["plc"], _]}],
                    {arm, [{timer, 5}], resume}},
                   reasserted({written, [{g, valve, true}]}, Ready, E)),
     ?_assertEqual({E#engine{lost = [], pending = {step, x}}, [{next_event, step}]},
                   reasserted({written, []}, Ready, E#engine{pending = {step, x}})),
     ?_assertEqual({E#engine{conns = #{plc => down}, resume = Ready}, [],
                    {raise, {io, plc}, io, Ready}},
                   reasserted({io_lost, plc}, Ready, E)),
     ?_assertEqual({E#engine{resume = Ready}, [], {raise, {point, g, p, why}, io, Ready}},
                   reasserted({unavailable, g, p, why}, Ready, E))].

stepped_test_() ->
    Ready = {ready, processing, active},
    T = #task{ipc = Ready, woken_by = {timer, 5}},
    E = #engine{task = #task{ipc = Ready}, initialized = true, pending = {step, {timer, 5}}},
    Clean = T#task{woken_by = undefined},
    {Reset, ResetFx} = stepped({reset, T}, E),
    [?_assertEqual({E#engine{task = Clean, pending = {waits, [{timer, 9}]}}, [],
                    {arm, [{timer, 9}], step}},
                   stepped({wait, [{timer, 9}], T}, E)),
     ?_assertEqual({E#engine{task = Clean, pending = {waits, [{timer, 9}]}},
                    [{resumed, false}], {arm, [{timer, 9}], step}},
                   stepped({wait, [{timer, 9}], T}, E#engine{resumed = true})),
     ?_assertEqual([uninit, {state, setup, {arrow, 2}}, {next_event, run_init}], ResetFx),
     ?_assertEqual({reset, false, Clean},
                   {Reset#engine.cause, Reset#engine.initialized, Reset#engine.task}),
     ?_assertEqual({E#engine{task = Clean#task{ipc = {ready, idle, blocked}},
                             resume = {ready, idle, blocked}}, [],
                    {raise, #{}, step, {ready, idle, blocked}}},
                   stepped({error, #{}, T#task{ipc = {ready, idle, blocked}}}, E))].

woken_test_() ->
    R = make_ref(),
    Armed = [{handshake, R, in, available, true}, {timer, make_ref(), {link_down, out}}],
    Sig = fun(in, available) -> true; (_, _) -> false end,
    [?_assertEqual(undefined, woken([], Armed, Sig)),
     ?_assertEqual({handshake, in, available, true},
                   woken([{wake, in, {watch, R, available, true}}], Armed, Sig)),
     ?_assertEqual(undefined, woken([{wake, in, {watch, make_ref(), available, true}}], Armed, Sig)),
     ?_assertEqual({handshake, in, available, true},
                   woken([{wake, in, {signals, 3}}], Armed, Sig)),
     ?_assertEqual(undefined,
                   woken([{wake, in, {signals, 3}}], Armed, fun(_, _) -> false end)),
     ?_assertEqual({handshake, out, interrupted}, woken([{wake, out, interrupted}], Armed, Sig)),
     ?_assertEqual({handshake, in, completed},
                   woken([{wake, other, aborted}, {wake, in, completed}], Armed, Sig))].

ended_while_down_test_() ->
    Waits = {waits, [{handshake, in, available, true}]},
    [?_assertEqual(Waits, ended_while_down([], Waits)),
     ?_assertEqual({step, {handshake, in, interrupted}},
                   ended_while_down([{wake, in, interrupted}], Waits)),
     ?_assertEqual(Waits, ended_while_down([{wake, in, {signals, 1}}, {wake, out, aborted}], Waits)),
     ?_assertEqual({step, x}, ended_while_down([{wake, in, aborted}], {step, x}))].

events_test_() ->
    [?_assertEqual(unblocked, wake_event({handshake, l, not_busy, true}, {ready, idle, blocked})),
     ?_assertEqual(none, wake_event({handshake, l, not_busy, true}, {ready, idle, starved})),
     ?_assertEqual(unstarved, wake_event({handshake, l, available, true}, {ready, idle, starved})),
     ?_assertEqual(none, wake_event({handshake, l, interrupted}, {ready, idle, starved})),
     ?_assert(starves(available, true, false, {ready, processing, active})),
     ?_assertNot(starves(available, true, false, {ready, idle, starved})),
     ?_assertNot(starves(available, true, true, {ready, processing, active})),
     ?_assertNot(starves(not_busy, true, false, {ready, processing, active})),
     ?_assertNot(starves(available, true, false, setup))].

woken_by_test_() ->
    T = #task{},
    Woken = woken_by({answer, retry}, T),
    Timer = woken_by({timer, 5}, Woken),
    [?_assertEqual(T, woken_by(undefined, T)),
     ?_assertEqual({{answer, retry}, retry}, {Woken#task.woken_by, Woken#task.answer}),
     ?_assertEqual({{timer, 5}, undefined}, {Timer#task.woken_by, Timer#task.answer}),
     ?_assertEqual(T, clean(Woken)),
     ?_assertEqual(T, clean(T))].

crash_test_() ->
    [?_assert(ask_after_crash(#{crashed_in => setup})),
     ?_assert(ask_after_crash(#{crashed_in => {ready, idle, starved}, resumed => true})),
     ?_assertNot(ask_after_crash(#{crashed_in => {ready, idle, starved}, resumed => false})),
     ?_assertNot(ask_after_crash(#{}))].

stale_copy_test_() ->
    Ready = {ready, processing, active},
    [?_assertEqual(reconcile, stale_copy(Ready, true, false, undefined)),
     ?_assertEqual(ask, stale_copy(Ready, true, true, undefined)),
     ?_assertEqual(reconcile_at_start, stale_copy(down, true, false, paused)),
     ?_assertEqual(reconcile_at_start, stale_copy(down, true, true, paused)),
     %% An error waiting for the operator: the answer is acted on without the copy.
     ?_assertEqual(keep, stale_copy(down, true, false, error)),
     ?_assertEqual(keep, stale_copy(setup, true, false, undefined)),
     ?_assertEqual(keep, stale_copy(off, true, false, undefined)),
     %% Nothing dropped (an older copy than the one it holds, or none held).
     ?_assertEqual(keep, stale_copy(Ready, false, false, undefined)),
     ?_assertEqual(keep, stale_copy(down, false, false, paused))].

wait_news_test_() ->
    T = make_ref(), L = make_ref(), W = make_ref(), R = make_ref(), Other = make_ref(),
    Armed = [{timer, T, 500}, {timer, L, {link_down, in}}, {io, W, io, part},
             {reply, R}],
    [?_assertEqual({wake, {timer, 500}}, wait_news({timeout, T, x}, Armed)),
     ?_assertEqual({wake, {handshake, in, interrupted}}, wait_news({timeout, L, x}, Armed)),
     ?_assertEqual({wake, {io, io, part, true}},
                   wait_news({cell_hal_watch, W, true}, Armed)),
     ?_assertEqual({unavailable, io, part, <<"gone">>},
                   wait_news({cell_hal_unavailable, W, <<"gone">>}, Armed)),
     ?_assertEqual({wake, {reply, R, ok}}, wait_news({R, ok}, Armed)),
     %% Waits left since: nothing, or a reply nobody waits for.
     ?_assertEqual(none, wait_news({timeout, Other, x}, Armed)),
     ?_assertEqual(none, wait_news({cell_hal_watch, Other, true}, Armed)),
     ?_assertEqual(none, wait_news({cell_hal_unavailable, Other, <<"gone">>}, Armed)),
     ?_assertEqual(late, wait_news({Other, ok}, Armed)),
     %% A reference is only what it was armed as: a timer's is no watch, a watch's no
     %% reply.
     ?_assertEqual(none, wait_news({cell_hal_watch, T, true}, Armed)),
     ?_assertEqual(late, wait_news({W, ok}, Armed))].

newer_holder_test_() ->
    [?_assertEqual(none, newer_holder(a, 3, [])),
     ?_assertEqual(none, newer_holder(a, 3, [{a, 5}, {b, 3}, {c, 2}])),
     ?_assertEqual({ok, b}, newer_holder(a, 3, [{a, 3}, {b, 4}]))].

fields_test() ->
    T = take(#task{}, #{serial => <<"S">>}, 3, #{phase => in_transit}),
    ?assertEqual(3, gen(T)),
    ?assertEqual(#{phase => in_transit}, marker(T)),
    T1 = released(T#task{traced = <<"S">>}),
    ?assertEqual({undefined, 0, undefined, undefined},
                 {T1#task.product, gen(T1), marker(T1), T1#task.traced}),
    ?assertEqual(#{l => #{}}, links(set_links(T, #{l => #{}}))).

link_retry_test() ->
    Waits = lists:foldl(fun(_, [Last | _] = Acc) -> [link_retry_ms(Last) | Acc] end,
                        [link_retry_ms(undefined)], lists:seq(1, 7)),
    ?assertEqual([50, 100, 200, 400, 800, 1000, 1000, 1000], lists:reverse(Waits)).

-endif.
