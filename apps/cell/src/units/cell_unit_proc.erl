%% @doc The engine of a unit ({@link cell_unit}): a gen_statem whose states are the
%% unit's lifecycle states (seed 001), taking its transitions from
%% {@link cell_unit_fsm} and running each state's step sequence through
%% {@link cell_sequence_runner}, whose effects it carries out: outputs, HAL watches,
%% timers.
%%
%% <pre>
%%  state                what the engine does there
%%  booting              runs the booting sequence (parameters); an abort is an error
%%                       for the operator (Retry runs it again) → init when done
%%  init                 waits: GoHome, an action; after a crash, an error (Reset)
%%  go_home              references the unit → idle; IO that is down aborts it
%%  idle                 ready: Start → automatic, ButtonX → a user state
%%  automatic, {user, X} the main sequence → idle when done
%%  {action, A, From}    a service move → From when done
%%  stop                 the Stop sequence → stopped (an abort in it: stopped, then
%%                       fault_reaction)
%%  stopped              waits: GoHome, Stop again, an action; IO lost is no fault
%%                       (OFF, as a device task)
%%  fault_reaction       raises the fault's error (Reset; a lost connection's, `io',
%%                       Retry or Reset, as a task's), runs its sequence without
%%                       waiting for anything interrupted → fault (also if aborted)
%%  fault                waits: GoHome (Reset), an action
%%  any                  Halt holds the sequence at a resumable point; an actuator that
%%                       fails or IO that is lost aborts it (→ fault_reaction)
%% </pre>
%%
%% Like a device task, a unit registers with the cell, reports an IPC-2541 state (see
%% {@link cell_unit_fsm:ipc/2}) through the registry and a `task_state' event — one on
%% every change of its lifecycle state too, with `unit_state' and `unit_from' — and
%% takes the controller's commands:
%%
%% <ul>
%% <li>Start: GoHome where the unit is not referenced (Init, Stopped, Fault without an
%%     error waiting), then Automatic; Idle → Automatic; Halt released. An error
%%     waiting for the operator holds the unit until answered; Reset then references
%%     it and goes on while the cell runs.</li>
%% <li>Pause: Halt (IPC DOWN once it holds). Service mode: Halt, and the service flag
%%     the sequences see.</li>
%% <li>Stop: the Stop button (where the diagram has the arrow); Halt released.</li>
%% <li>Emergency stop: no step starts from the instant the registry's flag is set (the
%%     runner checks it before every step); the sequences are interrupted, the outputs
%%     made safe, and the unit stops: GoHome, Idle, Automatic, user states and
%%     actions → Stop (whose sequence cannot run: done at once) → Stopped,
%%     FaultReaction → Fault. It reports OFF until the release. Start afterwards
%%     references the unit again.</li>
%% </ul>
%%
%% Standing orders ({@link cell_unit:order/3}), given by a device task or another unit,
%% are kept in every state for the sequences to follow; they go with the process, so
%% whoever gives one gives it again after the unit restarted.
%%
%% A connection of the unit's IO that the HAL's server could not subscribe it to (away,
%% restarting) is down for the unit, as a lost one is, until the HAL's `{cell_hal_back,
%% Ref}' ({@link cell_hal:notify_back/0}) subscribes it again.
%%
%% After a crash the supervisor restarts the unit: its outputs are made safe, it
%% boots again into Init and, if the cell was running, raises an error naming the
%% crash: it moves again only after the operator's Reset. Steps run in this process;
%% a step that crashes is a crash of the unit.
-module(cell_unit_proc).
-behaviour(gen_statem).

-export([start_link/1, child_spec/1]).
-export([callback_mode/0, init/1, handle_event/4, terminate/3]).

-define(CYCLE(Gen), {'$unit_cycle', Gen}).
-define(TIMER(Key), {'$unit_timer', Key}).

-type origin() :: booting | fault | crash.

-record(data, {
    id :: atom(),
    spec :: cell_task:spec(),
    task :: cell_task:task(),                %% id, zone, lane: what events carry
    decl :: cell_unit:declaration(),
    seq :: cell_sequence:seq(),
    ipc = off :: cell_ipc:state(),
    request = stop :: start | pause | stop,
    estop = false :: boolean(),
    service = false :: boolean(),
    halt = false :: boolean(),
    auto = false :: boolean(),               %% the cell's Start asks for Automatic
    error :: undefined | {binary(), origin()},  %% an error waiting for the operator
    fault :: undefined | {cell_sequence_runner:where(), term()},  %% why FaultReaction
    crash :: term(),                         %% how the previous incarnation ended
    trigger :: cell_unit_fsm:trigger() | boot | undefined,
    ready = active :: cell_unit_fsm:ready(), %% what the sequence reported (Automatic, user)
    step :: undefined | {pos_integer(), module(), term()},
    watches = #{} :: #{term() => reference()},
    %% A watch's reference: its sequence key and the point it watches.
    refs = #{} :: #{reference() => {term(), {atom(), atom()}}},
    timers = #{} :: #{term() => reference()},
    gen = 0 :: non_neg_integer(),            %% cycle messages of older rounds are ignored
    cycle = false :: boolean(),              %% a cycle message is on its way
    settles = [] :: [gen_statem:from()],
    conns = #{} :: #{atom() => up | down},
    away = [] :: [atom()],                   %% connections the HAL's server, away, did
    back :: reference() | undefined,         %% not subscribe: again when it is back
    settings = #{} :: map(),                 %% the snapshot for the next GoHome
    in_force = #{} :: map(),                 %% the settings the sequences run on
    %% Whether steps are logged, as the log thresholds stood at a version of theirs.
    verbose :: undefined | {non_neg_integer(), boolean()}
}).

