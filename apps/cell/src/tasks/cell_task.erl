%% @doc The device task behaviour (seed 000 §2.3), and the functions a task module uses
%% on the task it is given.
%%
%% A device task covers a part of the machine small enough to need no parallelism
%% inside (a conveyor segment, a robot). Its module implements four callbacks, run by
%% the engine {@link cell_task_proc}:
%%
%% <ul>
%% <li>`init(Task)' — once when the task leaves OFF on Start, and again after a Reset:
%%     validate settings and hardware, leave the outputs as the task starts from. The
%%     engine has already loaded the task's product and its retained data from their
%%     files. Returns `{ok, Task}'
%%     or `{error, ErrorSpec, Task}' for the operator (the task waits in DOWN).</li>
%% <li>`reconcile(Held, Task)' — right after every successful init, before the first
%%     step: the restart reconciliation. `Held' (see `held()') is what the task's
%%     predecessor left: why the task starts (`start' from OFF, `crash' after its
%%     process died, `reset', `dropped' when the product it ran with turned out to be
%%     an old copy), its product as its file has it, the in-transit mark of
%%     a transfer cut off (see {@link cell_handshake}), the phase of each of its links,
%%     and its outputs as last commanded, read from the HAL before anything secured
%%     them ({@link commanded/3}). The task checks that record against its inputs
%%     before it acts, and decides where it goes on: it sets its own phase and
%%     re-asserts the outputs that phase needs (`{ok, Task}'), or, when record and
%%     sensors disagree, asks the operator a specific question (`{error, ErrorSpec,
%%     Task}': "records say panel P is in the gripper, the gripper sensor says empty:
%%     where is it?", each solution's meaning said in the text). The answer, Reset
%%     included, comes back to `reconcile' ({@link answer/1}) with the same `Held'; it
%%     runs until it returns `{ok, Task}'. Every task writes it: the cell spec refuses
%%     a module without it, as nothing else knows what the task's record means on the
%%     machine.</li>
%% <li>`step(Task)' — one step of the seed's DoStep body. It never blocks: it returns
%%     what it waits for next, and the engine calls it again when that has happened.
%%     `{continue, Task}' — step again at once; `{wait, Waits, Task}' — step again when
%%     any of the waits holds (see `wait()'), {@link woken_by/1} tells which;
%%     `{error, ErrorSpec, Task}' — an operator must answer (the seed's blocking
%%     `Error()'); the step runs again after Retry, Ignore or Close, with
%%     {@link answer/1} telling which; `{reset, Task}' — reinitialise (the seed's
%%     ResetException: uninit, then init).</li>
%% <li>`uninit(Task)' — on Stop, emergency stop or Reset: secure dangerous hardware,
%%     release what init took. It must not fail; errors in it are logged and ignored.
%%     The engine saves the product.</li>
%% </ul>
%%
%% Product persistence (seed 000 §2.3.5): the product is a task's own data, kept in a
%% file per zone and lane (`Data/Zone@Lane.product') so the task goes on where it was
%% after a stop, a crash or a power cut instead of asking for an empty machine. The
%% engine loads it before `init' (a file it cannot read is set aside only on the
%% operator's Reset) and every {@link set_product/2} and {@link clear_product/1} is on
%% disk when it returns, not only at uninit: after any crash the file says what the task
%% held at its last change. A task saves with its product whatever it must know to go on
%% (how far it got: cuts done, handed out); `reconcile' reads it back and holds it
%% against the machine. Ownership across a transfer follows the files' generations and
%% the in-transit mark ({@link cell_handshake}).
%%
%% Retained data (what PLC programmers call RETAIN or PERSISTENT variables): a task
%% keeps what must outlive its product and its process (a serial counter, tool wear,
%% the last serial made) as retained data, a small key-value store of its own with the
%% product's promise (see {@link cell_retain}). {@link retained/3} reads a value, {@link
%% retain/3} sets one, {@link retain_update/4} changes one by a function (a counter:
%% `{Serial, T1} = cell_task:retain_update(T, serial, fun(N) -> N + 1 end, 0)') and
%% {@link forget_retained/2} removes one; each change is on disk when it returns, so
%% the task acts on a value only once it is durable, and after a crash, a kill of the
%% node or a power cut the task goes on from the last value it made durable: a serial
%% is never made twice. The engine loads the file when the task starts; Stop, Reset
%% and a restart keep the data. A file that cannot be read is the operator's question
%% before the task runs (RETRY reads it again; RESET sets it aside and starts the store
%% empty, counters again from their defaults), never an empty store taken silently.
%% Values are plain data (numbers, atoms, binaries, lists, tuples, maps; keys atoms or
%% binaries) of at most 64 KiB for the whole store; anything else is refused with an
%% error (`{bad_retained, Key, Why}') and nothing is written. `cell_diag:retained/0'
%% and the panel's `GET /api/tasks/:id/retained' show the data.
%%
%% Waiting is waiting for a message: a waiting task costs no CPU. Between steps the
%% engine honours the controller's requests (Pause holds the task in DOWN and Start
%% resumes where it was; Stop ends in OFF through uninit) and the emergency stop.
%%
%% States change through the IPC-2541 events of §2.3.4, which a step raises with the
%% functions below: {@link starved/1}, {@link unstarved/1}, {@link blocked/1},
%% {@link unblocked/1}, {@link work_start/1}, {@link work_pause/2},
%% {@link work_resume/1}, {@link work_complete/1} change the READY sub-state;
%% {@link identifier_read/3}, {@link transfer_in/2}, {@link work_abort/2},
%% {@link transfer_out/2} do not.
-module(cell_task).

