%% @doc The engine of a device task: a gen_statem whose states are exactly the
%% IPC-2541 states of seed 000 §2.2, running a {@link cell_task} module.
%%
%% <pre>
%%  state                      what the engine does there
%%  off                        nothing runs; Start (no emergency stop) → setup (arrow 0)
%%  setup                      runs init, then reconcile: ok → READY (1), an error
%%                             of either → down (7); an answer to reconcile's runs
%%                             reconcile again (8)
%%  {ready, _, _}              runs steps; a step waits for a message (IO, timer,
%%                             reply), never sleeps. Pause, Stop and service mode are
%%                             honoured between steps → down (6); Reset → setup (2)
%%  down                       paused (Start → READY where it was, 5), or an error
%%                             waits for the operator (Retry/Ignore/Close → READY 5,
%%                             Reset → uninit, setup 8); Stop → uninit, off (9)
%%  any                        emergency stop → uninit, off, at once
%% </pre>
%%
%% The emergency stop is also an atomic flag checked before every step and every init,
%% so no step starts after it was raised, even before its message arrives here.
%%
%% The controller's emergency stop comes with a barrier: the task secures its outputs at
%% once, then holds back the bookkeeping of OFF (its new state recorded and announced,
%% its waits cancelled) until the controller says every task has secured its outputs.
%% Announcements woke the controller, the statistics and every subscriber while tasks
%% further down the fan-out were still waiting for a scheduler to secure theirs. A held
%% task runs no step; any other message ends the hold first.
%%
%% A connection of the task's IO lost while it runs takes it DOWN ("IO connection
%% lost"). When the operator retries with the connection back, the task goes on with
%% its outputs as it last commanded them: each output of that connection's groups the
%% task commanded (through {@link cell_task:out/4}) and the device no longer holds as
%% commanded (a write lost with the connection, a PLC that took its outputs to safe
%% values; the HAL reads them back at reconnect) is written again, and the log says
%% which, before its waits are armed again or its step runs again (see
%% {@link cell_task_outputs}). Securing (uninit: Stop, Reset, emergency stop) and init
%% start that record afresh, so a secured output is never set again by this path.
%%
%% After a crash the supervisor restarts the task; it restores its product from its
%% file, reads its outputs as the crashed incarnation left them and secures them
%% (uninit). If the cell runs, the task then initialises and reconciles as after any
%% start: its `reconcile' holds what its predecessor held against its inputs and either
%% agrees (the task goes on by itself: the crash is in the log and a warning) or asks
%% the operator where they disagree. The engine asks itself ("Task restarted after a
%% crash", Retry or Reset) only where reconcile cannot decide: the task died in init or
%% reconcile, or died again after going on by itself before it first waited, so a
%% crash that restarting does not cure never loops. Whatever the way into setup, init is
%% followed by the task's `reconcile' with what its predecessor held (see
%% {@link cell_task}): the task checks its record against its inputs before its first
%% step.
-module(cell_task_proc).
-behaviour(gen_statem).

-include("cell_task.hrl").
-include("cell_task_engine.hrl").

-export([start_link/1, child_spec/1, control/3, estop_secured/1, whereis/1, state/1, info/1,
         info/2, sync/1]).
-export([callback_mode/0, init/1, handle_event/4, terminate/3]).

-export_type([estop_barrier/0]).

%% The controller's emergency stop (see cell_member).
-type estop_barrier() :: cell_member:estop_barrier().

-define(STEP(Gen), {'$cell_step', Gen}).
-define(WAIT(Gen), {'$cell_wait', Gen}).
%% Room on the heap for what an emergency stop allocates (see headroom/0): about 8 KB.
-define(MIN_HEAP_WORDS, 987).

%% API

%% @doc Starts a task and returns once it has booted: registered with the cell, its
%% product loaded, its state decided. The controller never sees a half-started task.
-spec start_link(cell_task:spec()) -> gen_statem:start_ret().
start_link(Spec) ->
    case gen_statem:start_link(?MODULE, Spec, [{spawn_opt, [{min_heap_size, ?MIN_HEAP_WORDS}]}]) of
        {ok, Pid} ->
            %% boot is the first event the task handles; a call is answered after it.
            ok = sync(Pid),
            {ok, Pid};
        Other ->
            Other
    end.