%% -------------------------------------------------------------------------------------
%% API
%% -------------------------------------------------------------------------------------

%% @doc Starts a unit and returns once it has registered with the cell; it boots on.
-spec start_link(cell_task:spec()) -> gen_statem:start_ret().
start_link(Spec) ->
    case gen_statem:start_link(?MODULE, Spec, []) of
        {ok, Pid} ->
            ok = gen_statem:call(Pid, sync),
            {ok, Pid};
        Other ->
            Other
    end.

%% @doc The child spec of a unit under cell_task_sup.
-spec child_spec(cell_task:spec()) -> supervisor:child_spec().
child_spec(#{id := Id} = Spec) ->
    %% The outputs are made safe on shutdown: give the HAL time to take the writes.
    #{id => Id, start => {?MODULE, start_link, [Spec]}, shutdown => 5000}.

%% -------------------------------------------------------------------------------------
%% gen_statem
%% -------------------------------------------------------------------------------------

-spec callback_mode() -> gen_statem:callback_mode_result().
callback_mode() ->
    [handle_event_function, state_enter].

-spec init(cell_task:spec()) -> gen_statem:init_result(cell_unit_fsm:state()).
init(#{id := Id} = Spec) ->
    process_flag(trap_exit, true),
    %% The cell spec was checked at boot: a declaration failing here is a bug.
    {ok, Decl} = cell_unit:check(Spec),
    %% The node's emergency-stop flag is made once and never replaced: kept here, it is
    %% read before every step without a lookup.
    Flag = cell_registry:estop_flag(),
    {ok, Seq} = cell_sequence_runner:new(#{unit => Id, io => maps:get(io, Spec, []),
                                          actuators => maps:get(actuators, Decl),
                                          estop => fun() -> atomics:get(Flag, 1) =:= 1 end}),
    Task = cell_task:new(Spec),
    {ok, booting, #data{id = Id, spec = Spec, task = Task, decl = Decl, seq = Seq,
                        settings = cell_task:settings(Task),
                        in_force = cell_task:settings(Task)},
     [{next_event, internal, boot}]}.

