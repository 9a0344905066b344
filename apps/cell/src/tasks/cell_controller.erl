%% @doc The controller's control interface (seed 000 §2.3.1) for the whole cell: the
%% pending request (Start, Pause, Stop), the emergency stop, service mode; the cell
%% state (the task state of highest priority) and the flags.
%%
%% Commands are written to the registry first (a task that restarts reads them there),
%% then sent to every task. The emergency stop sets an atomic flag before anything
%% else, so no task starts another step once it is raised; a task that has not secured
%% its outputs shortly after is killed (its restart secures them), so one stuck task
%% cannot hold up the stop. Securing comes before bookkeeping: the tasks announce OFF
%% only once every task of the fan-out has secured its outputs (a barrier the last of
%% them reports here), so no task waits for a scheduler behind the announcements.
%%
%% The cell state is the highest state of a task. The registry counts the tasks per
%% state as they change (shared counters, no message); a task tells this process only
%% when the highest state it sees after its change is not the cell state last
%% published, so a change costs the same for 10 tasks or 10,000, and tasks moving
%% between states below the cell state cost this process nothing. Every change of the
%% cell state is published as a `cell_state' event.
%%
%% A cell that stopped by itself (its tasks came back OFF after an internal fault, see
%% {@link cell_registry:stopped_by_fault/1}, or the node started again after an
%% unexpected stop, see {@link cell_registry:node_stopped/0}) is told when the
%% controller starts: a
%% `request' event (Stop, by the cell, with the cause) and the alarm `cell:stopped',
%% which says why and what to do, and stays (raised again by every start of the
%% controller) until the operator's next Start clears it.
-module(cell_controller).
-behaviour(gen_server).

-export([start_link/0, start/0, start/1, pause/0, pause/1, stop/0, stop/1, estop/1,
         estop/2, estop_by/0, service_mode/1, service_mode/2, state/0, flags/0, tasks/0, sync/0]).