-include("cell_task.hrl").

-export([id/1, zone/1, lane/1, module/1, args/1, arg/3, settings/1, setting/3,
         get/2, get/3, put/3, product/1, set_product/2, clear_product/1, others_products/1,
         retained/1, retained/3, retain/3, retain_update/4, forget_retained/2,
         state/1, answer/1, woken_by/1, service_mode/1, io_groups/1, commanded/3, commanded/4]).
-export([starved/1, unstarved/1, blocked/1, unblocked/1, identifier_read/3,
         transfer_in/2, work_start/1, work_pause/2, work_resume/1, work_complete/1,
         work_abort/2, transfer_out/2]).
-export([error_spec/4, warning/4, warning/5, reset_warning/2, log/4]).
-export([in/2, in/3, read/2, read/3, out/3, out/4]).
%% For the engine and the handshake.
-export([new/1, set_state/3, publish/3, store/5, load_retained/1, transfer_out/3]).

-export_type([task/0, wait/0, step_result/0, spec/0, held/0, cause/0]).

%% Opaque to task modules: use the functions of this module on it.
-type task() :: #task{}.
-type wait() :: {timer, non_neg_integer()}
              | {reply, reference()}
              | {io, atom(), cell_hal_type:condition()}
              | {io, atom(), atom(), cell_hal_type:condition()}
              | {handshake, atom(), available | not_busy, boolean()}.
