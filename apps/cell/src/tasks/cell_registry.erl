%% @doc Owns the cell's shared tables, so they outlive any task or the controller:
%%
%% <ul>
%% <li>`cell_tasks' — one row per device task: its pid and what the controller, the
%%     panel and SHDR read without a process hop (state, flags, product serial and the product);</li>
%% <li>`cell_control' — the controller's commands to the tasks: the pending request,
%%     the emergency stop, service mode, read by a task when it (re)starts;</li>
%% <li>the emergency-stop flag, an atomic every task checks before each step, so no
%%     step starts once the stop was observed, even before its message arrives.</li>
%% </ul>
%%
%% It also tells a restarted task how its previous incarnation ended: it monitors
%% every registered task and remembers a crash reason until the task registers again,
%% and the state it died in (`crashed_in' in its row).
%%
%% The request and a stop the cell made by itself outlive the registry (an atomics
%% array made once per node): when the registry, or the whole controller's tree, starts
%% anew while the cell ran, the tasks come back OFF, and the cell remembers that it
%% stopped after an internal fault and why until the operator's next Start (see
%% {@link stopped_by_fault/1}).
-module(cell_registry).
-behaviour(gen_server).

-export([start_link/0, register_task/2, unregister_task/1, update/2, set_state/2, task/1,
         tasks/0, task_ids/0, pids/0, hold/3, holders/1, states/0, top_state/0, top_state_seen/0,
         published_state/0,
         control/1, set_control/2, estop_flag/0, estop_active/0]).
-export([product_count/0, last_progress/0, wake_on_progress/0, stay_asleep/0]).
-export([new_run/0, stopped_by_fault/1, node_stopped/0, stopped/0, clear_stopped/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([previous/0, control_key/0, fault/0]).

-type previous() :: fresh | clean | {crashed, term()}.
%% What stopped the cell by itself: a part of the controller the tasks depend on (its
%% services, the product journal, the handshake links) restarted them with it, or the
%% registry itself (alone, or with the whole controller's tree) started anew; or the
%% node itself stopped unexpectedly before this run (killed, crashed, its power cut).
-type fault() :: services | registry | node.
-type control_key() :: request | estop | estop_by | service_mode | cell_state.

-define(TASKS, cell_tasks).
-define(STATES, cell_task_states).
-define(PRODUCTS, cell_product_holders).
-define(CONTROL, cell_control).
%% The pids of the running tasks as one list, made when one comes or goes: the
%% emergency stop reaches a thousand tasks without a scan of their rows first.
-define(PIDS, cell_task_pids).
-define(ESTOP_KEY, {?MODULE, estop}).
%% Tasks per state, the cell state last published (see top_state/0), and how many
%% times the counts changed (see top_state_seen/0).
-define(COUNTS_KEY, {?MODULE, state_counts}).
-define(PUBLISHED, 8).
-define(VERSION, 9).
%% When a product last moved or work last started or ended (monotonic ms), and
%% whether the cell's guard asked to be told of the next such change (1): what the
%% guard against a silent deadlock reads, with no message on the way of a transfer.
-define(PROGRESS_KEY, {?MODULE, progress}).
-define(LAST, 1).
-define(WAKE, 2).
%% The request as the controller last set it, and a stop the cell made by itself (its
%% cause and when, system time in ms): kept across a restart of the registry.
-define(RUN_KEY, {?MODULE, run}).
-define(REQUEST, 1).
-define(FAULT, 2).
-define(FAULT_AT, 3).

-record(state, {monitors = #{} :: #{reference() => {atom(), pid()}},
                ended = #{} :: #{atom() => previous()}}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Registers the calling task process; answers how the previous incarnation of
%% the same task ended: `fresh' (none), `clean' (it stopped), `{crashed, Reason}'.
-spec register_task(atom(), map()) -> previous().
register_task(Id, Info) ->
    gen_server:call(?MODULE, {register, Id, self(), Info}).

%% @doc A task that ends cleanly says so before it goes.
-spec unregister_task(atom()) -> ok.
unregister_task(Id) ->
    gen_server:call(?MODULE, {unregister, Id}).

%% @doc Merges fields into a task's row; called by the task itself.
-spec update(atom(), map()) -> ok.
update(Id, Fields) ->
    case ets:lookup(?TASKS, Id) of
        [{Id, Row}] ->
            case maps:merge(Row, Fields) of
                %% Nothing new (a task saving its product again, say): nothing written.
                Row -> ok;
                New -> true = ets:insert(?TASKS, {Id, New}), ok
            end;
        [] ->
            ok
    end.

%% @doc A task's IPC-2541 state, kept in a table of its own (one insert per change) and
%% counted per state (see top_state/0). Only the task itself sets it (the registry,
%% once the task is gone), so the row's old state is the one counted.
-spec set_state(atom(), cell_ipc:state()) -> ok.
set_state(Id, State) ->
    Old = state_of(Id),
    true = ets:insert(?STATES, {Id, State}),
    ok = worked(Old, State),
    count(Old, State).

%% Work starting, pausing, resuming or ending is progress; the other changes of state
%% (starved, blocked, down ...) are not: a cell stuck in them moves nothing.
worked(Same, Same) -> ok;
worked({ready, processing, executing}, _) -> progress();
worked(_, {ready, processing, executing}) -> progress();
worked(_, _) -> ok.

%% Tasks in OFF are not counted: the cell is OFF when no task is above it.
count(Same, Same) ->
    ok;
count(Old, New) ->
    Counts = counts(),
    _ = Old =:= off orelse atomics:sub(Counts, slot(Old), 1),
    _ = New =:= off orelse atomics:add(Counts, slot(New), 1),
    atomics:add(Counts, ?VERSION, 1).

%% @doc The highest state a task is in (the cell state the controller publishes), from
%% the counts per state: at most six reads, whatever the number of tasks, and nothing
%% allocated (a task calls this at every change of state).
-spec top_state() -> cell_ipc:state().
top_state() ->
    cell_ipc:of_priority(top_slot(counts(), slot({ready, processing, executing})) - 1).

top_slot(_Counts, 1) ->
    1;
top_slot(Counts, Slot) ->
    case atomics:get(Counts, Slot) > 0 of
        true -> Slot;
        false -> top_slot(Counts, Slot - 1)
    end.

%% @doc As {@link top_state/0}, with how many times the counts had changed before it
%% was read: of two readings, the one with the higher number saw every change the
%% other saw. Tasks tell the controller what they read (see
%% cell_controller:task_state_changed/0); their messages may arrive in another order
%% than they were read in, and a reading older than one already acted on is stale.
-spec top_state_seen() -> {non_neg_integer(), cell_ipc:state()}.
top_state_seen() ->
    Version = atomics:get(counts(), ?VERSION),
    {Version, top_state()}.

%% @doc The cell state the controller last published, as top_state/0 compares it.
-spec published_state() -> cell_ipc:state().
published_state() ->
    cell_ipc:of_priority(atomics:get(counts(), ?PUBLISHED) - 1).

slot(State) ->
    cell_ipc:priority(State) + 1.

counts() ->
    persistent_term:get(?COUNTS_KEY).

%% @doc The task holds a product of a serial and generation now (`undefined': none).
%% Of two tasks naming one serial, the higher generation owns it: a task holding a
%% lower one is told `{cell_registry, stale, Serial, Gen}' and drops its copy. A task
%% that takes a serial another task holds in a record as new as its own or newer (a
%% serial read again at a station while the records put it elsewhere) holds it twice:
%% the cell's guard is told ({@link cell_guard:held_twice/1}), which asks the operator.
-spec hold(atom(), binary() | undefined, non_neg_integer()) -> ok.
hold(Id, Serial, Gen) ->
    %% Older copies leave the holders before this one is in: no one reading the
    %% holders sees the serial held twice for the instant in between.
    _ = Serial =:= undefined orelse tell_stale(Id, Serial, Gen),
    %% Beside the rows by serial, one by task names the serial it holds, so the old row
    %% goes without a scan of the table.
    case ets:lookup(?PRODUCTS, {task, Id}) of
        [{_, Serial, Gen}] ->
            %% Held already (a task saving its product again, say): the rows stand.
            ok;
        Index ->
            progress(),
            _ = [begin
                     true = ets:delete_object(?PRODUCTS, {Old, Id, OldGen}),
                     true = ets:delete_object(?PRODUCTS, Row)
                 end || {_, Old, OldGen} = Row <- Index],
            _ = Serial =:= undefined orelse
                ets:insert(?PRODUCTS, [{Serial, Id, Gen}, {{task, Id}, Serial, Gen}]),
            ok
    end,
    %% Again after: an older copy held meanwhile goes too; one as new or newer is a
    %% double holding.
    _ = Serial =:= undefined orelse
        (tell_stale(Id, Serial, Gen) andalso cell_guard:held_twice(Serial)),
    ok.

%% Every other holder of an older generation of the serial drops its copy: it leaves
%% the holders at once (it holds nothing the cell counts any more; an operator's answer
%% to it is not taken for a double holding) and is told. Whether one of the same or a
%% newer generation holds it: a double holding.
tell_stale(Id, Serial, Gen) ->
    lists:foldl(fun({_, Other, G}, Acc) when Other =/= Id, G < Gen ->
                        true = ets:delete_object(?PRODUCTS, {Serial, Other, G}),
                        true = ets:delete_object(?PRODUCTS, {{task, Other}, Serial, G}),
                        _ = case ets:lookup(?TASKS, Other) of
                                [{_, #{pid := Pid}}] ->
                                    Pid ! {cell_registry, stale, Serial, Gen};
                                _ ->
                                    ok
                            end,
                        Acc;
                   ({_, Other, _}, _Acc) when Other =/= Id ->
                        true;
                   (_, Acc) ->
                        Acc
                end, false, ets:lookup(?PRODUCTS, Serial)).

%% @doc How many rows the product holders take: 0 when no task holds a product.
-spec product_count() -> non_neg_integer().
product_count() ->
    ets:info(?PRODUCTS, size).

%% @doc When a product last moved or work last started or ended (monotonic ms).
-spec last_progress() -> integer().
last_progress() ->
    atomics:get(progress_ref(), ?LAST).

%% @doc The guard asks to be told of the next progress: {@link cell_guard:progress/0}
%% is called then, once. Set before the guard reads {@link last_progress/0},
%% so a change in between is either seen there or told.
-spec wake_on_progress() -> ok.
wake_on_progress() ->
    atomics:put(progress_ref(), ?WAKE, 1).

%% @doc The guard no longer needs to be told (it has armed its timer).
-spec stay_asleep() -> ok.
stay_asleep() ->
    atomics:put(progress_ref(), ?WAKE, 0).

progress() ->
    Ref = progress_ref(),
    atomics:put(Ref, ?LAST, erlang:monotonic_time(millisecond)),
    case atomics:get(Ref, ?WAKE) =:= 1 andalso atomics:compare_exchange(Ref, ?WAKE, 1, 0) of
        ok -> cell_guard:progress();
        _ -> ok
    end.

progress_ref() ->
    persistent_term:get(?PROGRESS_KEY).

%% @doc Who holds a serial, and with which generation.
-spec holders(binary()) -> [{atom(), non_neg_integer()}].
holders(Serial) ->
    [{Id, Gen} || {_, Id, Gen} <- ets:lookup(?PRODUCTS, Serial)].

%% @doc One task's row.
-spec task(atom()) -> {ok, map()} | {error, not_found}.
task(Id) ->
    case ets:lookup(?TASKS, Id) of
        [{Id, Row}] -> {ok, Row#{state => state_of(Id)}};
        [] -> {error, not_found}
    end.

%% @doc Every task's row, ordered by id.
-spec tasks() -> [map()].
tasks() ->
    [Row#{id => Id, state => state_of(Id)} || {Id, Row} <- lists:sort(ets:tab2list(?TASKS))].

state_of(Id) ->
    case ets:lookup(?STATES, Id) of
        [{Id, S}] -> S;
        [] -> off
    end.

%% @doc The pids of every running task, in no order: what a broadcast needs.
-spec pids() -> [pid()].
pids() ->
    ets:lookup_element(?PIDS, all, 2).

-spec task_ids() -> [atom()].
task_ids() ->
    lists:sort([Id || {Id, _} <- ets:tab2list(?TASKS)]).

%% @doc Every task's IPC-2541 state.
-spec states() -> [cell_ipc:state()].
states() ->
    [S || {_, S} <- ets:tab2list(?STATES)].

%% @doc A controller command as the tasks see it.
-spec control(control_key()) -> term().
control(Key) ->
    case ets:lookup(?CONTROL, Key) of
        [{Key, V}] -> V;
        [] -> default(Key)
    end.

default(request) -> stop;
default(estop) -> false;
default(estop_by) -> undefined;
default(service_mode) -> false;
default(cell_state) -> off.

-spec set_control(control_key(), term()) -> ok.
set_control(estop, On) when is_boolean(On) ->
    %% The atomic first: from this instant no task starts another step.
    atomics:put(estop_flag(), 1, case On of true -> 1; false -> 0 end),
    true = ets:insert(?CONTROL, {estop, On}),
    ok;
set_control(request, Request) ->
    true = ets:insert(?CONTROL, {request, Request}),
    atomics:put(run_ref(), ?REQUEST, request_code(Request)),
    ok;
set_control(cell_state, Cell) ->
    true = ets:insert(?CONTROL, {cell_state, Cell}),
    %% An exchange, a full barrier: whoever reads the counts after this also sees the
    %% cell state published, and a task that changed the counts before it sees them
    %% read (see cell_controller:task_state_changed/0).
    _ = atomics:exchange(counts(), ?PUBLISHED, slot(Cell)),
    ok;
set_control(Key, Value) ->
    true = ets:insert(?CONTROL, {Key, Value}),
    ok.

%% @doc The `cell' application starts: no request and no stop of an earlier run of it
%% are carried over (only restarts inside one run are).
-spec new_run() -> ok.
new_run() ->
    case persistent_term:get(?RUN_KEY, undefined) of
        undefined -> persistent_term:put(?RUN_KEY, atomics:new(?FAULT_AT, [{signed, true}]));
        Ref -> _ = [atomics:put(Ref, I, 0) || I <- lists:seq(1, ?FAULT_AT)], ok
    end.

%% @doc The tasks came back OFF while the cell ran, because of an internal fault: the
%% request becomes Stop, and the cell remembers why (see {@link stopped/0}) until the
%% operator's next Start ({@link clear_stopped/0}), across restarts of the registry.
-spec stopped_by_fault(fault()) -> ok.
stopped_by_fault(Fault) ->
    ok = set_control(request, stop),
    remember_stop(Fault).

%% @doc The node stopped unexpectedly before this run of the application (see
%% {@link cell_node_run}): the cell, OFF at its start, remembers it as a stop by a fault
%% until the operator's Start, so the operator is told why it stands.
-spec node_stopped() -> ok.
node_stopped() ->
    remember_stop(node).

remember_stop(Fault) ->
    atomics:put(run_ref(), ?FAULT_AT, os:system_time(millisecond)),
    atomics:put(run_ref(), ?FAULT, fault_code(Fault)).

%% @doc Why the cell stopped by itself and when (system time, ms), or `undefined'.
-spec stopped() -> {fault(), integer()} | undefined.
stopped() ->
    case atomics:get(run_ref(), ?FAULT) of
        0 -> undefined;
        Code -> {fault_of(Code), atomics:get(run_ref(), ?FAULT_AT)}
    end.

%% @doc The operator started the cell again.
-spec clear_stopped() -> ok.
clear_stopped() ->
    atomics:put(run_ref(), ?FAULT, 0).

fault_code(services) -> 1;
fault_code(registry) -> 2;
fault_code(node) -> 3.

fault_of(1) -> services;
fault_of(2) -> registry;
fault_of(3) -> node.

request_code(stop) -> 0;
request_code(start) -> 1;
request_code(pause) -> 2.

run_ref() ->
    persistent_term:get(?RUN_KEY).

%% @doc The emergency-stop atomic (1 while the emergency stop is active).
-spec estop_flag() -> atomics:atomics_ref().
estop_flag() ->
    persistent_term:get(?ESTOP_KEY).

-spec estop_active() -> boolean().
estop_active() ->
    atomics:get(estop_flag(), 1) =:= 1.

-spec init([]) -> {ok, #state{}}.
init([]) ->
    ?TASKS = ets:new(?TASKS, [named_table, public, {read_concurrency, true},
                              {write_concurrency, true}]),
    ?STATES = ets:new(?STATES, [named_table, public, {read_concurrency, true},
                                {write_concurrency, true}]),
    ?CONTROL = ets:new(?CONTROL, [named_table, public, {read_concurrency, true}]),
    ?PRODUCTS = ets:new(?PRODUCTS, [named_table, public, bag, {read_concurrency, true}]),
    ?PIDS = ets:new(?PIDS, [named_table, protected, {read_concurrency, true}]),
    true = ets:insert(?PIDS, {all, []}),
    %% Created once per node: replacing a persistent term costs a global scan, and a
    %% task holding the old reference would miss a stop.
    case persistent_term:get(?ESTOP_KEY, undefined) of
        undefined -> persistent_term:put(?ESTOP_KEY, atomics:new(1, []));
        Ref -> atomics:put(Ref, 1, 0)
    end,
    %% The counts start again with the tables (every task registers anew).
    case persistent_term:get(?COUNTS_KEY, undefined) of
        undefined -> persistent_term:put(?COUNTS_KEY, atomics:new(?VERSION, []));
        _ -> ok
    end,
    _ = [atomics:put(counts(), I, 0) || I <- lists:seq(1, ?PUBLISHED - 1)],
    case persistent_term:get(?PROGRESS_KEY, undefined) of
        undefined -> persistent_term:put(?PROGRESS_KEY, atomics:new(?WAKE, [{signed, true}]));
        _ -> ok
    end,
    atomics:put(progress_ref(), ?LAST, erlang:monotonic_time(millisecond)),
    atomics:put(progress_ref(), ?WAKE, 0),
    atomics:put(counts(), ?PUBLISHED, slot(off)),
    _ = persistent_term:get(?RUN_KEY, undefined) =:= undefined andalso new_run(),
    %% Started anew while the cell ran (this process, or the whole controller's tree,
    %% after a fault): the tasks, started after it, come back OFF.
    case atomics:get(run_ref(), ?REQUEST) of
        0 ->
            ok;
        _ ->
            ok = stopped_by_fault(registry),
            cell_log:error(cell, "the cell's controller was started anew after an internal "
                           "fault while the cell ran (its task registry among what "
                           "restarted); the tasks are OFF: check the machine and press "
                           "Start", [])
    end,
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({register, Id, Pid, Info}, _From, State0) ->
    State = collect_dead(Id, State0),
    Previous = maps:get(Id, State#state.ended, fresh),
    Ref = monitor(process, Pid),
    %% The product its previous incarnation held stays in the row until the restarted
    %% task has read its own file: others looking for who may hold a product see it
    %% meanwhile. Where a crashed incarnation died, and whether it had gone on by itself
    %% after a crash of its own (`resumed'), are for the restarted task to read.
    Kept = case ets:lookup(?TASKS, Id) of
               [{Id, OldRow}] when Previous =:= clean; Previous =:= fresh ->
                   maps:with([product, resumed], OldRow);
               [{Id, OldRow}] -> maps:with([product, resumed, crashed_in], OldRow);
               [] -> #{}
           end,
    true = ets:insert(?TASKS, {Id, maps:merge(Kept, maps:remove(state, Info#{pid => Pid}))}),
    ok = set_state(Id, maps:get(state, Info, off)),
    {reply, Previous, keep_pids(State#state{monitors = maps:put(Ref, {Id, Pid}, State#state.monitors),
                                       ended = maps:remove(Id, State#state.ended)})};
handle_call({unregister, Id}, {Pid, _}, #state{monitors = Mons} = State) ->
    Refs = [R || {R, {I, _}} <- maps:to_list(Mons), I =:= Id],
    _ = [demonitor(R, [flush]) || R <- Refs],
    case ets:lookup(?TASKS, Id) of
        [{Id, #{pid := Pid} = Row}] -> true = ets:insert(?TASKS, {Id, maps:remove(pid, Row)});
        _ -> ok
    end,
    {reply, ok, keep_pids(State#state{monitors = maps:without(Refs, Mons),
                                 ended = maps:put(Id, clean, State#state.ended)})}.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'DOWN', Ref, process, _Pid, Reason}, State) ->
    {noreply, down(Ref, Reason, State)}.

%% A task restarted by its supervisor may register before this process has handled the
%% old incarnation's 'DOWN'. An incarnation that is gone without unregistering crashed,
%% and the monitor guarantees its 'DOWN' arrives: wait for exactly that message.
collect_dead(Id, #state{monitors = Mons} = State) ->
    case [{R, P} || {R, {I, P}} <- maps:to_list(Mons), I =:= Id] of
        [{Ref, Pid}] ->
            case is_process_alive(Pid) of
                false ->
                    receive
                        {'DOWN', Ref, process, Pid, Reason} -> down(Ref, Reason, State)
                    end;
                true ->
                    State
            end;
        [] ->
            State
    end.

keep_pids(#state{monitors = Mons} = State) ->
    true = ets:insert(?PIDS, {all, [Pid || {_, Pid} <- maps:values(Mons)]}),
    State.

down(Ref, Reason, #state{monitors = Mons, ended = Ended} = State) ->
    case maps:take(Ref, Mons) of
        {{Id, Pid}, Mons1} ->
            Previous = case Reason of
                           normal -> clean;
                           shutdown -> clean;
                           {shutdown, _} -> clean;
                           _ -> {crashed, Reason}
                       end,
            case ets:lookup(?TASKS, Id) of
                [{Id, #{pid := Pid} = Row}] ->
                    %% Where it died tells its restart whether it may go on by itself.
                    Died = case Previous of
                               {crashed, _} -> #{crashed_in => state_of(Id)};
                               _ -> #{}
                           end,
                    true = ets:insert(?TASKS, {Id, maps:merge(maps:remove(pid, Row), Died)}),
                    %% The task's state went with its process: tell the cell.
                    case state_of(Id) of
                        off -> ok;
                        Old ->
                            ok = set_state(Id, off),
                            cell_events:publish(cell_events:new(task_state, Id,
                                                                #{state => off, from => Old,
                                                                  cause => exited})),
                            cell_controller:task_state_changed()
                    end;
                _ ->
                    ok
            end,
            keep_pids(State#state{monitors = Mons1, ended = maps:put(Id, Previous, Ended)});
        error ->
            State
    end.