%% @doc The child spec of a task under cell_task_sup.
-spec child_spec(cell_task:spec()) -> supervisor:child_spec().
child_spec(#{id := Id} = Spec) ->
    %% uninit secures the hardware on shutdown: give it time.
    #{id => Id, start => {?MODULE, start_link, [Spec]}, shutdown => 5000}.

%% @doc A command of the controller: `request' (start | pause | stop), `estop'
%% (`{true, Barrier}', see {@link estop_barrier()}, or `false'), `estop_settled' (the
%% barrier's atomics: every task secured its outputs), `service_mode' (boolean),
%% `settings' (the snapshot for the next start).
-spec control(pid(), request | estop | estop_settled | service_mode | settings, term()) -> ok.
control(Pid, Key, Value) ->
    cell_member:control(Pid, Key, Value).

%% @doc The pid of a running task.
-spec whereis(atom()) -> pid() | undefined.
whereis(Id) ->
    case cell_registry:task(Id) of
        {ok, #{pid := Pid}} -> Pid;
        _ -> undefined
    end.

%% @doc The task's IPC-2541 state, after every message sent to it before.
-spec state(pid() | atom()) -> cell_ipc:state().
state(Task) ->
    gen_statem:call(pid(Task), state).

%% @doc State, request, why it is DOWN, what it waits for (`waits', the waits of its
%% last step while it waits), its phase (if its module keeps one), its product.
-spec info(pid() | atom()) -> map().
info(Task) ->
    gen_statem:call(pid(Task), info).

%% @doc As {@link info/1}, waiting at most `Timeout' milliseconds.
-spec info(pid() | atom(), timeout()) -> map().
info(Task, Timeout) ->
    gen_statem:call(pid(Task), info, Timeout).

%% @doc Returns once the task has handled every message sent to it before.
-spec sync(pid() | atom()) -> ok.
sync(Task) ->
    gen_statem:call(pid(Task), sync).

pid(Pid) when is_pid(Pid) -> Pid;
pid(Id) when is_atom(Id) ->
    case ?MODULE:whereis(Id) of
        undefined -> erlang:error({no_such_task, Id});
        Pid -> Pid
    end.

%% gen_statem

-spec callback_mode() -> gen_statem:callback_mode_result().
callback_mode() ->
    [handle_event_function, state_enter].

-spec init(cell_task:spec()) -> gen_statem:init_result(cell_ipc:state()).
init(Spec) ->
    process_flag(trap_exit, true),
    Task = cell_task:new(Spec),
    {ok, off, #engine{task = Task, spec = Spec, settings = Task#task.settings,
                      estop_flag = cell_registry:estop_flag()},
     [{next_event, internal, boot}]}.

-spec handle_event(gen_statem:event_type(), term(), cell_ipc:state(), #engine{}) ->
          gen_statem:event_handler_result(cell_ipc:state()).

%% The engine's state is the task's state: every change went through cell_task:set_state/3,
%% which checked it against the seed's table and told the cell.
handle_event(enter, _Old, State, #engine{task = #task{ipc = State}}) ->
    keep_state_and_data;

%% Secured by the emergency stop, waiting for the others to secure theirs: the
%% controller's word that they have ends the hold, and so does anything else.
handle_event(info, {control, estop_settled, Held}, State, #engine{held = Held} = D) ->
    leave(off, State, D);
handle_event(Type, Msg, State, #engine{held = Held} = D) when Held =/= undefined, Type =/= enter ->
    {next_state, off, D1, Actions} = leave(off, State, D),
    {next_state, off, D1, Actions ++ [{next_event, Type, Msg}]};

%% --------------------------------------------------------------------------------------
%% off
%% --------------------------------------------------------------------------------------
handle_event(internal, boot, off, D) ->
    boot(D);

%% --------------------------------------------------------------------------------------
%% setup: init runs within the event that entered the state
%% --------------------------------------------------------------------------------------
handle_event(internal, run_init, setup, D) ->
    run_init(D);
handle_event(internal, {reconcile, Woken}, setup, D) ->
    run_reconcile(Woken, undefined, D);
handle_event(internal, {crashed, Reason}, setup, D) ->
    raise(setup, crash_error(Reason, D), crash, D);
handle_event(internal, product_damaged, setup, D) ->
    raise(setup, damaged_error(D), product_file, D);
handle_event(internal, retain_damaged, setup, D) ->
    raise(setup, retain_damaged_error(D), retain_file, D);
handle_event(internal, in_transit, setup, D) ->
    raise(setup, transit_error(D), transit, D);

%% --------------------------------------------------------------------------------------
%% READY: steps, waits, and the requests honoured between steps
%% --------------------------------------------------------------------------------------
handle_event(info, ?STEP(Gen), {ready, _, _} = S, #engine{gen = Gen, pending = {step, _}} = D) ->
    run_step(S, D);
handle_event(internal, step, {ready, _, _} = S, D) ->
    run_step(S, D);
handle_event(info, {timeout, _, ?WAIT(Gen)} = Msg, {ready, _, _} = S,
             #engine{gen = Gen} = D) ->
    wait_news(Msg, S, D);
handle_event(info, {cell_hal_watch, _, _} = Msg, {ready, _, _} = S, D) ->
    wait_news(Msg, S, D);
handle_event(info, {cell_hal_unavailable, _, _} = Msg, {ready, _, _} = S, D) ->
    wait_news(Msg, S, D);
handle_event(info, {cell_hal_conn, Conn, down}, {ready, _, _} = S, D) ->
    %% The task's IO is gone: nothing it reads can be trusted.
    proceed(cell_task_core:io_lost(Conn, S, D));
handle_event(info, {Ref, _} = Msg, {ready, _, _} = S, D) when is_reference(Ref) ->
    wait_news(Msg, S, D);

%% --------------------------------------------------------------------------------------
%% down: paused, or an error waiting for the operator
%% --------------------------------------------------------------------------------------
handle_event(internal, stop, down, D) ->
    leave(stop, down, D);
handle_event(info, {cell_alarm, answer, Id, Solution, Who}, down,
             #engine{down = {error, Id, Origin}, task = T} = D) ->
    %% A copy found older than another task's record (the registry's word may still be
    %% on its way) is dropped before the answer is acted on, as if that word had come
    %% first: the answer was accepted because this task no longer holds the product.
    answered(Origin, Solution, Who, D#engine{task = drop_if_older(T)});
handle_event(info, {Ref, _} = Msg, down, D) when is_reference(Ref) ->
    %% An answer the task will wait for when it resumes: keep it for then.
    case D#engine.pending of
        {waits, Waits} ->
            case lists:member({reply, Ref}, Waits) of
                true -> {keep_state_and_data, [postpone]};
                false -> late_reply(Msg, D)
            end;
        _ ->
            late_reply(Msg, D)
    end;

%% --------------------------------------------------------------------------------------
%% every state
%% --------------------------------------------------------------------------------------
%% A command of the controller: kept as every member keeps it, then what it does here
%% is cell_task_core's to say (an `estop_settled' reaching a task not held is the end of
%% a barrier it did not hold at: it was OFF already).
handle_event(info, {control, Key, Value}, State, D) ->
    {D1, Action} = cell_task_core:control(Key, Value, State, D),
    controlled(Action, State, D1);
handle_event(info, ?STEP(_), _State, _D) ->
    keep_state_and_data;
handle_event(info, {timeout, _, ?WAIT(_)}, _State, _D) ->
    keep_state_and_data;
handle_event(info, {cell_alarm, answer, _Id, _Solution, _Who}, _State, _D) ->
    %% An answer to an error this task has since withdrawn (stop, emergency stop).
    keep_state_and_data;
handle_event(info, {cell_handshake, _, _} = Msg, State, D) ->
    handshake(Msg, State, D);
handle_event(info, {cell_handshake, _, _, _} = Msg, State, D) ->
    handshake(Msg, State, D);
handle_event(info, {cell_handshake_watch, _, _, _, _} = Msg, State, D) ->
    handshake(Msg, State, D);
handle_event(info, {{'LINK_DOWN', _}, _, process, _, _} = Msg, State, D) ->
    handshake(Msg, State, D);
handle_event(info, {cell_hal_conn, Conn, Status}, _State, D) ->
    {keep_state, cell_task_core:conn_status(Conn, Status, D)};
handle_event(info, {cell_hal_watch, _Ref, _Value}, _State, _D) ->
    %% A watch of a wait the task has since left.
    keep_state_and_data;
handle_event(info, {cell_hal_unavailable, _Ref, _Why}, _State, _D) ->
    keep_state_and_data;
handle_event(info, {cell_registry, stale, Serial, Gen}, State, #engine{task = T0} = D) ->
    %% Running on a copy found old (another task took the product on in a newer record
    %% after this one restarted): what it does rests on a product it does not hold.
    T = drop_stale(T0, Serial, Gen),
    Dropped = T#task.product =:= undefined andalso T0#task.product =/= undefined,
    case cell_task_core:stale(Serial, Dropped, State, D#engine{task = T}) of
        {ask, Transition} ->
            %% The same serial back again (read again on a part its sensors see):
            %% dropping it once more would go round for ever. The operator sees to the
            %% part.
            handed_on_again(State, Serial, carry_out(Transition));
        Transition ->
            transit(Transition)
    end;
handle_event(info, {cell_registry, sole_holder, _} = Msg, State, D) ->
    handshake(Msg, State, D);
handle_event(info, {cell_registry, forget, Serial, Who}, State, D) ->
    forget(State, Serial, Who, D);
handle_event(info, {Ref, _} = Msg, _State, D) when is_reference(Ref) ->
    late_reply(Msg, D);
handle_event(info, {'EXIT', _Pid, Reason}, _State, _D) ->
    case cell_member:exit_signal(Reason) of
        ignore -> keep_state_and_data;
        Stop -> Stop
    end;
handle_event(info, Msg, _State, D) ->
    %% HAL news of a point the task's code subscribed to, a hardware object's message:
    %% the task module's, if it takes them; anything else is a bug.
    stray(Msg, D);
handle_event({call, From}, state, State, _D) ->
    {keep_state_and_data, [{reply, From, State}]};
handle_event({call, From}, sync, _State, _D) ->
    {keep_state_and_data, [{reply, From, ok}]};
handle_event({call, From}, info, State, D) ->
    {keep_state_and_data, [{reply, From, describe(State, D)}]}.

-spec terminate(term(), cell_ipc:state(), #engine{}) -> ok.
terminate(Reason, _State, #engine{task = #task{id = Id}} = D) ->
    %% Whatever ended the task, its outputs are left safe.
    _ = carry_out(cell_task_core:uninit(D)),
    cell_member:leave(Id, Reason).

%% --------------------------------------------------------------------------------------
%% Boot, start and init
%% --------------------------------------------------------------------------------------

boot(#engine{task = #task{id = Id, module = Mod} = T, spec = Spec} = D0) ->
    {Previous, Controls} = cell_member:join(Spec, #{}),
    D2 = retained(joined(Controls, D0)),
    %% A product's own fields may name atoms only the task's module holds: loaded
    %% before its file is read, on a node just started too (cell_product names its
    %% own), whatever read the retained data first.
    {module, Mod} = code:ensure_loaded(Mod),
    D = case cell_product:load(T#task.product_path) of
            {ok, Stored} ->
                D2#engine{task = restore(D2#engine.task, Stored)};
            {error, Reason} ->
                cell_log:error(Id, "the product file ~ts cannot be read (~tp); the "
                               "operator is asked when the cell starts",
                               [T#task.product_path, Reason]),
                D2#engine{load_error = Reason, task = cell_handshake:attach_all(D2#engine.task)}
        end,
    case Previous of
        {crashed, Why} ->
            %% The outputs of the crashed incarnation may still be set: read as it
            %% left them, for reconcile.
            proceed(cell_task_core:crashed(Why, ask_after_crash(Id), outputs(D#engine.task),
                                           D));
        _ ->
            start_from_off(D)
    end.

%% The task's retained data, as its file holds them; a file that cannot be read is the
%% operator's question before the task runs, never an empty store.
retained(#engine{task = #task{id = Id, retain_path = Path} = T} = D) ->
    case cell_task:load_retained(T) of
        {ok, T1} ->
            D#engine{task = T1, retain_error = undefined};
        {error, Reason} ->
            cell_log:error(Id, "the retained data file ~ts cannot be read: ~ts; the task "
                           "does not run: the operator is asked when the cell starts",
                           [Path, cell_retain:text(Reason)]),
            D#engine{retain_error = Reason}
    end.

%% Whether the operator is asked about the crash rather than the task's reconcile: the
%% task died where reconcile cannot decide (in init or reconcile itself), or it died
%% again after it had gone on by itself from a crash, before its first wait (a fault
%% that restarting does not cure: it would loop).
ask_after_crash(Id) ->
    case cell_registry:task(Id) of
        {ok, Row} -> cell_task_core:ask_after_crash(Row);
        _ -> false
    end.

%% A crash the task goes on from by itself is never silent: a warning says so until an
%% operator closes it (and the alarms' history keeps who did).
crash_warning(Why, #engine{task = #task{id = Id, product = P}}) ->
    cell_alarms:warning(
      Id, <<"crash_resumed">>, "Task restarted after a crash",
      io_lib:format("The task stopped unexpectedly and was restarted: ~ts.~nIts outputs "
                    "were secured. Before it moves again it holds its record (product ~ts) "
                    "against its sensors: where they agree it goes on by itself, where "
                    "they do not it asks you with an error of its own.~nNothing else is "
                    "needed. If this warning comes back, report it to maintenance with the "
                    "log. Close it once read.",
                    [cell_member:crash_text(Why), cell_task_core:serial_text(P)])).

%% Boot, or Start in OFF: cell_task_core:start/1 says whether the task starts.
start_from_off(D) ->
    transit(cell_task_core:start(D)).

run_init(#engine{retain_error = Why} = D) when Why =/= undefined ->
    %% However setup was entered (a Reset, a product forgotten), nothing runs without
    %% the task's retained data.
    raise(setup, retain_damaged_error(D), retain_file, D);
run_init(D) ->
    case estop_raised(D) of
        true -> leave(estop, setup, D#engine{estop = true});
        false -> proceed(io_check(D))
    end.

%% init, every IO group of the task configured and its connection up.
init_task(#engine{task = #task{module = Mod} = T0} = D) ->
    %% init commands the outputs afresh.
    T = T0#task{answer = undefined, woken_by = undefined, commanded = cell_task_outputs:new()},
    %% Taken before init writes an output.
    D1 = D#engine{predecessor = predecessor(D), lost = []},
    Result = setup_call(fun() -> Mod:init(T) end, bad_init_result, Mod),
    proceed(cell_task_core:inited(Result, D1)).

%% What the task's predecessor left (cell_task:held()): taken once per way into setup,
%% kept while reconcile asks the operator.
predecessor(#engine{predecessor = #{} = Held}) ->
    Held;
predecessor(#engine{cause = Cause, crash_outputs = Crashed, task = T}) ->
    #{cause => Cause, product => T#task.product, marker => T#task.marker,
      links => maps:map(fun(_, View) -> maps:get(phase, View, idle) end, T#task.links),
      outputs => case Crashed of
                     undefined -> outputs(T);
                     _ -> Crashed
                 end}.

%% The outputs of the task's IO groups as last commanded (the HAL keeps them); those
%% it cannot read are left out.
outputs(#task{io = Groups}) ->
    maps:from_list(
      [{G, maps:from_list([{P, V} || #{name := P, dir := out} <- Points,
                                     {ok, V} <- [cell_hal:read(G, P)]])}
       || G <- Groups, {ok, Points} <- [cell_hal:points(G)]]).

%% The task's reconcile, after init and after each answer to the question it asked;
%% `Then' is what the first step is told woke it.
run_reconcile(Woken, Then, #engine{task = #task{module = Mod} = T0, predecessor = Held} = D) ->
    case estop_raised(D) of
        true ->
            leave(estop, setup, D#engine{estop = true});
        false ->
            T = cell_task_core:woken_by(Woken, T0),
            Result = setup_call(fun() -> Mod:reconcile(Held, T) end, bad_reconcile_result, Mod),
            proceed(cell_task_core:reconciled(Result, Then, D))
    end.

%% init or reconcile called: what it returned, or `{io, Spec}' when it read or wrote a
%% point whose connection is down or that its device cannot serve. Anything else is
%% the module's bug (`Bad').
setup_call(Call, Bad, Mod) ->
    try Call() of
        {ok, _} = Ok -> Ok;
        {error, _Spec, _} = Error -> Error;
        Other -> erlang:error({Bad, Mod, Other})
    catch
        throw:{cell_io_lost, Group, _Point, _Commanded} ->
            {io, {io, group_conn(Group)}};
        throw:{cell_io_unavailable, Group, Point, Why} ->
            {io, {point, Group, Point, Why}}
    end.

%% --------------------------------------------------------------------------------------
%% Steps and waits
%% --------------------------------------------------------------------------------------

run_step(State, D0) ->
    case estop_raised(D0) of
        true ->
            leave(estop, State, D0#engine{estop = true});
        false when D0#engine.request =:= start, D0#engine.deferred =:= undefined ->
            %% Running, nothing held back: the common case, at every step.
            do_step(D0);
        false ->
            %% Every step boundary is a wait point: a Pause or Stop that came while the
            %% task was elsewhere (re-initialising after a Reset, say) is honoured here,
            %% unless a transfer holds it back.
            case try_pause(State, D0) of
                {paused, Result} -> Result;
                {hold, D} -> do_step(D)
            end
    end.

do_step(#engine{task = #task{module = Mod, ipc = State} = T0, pending = {step, Woken}} = D) ->
    T = cell_task_core:woken_by(Woken, T0),
    try Mod:step(T) of
        Result -> after_step(cell_task_core:step_result(Mod, Result), D)
    catch
        %% The step read or wrote a point whose connection is down: the step's work is
        %% dropped and runs again, as it was woken, after Retry; what it commanded
        %% before is what is written again then (see reassert/2).
        throw:{cell_io_lost, Group, _Point, Commanded} ->
            io_lost(Group, State, D#engine{task = commanded(Commanded, D#engine.task)});
        %% A point its device cannot serve: the same, the connection itself being up.
        throw:{cell_io_unavailable, Group, Point, Why} ->
            proceed(cell_task_core:unavailable(Group, Point, Why, State, D))
    end.

after_step({continue, T}, #engine{task = #task{ipc = Ipc}} = D) ->
    D1 = D#engine{task = cell_task_core:clean(T), pending = {step, undefined}},
    case T#task.ipc of
        Ipc -> next_step(Ipc, D1);
        New -> {next_state, New, D1, next_step(D1)}
    end;
after_step(Result, D) ->
    proceed(cell_task_core:stepped(Result, D)).

%% The step after a `continue' comes after whatever reached the task meanwhile (a
%% Pause, a Stop, a link's message): a message to itself, behind them. With nothing
%% waiting the step runs at once, which is the same order without the message.
next_step(#engine{gen = Gen}) ->
    case erlang:process_info(self(), message_queue_len) of
        {message_queue_len, 0} -> [{next_event, internal, step}];
        _ -> self() ! ?STEP(Gen), []
    end.

%% As next_step/1, the task staying in `State': with nothing waiting, the next step
%% runs within this event, without a turn through gen_statem (nothing could come
%% between the two: no message is there, and the state is the same).
next_step(State, #engine{gen = Gen} = D) ->
    case erlang:process_info(self(), message_queue_len) of
        {message_queue_len, 0} -> run_step(State, D);
        _ -> self() ! ?STEP(Gen), {keep_state, D}
    end.

%% The waits armed, and what that came to told to cell_task_core:armed/3: all armed,
%% or an IO wait that cannot be placed (the HAL restarting its connections), those
%% armed before it to be left.
arm(Waits, After, #engine{gen = Gen} = D) ->
    arm(Waits, Gen, [], After, D).

arm([], _Gen, Armed, After, D) ->
    proceed(cell_task_core:armed({ok, lists:reverse(Armed)}, After, D));
arm([W | Waits], Gen, Armed, After, #engine{task = T} = D) ->
    case arm_one(W, Gen, T) of
        {io_lost, Group} ->
            proceed(cell_task_core:armed({io_lost, group_conn(Group), lists:reverse(Armed)},
                                         After, D));
        {One, T1} ->
            arm(Waits, Gen, [One | Armed], After, D#engine{task = T1})
    end.

arm_one({timer, Ms}, Gen, T) when is_integer(Ms), Ms >= 0 ->
    {{timer, erlang:start_timer(Ms, self(), ?WAIT(Gen)), Ms}, T};
arm_one({reply, Ref}, _Gen, T) when is_reference(Ref) ->
    {{reply, Ref}, T};
arm_one({handshake, Link, Signal, Value}, Gen, T0)
  when Signal =:= available; Signal =:= not_busy ->
    case cell_handshake:arm(T0, Link, {Signal, Value}) of
        {ok, Ref} ->
            arm_watch(Ref, Link, Signal, Value, T0);
        {link_down, Ms, T1} ->
            %% The link is restarting, or its node is out of reach. Look again after
            %% a backoff: the step runs, sees the link as it is, and offers or waits
            %% again; a greeting of the link ends the wait sooner.
            TRef = erlang:start_timer(Ms, self(), ?WAIT(Gen)),
            {{timer, TRef, {link_down, Link}}, T1}
    end;
arm_one({io, Point, Cond}, Gen, #task{io = [Group | _]} = T) ->
    arm_one({io, Group, Point, Cond}, Gen, T);
arm_one({io, Group, Point, Cond}, _Gen, T) ->
    case cell_hal:watch(Group, Point, Cond) of
        {ok, Ref} -> {{io, Ref, Group, Point}, T};
        {error, disconnected} -> {io_lost, Group};
        {error, Reason} -> erlang:error({bad_wait, {io, Group, Point, Cond}, Reason})
    end;
arm_one(Other, _Gen, _T) ->
    erlang:error({bad_wait, Other}).

arm_watch(Ref, Link, Signal, Value, T0) ->
    %% Seed 000 §2.3.4: a downstream task waiting for an offer is starved.
    T = case cell_task_core:starves(Signal, Value, cell_handshake:available(T0, Link),
                                    T0#task.ipc) of
            true -> cell_task:starved(T0);
            false -> T0
        end,
    {{handshake, Ref, Link, Signal, Value}, T}.

wake(Woken, State, D) ->
    transit(cell_task_core:wake(Woken, State, D)).

%% A timer, a HAL watch or an answer reached a READY task: what it means to its waits
%% is cell_task_core's to say.
wait_news(Msg, State, #engine{armed = Armed} = D) ->
    case cell_task_core:wait_news(Msg, Armed) of
        {wake, Woken} ->
            wake(Woken, State, D);
        {unavailable, Group, Point, Why} ->
            %% The point waited for cannot be served (a PLC refusing its address):
            %% Retry arms the wait again.
            proceed(cell_task_core:unavailable(Group, Point, Why, State, D));
        late ->
            late_reply(Msg, D);
        none ->
            keep_state_and_data
    end.

%% --------------------------------------------------------------------------------------
%% Pause, resume, stop, errors
%% --------------------------------------------------------------------------------------

%% What a command does in the task's state (cell_task_core:control/4), carried out.
controlled(start, _State, D) ->
    start_from_off(D);
controlled(boundary, State, D) ->
    hold_or_pause(State, D);
controlled(resume, _State, D) ->
    resume(D);
controlled(reconcile, State, D) ->
    %% Its product was dropped as an old copy while it was paused: where it was rests
    %% on a product it no longer holds, so it reconciles again instead (as a task
    %% running when its copy is dropped does).
    leave({reconcile, 8}, State, D);
controlled(stop, State, D) ->
    leave(stop, State, D);
controlled({secure, Barrier}, State, D) ->
    {keep_state, carry_out(cell_task_core:leave({secure, Barrier}, State, D))};
controlled({secured, Barrier}, _State, D) ->
    ok = estop_secured(Barrier),
    {keep_state, D};
controlled(keep, _State, D) ->
    {keep_state, D}.

%% A Pause, Stop or service mode reached a READY task. The seed allows stopping only
%% before downstream commits: a transfer under way holds it back until it ends; an
%% open offer is withdrawn first (and made again at resume), unless downstream has
%% just begun to take it.
hold_or_pause(State, D) ->
    at_boundary(try_pause(State, D)).

%% Paused, or going on where it is.
at_boundary({paused, Result}) -> Result;
at_boundary({hold, D}) -> {next_state, (D#engine.task)#task.ipc, D}.

%% What a Pause, Stop or service mode does at this boundary is cell_task_core's to
%% say; the TryAbortOffering it asks for is made here, and its answers told back.
try_pause(State, D) ->
    pause_news(boundary, State, D).

pause_news(Event, State, D) ->
    paused(cell_task_core:pause(Event, State, D), State, D).

%% What cell_task_core:pause/3 said, carried out: `{hold, D}' (the task goes on) or
%% `{paused, Result}'. The TryAbortOffering it asks for are made here, and their
%% answers told back.
paused({go_on, D1}, _State, _D) ->
    {hold, D1};
paused({withdraw, Offers}, State, D) ->
    {Results, T1} = lists:mapfoldl(fun withdraw/2, D#engine.task, Offers),
    pause_news({withdrawn, Results}, State, D#engine{task = T1});
paused({pause, Transition}, _State, _D) ->
    {paused, transit(Transition)}.

withdraw(Link, T) ->
    {Ok, T1} = cell_handshake:try_abort_offering(T, Link),
    {{Link, Ok}, T1}.

%% Arrow 5 (cell_task_core:checked/3 decides): the task's connections looked at
%% first, since the IO it would resume with may still be gone.
resume(#engine{conns = Conns} = D) ->
    Found = [conn_up(Conn, Conns) || Conn <- maps:keys(Conns)],
    proceed(cell_task_core:checked(resume, Found, D)).

%% Going on after a connection of the task's IO was lost: every output of that
%% connection's groups the task commanded and the device does not hold as commanded (a
%% write lost with the connection, a PLC that took its outputs to safe values; the HAL
%% read them back at reconnect) is written again (cell_task_outputs:writes/3 says which).
%% Outputs of connections that stayed up, and anything secured since (uninit clears
%% the image), are left alone. What that came to is cell_task_core:reasserted/3's.
reassert(Ready, D) ->
    proceed(cell_task_core:reasserted(write_again(D), Ready, D)).

write_again(#engine{lost = []}) ->
    {written, []};
write_again(#engine{lost = Lost, task = #task{io = Groups, commanded = Image}}) ->
    Ours = [G || G <- Groups, lists:member(group_conn(G), Lost)],
    Now = maps:from_list([{{G, P}, V} || {G, P} <- maps:keys(Image), lists:member(G, Ours),
                                         {ok, V} <- [cell_hal:read(G, P)]]),
    Writes = cell_task_outputs:writes(Image, Ours, Now),
    case write_all(Writes) of
        ok -> {written, Writes};
        {io_lost, Group} -> {io_lost, group_conn(Group)};
        Unavailable -> Unavailable
    end.

%% What a step dropped at a lost connection had commanded until then.
commanded(Commanded, T) when is_map(Commanded) ->
    T#task{commanded = Commanded}.

write_all([]) ->
    ok;
write_all([{G, P, V} | Rest]) ->
    case cell_hal:write(G, P, V) of
        ok -> write_all(Rest);
        {error, disconnected} -> {io_lost, G};
        {error, {unavailable, Why}} -> {unavailable, G, P, Why};
        {error, Reason} -> erlang:error({io, G, P, Reason})
    end.

%% A request of the task's IO in `State' found the connection of `Group' lost (down,
%% or its HAL process restarting): cell_task_core:io_lost/3.
io_lost(Group, State, D) ->
    proceed(cell_task_core:io_lost(group_conn(Group), State, D)).

raise(State, Spec, Origin, D) ->
    leave({error, alarm(Spec, D), Origin}, State, D).

%% The error raised for the operator; its alarm's id.
alarm(Spec, #engine{task = #task{id = Id}}) ->
    {ok, AlarmId} = cell_alarms:raise_error(Id, error_spec(Spec), self()),
    AlarmId.

%% The operator answered an error: cell_task_core:answered/4's transition, carried
%% out, and then what it takes more than effects to go on with (then/2).
answered(Origin, Solution, Who, D) ->
    proceed(cell_task_core:answered(Origin, Solution, Who, D)).

then(resume, D) ->
    resume(D);
then({reassert, Ready}, D) ->
    reassert(Ready, D);
then({arm, Waits, After}, D) ->
    arm(Waits, After, D);
then(boundary, D) ->
    hold_or_pause((D#engine.task)#task.ipc, D);
then(start, D) ->
    start_from_off(D);
then(init, D) ->
    init_task(D);
then({raise, Spec, Origin, From}, D) ->
    raise(From, Spec, Origin, D);
then({down_again, Spec}, D) ->
    %% Still DOWN: the error is new, its origin the same.
    {keep_state, D#engine{down = {error, alarm(Spec, D), io}}};
then({reconcile, Woken}, D) ->
    run_reconcile(undefined, Woken, D);
then({product_file, set_aside, Who}, #engine{task = #task{id = Id, product_path = Path}} = D) ->
    case set_aside(Path) of
        {ok, Aside} ->
            cell_log:notice(Id, "~ts set the damaged product file aside as ~ts; the task "
                            "starts without a product", [Who, Aside]);
        {error, Why} ->
            %% Still there: read again below, and asked again if still damaged.
            cell_log:error(Id, "the damaged product file ~ts could not be set aside: ~ts",
                           [Path, file:format_error(Why)])
    end,
    then({product_file, reload, Who}, D);
then({product_file, reload, _Who}, #engine{task = #task{product_path = Path} = T} = D) ->
    case cell_product:load(Path) of
        {ok, Stored} ->
            %% Mended (or removed) meanwhile: taken as at boot, and set up as at any
            %% start, so a product marked in transit is the operator's question
            %% before the task can send it on.
            transit(cell_task_core:setup_again(D#engine{task = restore(T, Stored),
                                                        load_error = undefined}));
        {error, Reason} ->
            transit(cell_task_core:setup_again(D#engine{load_error = Reason}))
    end;
then({retain_file, set_aside, Who}, #engine{task = #task{id = Id, retain_path = Path}} = D) ->
    case set_aside(Path) of
        {ok, Aside} ->
            cell_log:notice(Id, "~ts set the damaged retained data file aside as ~ts; the "
                            "task starts with no retained data, its counters again from "
                            "their defaults", [Who, Aside]);
        {error, Why} ->
            %% Still there: read again below, and asked again if still unreadable.
            cell_log:error(Id, "the damaged retained data file ~ts could not be set aside: "
                           "~ts", [Path, file:format_error(Why)])
    end,
    retained_again(D);
then({retain_file, reload, _Who}, D) ->
    retained_again(D).

%% A damaged file of the task's record moved out of the way, under a name that says
%% so and when.
set_aside(Path) ->
    Aside = <<Path/binary, ".damaged-", (integer_to_binary(os:system_time(second)))/binary>>,
    case file:rename(Path, Aside) of
        ok -> {ok, Aside};
        {error, _} = Error -> Error
    end.

%% The retained data read again (mended, restored or set aside meanwhile): the task
%% goes on into setup as from OFF, or is asked again.
retained_again(D) ->
    transit(cell_task_core:setup_again(retained(D))).

%% @doc Marks the caller's slot of the emergency stop's barrier: its outputs are
%% secured. The last of the fan-out tells the controller.
-spec estop_secured(estop_barrier()) -> ok.
estop_secured(Barrier) ->
    cell_member:estop_secured(Barrier).

%% Entering READY, the task collects its heap, which never shrinks below
%% ?MIN_HEAP_WORDS: securing the outputs at an emergency stop then fits in the free
%% heap. Without this, tasks started together fill their heaps in step, and at an
%% emergency stop now and then every one of them collects before it can secure its
%% outputs (1000 tasks: a stop 3 ms slower).
headroom() ->
    _ = erlang:garbage_collect(),
    ok.

%% The flag is made once per node and never replaced, so the task keeps it.
estop_raised(#engine{estop_flag = Flag}) ->
    atomics:get(Flag, 1) =:= 1.

%% uninit is the seed's "must not fail": an error in it is logged, never raised, so
%% a failing uninit cannot keep a task from stopping.
secure_outputs(#engine{task = #task{module = Mod, id = Id} = T} = D) ->
    T1 = try
             Mod:uninit(T)
         catch
             Class:Reason:Stack ->
                 cell_log:error(Id, "uninit failed (~tp:~tp); outputs may not be secured",
                                [Class, Reason]),
                 cell_log:trace(Id, "uninit failed: ~tp", [Stack]),
                 T
         end,
    T2 = case T1 of
             #task{} -> T1;
             _ -> T
         end,
    %% Secured: what the task commanded before is not written again (see reassert/2).
    D#engine{task = T2#task{commanded = cell_task_outputs:new()}}.

%% The task leaves what it was doing (cell_task_core:leave/3), or another transition
%% of the core that moves it: carried out, the engine in the state it took the task to
%% (the engine's state is always the task's), its next events next.
leave(How, State, D) ->
    transit(cell_task_core:leave(How, State, D)).

%% A transition that names what the engine goes on with once its effects are carried
%% out (cell_task_core:then()): carried out, then that.
proceed({_, _} = Transition) ->
    transit(Transition);
proceed({D, Effects, Then}) ->
    then(Then, carry_out({D, Effects})).

transit({_, Effects} = Transition) ->
    D = carry_out(Transition),
    {next_state, (D#engine.task)#task.ipc, D,
     [{next_event, internal, Event} || {next_event, Event} <- Effects]}.

%% A transition of cell_task_core carried out: its effects in order (its next events
%% are the caller's).
carry_out({D, Effects}) ->
    lists:foldl(fun effect/2, D, Effects).

effect({withdraw_alarm, AlarmId}, D) ->
    ok = cell_alarms:withdraw(AlarmId),
    D;
effect({cancel, Armed}, D) ->
    %% Not waited for: a timer that fires meanwhile sends a message of an older
    %% round, which is ignored.
    _ = [erlang:cancel_timer(TRef, [{async, true}, {info, false}]) || {timer, TRef, _} <- Armed],
    _ = [cell_hal:cancel_watch(Ref) || {io, Ref, _, _} <- Armed],
    D;
effect(interrupt_links, #engine{task = T} = D) ->
    D#engine{task = cell_handshake:interrupt_all(T)};
effect(uninit, D) ->
    secure_outputs(D);
effect(forget_product, #engine{task = T} = D) ->
    D#engine{task = not_here(T)};
effect({reoffer, Offers}, #engine{task = T} = D) ->
    D#engine{task = cell_handshake:reoffer(T, Offers)};
effect(headroom, D) ->
    ok = headroom(),
    D;
effect({resumed, Resumed}, #engine{task = #task{id = Id}} = D) ->
    ok = cell_registry:update(Id, #{resumed => Resumed}),
    D;
effect(keep_product, #engine{task = #task{product = P, gen = G} = T} = D) ->
    D#engine{task = cell_task:store(T, P, G, undefined, #{})};
effect({log, notice, Format, Args}, #engine{task = #task{id = Id}} = D) ->
    cell_log:notice(Id, Format, Args),
    D;
effect({log, warning, Format, Args}, #engine{task = #task{id = Id}} = D) ->
    cell_log:warning(Id, Format, Args),
    D;
effect({crashed, Why}, #engine{task = T} = D) ->
    ok = cell_member:crashed(T, "task", "", Why),
    D;
effect({crash_warning, Why}, D) ->
    ok = crash_warning(Why, D),
    D;
effect(predecessor, D) ->
    D#engine{predecessor = predecessor(D)};
effect({ipc_event, unblocked}, #engine{task = T} = D) ->
    D#engine{task = cell_task:unblocked(T)};
effect({ipc_event, unstarved}, #engine{task = T} = D) ->
    D#engine{task = cell_task:unstarved(T)};
effect({estop_secured, Barrier}, D) ->
    ok = estop_secured(Barrier),
    D;
effect({state, To, Cause}, #engine{task = T} = D) ->
    D#engine{task = cell_task:set_state(T, To, Cause)};
effect({next_event, _}, D) ->
    D.

%% The controller's commands as the task joined the cell.
joined(#{request := Request, estop := Estop, service_mode := Service}, #engine{task = T} = D) ->
    D#engine{request = Request, estop = Estop, task = T#task{service_mode = Service}}.

%% A message the engine does not know goes to the task module's handle_info/2; a task
%% module without one expects none, and the task crashes (it is restarted, and the
%% operator told, as after any crash).
stray(Msg, #engine{task = #task{module = Mod, id = Id} = T} = D) ->
    case erlang:function_exported(Mod, handle_info, 2) of
        true ->
            {ok, T1} = Mod:handle_info(Msg, T),
            {keep_state, D#engine{task = T1}};
        false ->
            cell_member:unexpected(Id, Msg)
    end.

%% A reply the task no longer waits for: it came after a timer of the same wait, or
%% after the task left the wait (Pause, Stop, an error, the emergency stop). The task
%% module may want it (handle_info/2); otherwise it is dropped, being late, not wrong.
late_reply(Msg, #engine{task = #task{module = Mod, id = Id}} = D) ->
    case erlang:function_exported(Mod, handle_info, 2) of
        true ->
            stray(Msg, D);
        false ->
            cell_log:trace(Id, "dropped a reply it no longer waits for: ~tp", [Msg]),
            keep_state_and_data
    end.

%% --------------------------------------------------------------------------------------
%% Handshakes and product ownership
%% --------------------------------------------------------------------------------------

%% A message of a link: the bookkeeping is cell_handshake's; a READY task waiting on
%% that link wakes, with the events the seed raises there.
handshake(Msg, State, #engine{task = T0} = D0) ->
    {T, Wakes} = cell_handshake:handle(Msg, T0),
    D = D0#engine{task = T},
    case cell_task_core:link_news(Wakes, State, D) of
        {wake, Transition} ->
            transit(Transition);
        Boundary ->
            at_boundary(paused(Boundary, State, D))
    end.

%% What the task's product file holds becomes the task's product (at boot, and at a
%% Retry after the file was damaged).
%% The record of the product file taken, and the task's partners told what it holds.
restore(T, Stored) ->
    cell_handshake:attach_all(take_loaded(T, Stored)).

take_loaded(#task{id = Id} = T, undefined) ->
    %% What the crashed incarnation held in the registry and no longer in its file (it
    %% died between the two) is not held by anyone.
    ok = cell_registry:hold(Id, undefined, 0),
    ok = cell_registry:update(Id, #{product => undefined}),
    T#task{product = undefined, gen = 0, marker = undefined};
take_loaded(T, #{product := Product, gen := Gen, marker := Marker}) ->
    dedupe(T#task{product = Product, gen = Gen, marker = Marker}).

%% A product found at boot that another task holds in a newer record is a stale copy
%% a crash left behind.
dedupe(#task{id = Id, product = #{serial := S}, gen = G} = T) ->
    ok = cell_registry:hold(Id, S, G),
    case drop_if_older(T) of
        T ->
            ok = cell_registry:update(Id, #{serial => S, product => T#task.product}),
            T;
        Dropped ->
            Dropped
    end.

%% The product's copy is dropped if another task holds it in a newer record.
drop_if_older(#task{id = Id, product = #{serial := S}, gen = G} = T) ->
    case cell_task_core:newer_holder(Id, G, cell_registry:holders(S)) of
        none -> T;
        {ok, Other} -> drop(T, io_lib:format("task ~ts holds it in a newer record", [Other]))
    end;
drop_if_older(T) ->
    T.

drop_stale(#task{product = #{serial := S}, gen = G} = T, S, Newer) when G < Newer ->
    drop(T, "another task holds it in a newer record");
drop_stale(T, _Serial, _Gen) ->
    T.

%% The operator said the product this task holds, which another task holds too, is
%% not here (see cell_guard): as a Reset that forgets it, the task secures its outputs,
%% forgets the product and initialises again; an error it waited on is withdrawn.
forget(State, S, Who, #engine{task = #task{id = Id, product = #{serial := S}}} = D0) ->
    cell_log:notice(Id, "~ts said product ~ts is not at this task: it is forgotten", [Who, S]),
    leave(forget, State, D0);
forget(_State, _Serial, _Who, _D) ->
    keep_state_and_data.

%% The operator said the task's product is not here: forgotten, and the links that
%% handed it in told, so that a copy upstream (the panel still there) is the product.
not_here(#task{product = #{serial := S}} = T) ->
    cell_task:clear_product(cell_handshake:disown_all(T, S));
not_here(T) ->
    cell_task:clear_product(T).

handed_on_again(State, Serial, D) ->
    Spec = cell_task:error_spec(
             <<"handed_on_again">>, "Product handed on before is here again",
             io_lib:format("This station has product ~ts again, but it handed it on to the next "
                           "station before, which holds it or has sent it on: the part here is a "
                           "second part with the same serial, or it came back past the records. "
                           "Take it out by hand (report a serial on two parts to maintenance), "
                           "then press Reset: the station starts again from what its sensors "
                           "see.", [Serial]),
             [reset]),
    raise(State, Spec, handed_on, D).

drop(#task{id = Id, product = #{serial := S}} = T, Why) ->
    cell_log:notice(Id, "dropped an old copy of product ~ts: ~ts", [S, Why]),
    cell_task:store(T, undefined, 0, undefined, #{sync => false}).

%% --------------------------------------------------------------------------------------
%% IO
%% --------------------------------------------------------------------------------------

%% Before init, each IO group of the task as the HAL knows it, and its connection,
%% looked at once however many of the groups it serves (cell_task_core:checked/3
%% decides).
io_check(#engine{task = #task{io = Groups}, conns = Conns} = D) ->
    {Found, _} = lists:mapfoldl(
                   fun(G, Seen) ->
                           case cell_hal:connection_of(G) of
                               {ok, Conn} when is_map_key(Conn, Seen) ->
                                   {maps:get(Conn, Seen), Seen};
                               {ok, Conn} ->
                                   F = conn_up(Conn, Conns),
                                   {F, Seen#{Conn => F}};
                               {error, unknown_group} ->
                                   {{group, G, unconfigured}, Seen}
                           end
                   end, #{}, Groups),
    cell_task_core:checked(init, Found, D).

%% A connection of the task's IO as it is, subscribed to first. One the task took for
%% down is read again from the HAL: a request that found the HAL's process restarting
%% takes it for down, and the `up' that ends the restart (or no change at all) may not
%% have reached the task yet. One whose subscription the HAL's server could not take
%% (restarting) is asked for again next time.
conn_up(Conn, Conns) ->
    case Conns of
        #{Conn := up} ->
            {conn, Conn, up};
        #{Conn := down} ->
            case cell_hal:status(Conn) of
                up -> {conn, Conn, up};
                _ -> {conn, Conn, down}
            end;
        #{} ->
            case cell_hal:subscribe_connection(Conn) of
                {ok, Status} -> {conn, Conn, Status};
                {error, _} -> {conn, Conn, unsubscribed}
            end
    end.

group_conn(Group) ->
    case cell_hal:connection_of(Group) of
        {ok, Conn} -> Conn;
        {error, _} -> Group
    end.

%% The error an IO error of cell_task_core names (cell_task_core:io_spec()), worded
%% with what the HAL says of it; the task's own errors as they are.
error_spec({io, Conn}) -> io_error(Conn);
error_spec({io_config, Group}) -> io_config_error(Group);
error_spec({point, Group, Point, Why}) -> point_error(Group, Point, Why);
error_spec(#{} = Spec) -> Spec.

io_error(Conn) ->
    {Where, Why} = case cell_hal:info(Conn) of
                       {ok, #{endpoint := E, reason := R}} -> {E, R};
                       _ -> {<<"unknown">>, <<"it is not configured">>}
                   end,
    cell_task:error_spec(
      <<"io">>, "IO connection lost",
      io_lib:format("The connection ~ts (~ts) to this task's IO is down: ~ts.~nThe task "
                    "holds; nothing it reads from there can be trusted. Check the PLC and "
                    "the network, then select RETRY once the connection is back.",
                    [Conn, Where, Why]),
      [retry]).

point_error(Group, Point, Why) ->
    cell_task:error_spec(
      <<"io_point">>, "IO point unavailable",
      io_lib:format("The point ~ts of the IO group ~ts cannot be used: ~ts.~nThe task "
                    "holds. Check the PLC program (the variable may have been renamed, "
                    "removed or retyped, or the PLC may refuse its address), then select "
                    "RETRY.",
                    [Point, Group, Why]),
      [retry]).

io_config_error(Group) ->
    cell_task:error_spec(
      <<"io">>, "IO group not configured",
      io_lib:format("The IO group ~ts this task uses is not configured in the HAL. "
                    "Check the cell's configuration, then select RETRY.", [Group]),
      [retry]).

%% --------------------------------------------------------------------------------------
%% Errors the engine raises itself
%% --------------------------------------------------------------------------------------

crash_error(Why, #engine{task = #task{product = P}}) ->
    cell_task:error_spec(
      <<"crashed">>, "Task restarted after a crash",
      io_lib:format("The task stopped unexpectedly and was restarted: ~ts.~n"
                    "Its product (~ts) was restored from its file and its outputs were "
                    "secured.~nCheck the machine, then select RETRY to continue with the "
                    "product as saved, or RESET to forget the product and start empty.",
                    [cell_member:crash_text(Why), cell_task_core:serial_text(P)]),
      [retry, reset]).

damaged_error(#engine{task = #task{product_path = Path}, load_error = Why}) ->
    cell_task:error_spec(
      <<"product_file">>, "Product file damaged",
      io_lib:format("The product file ~ts cannot be read (~tp).~nSelect RETRY to read it "
                    "again, or RESET to set it aside and start without a product.",
                    [Path, Why]),
      [retry, reset]).

retain_damaged_error(#engine{task = #task{retain_path = Path}, retain_error = Why}) ->
    cell_task:error_spec(
      <<"retain_file">>, "Retained data damaged",
      io_lib:format("The task's retained data (its counters, such as the last serial "
                    "made) cannot be read from ~ts: ~ts.~nThe task does not run: starting "
                    "it without them could repeat serials already made. Restore the file "
                    "from a backup if there is one, then select RETRY to read it again. "
                    "Select RESET to set the file aside and start the task with no "
                    "retained data: its counters start again from their defaults, so check "
                    "what the next serials will be.",
                    [Path, cell_retain:text(Why)]),
      [retry, reset]).

transit_error(#engine{task = #task{product = P, marker = #{link := Link, from := downstream}}}) ->
    %% Leaving this task: if the link could be asked it settled this already (its
    %% record says whether the next station took the product), so it could not be.
    cell_task:error_spec(
      <<"in_transit">>, "Product transfer interrupted",
      io_lib:format("Product ~ts was leaving this station over the handshake ~ts when the "
                    "transfer was interrupted, and the handshake cannot be asked whether "
                    "the next station took it: the next station may hold the product or "
                    "may already have sent it on.~nCheck where the product is. Select "
                    "IGNORE only if it is on this station: the task goes on with it (if "
                    "the next station took it after all, the handshake refuses this copy "
                    "when it is back and the task drops it). Select RESET if it is not "
                    "here: the task forgets it.",
                    [cell_task_core:serial_text(P), Link]),
      [ignore, reset]);
transit_error(#engine{task = #task{product = P, marker = #{link := Link}}}) ->
    cell_task:error_spec(
      <<"in_transit">>, "Product transfer interrupted",
      io_lib:format("Product ~ts was moving over the handshake ~ts when the transfer was "
                    "interrupted.~nCheck where the product is. Select IGNORE if it is on "
                    "this station: the task goes on with it. Select RESET if it is not: "
                    "the task forgets it (take it out of the machine by hand).",
                    [cell_task_core:serial_text(P), Link]),
      [ignore, reset]).


describe(State, #engine{task = T} = D) ->
    #{id => T#task.id, state => State, request => D#engine.request, estop => D#engine.estop,
      service_mode => T#task.service_mode, down => D#engine.down,
      pending => D#engine.pending, product => T#task.product,
      waits => case D#engine.pending of {waits, Ws} when State =/= off -> Ws; _ -> [] end,
      phase => maps:get(phase, T#task.data, undefined),
      initialized => D#engine.initialized, settings => T#task.settings,
      gen => T#task.gen, marker => T#task.marker, data => T#task.data,
      links => maps:map(fun(_, V) -> maps:without([last_product, mref], V) end,
                        T#task.links)}.