%% `{timer, Ms}': Ms milliseconds have passed. `{reply, Ref}': the task process
%% received `{Ref, Term}' (an answer to an asynchronous request it made, such as a
%% hardware object's). `{io, Point, Cond}' or `{io, Group, Point, Cond}': an IO point
%% reached a condition (`{eq, V} | {ne, V} | {gt, V} ...', see cell_hal), woken by the
%% HAL, never polled; `woken_by/1' gives `{io, Group, Point, Value}'.
%% `{handshake, Link, Signal, Value}': a signal of a handshake
%% link has that value (see {@link cell_handshake}); a transfer on the link that ends
%% (completed, aborted, interrupted) ends the wait too.
-type step_result() :: {continue, task()}
                     | {wait, wait() | [wait()], task()}
                     | {error, cell_alarms:spec(), task()}
                     | {reset, task()}.
-type spec() :: #{id := atom(), module := module(), zone := binary(), lane := binary(),
                  io => [atom()], settings => map() | atom(), args => map(),
                  work => boolean(), links => #{atom() => #{role := up | down}}}.

%% Why a task starts: from OFF on Start (after a Stop, or with the node's boot), after
%% its process crashed (the cell running), after a Reset, or, running, because the
%% product it held was found to be an old copy another task holds in a newer record
%% (it was dropped: the task reconciles again without it).
-type cause() :: start | crash | reset | dropped.
%% What the task's predecessor left, for `reconcile'.
-type held() :: #{cause := cause(),
                  product := cell_product:product() | undefined,
                  marker := cell_product:marker(),
                  links := #{atom() => cell_handshake_link:phase()},
                  outputs := #{atom() => #{atom() => cell_hal_type:value()}}}.

-callback init(task()) -> {ok, task()} | {error, cell_alarms:spec(), task()}.
-callback reconcile(held(), task()) -> {ok, task()} | {error, cell_alarms:spec(), task()}.
-callback step(task()) -> step_result().
-callback uninit(task()) -> task().
%% Messages the engine does not know (an unsolicited message of a hardware object, a
%% reply the task no longer waits for). A module without it expects none: such a
%% message crashes the task (a late reply is dropped).
-callback handle_info(term(), task()) -> {ok, task()}.
-optional_callbacks([handle_info/2]).

%% @private The task of a spec, before anything is loaded.
-spec new(spec()) -> task().
new(#{id := Id, module := Mod, zone := Zone, lane := Lane} = Spec) ->
    Path = cell_product:path(Zone, Lane),
    Retain = cell_retain:path(Zone, Lane),
    #task{id = Id, module = Mod, zone = Zone, lane = Lane,
          args = maps:get(args, Spec, #{}), io = maps:get(io, Spec, []),
          settings = case maps:get(settings, Spec, #{}) of
                         Fixed when is_map(Fixed) -> Fixed;
                         Name when is_atom(Name) -> cell_settings:get(Name)
                     end,
          links = maps:map(fun(_, #{role := Role}) ->
                                   #{role => Role, phase => idle, available => false,
                                     not_busy => false}
                           end, maps:get(links, Spec, #{})),
          product_path = Path, product_file = cell_file:record_file(Path),
          retain_path = Retain, retain_file = cell_file:record_file(Retain)}.

%% Accessors

%% @doc The task's id in the cell spec.
-spec id(task()) -> atom().
id(#task{id = Id}) -> Id.

%% @doc The task's zone (the machine part it covers, as the spec names it).
-spec zone(task()) -> binary().
zone(#task{zone = Z}) -> Z.

%% @doc The task's lane, as the spec names it.
-spec lane(task()) -> binary().
lane(#task{lane = L}) -> L.

%% @doc The task's module.
-spec module(task()) -> module().
module(#task{module = M}) -> M.

%% @doc The arguments the cell spec gave the task.
-spec args(task()) -> map().
args(#task{args = A}) -> A.

%% @doc One argument the cell spec gave the task, or `Default'.
-spec arg(task(), term(), term()) -> term().
arg(#task{args = A}, Key, Default) -> maps:get(Key, A, Default).

%% @doc The task's settings, as the snapshot taken at the last Start.
-spec settings(task()) -> map().
settings(#task{settings = S}) -> S.

%% @doc One field of the task's settings snapshot, or `Default'.
-spec setting(task(), term(), term()) -> term().
setting(#task{settings = S}, Key, Default) -> maps:get(Key, S, Default).

%% @doc A field of the task module's own data.
-spec get(task(), term()) -> term().
get(#task{data = D}, Key) -> maps:get(Key, D).

%% @doc A field of the task module's own data, or `Default' when it has none.
-spec get(task(), term(), term()) -> term().
get(#task{data = D}, Key, Default) -> maps:get(Key, D, Default).

%% @doc Sets a field of the task module's own data (kept in memory only: what must
%% outlive the process goes with the product or in the retained data).
-spec put(task(), term(), term()) -> task().
put(#task{data = D} = T, Key, Value) -> T#task{data = maps:put(Key, Value, D)}.

%% @doc The product the task holds, or `undefined'.
-spec product(task()) -> cell_product:product() | undefined.
product(#task{product = P}) -> P.

%% @doc Takes or changes the product; it is on disk when this returns. A product of
%% another serial (a new panel read by a scanner, say) starts a new history.
-spec set_product(task(), cell_product:product()) -> task().
set_product(#task{product = Old, gen = Gen, marker = Marker} = T, Product) ->
    case cell_product:validate(Product) of
        ok ->
            case cell_product:serial(Old) =:= cell_product:serial(Product) of
                true -> store(T, Product, Gen, Marker, #{});
                false -> store(T, Product, 1, undefined, #{})
            end;
        {error, Reason} ->
            erlang:error(Reason)
    end.

%% @doc The products the cell's other tasks hold now, by task (as each last saved it):
%% what a task reads to tell whether a product its sensors see is in some record.
-spec others_products(task()) -> [{atom(), cell_product:product()}].
others_products(#task{id = Id}) ->
    [{Other, P} || #{id := Other, product := P} <- cell_registry:tasks(), Other =/= Id,
                   is_map(P)].

%% @doc The task holds no product any more; its file is removed.
-spec clear_product(task()) -> task().
clear_product(T) ->
    store(T, undefined, 0, undefined, #{}).

%% @doc A value the task retained, or `Default' when it has none.
-spec retained(task(), cell_retain:key(), term()) -> term().
retained(#task{retained = R}, Key, Default) ->
    maps:get(Key, R, Default).

%% @doc Everything the task retained.
-spec retained(task()) -> cell_retain:data().
retained(#task{retained = R}) ->
    R.

%% @doc Retains `Value' under `Key'; it is on disk when this returns. A key or value
%% {@link cell_retain} refuses raises `{bad_retained, Key, Why}', and nothing is
%% written.
-spec retain(task(), cell_retain:key(), term()) -> task().
retain(#task{retained = R} = T, Key, Value) ->
    case R of
        #{Key := Value} ->
            T;
        #{} ->
            case cell_retain:put(R, Key, Value) of
                {ok, R1} -> keep(T, R1);
                {error, Refusal} -> erlang:error(Refusal)
            end
    end.

%% @doc Applies `Fun' to the value retained under `Key' (to `Default' when there is
%% none) and retains the result, which it returns with the task; it is on disk when
%% this returns. A serial counter: `{N, T1} = retain_update(T, serial, fun(S) -> S + 1
%% end, 0)' gives 1, 2, 3 ... across restarts, crashes and power cuts.
-spec retain_update(task(), cell_retain:key(), fun((term()) -> term()), term()) ->
          {term(), task()}.
retain_update(#task{retained = R} = T, Key, Fun, Default) ->
    case cell_retain:update(R, Key, Fun, Default) of
        {ok, New, R1} -> {New, keep(T, R1)};
        {error, Refusal} -> erlang:error(Refusal)
    end.

%% @doc Removes what the task retained under `Key'; durable when this returns.
-spec forget_retained(task(), cell_retain:key()) -> task().
forget_retained(#task{retained = R} = T, Key) ->
    case maps:is_key(Key, R) of
        true -> keep(T, cell_retain:remove(R, Key));
        false -> T
    end.

keep(#task{id = Id, retain_file = File} = T, Data) ->
    case cell_retain:save(File, Data, #{}) of
        ok ->
            ok = cell_registry:update(Id, #{retained => Data}),
            T#task{retained = Data};
        {error, Reason} ->
            %% Nothing may act on a value that is not durable: the task crashes and
            %% the operator is told why (as for a product not saved).
            erlang:error({retained_not_saved, Reason})
    end.

%% @private The task's retained data from its file, when the task starts; the
%% registry row says what was loaded or why nothing could be.
-spec load_retained(task()) -> {ok, task()} | {error, term()}.
load_retained(#task{id = Id, module = Mod, retain_path = Path} = T) ->
    %% The atoms of the task's code exist before its file is read.
    _ = code:ensure_loaded(Mod),
    case cell_retain:load(Path) of
        {ok, Data} ->
            ok = cell_registry:update(Id, #{retained => Data, retained_error => undefined}),
            {ok, T#task{retained = Data}};
        {error, Reason} = Error ->
            ok = cell_registry:update(Id, #{retained => undefined, retained_error => Reason}),
            Error
    end.

%% @private Stores the task's product with its generation and marker (`undefined'
%% removes the file), and tells the registry.
-spec store(task(), cell_product:product() | undefined, non_neg_integer(),
            cell_product:marker(), cell_file:options()) -> task().
store(#task{id = Id, product_file = File} = T, Product, Gen, Marker, Opts) ->
    Stored = case Product of
                 undefined -> undefined;
                 _ -> cell_product:stored(Product, Gen, Marker)
             end,
    Serial = cell_product:serial(Product),
    Fields = #{item => Serial, product => Product, in_transit => Marker =/= undefined},
    %% Taking a product is in the trace journal before the task holds it: after a
    %% crash the statistics know it entered, and with what, even if the event never
    %% reached them. Taken in a hand-over (in transit), its transfer in is the record.
    Journal = case Serial of
                  undefined -> #{};
                  _ when Serial =:= T#task.traced; Marker =/= undefined -> #{};
                  _ -> journal(T, product_saved, Fields)
              end,
    case cell_product:save(File, Stored, Opts) of
        ok ->
            ok = cell_registry:hold(Id, Serial, Gen),
            ok = cell_registry:update(Id, #{serial => Serial, product => Product}),
            %% Watchers (panel, SHDR) see the task's product change at once.
            ok = publish(T, product_saved, maps:merge(Fields, Journal)),
            T#task{product = Product, gen = Gen, marker = Marker, traced = Serial};
        {error, Reason} ->
            %% Nothing may go on as if the product were saved: the task crashes and
            %% comes back DOWN with this reason for the operator.
            erlang:error({product_not_saved, Reason})
    end.

%% @doc The task's IPC-2541 state.
-spec state(task()) -> cell_ipc:state().
state(#task{ipc = S}) -> S.

%% @doc The operator's answer to the error the last step returned, in the step that
%% runs after it; `undefined' otherwise.
-spec answer(task()) -> cell_alarms:solution() | undefined.
answer(#task{answer = A}) -> A.

%% @doc What ended the wait before this step: `{timer, Ms}', `{reply, Ref, Term}',
%% `{answer, Solution}', or `undefined' (the first step, or after `continue').
-spec woken_by(task()) -> term().
woken_by(#task{woken_by = W}) -> W.

%% @doc In `reconcile': an output of the task's default IO group as the predecessor
%% last commanded it, or `undefined' if it was not readable.
-spec commanded(held(), task(), atom()) -> cell_hal_type:value() | undefined.
commanded(Held, T, Point) ->
    commanded(Held, T, default_group(T), Point).

%% @doc As {@link commanded/3}, for an output of one of the task's IO groups.
-spec commanded(held(), task(), atom(), atom()) -> cell_hal_type:value() | undefined.
commanded(#{outputs := Outs}, _T, Group, Point) ->
    maps:get(Point, maps:get(Group, Outs, #{}), undefined).

%% @doc True in service mode: movements must be limited to harmless speeds.
-spec service_mode(task()) -> boolean().
service_mode(#task{service_mode = S}) -> S.

%% @doc The IO group instances of the task; the first is its default group.
-spec io_groups(task()) -> [atom()].
io_groups(#task{io = Io}) -> Io.

%% IPC-2541 events (seed 000 §2.3.4)

%% @doc The task waits for a product: READY-IDLE-STARVED.
-spec starved(task()) -> task().
starved(T) -> event(T, equipment_starved, #{}).

%% @doc The previous device offers a product: READY-PROCESSING-ACTIVE.
-spec unstarved(task()) -> task().
unstarved(T) -> event(T, equipment_unstarved, #{}).

%% @doc The task waits for the next device to take its product: READY-IDLE-BLOCKED.
-spec blocked(task()) -> task().
blocked(T) -> event(T, equipment_blocked, #{}).

%% @doc The next device requests the product: READY-PROCESSING-ACTIVE.
-spec unblocked(task()) -> task().
unblocked(T) -> event(T, equipment_unblocked, #{}).

%% @doc A product serial was read by a scanner. No state change.
-spec identifier_read(task(), binary(), binary()) -> task().
identifier_read(T, Serial, Scanner) ->
    event(T, item_identifier_read, #{item => Serial, scanner => Scanner}).

%% @doc The task received a product. No state change.
-spec transfer_in(task(), binary()) -> task().
transfer_in(T, Serial) ->
    event(T, item_transfer_in, journaled(T, item_transfer_in, #{item => Serial})).

%% @doc Processing of the product starts: READY-PROCESSING-EXECUTING.
-spec work_start(task()) -> task().
work_start(T) -> event(T, item_work_start, item(T)).

%% @doc Processing stops for a while: READY-PROCESSING-ACTIVE.
-spec work_pause(task(), binary()) -> task().
work_pause(T, PauseId) -> event(T, item_work_pause, (item(T))#{pause_id => PauseId}).

%% @doc Processing goes on: READY-PROCESSING-EXECUTING.
-spec work_resume(task()) -> task().
work_resume(T) -> event(T, item_work_resume, item(T)).

%% @doc Every instruction of the recipe is done: READY-PROCESSING-ACTIVE.
-spec work_complete(task()) -> task().
work_complete(T) -> event(T, item_work_complete, item(T)).

%% @doc Processing is cancelled before completion. No state change.
-spec work_abort(task(), binary()) -> task().
work_abort(T, AbortId) -> event(T, item_work_abort, (item(T))#{abort_id => AbortId}).

%% @doc The product has left the task's zone. No state change.
-spec transfer_out(task(), binary()) -> task().
transfer_out(#task{product = Product} = T, Serial) ->
    transfer_out(T, Serial, Product).

%% @private As {@link transfer_out/2}, for the product that left (the handshake lets its
%% task's product go before the transfer ends). Its exit record says whether it left
%% failed: applied again after a crash, the record tells the statistics the same as the
%% first time, whatever they then know of the product's fields (their changes are not
%% in the journal).
-spec transfer_out(task(), binary(), cell_product:product() | undefined) -> task().
transfer_out(T, Serial, Product) ->
    Fields = case Product of
                 #{serial := Serial} -> #{item => Serial,
                                          failed => maps:get(failed, Product, false) =:= true};
                 _ -> #{item => Serial}
             end,
    event(T, item_transfer_out, journaled(T, item_transfer_out, Fields)).

%% The fields of an event of the product's way, with the id of its record in the trace
%% journal: the record is durable when this returns (see cell_trace_journal).
journaled(T, Type, Fields) ->
    maps:merge(Fields, journal(T, Type, Fields)).

journal(#task{id = Id, zone = Z, lane = L}, Type, Fields) ->
    %% The event carries its record's id and time: the statistics take it the same
    %% whether from the event or from the record (see cell_stats).
    At = erlang:system_time(microsecond),
    case cell_trace_journal:append(Fields#{type => Type, task => Id, zone => Z, lane => L,
                                           at => At}) of
        {ok, JournalId} -> #{journal => JournalId, at => At};
        %% A task outside a cell's supervisor (a test of its module alone).
        {error, not_running} -> #{};
        %% Nothing may go on as if the record were kept: as for a product not saved.
        {error, Reason} -> erlang:error({trace_not_saved, Reason})
    end.

item(#task{product = undefined}) -> #{};
item(#task{product = #{serial := S}}) -> #{item => S}.

event(#task{ipc = From} = T, Type, Fields) ->
    case cell_ipc:is_ready(From) of
        true ->
            ok = publish(T, Type, Fields),
            set_state(T, cell_ipc:event_state(Type, From), {event, Type});
        false when Type =:= item_identifier_read; Type =:= item_transfer_in;
                   Type =:= item_work_abort; Type =:= item_transfer_out ->
            ok = publish(T, Type, Fields),
            T;
        false ->
            erlang:error({event_outside_ready, Type, From})
    end.

%% @private Changes the task's state, checked against the seed's table, and tells the
%% cell: a `task_state' event and the registry row the controller reads.
-spec set_state(task(), cell_ipc:state(), cell_ipc:cause()) -> task().
set_state(#task{ipc = Same} = T, Same, _Cause) ->
    T;
set_state(#task{ipc = From, id = Id} = T, To, Cause) ->
    case cell_ipc:check(From, To, Cause) of
        ok -> ok;
        {error, Illegal} -> erlang:error(Illegal)
    end,
    ok = cell_registry:set_state(Id, To),
    ok = publish(T, task_state, #{state => To, from => From, cause => Cause}),
    ok = cell_controller:task_state_changed(),
    case cell_log:enabled(verbose, Id) of
        true -> cell_log:debug(Id, "~ts -> ~ts", [cell_ipc:name(From), cell_ipc:name(To)]);
        false -> ok
    end,
    T#task{ipc = To}.

%% @private
-spec publish(task(), cell_events:type(), map()) -> ok.
publish(#task{id = Id, zone = Z, lane = L}, Type, Fields) ->
    cell_events:publish(Type, Id, Fields#{zone => Z, lane => L}).

%% IO (seed 000 §4: a task reads and writes points by name, never a driver)

%% @doc The value of a point of the task's default IO group (the first of its spec's
%% `io'). An input whose connection is down is not read: the task goes DOWN with an
%% error naming the connection, and the step runs again after Retry once it is back.
%% A point the device cannot serve (a PLC symbol gone or retyped) is the same with an
%% error naming the point.
-spec in(task(), atom()) -> cell_hal_type:value().
in(T, Point) ->
    in(T, default_group(T), Point).

%% @doc The value of a point of one of the task's IO groups.
-spec in(task(), atom(), atom()) -> cell_hal_type:value().
in(T, Group, Point) ->
    case cell_hal:read(Group, Point) of
        {ok, Value} -> Value;
        {error, disconnected} -> io_lost(T, Group, Point);
        {error, not_yet_read} -> io_lost(T, Group, Point);
        {error, {unavailable, Why}} -> throw({cell_io_unavailable, Group, Point, Why});
        {error, Reason} -> erlang:error({io, Group, Point, Reason})
    end.

%% @doc A point's value or why there is none, for code that decides itself.
-spec read(task(), atom()) -> {ok, cell_hal_type:value()} | {error, term()}.
read(T, Point) ->
    read(T, default_group(T), Point).

%% @doc As {@link read/2}, for a point of one of the task's IO groups.
-spec read(task(), atom(), atom()) -> {ok, cell_hal_type:value()} | {error, term()}.
read(_T, Group, Point) ->
    cell_hal:read(Group, Point).

%% @doc Commands an output of the task's default IO group; it is written through in
%% order, without waiting for the device. The task remembers what it commanded: when a
%% connection it lost is back and the operator retries, the engine writes again each
%% output the device no longer holds as commanded (a write lost with the connection,
%% a PLC that took its outputs to safe values), then the task goes on.
-spec out(task(), atom(), cell_hal_type:value()) -> task().
out(T, Point, Value) ->
    out(T, default_group(T), Point, Value).

%% @doc As {@link out/3}, for an output of one of the task's IO groups.
-spec out(task(), atom(), atom(), cell_hal_type:value()) -> task().
out(T, Group, Point, Value) ->
    case cell_hal:write(Group, Point, Value) of
        ok -> T#task{commanded = cell_task_outputs:command(T#task.commanded, Group, Point, Value)};
        {error, disconnected} -> io_lost(T, Group, Point);
        {error, {unavailable, Why}} -> throw({cell_io_unavailable, Group, Point, Why});
        {error, Reason} -> erlang:error({io, Group, Point, Reason})
    end.

%% The engine drops the step and runs it again after Retry; what the step commanded
%% before it found the connection lost goes with the throw, so that the outputs written
%% again at that Retry are those it last commanded (see cell_task_proc).
-spec io_lost(task(), atom(), atom()) -> no_return().
io_lost(#task{commanded = Commanded}, Group, Point) ->
    throw({cell_io_lost, Group, Point, Commanded}).

default_group(#task{io = [G | _]}) -> G;
default_group(#task{id = Id}) -> erlang:error({no_io_group, Id}).

%% Errors, warnings, log

%% @doc An error for the operator, to return from `init' or `step':
%% `{error, cell_task:error_spec(<<"lost">>, "Product lost", Text, [retry, ignore, reset]), T}'.
-spec error_spec(binary(), iodata(), iodata(), [cell_alarms:solution()]) -> cell_alarms:spec().
error_spec(Id, Caption, Description, Solutions) ->
    #{id => Id, caption => Caption, description => Description, solutions => Solutions}.

%% @doc Sets (or updates) a warning; the task goes on at once.
-spec warning(task(), binary(), iodata(), iodata()) -> task().
warning(T, WarningId, Caption, Description) ->
    warning(T, WarningId, Caption, Description, #{}).

%% @doc As {@link warning/4}, with a qualifier: `#{qualifier => high}' for a value above
%% its limit, `low' below.
-spec warning(task(), binary(), iodata(), iodata(), cell_alarms:options()) -> task().
warning(#task{id = Id} = T, WarningId, Caption, Description, Opts) ->
    ok = cell_alarms:warning(Id, WarningId, Caption, Description, Opts),
    T.

%% @doc Resets a warning this task set.
-spec reset_warning(task(), binary()) -> task().
reset_warning(#task{id = Id} = T, WarningId) ->
    ok = cell_alarms:reset_warning(Id, WarningId),
    T.

%% @doc Logs to the task log at one of the seed's levels (silent, brief, verbose) or
%% as error / warning.
-spec log(task(), cell_log:level(), io:format(), [term()]) -> ok.
log(#task{id = Id}, Level, Format, Args) ->
    cell_log:log(Level, Id, Format, Args).