-spec handle_event(gen_statem:event_type(), term(), cell_unit_fsm:state(), #data{}) ->
          gen_statem:event_handler_result(cell_unit_fsm:state()).

%% Every state change is announced on entry: the registry, a task_state event, the log.
handle_event(enter, booting, booting, _D) ->
    %% The first state: announced once the unit has registered.
    keep_state_and_data;
handle_event(enter, Old, New, D) ->
    {keep_state, report(Old, New, D)};

%% --------------------------------------------------------------------------------------
%% booting: register, then the booting sequence
%% --------------------------------------------------------------------------------------
handle_event(internal, boot, booting, D) ->
    boot(D);

%% --------------------------------------------------------------------------------------
%% every state: a state was entered; its sequence runs and is sent what it waits for
%% --------------------------------------------------------------------------------------
handle_event(internal, entered, State, D) ->
    entered(State, D);
handle_event(internal, fault, stopped, D) ->
    %% A Stop that was aborted has ended: the fault follows from Stopped.
    transition(aborted, stopped, D);
handle_event(info, ?CYCLE(Gen), State, #data{gen = Gen} = D) ->
    cycle(State, D);
handle_event(info, ?CYCLE(_), _State, _D) ->
    keep_state_and_data;
handle_event(info, {timeout, TRef, ?TIMER(Key)}, State, #data{timers = Timers, seq = Seq} = D) ->
    case maps:find(Key, Timers) of
        {ok, TRef} ->
            run(State, cell_sequence_runner:event(Seq, {timer, Key}, now_ms()),
                D#data{timers = maps:remove(Key, Timers)});
        _ ->
            keep_state_and_data
    end;
handle_event(info, {cell_hal_watch, Ref, Value}, State,
             #data{refs = Refs, watches = W, seq = Seq} = D) ->
    case maps:take(Ref, Refs) of
        {{Key, _Point}, Refs1} ->
            run(State, cell_sequence_runner:event(Seq, {watch, Key, Value}, now_ms()),
                D#data{refs = Refs1, watches = maps:remove(Key, W)});
        error ->
            keep_state_and_data
    end;
handle_event(info, {cell_hal_unavailable, Ref, Why}, State,
             #data{refs = Refs, watches = W, seq = Seq} = D) ->
    %% The point a step waits for cannot be read (the PLC refuses its address): the
    %% sequence is aborted as for a watch the HAL could not place, never left waiting.
    case maps:take(Ref, Refs) of
        {{Key, Point}, Refs1} ->
            run(State, cell_sequence_runner:fail(Seq, {io, Point, {unavailable, Why}}),
                D#data{refs = Refs1, watches = maps:remove(Key, W)});
        error ->
            keep_state_and_data
    end;
handle_event(info, {Ref, Term} = Msg, State, #data{seq = Seq} = D) when is_reference(Ref) ->
    case cell_sequence_runner:expects(Seq, Ref) of
        true -> run(State, cell_sequence_runner:event(Seq, {reply, Ref, Term}, now_ms()), D);
        false -> late_reply(Msg, D)
    end;
handle_event(info, {cell_hal_conn, Conn, Status}, State, D) ->
    connection(Conn, Status, State, D);
handle_event(info, {cell_hal_back, Ref}, State, #data{id = Id, back = Ref, away = Away} = D0) ->
    D = resubscribe(Away, D0#data{away = [], back = undefined}),
    _ = [cell_log:info(Id, "the HAL is back: connection ~ts followed again (~ts)",
                       [C, maps:get(C, D#data.conns)])
         || C <- Away, not lists:member(C, D#data.away)],
    keep(State, D);
handle_event(info, {cell_hal_back, _Ref}, _State, _D) ->
    %% The HAL's word for a wait the unit has since given up (it asks once at a time).
    keep_state_and_data;

%% --------------------------------------------------------------------------------------
%% every state: the operator's answer to the unit's error
%% --------------------------------------------------------------------------------------
handle_event(info, {cell_alarm, answer, Id, Solution, _Who}, State,
             #data{error = {Id, Origin}} = D) ->
    answered(Origin, Solution, State, D#data{error = undefined});
handle_event(info, {cell_alarm, answer, _Id, _Solution, _Who}, _State, _D) ->
    %% An answer to an error the unit has since taken back.
    keep_state_and_data;

%% --------------------------------------------------------------------------------------
%% every state: the controller, the unit's buttons, queries
%% --------------------------------------------------------------------------------------
handle_event(info, {control, Key, Value}, State, D) ->
    control(Key, Value, State, D);
handle_event({call, From}, {button, Button}, State, D) ->
    button(Button, From, State, D);
handle_event({call, From}, {order, Key, Value}, State, #data{seq = Seq} = D)
  when is_atom(Key) ->
    %% A standing order for the sequences, in any state: the one waiting for it runs.
    with_reply(From, ok, run(State, cell_sequence_runner:set_order(Seq, Key, Value, now_ms()),
                             D));
handle_event({call, From}, {halt, On}, State, D) when is_boolean(On) ->
    {Outcome, D1} = halt_flag(On, State, D),
    with_reply(From, ok, outcome(Outcome, State, D1));
handle_event({call, From}, settle, _State, #data{cycle = true, settles = S} = D) ->
    {keep_state, D#data{settles = [From | S]}};
handle_event({call, From}, settle, _State, _D) ->
    {keep_state_and_data, [{reply, From, ok}]};
handle_event({call, From}, state, _State, #data{ipc = Ipc}) ->
    {keep_state_and_data, [{reply, From, Ipc}]};
handle_event({call, From}, unit_state, State, _D) ->
    {keep_state_and_data, [{reply, From, State}]};
handle_event({call, From}, sync, _State, _D) ->
    {keep_state_and_data, [{reply, From, ok}]};
handle_event({call, From}, info, State, D) ->
    {keep_state_and_data, [{reply, From, describe(State, D)}]};
handle_event(info, {'EXIT', _Pid, Reason}, _State, _D) ->
    case cell_member:exit_signal(Reason) of
        ignore -> keep_state_and_data;
        Stop -> Stop
    end;
handle_event(info, Msg, _State, #data{id = Id}) ->
    %% Nothing else is sent to a unit: the engine subscribes to no point (it watches),
    %% and its sequences' steps run here. A message of another kind is a bug.
    cell_member:unexpected(Id, Msg).

-spec terminate(term(), cell_unit_fsm:state(), #data{}) -> ok.
terminate(Reason, _State, #data{id = Id} = D) ->
    %% Whatever ended the unit, its outputs are left safe.
    secure(D),
    cell_member:leave(Id, Reason).

%% -------------------------------------------------------------------------------------
%% Boot
%% -------------------------------------------------------------------------------------

boot(#data{spec = Spec} = D0) ->
    {Previous, #{request := Request, estop := Estop, service_mode := Service}} =
        cell_member:join(Spec, #{kind => unit, unit_state => booting}),
    D1 = subscribe_io(D0#data{request = Request, estop = Estop,
                              service = Service, halt = Request =:= pause orelse Service,
                              seq = cell_sequence_runner:set_service(D0#data.seq, Service),
                              trigger = boot}),
    D = case Previous of
            {crashed, Why} ->
                ok = cell_member:crashed(D1#data.task, "unit", "; its outputs are made safe, "
                                         "its position is unknown", Why),
                secure(D1),
                D1#data{crash = Why};
            _ ->
                %% A unit joining a running cell references itself and goes to work.
                D1#data{auto = Request =:= start}
        end,
    {keep_state, report(undefined, booting, D), [{next_event, internal, entered}]}.

%% -------------------------------------------------------------------------------------
%% Transitions and sequences
%% -------------------------------------------------------------------------------------

%% A trigger the diagrams allow here (checked by the caller): the running sequence
%% stops at once and the next state is entered.
transition(Trigger, State, D) ->
    transition(Trigger, State, D, entered).

transition(Trigger, State, D0, Next) ->
    {ok, To} = cell_unit_fsm:next(State, Trigger),
    D = leave(State, To, interrupt(D0)),
    {next_state, To, D#data{trigger = Trigger}, [{next_event, internal, Next}]}.

leave(From, To, D0) ->
    D1 = case From of
             automatic -> D0#data{ready = active};
             {user, _} -> D0#data{ready = active};
             _ -> D0
         end,
    D2 = case To of
             automatic -> D1#data{auto = false};
             go_home -> withdraw(D1#data{fault = undefined});
             _ -> D1
         end,
    D2#data{step = undefined}.

%% A state was entered: a non-active one may be left at once for what the cell's
%% Start asks; otherwise the state's sequence starts.
entered(State, D0) ->
    D = prepare(State, D0),
    case cell_unit_fsm:is_non_active(State) andalso arrive(State, D) of
        {go, Trigger} -> transition(Trigger, State, D);
        _ -> start_sequence(State, D)
    end.

prepare(init, #data{crash = Why, request = Request} = D) when Why =/= undefined ->
    case Request of
        stop -> D#data{crash = undefined};
        _ -> raise(crash, crash_error(Why), D#data{crash = undefined})
    end;
prepare(go_home, #data{settings = S} = D) ->
    subscribe_io(D#data{in_force = S});
prepare(fault_reaction, #data{fault = {Where, Why}} = D) ->
    raise(fault, fault_error(Where, Why), D);
prepare(_State, D) ->
    D.

%% What the cell's Start asks of a unit arriving in a non-active state.
arrive(State, #data{auto = true, estop = false, error = Error}) ->
    case cell_unit_fsm:on_start(State, #{error => Error =/= undefined}) of
        none -> stay;
        Trigger -> {go, Trigger}
    end;
arrive(_State, _D) ->
    stay.

start_sequence(go_home, #data{conns = Conns0} = D) when Conns0 =/= #{} ->
    %% Referencing needs the IO: asked of the HAL itself, since its news of a
    %% reconnection may still be on the way here.
    Conns = maps:map(fun(C, _) ->
                             case lists:member(C, D#data.away) of
                                 true -> down;
                                 false -> cell_hal:status(C)
                             end
                     end, Conns0),
    case [C || {C, down} <- lists:sort(maps:to_list(Conns))] of
        [Conn | _] ->
            transition(aborted, go_home, D#data{conns = Conns,
                                                fault = {where(D), {io_lost, Conn}}});
        [] ->
            begin_sequence(go_home, D#data{conns = Conns})
    end;
start_sequence(State, D) ->
    begin_sequence(State, D).

begin_sequence(State, #data{decl = #{sequences := Seqs}, seq = Seq} = D) ->
    case maps:find(key(State), Seqs) of
        {ok, {Mod, Args}} ->
            Opts = #{now => now_ms(), haltable => cell_unit_fsm:haltable(State),
                     halt => D#data.halt, service => D#data.service,
                     settings => D#data.in_force},
            run(State, cell_sequence_runner:start(Seq, Mod, Args, Opts), D);
        error ->
            case cell_unit_fsm:is_active(State) of
                true -> outcome(done, State, D);
                false -> keep(State, D)
            end
    end.

key({action, A, _From}) -> {action, A};
key(State) -> State.

%% What the sequences answered to one event (see cell_sequence_runner): carried out.
run(State, {Outcome, Seq, Effects}, D) ->
    {Outcome1, D1} = carry_out(Outcome, Effects, State, D#data{seq = Seq}),
    outcome(Outcome1, State, D1).

%% A cycle message: the step that is due runs. This is the unit's hot path: most
%% cycles leave another step due (one step per cycle, or a step coming round again in
%% one go), and carry out nothing but the steps they entered, none of them logged.
%% Such a cycle sets the unit's step and its sequences in one update and goes on to
%% the next cycle (see next_cycle/2), nothing more: the IPC-2541 state cannot have changed (Halt has not
%% taken hold, a sequence still runs, and IPC events report themselves), and nobody
%% waiting for the unit to settle can be answered while a cycle is due, so neither
%% report/3 nor keep/2 has anything to do.
cycle(State, #data{seq = Seq} = D0) ->
    {Outcome, Seq1, Effects} = cell_sequence_runner:cycle(Seq, now_ms()),
    {Verbose, D} = verbose(D0),
    case {Outcome, Verbose, last_step(Effects)} of
        {continue, false, {_, _, _} = Step} ->
            next_cycle(State, D#data{seq = Seq1, step = Step});
        _ ->
            case carry_out(Outcome, Effects, State, D#data{seq = Seq1}) of
                {continue, D1} -> next_cycle(State, D1);
                {Outcome1, D1} -> outcome(Outcome1, State, D1#data{cycle = false})
            end
    end.

%% The next cycle comes behind whatever reached the unit meanwhile (a button, an
%% order, a HAL watch, a settle call): a message to itself, behind them. With nothing
%% waiting it runs at once, within this event: the same order, without a trip through
%% the mailbox.
next_cycle(State, #data{gen = Gen} = D) ->
    case erlang:process_info(self(), message_queue_len) of
        {message_queue_len, 0} ->
            cycle(State, D);
        _ ->
            self() ! ?CYCLE(Gen),
            {keep_state, D}
    end.

%% The step entered last, when steps entered are all there is to carry out.
last_step([{step, Depth, Mod, Step}]) -> {Depth, Mod, Step};
last_step([{step, _, _, _} | Rest]) -> last_step(Rest);
last_step(_) -> other.

carry_out(Outcome, Effects, State, D) ->
    case exec(Effects, State, D) of
        {ok, D1} ->
            {Outcome, D1};
        {error, Why, D1} ->
            {Outcome2, Seq, Effects2} = cell_sequence_runner:fail(D1#data.seq, Why),
            carry_out(Outcome2, Effects2, State, D1#data{seq = Seq})
    end.

outcome(continue, State, #data{gen = Gen} = D) ->
    self() ! ?CYCLE(Gen),
    keep(State, D#data{cycle = true});
outcome(done, State, D) ->
    case cell_unit_fsm:next(State, done) of
        {ok, _} -> transition(done, State, D);
        error -> keep(State, D)       %% the sequence of Idle or Stopped has ended
    end;
outcome({aborted, Where, Why}, State, D) ->
    aborted(State, Where, Why, D);
outcome(estop, State, D) ->
    %% A step was due and the emergency stop's flag is set: its message is on the way
    %% (or was handled before this unit started: the request it read stays as it is).
    estop(State, D#data{estop = true, auto = false});
outcome(_WaitOrIdle, State, D) ->
    keep(State, D).

%% Nothing changes state: the IPC-2541 state may have (Halt took hold), and whoever
%% waits for the unit to settle is answered once no step is due.
keep(State, D0) ->
    D = report(State, State, D0),
    case D of
        #data{cycle = false, settles = [_ | _] = Settles} ->
            {keep_state, D#data{settles = []}, [{reply, F, ok} || F <- Settles]};
        _ ->
            {keep_state, D}
    end.

%% The sequence was aborted (or an actuator failed).
aborted(booting, Where, Why, D) ->
    keep(booting, raise(booting, booting_error(Where, Why), D));
aborted(fault_reaction, Where, Why, #data{id = Id} = D) ->
    %% The seed: an aborted FaultReaction ends in Fault directly.
    cell_log:error(Id, "the fault reaction was cut short~ts: ~ts",
                   [where_text(Where), cell_sequence:format_reason(Why)]),
    transition(done, fault_reaction, D);
aborted(stop, Where, Why, D) ->
    %% The diagrams draw no arrow from Stop to FaultReaction: Stop ends, and the fault
    %% follows from Stopped at once.
    transition(done, stop, D#data{fault = {Where, Why}}, fault);
aborted(State, Where, Why, #data{id = Id} = D) ->
    case cell_unit_fsm:next(State, aborted) of
        {ok, _} ->
            transition(aborted, State, D#data{fault = {Where, Why}});
        error ->
            %% Init or Fault: nothing of the unit runs; an actuator reported late.
            cell_log:warning(Id, "in ~ts~ts: ~ts", [cell_unit_fsm:name(State), where_text(Where),
                                                   cell_sequence:format_reason(Why)]),
            keep(State, D)
    end.

%% A fault from outside the sequence: a button, IO lost.
external_fault(stop, Why, D) ->
    {ok, transition(done, stop, D#data{fault = {where(D), Why}}, fault)};
external_fault(State, Why, D) ->
    case cell_unit_fsm:next(State, aborted) of
        {ok, _} -> {ok, transition(aborted, State, D#data{fault = {where(D), Why}})};
        error -> not_allowed
    end.

where(#data{seq = Seq}) -> cell_sequence_runner:where(Seq).

%% Stops every sequence at once; messages of their watches and timers still on the
%% way are recognised as old and dropped.
interrupt(#data{seq = Seq, gen = Gen} = D) ->
    {Seq1, Effects} = cell_sequence_runner:interrupt(Seq),
    {ok, D1} = exec(Effects, undefined, D#data{seq = Seq1}),
    D1#data{gen = Gen + 1, cycle = false}.

%% Sets or releases Halt on the running sequence.
halt_flag(On, State, #data{seq = Seq} = D) ->
    {Outcome, Seq1, Effects} = cell_sequence_runner:set_halt(Seq, On, now_ms()),
    carry_out(Outcome, Effects, State, D#data{halt = On, seq = Seq1}).

%% -------------------------------------------------------------------------------------
%% The controller
%% -------------------------------------------------------------------------------------

control(request, start, State, #data{estop = false} = D) ->
    %% Halt released; then referenced where needed, and on to Automatic.
    case halt_flag(false, State, (member(request, start, D))#data{auto = true}) of
        {Quiet, D1} when Quiet =:= wait; Quiet =:= idle ->
            case cell_unit_fsm:is_non_active(State) andalso arrive(State, D1) of
                {go, Trigger} -> transition(Trigger, State, D1);
                _ -> keep(State, D1)
            end;
        {Outcome, D1} ->
            outcome(Outcome, State, D1)
    end;
control(request, start, State, D) ->
    %% The controller refuses Start during the emergency stop; nothing moves.
    keep(State, D);
control(request, pause, State, D) ->
    {Outcome, D1} = halt_flag(true, State, member(request, pause, D)),
    outcome(Outcome, State, D1);
control(request, stop, State, D0) ->
    D = (member(request, stop, D0))#data{auto = false},
    case cell_unit_fsm:next(State, stop) of
        {ok, _} ->
            transition(stop, State, D#data{halt = false});
        error ->
            {Outcome, D1} = halt_flag(false, State, D),
            outcome(Outcome, State, D1)
    end;
control(estop, {true, Barrier} = Estop, State, D) ->
    %% Secured at once, and counted in the controller's barrier; a unit announces its
    %% state at once, it holds nothing back.
    Result = estop(State, (member(estop, Estop, D))#data{auto = false, halt = false}),
    ok = cell_member:estop_secured(Barrier),
    Result;
control(estop_settled, _, _State, _D) ->
    keep_state_and_data;
control(estop, false, booting, #data{estop = true, error = undefined} = D) ->
    %% The booting sequence was interrupted: it runs again from its start.
    {keep_state, report(booting, booting, member(estop, false, D)),
     [{next_event, internal, entered}]};
control(estop, false, State, D) ->
    keep(State, member(estop, false, D));
control(service_mode, On, State, #data{seq = Seq} = D0) ->
    D = (member(service_mode, On, D0))#data{seq = cell_sequence_runner:set_service(Seq, On)},
    case On of
        true ->
            %% The seed: DOWN after the current motion, speeds limited afterwards.
            {Outcome, D1} = halt_flag(true, State, D),
            outcome(Outcome, State, D1);
        false ->
            keep(State, D)
    end;
control(settings, Settings, State, D) when is_map(Settings) ->
    %% In force from the next GoHome, when the unit starts over.
    keep(State, (member(settings, Settings, D))#data{settings = Settings}).

%% A command of the controller, kept as every member keeps it (see cell_member).
member(Key, Value, #data{request = Request, estop = Estop, service = Service} = D) ->
    #{request := Request1, estop := Estop1, service_mode := Service1} =
        cell_member:controlled(Key, Value, #{request => Request, estop => Estop,
                                             service_mode => Service}),
    D#data{request = Request1, estop = Estop1, service = Service1}.

%% The emergency stop: everything stops at once and the outputs are made safe.
estop(State, D0) ->
    D = interrupt(D0),
    secure(D),
    case State of
        stop -> transition(done, stop, D);
        fault_reaction -> transition(done, fault_reaction, D);
        stopped -> keep(stopped, D);
        _ ->
            case cell_unit_fsm:next(State, stop) of
                {ok, _} -> transition(stop, State, D);
                error -> keep(State, D)           %% booting, init, fault
            end
    end.

%% -------------------------------------------------------------------------------------
%% Buttons
%% -------------------------------------------------------------------------------------

button(Button, From, State, #data{decl = #{user_states := Users, actions := Actions}} = D) ->
    Moves = case Button of
                go_home -> true;
                start -> true;
                {user, _} -> true;
                {action, _} -> true;
                _ -> false
            end,
    Check = case Button of
                _ when Moves, D#data.estop -> {error, estop_active};
                {user, X} -> known(lists:member(X, Users), {unknown_user_state, X});
                {action, A} -> known(lists:member(A, Actions), {unknown_action, A});
                _ -> ok
            end,
    case Check of
        ok -> press(Button, From, State, D);
        Error -> {keep_state_and_data, [{reply, From, Error}]}
    end.

known(true, _) -> ok;
known(false, Why) -> {error, Why}.

press({abort, Reason}, From, State, D) ->
    case external_fault(State, Reason, D) of
        {ok, Result} -> with_reply(From, ok, Result);
        not_allowed -> not_allowed(From, {abort, Reason}, State)
    end;
press(Button, From, State, D) ->
    case cell_unit_fsm:next(State, Button) of
        {ok, _} when Button =:= stop -> with_reply(From, ok, transition(stop, State, D#data{auto = false}));
        {ok, _} -> with_reply(From, ok, transition(Button, State, D));
        error -> not_allowed(From, Button, State)
    end.

not_allowed(From, Button, State) ->
    {keep_state_and_data, [{reply, From, {error, {not_allowed, Button, State}}}]}.

with_reply(From, Reply, {next_state, S, D, Actions}) ->
    {next_state, S, D, [{reply, From, Reply} | Actions]};
with_reply(From, Reply, {keep_state, D, Actions}) ->
    {keep_state, D, [{reply, From, Reply} | Actions]};
with_reply(From, Reply, {keep_state, D}) ->
    {keep_state, D, [{reply, From, Reply}]}.

%% -------------------------------------------------------------------------------------
%% Errors for the operator
%% -------------------------------------------------------------------------------------

raise(Origin, Spec, #data{id = Id} = D0) ->
    D = withdraw(D0),
    {ok, AlarmId} = cell_alarms:raise_error(Id, Spec, self()),
    D#data{error = {AlarmId, Origin}}.

withdraw(#data{error = {AlarmId, _}} = D) ->
    ok = cell_alarms:withdraw(AlarmId),
    D#data{error = undefined};
withdraw(D) ->
    D.

answered(booting, retry, booting, D) ->
    {keep_state, D, [{next_event, internal, entered}]};
answered(fault, retry, State, D) ->
    %% Offered for a lost connection only: the same as Reset.
    answered(fault, reset, State, D);
answered(_Origin, reset, State, #data{request = Request} = D0) ->
    %% Reset: referenced (GoHome) now if the cell runs, else at the next Start.
    D = D0#data{auto = Request =:= start},
    case cell_unit_fsm:is_non_active(State) andalso arrive(State, D) of
        {go, Trigger} -> transition(Trigger, State, D);
        _ -> keep(State, D)
    end;
answered(_Origin, _Solution, State, D) ->
    keep(State, D).

fault_error(Where, {io_lost, _Conn} = Why) ->
    io_error(Where, Why);
fault_error(Where, {io, _Point, disconnected} = Why) ->
    %% A point written or read while its connection was down, before the news of the
    %% loss came: the same.
    io_error(Where, Why);
fault_error(Where, Why) ->
    Reason = cell_sequence:format_reason(Why),
    cell_task:error_spec(
      <<"fault">>, Reason,
      io_lib:format("The unit stopped on a fault~ts: ~ts.~nCheck the machine, then select "
                    "RESET: the unit references itself (GoHome) when the cell runs.",
                    [where_text(Where), Reason]),
      [reset]).

%% As a device task's lost IO: answered once the connection is back.
io_error(Where, Why) ->
    Reason = cell_sequence:format_reason(Why),
    cell_task:error_spec(
      <<"io">>, Reason,
      io_lib:format("The unit stopped on a fault~ts: ~ts.~nOnce the connection is back, "
                    "select RETRY (or RESET): the unit references itself (GoHome) when "
                    "the cell runs.", [where_text(Where), Reason]),
      [retry, reset]).

booting_error(Where, Why) ->
    cell_task:error_spec(
      <<"booting">>, "Booting failed",
      io_lib:format("The unit could not get its equipment ready~ts: ~ts.~nCheck the "
                    "connection and the equipment, then select RETRY.",
                    [where_text(Where), cell_sequence:format_reason(Why)]),
      [retry]).

crash_error(Why) ->
    cell_task:error_spec(
      <<"crashed">>, "Unit restarted after a crash",
      io_lib:format("The unit stopped unexpectedly and was restarted: ~ts.~nIts outputs "
                    "were made safe; where its actuators are is not known.~nCheck the "
                    "machine, then select RESET: the unit references itself (GoHome) when "
                    "the cell runs.", [cell_member:crash_text(Why)]),
      [reset]).

where_text(#{module := undefined}) -> "";
where_text(#{module := Mod, step := Step}) ->
    io_lib:format(" (sequence ~ts, step ~ts)", [Mod, step_text(Step)]).

step_text(S) when is_atom(S) -> atom_to_list(S);
step_text(S) -> io_lib:format("~tp", [S]).

%% -------------------------------------------------------------------------------------
%% IO
%% -------------------------------------------------------------------------------------

%% The connections of the unit's IO groups, watched: losing one aborts what runs.
subscribe_io(#data{spec = Spec, conns = Conns} = D) ->
    New = lists:usort([Conn || Group <- maps:get(io, Spec, []),
                               {ok, Conn} <- [cell_hal:connection_of(Group)],
                               not is_map_key(Conn, Conns)]),
    %% Known already, or a group not configured yet (its points fail when used,
    %% naming them).
    resubscribe(New, D).

%% A connection the HAL's server could not subscribe to, being away (it restarts), is
%% down for the unit, as a lost connection is: what runs is aborted (the unit stops on
%% the fault) and GoHome refuses to start. It is subscribed to again when the HAL says
%% it is back.
resubscribe(Conns, D) ->
    lists:foldl(
      fun(Conn, #data{conns = Cs, away = Away, back = Back} = Di) ->
              case cell_hal:subscribe_connection(Conn) of
                  {ok, Status} ->
                      Di#data{conns = Cs#{Conn => Status}};
                  {error, disconnected} ->
                      cell_log:warning(Di#data.id, "the HAL is restarting: connection ~ts "
                                       "is taken as lost until it is back", [Conn]),
                      Di#data{conns = Cs#{Conn => down}, away = lists:usort([Conn | Away]),
                              back = case Back of
                                         undefined -> cell_hal:notify_back();
                                         _ -> Back
                                     end};
                  {error, unknown_connection} ->
                      Di
              end
      end, D, Conns).

connection(Conn, down, State, #data{conns = Conns} = D0) when is_map_key(Conn, Conns) ->
    D = D0#data{conns = Conns#{Conn => down}},
    %% Stopped is OFF: as for a device task that is OFF, a connection lost is no fault
    %% (the node stopping takes the HAL down before its units); GoHome, which leaves
    %% it, checks the IO first.
    case cell_unit_fsm:is_active(State) orelse State =:= idle of
        true ->
            case external_fault(State, {io_lost, Conn}, D) of
                {ok, Result} -> Result;
                not_allowed -> keep(State, D)   %% booting (its writes fail), fault_reaction
            end;
        false ->
            keep(State, D)
    end;
connection(Conn, Status, State, #data{conns = Conns} = D) when is_map_key(Conn, Conns) ->
    keep(State, D#data{conns = Conns#{Conn => Status}});
connection(_Conn, _Status, _State, _D) ->
    keep_state_and_data.

%% Carries out what the sequences returned, in order. An output or a watch the HAL
%% refuses stops there: the sequence is aborted with the reason.
exec([], _State, D) ->
    {ok, D};
exec(Effects, State, D0) ->
    {Verbose, D} = verbose(D0),
    exec(Effects, State, Verbose, D).

exec([], _State, _Verbose, D) ->
    {ok, D};
exec([{step, _, _, _}, {step, _, _, _} = Next | Rest], State, false, D) ->
    %% Steps entered one after another in one go, none logged: only the last one is
    %% the unit's step once they are carried out, the others need no update of #data.
    exec([Next | Rest], State, false, D);
exec([{step, Depth, Mod, Step} | Rest], State, Verbose, #data{id = Id} = D) ->
    case Verbose of
        true -> cell_log:debug(Id, "~ts~ts: step ~ts",
                               [lists:duplicate(2 * (Depth - 1), $\s), Mod, step_text(Step)]);
        false -> ok
    end,
    exec(Rest, State, Verbose, D#data{step = {Depth, Mod, Step}});
exec([E | Rest], State, Verbose, D) ->
    case exec1(E, State, D) of
        {ok, D1} -> exec(Rest, State, Verbose, D1);
        {error, _, _} = Error -> Error
    end.

exec1({write, {G, P}, V}, _State, D) ->
    case cell_hal:write(G, P, V) of
        ok -> {ok, D};
        {error, Why} -> {error, {io, {G, P}, Why}, D}
    end;
exec1({watch, Key, {G, P}, Cond}, _State, D0) ->
    D = cancel_watch(Key, D0),
    case cell_hal:watch(G, P, Cond) of
        {ok, Ref} ->
            {ok, D#data{watches = (D#data.watches)#{Key => Ref}, refs = (D#data.refs)#{Ref => {Key, {G, P}}}}};
        {error, Why} ->
            {error, {io, {G, P}, Why}, D}
    end;
exec1({cancel_watch, Key}, _State, D) ->
    {ok, cancel_watch(Key, D)};
exec1({timer, Key, Ms}, _State, D0) ->
    D = cancel_timer(Key, D0),
    TRef = erlang:start_timer(Ms, self(), ?TIMER(Key)),
    {ok, D#data{timers = (D#data.timers)#{Key => TRef}}};
exec1({cancel_timer, Key}, _State, D) ->
    {ok, cancel_timer(Key, D)};
exec1({ipc, Event}, State, #data{ready = Ready, task = T} = D) ->
    case State of
        automatic -> {ok, ipc_event(Event, Ready, T, State, D)};
        {user, _} -> {ok, ipc_event(Event, Ready, T, State, D)};
        _ -> {error, {not_ready, Event, State}, D}
    end.

%% Whether steps are logged, asked once for all the effects of an event. The answer is
%% kept: the question comes with every cycle, and cell_log is asked again only once
%% a threshold has changed.
verbose(#data{id = Id, verbose = Kept} = D) ->
    Version = cell_log:levels_version(),
    case Kept of
        {Version, On} ->
            {On, D};
        _ ->
            On = cell_log:enabled(verbose, Id),
            {On, D#data{verbose = {Version, On}}}
    end.

%% An IPC-2541 event of the sequence: published, and the state it leads to reported at
%% once, as a task's events are.
ipc_event(Event, Ready, T, State, D) ->
    ok = cell_task:publish(T, Event, #{}),
    {ready, A, B} = cell_ipc:event_state(Event, ready_state(Ready)),
    report(State, State, D#data{ready = sub_state({ready, A, B})}).

ready_state(starved) -> {ready, idle, starved};
ready_state(blocked) -> {ready, idle, blocked};
ready_state(active) -> {ready, processing, active};
ready_state(executing) -> {ready, processing, executing}.

sub_state({ready, _, Sub}) -> Sub.

cancel_watch(Key, #data{watches = W, refs = R} = D) ->
    case maps:take(Key, W) of
        {Ref, W1} ->
            _ = cell_hal:cancel_watch(Ref),
            D#data{watches = W1, refs = maps:remove(Ref, R)};
        error ->
            D
    end.

cancel_timer(Key, #data{timers = T} = D) ->
    case maps:take(Key, T) of
        {TRef, T1} ->
            _ = erlang:cancel_timer(TRef),
            D#data{timers = T1};
        error ->
            D
    end.

%% The actuators' safe positions and the unit's safe outputs. A write that fails is
%% logged: nothing may keep a unit from stopping.
secure(#data{id = Id, seq = Seq, decl = #{safe_outputs := Safe}, spec = Spec}) ->
    Io = maps:get(io, Spec, []),
    Writes = cell_sequence_runner:secure(Seq)
        ++ [{write, safe_point(P, Io), V} || {P, V} <- Safe, safe_point(P, Io) =/= none],
    lists:foreach(
      fun({write, {G, P}, V}) ->
              try cell_hal:write(G, P, V) of
                  ok -> ok;
                  {error, Why} ->
                      cell_log:error(Id, "could not make output ~ts.~ts safe: ~tp", [G, P, Why])
              catch
                  exit:Why ->
                      cell_log:error(Id, "could not make output ~ts.~ts safe: ~tp", [G, P, Why])
              end
      end, Writes).

safe_point({G, P}, _Io) -> {G, P};
safe_point(P, [G | _]) -> {G, P};
safe_point(_P, []) -> none.

%% -------------------------------------------------------------------------------------
%% Reporting
%% -------------------------------------------------------------------------------------

%% The unit's IPC-2541 state follows from its lifecycle state; every change of either
%% goes to the registry and out as a task_state event.
report(Old, New, #data{id = Id, ipc = FromIpc, task = T, trigger = Trigger} = D) ->
    ToIpc = ipc(New, D),
    case Old =:= New andalso ToIpc =:= FromIpc of
        true ->
            D;
        false ->
            ok = cell_registry:set_state(Id, ToIpc),
            Cause = case Old =:= New of
                        true -> unit;
                        false ->
                            ok = cell_registry:update(Id, #{unit_state => New}),
                            {unit, Trigger}
                    end,
            ok = cell_task:publish(T, task_state, #{state => ToIpc, from => FromIpc,
                                                    cause => Cause, unit_state => New,
                                                    unit_from => Old}),
            ok = cell_controller:task_state_changed(),
            log_change(Old, New, FromIpc, ToIpc, D),
            D#data{ipc = ToIpc}
    end.

log_change(Same, Same, FromIpc, ToIpc, #data{id = Id}) ->
    case cell_log:enabled(verbose, Id) of
        true -> cell_log:debug(Id, "~ts -> ~ts", [cell_ipc:name(FromIpc), cell_ipc:name(ToIpc)]);
        false -> ok
    end;
log_change(undefined, New, _FromIpc, _ToIpc, #data{id = Id}) ->
    cell_log:info(Id, "~ts", [cell_unit_fsm:name(New)]);
log_change(Old, New, _FromIpc, ToIpc, #data{id = Id, trigger = Trigger}) ->
    cell_log:info(Id, "~ts -> ~ts (~ts; ~ts)",
                  [cell_unit_fsm:name(Old), cell_unit_fsm:name(New), trigger_text(Trigger),
                   cell_ipc:name(ToIpc)]).

trigger_text({user, X}) -> ["button ", atom_to_list(X)];
trigger_text({action, A}) -> ["button ", atom_to_list(A)];
trigger_text(T) when is_atom(T) -> atom_to_list(T).

ipc(State, #data{estop = Estop, ready = Ready, decl = #{idle := Idle}} = D) ->
    cell_unit_fsm:ipc(State, #{estop => Estop, halted => halted(State, D), ready => Ready,
                               idle => Idle}).

%% Halt has taken hold: asked for, and the sequence holds (or none runs).
halted(State, #data{halt = Halt, seq = Seq}) ->
    Halt andalso cell_unit_fsm:haltable(State)
        andalso (cell_sequence_runner:held(Seq) orelse not cell_sequence_runner:running(Seq)).

describe(State, #data{id = Id, ipc = Ipc, error = Error, fault = Fault, seq = Seq} = D) ->
    #{id => Id, kind => unit, state => Ipc, unit_state => State, request => D#data.request,
      estop => D#data.estop, service_mode => D#data.service, halt => D#data.halt,
      down => case {Error, Ipc} of
                  {{AlarmId, Origin}, _} -> {error, AlarmId, Origin};
                  {undefined, down} when D#data.halt, D#data.service -> {paused, service};
                  {undefined, down} when D#data.halt -> {paused, pause};
                  _ -> undefined
              end,
      fault => case Fault of
                   undefined -> undefined;
                   {Where, Why} -> iolist_to_binary([cell_sequence:format_reason(Why),
                                                     where_text(Where)])
               end,
      step => D#data.step, sequence => cell_sequence_runner:describe(Seq),
      product => undefined, settings => D#data.in_force}.

%% A reply no sequence waits for any more: it came after the step that asked was
%% interrupted or timed out. Late, not wrong: dropped.
late_reply(Msg, #data{id = Id}) ->
    cell_log:trace(Id, "dropped a reply it no longer waits for: ~tp", [Msg]),
    keep_state_and_data.

now_ms() ->
    erlang:monotonic_time(millisecond).