%% For the tasks and the registry.
-export([task_state_changed/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(ESTOP_DEADLINE_MS, 1000).
-define(STOPPED, <<"stopped">>).

-record(state, {cell = off :: cell_ipc:state(),
                %% how many changes of the counts the cell state above has seen (see
                %% cell_registry:top_state_seen/0)
                seen = 0 :: non_neg_integer(),
                estop_timer :: reference() | undefined,
                %% the emergency stop's fan-out, until every task secured its outputs
                barrier :: barrier() | undefined}).

%% The emergency stop's fan-out: the barrier's atomics, the tasks in slot order, and
%% who raised it, answered once the stop is settled.
-type barrier() :: {atomics:atomics_ref(), [pid()], binary(), gen_server:from()}.

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Start (or resume after Pause): refused while the emergency stop is active.
-spec start() -> ok | {error, estop_active}.
start() -> start(<<"cell">>).

%% @doc As {@link start/0}, `Who' (a user's name) recorded with the request.
-spec start(binary()) -> ok | {error, estop_active}.
start(Who) -> gen_server:call(?MODULE, {request, start, Who}).

%% @doc Pause: every task holds in DOWN at its next wait point.
-spec pause() -> ok.
pause() -> pause(<<"cell">>).

%% @doc As {@link pause/0}, `Who' recorded with the request.
-spec pause(binary()) -> ok.
pause(Who) -> gen_server:call(?MODULE, {request, pause, Who}).

%% @doc Stop: every task ends in OFF through uninit.
-spec stop() -> ok.
stop() -> stop(<<"cell">>).

%% @doc As {@link stop/0}, `Who' recorded with the request.
-spec stop(binary()) -> ok.
stop(Who) -> gen_server:call(?MODULE, {request, stop, Who}).

%% @doc Raises or releases the emergency stop. Raising it also sets the request to
%% Stop: after a release the cell waits for a new Start. Raising it returns once every
%% task has secured its outputs (a task stuck in a step: once the deadline killed it),
%% with the operator's alarm raised.
-spec estop(boolean()) -> ok.
estop(On) -> estop(On, <<"cell">>).

%% @doc As {@link estop/1}, `Who' recorded with it.
-spec estop(boolean(), binary()) -> ok.
estop(On, Who) when is_boolean(On) ->
    case On of
        %% The flag first, from the caller, before any queueing: no task starts a step
        %% from here on. Who raised it is kept with it, for whoever may release it
        %% after a restart (the monitor its circuit's).
        true ->
            ok = cell_registry:set_control(estop_by, Who),
            ok = cell_registry:set_control(estop, true);
        false -> ok
    end,
    gen_server:call(?MODULE, {estop, On, Who}).

%% @doc Who raised the emergency stop that is active (the last to raise it, as given
%% to {@link estop/2}); `undefined' when none is.
-spec estop_by() -> binary() | undefined.
estop_by() ->
    case cell_registry:control(estop) of
        true -> cell_registry:control(estop_by);
        false -> undefined
    end.

%% @doc Service mode: tasks pause after their current motion; a Start then runs them
%% with the service flag set (speeds limited).
-spec service_mode(boolean()) -> ok.
service_mode(On) -> service_mode(On, <<"cell">>).

%% @doc As {@link service_mode/1}, `Who' recorded with it.
-spec service_mode(boolean(), binary()) -> ok.
service_mode(On, Who) when is_boolean(On) ->
    gen_server:call(?MODULE, {service_mode, On, Who}).

%% @doc The cell's IPC-2541 state.
-spec state() -> cell_ipc:state().
state() ->
    cell_registry:control(cell_state).

%% @doc The control interface's read-only properties for the cell.
-spec flags() -> #{state := cell_ipc:state(), request := start | pause | stop,
                   estop := boolean(), service_mode := boolean(), has_alarm := boolean(),
                   has_error := boolean(), has_warning := boolean()}.
flags() ->
    #{state => state(), request => cell_registry:control(request),
      estop => cell_registry:control(estop),
      service_mode => cell_registry:control(service_mode),
      has_alarm => cell_alarms:has_alarm(), has_error => cell_alarms:has_error(),
      has_warning => cell_alarms:has_warning()}.

%% @doc Every task: id, module, zone, lane, state, product serial, pid.
-spec tasks() -> [map()].
tasks() ->
    cell_registry:tasks().

%% @doc Returns once every task has handled every command the controller sent it
%% before (the controller asks them itself, so its own messages come first).
-spec sync() -> ok.
sync() ->
    gen_server:call(?MODULE, sync, infinity).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    %% A thousand tasks change state at once (an emergency stop): their events wait
    %% outside the heap, so a collection in the middle of the burst copies none of them.
    process_flag(message_queue_data, off_heap),
    %% The cell state as the tasks are now, without an event (as at every boot); a
    %% task that changes meanwhile finds it published, or is seen in the check after.
    Cell = cell_registry:top_state(),
    ok = cell_registry:set_control(cell_state, Cell),
    ok = tell_stopped(cell_registry:stopped()),
    {ok, follow(#state{cell = Cell})}.

%% The cell stopped by itself: the operator is told why, and what to do.
tell_stopped(undefined) ->
    ok;
tell_stopped({Fault, At}) ->
    Caption = case Fault of
                  node -> <<"Cell stopped by an unexpected restart">>;
                  _ -> <<"Cell stopped after an internal fault">>
              end,
    ok = cell_alarms:alarm(cell, ?STOPPED, Caption, stopped_text(Fault, At)),
    ok = cell_alarms:sync(),
    publish(request, #{request => stop, who => <<"cell">>, cause => Caption}).

stopped_text(Fault, At) ->
    Why = case Fault of
              services -> "a part of the cell's controller the tasks depend on (its services, "
                          "the product journal or the handshake links) failed and was started "
                          "again, and the tasks with it";
              registry -> "the cell's controller was started anew (its task registry among "
                          "what restarted)";
              node -> "the cell's runtime started again after its node stopped unexpectedly "
                      "(the power cut, or the node killed or crashed); whatever ran then was "
                      "cut short"
          end,
    io_lib:format("At ~ts ~ts. The tasks came back OFF and nothing has moved since.~nCheck "
                  "the machine: products part-way through a station, a robot or a belt "
                  "stopped mid-move. Then press Start: each task holds its record against "
                  "its sensors and goes on where they agree, or asks where they do not. The "
                  "log says more about the fault.",
                  [calendar:system_time_to_rfc3339(At, [{unit, millisecond}, {offset, "Z"}]),
                   Why]).

-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, term(), #state{}} | {noreply, #state{}}.
handle_call({request, start, Who}, _From, State) ->
    case cell_registry:control(estop) of
        true ->
            {reply, {error, estop_active}, State};
        false ->
            ok = snapshot(),
            ok = request(start, Who),
            ok = started_again(cell_registry:stopped()),
            {reply, ok, State}
    end;
handle_call(sync, From, State) ->
    _ = [catch cell_task_proc:sync(Pid) || #{pid := Pid} <- cell_registry:tasks()],
    %% Each task's state events reached this mailbox before its answer above; answer
    %% the caller after them, so the cell state is settled too.
    self() ! {synced, From},
    {noreply, State};
handle_call({request, Request, Who}, _From, State) ->
    ok = request(Request, Who),
    {reply, ok, State};
handle_call({estop, true, Who}, From, State0) ->
    ok = cell_registry:set_control(estop, true),
    %% A task that takes the emergency stop also takes Stop as its request: one
    %% message each, the fastest fan-out there is.
    ok = cell_registry:set_control(request, stop),
    State = settle(State0),
    %% The log, the alarm and the answer wait until the tasks have secured their
    %% outputs: until then the schedulers are theirs.
    {Ref, Pids} = estop_fanout(),
    cancel(State#state.estop_timer),
    TRef = erlang:start_timer(?ESTOP_DEADLINE_MS, self(), estop_deadline),
    Pending = State#state{estop_timer = TRef, barrier = {Ref, Pids, Who, From}},
    case Pids of
        [] -> {noreply, settle(Pending)};
        [_ | _] -> {noreply, Pending}
    end;
handle_call({estop, false, Who}, _From, State0) ->
    State = settle(State0),
    ok = cell_registry:set_control(estop, false),
    ok = cell_registry:set_control(estop_by, undefined),
    broadcast(estop, false),
    cell_log:notice(cell, "emergency stop released (~ts); press Start to go on", [Who]),
    ok = cell_alarms:clear_alarm(cell, <<"estop">>),
    ok = cell_alarms:sync(),
    ok = publish(estop, #{active => false, who => Who}),
    {reply, ok, State};
handle_call({service_mode, On, Who}, _From, State) ->
    ok = cell_registry:set_control(service_mode, On),
    broadcast(service_mode, On),
    cell_log:notice(cell, "service mode ~ts (~ts)", [case On of true -> "on"; false -> "off" end,
                                                     Who]),
    ok = publish(service_mode, #{active => On, who => Who}),
    {reply, ok, State}.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_state_seen, Version, Seen}, #state{seen = Last} = State)
  when Version >= Last ->
    {noreply, follow(cell_state(Seen, State#state{seen = Version}))};
handle_info({cell_state_seen, _Older, _Seen}, State) ->
    %% Read before changes the cell state has already followed (its task was
    %% descheduled between reading and telling): the counts have the last word.
    {noreply, follow(State)};
handle_info({estop_secured, Ref}, #state{barrier = {Ref, _, _, _}} = State) ->
    {noreply, settle(State)};
handle_info({estop_secured, _}, State) ->
    {noreply, State};
handle_info({timeout, TRef, estop_deadline}, #state{estop_timer = TRef} = State) ->
    Secured = secured(State#state.barrier),
    _ = [begin
             cell_log:error(Id, "did not stop within ~p ms of the emergency stop; killed "
                            "(its restart secures its outputs)", [?ESTOP_DEADLINE_MS]),
             exit(Pid, kill)
         end || #{id := Id, pid := Pid, state := S} <- cell_registry:tasks(), S =/= off,
                not sets:is_element(Pid, Secured), cell_registry:control(estop)],
    {noreply, settle(State#state{estop_timer = undefined})};
handle_info({timeout, _, estop_deadline}, State) ->
    {noreply, State};
handle_info({synced, From}, State) ->
    gen_server:reply(From, ok),
    {noreply, State}.

%% At Start (seed 000 §3.1, §3.2.3) every task is handed a snapshot of its settings
%% taken now; a task applies it only when it leaves OFF, so a task resuming after Pause
%% keeps the settings it runs on and a change saved while the cell runs applies at the
%% next Start. Deciding this per task, not by the cell state seen here, keeps a Start
%% that follows a Stop at once from missing the snapshot. The machine's log level
%% applies; the recipe buffer is emptied so recipes changed meanwhile are read again.
snapshot() ->
    Snapshot = cell_settings:snapshot(),
    Machine = maps:get(machine, Snapshot, #{}),
    ok = cell_log:set_default_level(maps:get(log_level, Machine, brief)),
    ok = cell_recipe_buffer:clear(),
    lists:foreach(fun(#{pid := Pid, settings_key := Key}) when Key =/= undefined ->
                          cell_task_proc:control(Pid, settings, maps:get(Key, Snapshot, #{}));
                     (_) ->
                          ok
                  end, cell_registry:tasks()).

request(Request, Who) ->
    ok = cell_registry:set_control(request, Request),
    broadcast(request, Request),
    cell_log:notice(cell, "~ts requested (~ts)", [request_name(Request), Who]),
    publish(request, #{request => Request, who => Who}).

%% The operator started the cell that had stopped by itself: the alarm goes.
started_again(undefined) ->
    ok;
started_again(_) ->
    ok = cell_registry:clear_stopped(),
    ok = cell_alarms:clear_alarm(cell, ?STOPPED),
    cell_alarms:sync().

%% The emergency stop to every task, each with its slot of the barrier.
estop_fanout() ->
    Pids = cell_registry:pids(),
    Total = length(Pids),
    Ref = atomics:new(Total + 1, [{signed, false}]),
    Controller = self(),
    fan_out(Pids, estop, fun(Slot) -> {true, {Ref, Slot, Total, Controller}} end),
    {Ref, Pids}.

%% Every task of the fan-out secured its outputs (or the deadline passed, or the
%% emergency stop changed): the held tasks announce OFF, the operator is told, and the
%% caller answered.
settle(#state{barrier = undefined} = State) ->
    State;
settle(#state{barrier = {Ref, Pids, Who, From}} = State) ->
    _ = [cell_task_proc:control(Pid, estop_settled, Ref) || Pid <- Pids],
    cell_log:error(cell, "emergency stop (~ts)", [Who]),
    ok = cell_alarms:alarm(cell, <<"estop">>, "Emergency stop",
                           "The emergency stop is active. Release it, then press Start."),
    ok = cell_alarms:sync(),
    ok = publish(estop, #{active => true, who => Who}),
    gen_server:reply(From, ok),
    State#state{barrier = undefined}.

%% The tasks of the fan-out that secured their outputs.
secured(undefined) ->
    sets:new([{version, 2}]);
secured({Ref, Pids, _, _}) ->
    Slots = lists:zip(Pids, lists:seq(1, length(Pids))),
    sets:from_list([Pid || {Pid, Slot} <- Slots, atomics:get(Ref, Slot) =:= 1],
                   [{version, 2}]).

broadcast(Key, Value) ->
    fan_out(cell_registry:pids(), Key, fun(_Slot) -> Value end).

%% A command to every task, its value made for the task's place in the list (its slot).
%% At high priority, so that no task woken by the first messages runs before the last
%% is sent.
fan_out(Pids, Key, ValueOf) ->
    Was = process_flag(priority, high),
    _ = lists:foldl(fun(Pid, Slot) ->
                            cell_task_proc:control(Pid, Key, ValueOf(Slot)),
                            Slot + 1
                    end, 1, Pids),
    _ = process_flag(priority, Was),
    ok.

%% @private After a task changed its state (in the registry, and its `task_state'
%% event sent): the controller is told the highest state the task sees if that is not
%% the cell state published, with how many changes of the counts that reading saw. Two
%% tasks' messages may arrive in the other order than they read in (one descheduled in
%% between): the controller passes over a reading older than one it has followed. The counts are changed before the published state is
%% read, and the controller publishes before it reads the counts (both full barriers),
%% so of a task's change and a publication racing it one always sees the other.
-spec task_state_changed() -> ok.
task_state_changed() ->
    {Version, Top} = cell_registry:top_state_seen(),
    case cell_registry:published_state() =:= Top orelse whereis(?MODULE) of
        true -> ok;
        undefined -> ok;
        Pid -> Pid ! {cell_state_seen, Version, Top}, ok
    end.

%% The state a task saw becomes the cell state (so the cell passes through the states
%% its tasks showed, in order), then the counts have the last word.
follow(#state{cell = Cell, seen = Seen} = State) ->
    case cell_registry:top_state_seen() of
        {Version, Cell} -> State#state{seen = max(Seen, Version)};
        {Version, Top} -> follow(cell_state(Top, State#state{seen = max(Seen, Version)}))
    end.

cell_state(Same, #state{cell = Same} = State) ->
    State;
cell_state(Cell, #state{cell = Was} = State) ->
    ok = cell_registry:set_control(cell_state, Cell),
    %% Entering or leaving READY is news for the operator; READY's sub-states change
    %% with every product and are detail.
    Level = case cell_ipc:is_ready(Cell) andalso cell_ipc:is_ready(Was) of
                true -> verbose;
                false -> brief
            end,
    cell_log:log(Level, cell, "cell state ~ts", [cell_ipc:name(Cell)]),
    ok = publish(cell_state, #{state => Cell, from => Was}),
    State#state{cell = Cell}.

publish(Type, Fields) ->
    cell_events:publish(cell_events:new(Type, cell, Fields)).

cancel(undefined) -> ok;
cancel(TRef) -> _ = erlang:cancel_timer(TRef), ok.

request_name(start) -> "Start";
request_name(pause) -> "Pause";
request_name(stop) -> "Stop".
