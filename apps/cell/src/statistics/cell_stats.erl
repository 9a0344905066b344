%% @doc Statistics and traceability: what the cell did, per shift and in total, and
%% every product's history by serial, kept in the cell's database (`Databases/', see
%% {@link cell_db}) so they survive restarts.
%%
%% The process only listens: it subscribes to {@link cell_events} and never calls a
%% task, so a task never waits for it. It counts in memory and writes the counters in
%% one transaction a second (a crash loses at most that second); a product's history is
%% handed as it happens to {@link cell_stats_writer}, which writes it in batches.
%%
%% <b>The product's way survives any crash.</b> What a task does with a product
%% (takes it, transfers it in or out) and an operator's answers are first made durable
%% by their writer in the trace journal ({@link cell_trace_journal}); the statistics
%% take those from the journal, in its order, and skip the events that follow them;
%% while the database is closed too (the journal is read once it opens, then older
%% records come first, whichever way each record reached the statistics).
%% Once a second, when records were applied or histories written, the histories
%% handed over are written and their tables flushed to the disk, then the counters
%% are written together with the books (which products are in the cell, how each one
%% that left did) and the id of the last record applied, in one transaction, and the
%% journal is trimmed up to it. The books are never written ahead of the counters: a
%% crash leaves both as they were at the same record. When the
%% database opens (at every start of the process) the records after that id are
%% applied again, before any event: each gives the same history entries (a record's
%% entries are keyed by its id and made of the record alone, and the history keeps one
%% copy of an entry) and is counted once, so after any crash a product that left is
%% recorded as left, once, with its whole history. Made of the record alone: a product
%% leaves good or failed as its exit record says, not as the statistics knew it (the
%% saves that marked it failed are not in the journal, and a crash may have taken them
%% from the statistics); an answer goes to the product its record names, or to none;
%% what changed in a product's fields since its task last saved it is written only
%% when the record is applied as it is made, never when it is applied again.
%% Who holds a product is then taken from the registry; a
%% product a task holds whose entry was never recorded enters with what its product
%% file says, and the log says so. A product counted as scrapped that then leaves
%% (see {@link cell_stats_trace:left_after_scrap/1}) is counted as left instead.
%%
%% <b>Time per IPC-2541 state</b>, per task: each `task_state' event closes the time
%% spent in the state before. The time is split at shift boundaries and added to the
%% shift and to the total, in microseconds. A new shift plan (the `statistics'
%% settings' `shifts') saved while the runtime runs applies when the running shift
%% ends, or at the runtime's next start; a shift's span is kept as the plan had it
%% when the shift was first counted, so reports of past shifts stay right. The state
%% each task is in, and since when, is written with the counters; a query adds that
%% open stretch up to the last write, so the process does no work for a task that
%% stays in its state (a thousand waiting tasks cost it nothing) and closes the open
%% stretches only when a shift ends. Time while the runtime was not running (from the
%% last write before a stop or crash until the next start) is counted as OFF, the time
%% before it in the state the task was in, so for every task the states add up to the
%% wall-clock time since it was first seen.
%%
%% <b>Products.</b> A serial first saved by a task enters the cell (`in'); a
%% transfer out of a task that hands to no other task of this cell takes it out
%% (`out', `good' or `failed' by the failed flag its exit record carries, see
%% {@link cell_stats_trace:left_failed/2}); a product no task holds any more
%% for two writes in a row (about two seconds: a handshake hands over in far less) was
%% forgotten inside the cell (`scrapped': an operator's Reset, say). So at every
%% moment `in = out + scrapped + in_cell'. Per task: items in and out, work completed
%% and aborted, errors, crashes; cycle time (between two products out), lead time
%% (a product's time in the task, or in the cell) and work time (work start to
%% complete) as count, sum, min and max.
%%
%% <b>History</b> by serial: entry with recipe, every item event (identifier read,
%% transfer in and out, work start, pause, resume, complete, abort), every change of
%% the product's fields (failed flag, progress, inspection results ...), the errors and
%% warnings raised and answered while a task held it, and how it left. Other parts of
%% the runtime add their own records with {@link record/3}.
%%
%% The tables and the reports read from them are {@link cell_stats_db}'s; the time
%% per state and the shifts, pure, {@link cell_stats_clock}'s. The traceability tables
%% live on disc only, so memory does not grow with the number of products; they are
%% purged after the `statistics' settings' `trace_days' (or sooner, past
%% `trace_max_records'), shift counters after `shift_days'.
%%
%% If the database cannot be opened the statistics go on in memory, say why in the
%% log, and try again every ten seconds. A product's way (taken, transferred, left)
%% is counted only once it opens: which of the journal's records the database already
%% holds, and which products it had in the cell, is known then, and the records are
%% applied in the journal's order. Reading back what they wrote (the products
%% in the cell, the id of the last record applied) is part of opening it: a read that
%% fails leaves the database closed, never taken for an empty one.
-module(cell_stats).
-behaviour(gen_server).

-export([start_link/1, child_spec/1, exits/1]).
-export([flush/0, record/3, summary/0, summary/1, counters/1, time_check/0, periods/0,
         shift_now/0, product/1, products_out/2, in_cell/0, tables/0, node_restarts/0]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-export_type([period/0, options/0]).

-type period() :: total | cell_stats_shift:id().
-type options() :: #{exits => all | [atom()]}.

-define(FLUSH_MS, 1000).
-define(RETRY_MS, 10000).
-define(LOAD_MS, 60000).
-define(PURGE_MS, 3600000).
-define(BACKLOG_MAX, 10000).
-define(JOURNAL_WARNING, <<"trace_journal">>).
-define(EVENTS, [task_state, item_identifier_read, item_transfer_in, item_work_start,
                 item_work_pause, item_work_resume, item_work_complete, item_work_abort,
                 item_transfer_out, alarm_raised, alarm_cleared, product_saved,
                 task_crashed]).

-record(prod, {entered :: integer(),                  %% wall µs
               recipe = <<>> :: binary(),
               failed = false :: boolean(),
               entry :: atom(),                        %% the task it entered at
               holder :: atom() | undefined,           %% the task holding it now
               by :: atom(),                           %% the last task that held it
               unheld = 0 :: 0..2,                     %% writes seen with no holder
               last :: map() | undefined,              %% its fields as last saved
               at = #{} :: #{{atom(), in | work} => integer()}}).

-record(st, {db = closed :: closed | open,
             exits :: all | [atom()],
             started :: integer(),                              %% wall µs
             clock :: cell_stats_clock:clock(),     %% each task's state, the shift
             pending :: ets:tid(),        %% {Key, add | min | max | set | first, Value}
             products = #{} :: #{binary() => #prod{}},
             holding = #{} :: #{atom() => binary()},            %% task -> serial
             last_out = #{} :: #{atom() => integer()},          %% task | cell -> wall µs
             %% The books not yet written: rows of the products in the cell to write
             %% (or to delete), summaries of products that left (see write_open/3).
             book_open = #{} :: #{binary() => map() | delete},
             book_left = #{} :: #{binary() => map()},
             backlog = [] :: [fun(() -> term())],
             backlog_len = 0 :: non_neg_integer(),
             backlog_dropped = 0 :: non_neg_integer(),   %% the oldest, past the limit
             writer :: pid() | undefined,                       %% see cell_stats_writer
             batch = 0 :: non_neg_integer(),                    %% the last batch handed over
             writing = false :: boolean(),                      %% ... and not done yet
             queued = [] :: [fun(() -> term())],                %% for the next, newest first
             seq = 0 :: non_neg_integer(),
             %% The trace journal (see cell_trace_journal): read once the database is
             %% open; the last record applied, the last whose effects are durable, and
             %% the record being applied now with a count of its history entries (so a
             %% record applied again writes the very same entries) and whether a run
             %% before this one may have applied it (see apply_record/4).
             attached = false :: boolean(),
             applied :: cell_trace_journal:id() | undefined,
             saved :: cell_trace_journal:id() | undefined,
             applying :: {cell_trace_journal:id(), non_neg_integer(), live | replay}
                       | undefined,
             unsynced = false :: boolean(),     %% histories written since the last flush
             %% The journal's warning is up (unknown at start: set or reset at once).
             journal_warned = unknown :: boolean() | unknown,
             %% The products that left while the journal was read at start, and by which
             %% task; and those a task still holds in its file though they left through it
             %% (a crash between its record and its file): its copy until it lets go.
             gone = #{} :: #{binary() => atom()},
             stale = #{} :: #{binary() => atom()},
             %% When to try opening the database again; 0 until it could not be.
             retry_at = 0 :: integer() | infinity,
             purge_at = 0 :: integer()}).

%%====================================================================
%% API
%%====================================================================

-spec start_link(options()) -> {ok, pid()} | {error, term()}.
start_link(Opts) ->
    case Opts of
        #{exits := E} when E =/= all, not is_list(E) -> {error, {bad_option, exits}};
        _ when is_map(Opts) ->
            case maps:keys(Opts) -- [exits] of
                [] -> gen_server:start_link({local, ?MODULE}, ?MODULE, Opts, []);
                [K | _] -> {error, {bad_option, K}}
            end;
        _ -> {error, {bad_option, options}}
    end.

%% @doc The child spec for the controller's supervisor, from the cell spec.
-spec child_spec(cell_spec:spec()) -> supervisor:child_spec().
child_spec(Spec) ->
    #{id => ?MODULE, start => {?MODULE, start_link, [#{exits => exits(Spec)}]},
      shutdown => 10000}.

%% @doc The tasks whose products leave the cell when they transfer them out: those
%% that hand over to no task of this cell (a link to another node's task leaves it).
-spec exits(cell_spec:spec()) -> [atom()].
exits(#{tasks := Tasks} = Spec) ->
    Links = maps:get(links, Spec, []),
    Internal = [F || #{from := F, to := To} <- Links, is_atom(To)],
    [Id || #{id := Id} <- Tasks, not lists:member(Id, Internal)].

%% @doc Writes what is counted so far; returns when it is in the database.
-spec flush() -> ok | {error, database_closed}.
flush() ->
    gen_server:call(?MODULE, flush, 30000).

%% @doc Adds a record to a product's history (an inspection result, a measurement).
%% Never waits: the record is written by the statistics process.
-spec record(binary(), atom() | binary(), term()) -> ok.
record(Serial, What, Detail) when is_binary(Serial) ->
    gen_server:cast(?MODULE, {record, Serial, What, Detail, now_us()}).

%% @doc The current shift and the total.
-spec summary() -> #{shift := map(), total := map()}.
summary() ->
    #{shift => summary(shift_now()), total => summary(total)}.

%% @doc What happened in one period (a shift id or `total'), in words a report uses:
%% times in milliseconds, per task time in each state, items, cycle, lead and work
%% times; for the cell items in, out, good, failed, scrapped, lead and cycle times and
%% throughput per hour. Read from the database (what was written up to a second ago).
-spec summary(period()) -> map().
summary(Period) ->
    cell_stats_db:summary(Period, fun shift_starts/0).

%% @doc The counters of a period up to the last write: `#{Scope => #{Metric =>
%% Value}}', times in microseconds, the time of tasks still in their state included.
-spec counters(period()) -> #{atom() => map()}.
counters(Period) ->
    cell_stats_db:counters(Period, fun shift_starts/0).

%% @doc For every task seen, the time counted in its states and the time from when it
%% was first seen to the last write, in microseconds, read together: the books are
%% right when the two are equal (for tests and diagnostics).
-spec time_check() -> #{atom() => {non_neg_integer(), non_neg_integer()}}.
time_check() ->
    cell_stats_db:time_check().

%% @doc How many times the node started again, after a clean stop and after an
%% unexpected one (killed, crashed, power cut), as the node's run record counts them
%% (see {@link cell_node_run}).
-spec node_restarts() -> #{clean := non_neg_integer(), unexpected := non_neg_integer()}.
node_restarts() ->
    cell_node_run:counts().

%% @doc The periods recorded: `total' and the shifts, oldest first.
-spec periods() -> [period()].
periods() ->
    cell_stats_db:periods().

%% @doc The shift running now, by the `statistics' settings.
-spec shift_now() -> cell_stats_shift:id().
shift_now() ->
    #{id := Id} = cell_stats_shift:at(cell_stats_clock:local(now_us()), shift_starts()),
    Id.

%% @doc A product's history: where it is or how it left (as written with the counters,
%% or, for up to a second until it is, as its history says), and every record, oldest
%% first (times in milliseconds since the epoch).
-spec product(binary()) -> {ok, map()} | {error, not_found}.
product(Serial) when is_binary(Serial) ->
    cell_stats_db:product(Serial).

%% @doc The products that left the cell between two times (milliseconds since the
%% epoch, both included), each as the time it left and whether it was good or failed.
-spec products_out(integer(), integer()) -> [{integer(), good | failed}].
products_out(From, To) ->
    cell_stats_db:products_out(From, To).

%% @doc How many products are in the cell.
-spec in_cell() -> non_neg_integer().
in_cell() ->
    cell_stats_db:in_cell().

%% @doc The tables, for {@link cell_db:ensure_tables/2}.
-spec tables() -> [cell_db:table()].
tables() ->
    cell_stats_db:tables().

%%====================================================================
%% gen_server
%%====================================================================

-spec init(options()) -> {ok, #st{}, {continue, open}}.
init(Opts) ->
    process_flag(trap_exit, true),
    %% Counting never competes with the tasks: a burst of events (an emergency stop
    %% of a thousand tasks) is counted once the tasks have done what it asked of them.
    process_flag(priority, low),
    %% A burst waits outside the heap: a collection never copies the queue.
    process_flag(message_queue_data, off_heap),
    ok = cell_events:subscribe(?EVENTS),
    %% The shift plan is there (its file read by the settings owner) before the cell
    %% has started.
    ok = cell_settings:register(cell_stats_settings),
    Now = now_us(),
    %% Every task as the registry has it now: counting starts here.
    Tasks = maps:from_list([{Id, {cell_stats_clock:state_name(S), Now}}
                            || #{id := Id, state := S} <- cell_registry:tasks()]),
    Holding = maps:from_list([{Id, S} || #{id := Id, serial := S} <- cell_registry:tasks(),
                                         is_binary(S)]),
    %% What is counted until the next write, kept outside the heap: a thousand tasks
    %% change thousands of counters a second, and a map of them would be copied at
    %% every collection.
    Pending = ets:new(cell_stats_pending, [set, private]),
    {ok, Writer} = cell_stats_writer:start_link(),
    {ok, #st{exits = maps:get(exits, Opts, all), started = Now,
             clock = cell_stats_clock:new(Tasks),
             holding = Holding, pending = Pending, writer = Writer},
     {continue, open}}.

-spec handle_continue(open, #st{}) -> {noreply, #st{}}.
handle_continue(open, St) ->
    _ = erlang:send_after(?FLUSH_MS, self(), flush),
    {noreply, open(St)}.

-spec handle_call(term(), gen_server:from(), #st{}) -> {reply, term(), #st{}}.
handle_call(flush, _From, St) ->
    St1 = history_written(flush(St)),
    {reply, flushed(St1), St1}.

flushed(#st{db = open}) -> ok;
flushed(#st{db = closed}) -> {error, database_closed}.

-spec handle_cast(term(), #st{}) -> {noreply, #st{}}.
handle_cast({record, Serial, What, Detail, At}, St) ->
    Task = case St#st.products of
               #{Serial := #prod{holder = H}} -> H;
               _ -> undefined
           end,
    {noreply, trace(Serial, At, Task, #{event => What, detail => Detail}, St)}.

-spec handle_info(term(), #st{}) -> {noreply, #st{}} | {stop, term(), #st{}}.
handle_info({cell_event, #{journal := _}}, St) ->
    %% Its record is taken from the journal, in the journal's order: it came before
    %% the event, or it comes with the older records once the database is open (an
    %% exit applied before the entry the journal holds would count the product as
    %% left, then entered, then scrapped).
    {noreply, St};
handle_info({cell_event, Event}, St) ->
    {noreply, event(Event, St)};
handle_info({cell_trace_journal, Records}, St) ->
    {noreply, lists:foldl(fun(R, Acc) -> journal_record(R, live, Acc) end, St, Records)};
handle_info(flush, St) ->
    _ = erlang:send_after(?FLUSH_MS, self(), flush),
    {noreply, flush(St)};
handle_info({cell_stats_writer, N, Result}, #st{batch = N} = St) ->
    {noreply, batch_done(Result, St#st{writing = false})};
handle_info({cell_stats_writer, _Old, Result}, St) ->
    %% A batch overtaken by a write that waited for it (see history_written/1).
    {noreply, batch_done(Result, St)};
handle_info({'EXIT', Writer, Reason}, #st{writer = Writer} = St) ->
    {stop, {history_writer, Reason}, St#st{writer = undefined}}.

%% What was counted is written, if the database is open; it is not opened now.
-spec terminate(term(), #st{}) -> ok.
terminate(_Reason, #st{db = open} = St) ->
    St1 = flush(St#st{retry_at = infinity}),
    %% The histories handed over are written too, unless their writer is what failed.
    _ = St1#st.writer =/= undefined andalso history_written(St1),
    ok;
terminate(_Reason, _St) ->
    ok.

%%====================================================================
%% Events
%%====================================================================

event(#{type := task_state, task := T, state := S} = E, St) ->
    clock(fun(C) -> cell_stats_clock:task_state(T, cell_stats_clock:state_name(S),
                                                 event_us(E), fun shift_starts/0, C)
          end, St);
event(#{type := product_saved, task := T} = E, St) ->
    saved(T, maps:get(item, E, undefined), maps:get(product, E, undefined), event_us(E), St);
event(#{type := item_transfer_in, task := T, item := S} = E, St) ->
    At = event_us(E),
    St1 = at(S, {T, in}, At, count([{T, in}], At, St)),
    trace_event(E, At, St1);
event(#{type := item_transfer_out, task := T, item := S} = E, St) ->
    At = event_us(E),
    St1 = trace_event(E, At, count([{T, out}], At, St)),
    St2 = timing({T, lead}, since(S, {T, in}, St1), At, St1),
    St3 = timing({T, cycle}, maps:get(T, St2#st.last_out, undefined), At, St2),
    St4 = St3#st{last_out = maps:put(T, At, St3#st.last_out)},
    case exit_task(T, St4) of
        true -> leave(S, T, At, maps:get(failed, E, undefined), St4);
        false -> St4
    end;
event(#{type := item_work_start, item := S, task := T} = E, St) ->
    At = event_us(E),
    trace_event(E, At, at(S, {T, work}, At, St));
event(#{type := item_work_complete, item := S, task := T} = E, St) ->
    At = event_us(E),
    St1 = timing({T, work}, since(S, {T, work}, St), At, count([{T, completed}], At, St)),
    trace_event(E, At, St1);
event(#{type := item_work_abort, task := T, item := _} = E, St) ->
    At = event_us(E),
    trace_event(E, At, count([{T, aborted}], At, St));
event(#{type := alarm_answered, task := T} = E, St) ->
    Entry = #{event => alarm_answered, id => maps:get(alarm, E, <<>>),
              caption => maps:get(caption, E, <<>>), solution => maps:get(solution, E),
              who => maps:get(who, E, <<>>)},
    case E of
        #{item := S} when is_binary(S) -> trace(S, event_us(E), T, Entry, St);
        %% Its task held no product when it was answered (the record says so): not the
        %% one the statistics have it holding when the record is applied again.
        _ -> St
    end;
event(#{item := S} = E, St) when is_binary(S) ->
    %% identifier read, work pause and resume: history only.
    trace_event(E, event_us(E), St);
event(#{type := alarm_raised, task := T, alarm := A} = E, St) when T =/= cell ->
    At = event_us(E),
    St1 = case maps:get(kind, A, error) of
              error -> count([{T, errors}], At, St);
              warning -> count([{T, warnings}], At, St);
              alarm -> St
          end,
    held_trace(T, At, #{event => alarm_raised, kind => maps:get(kind, A, error),
                        id => maps:get(id, A, <<>>), caption => maps:get(caption, A, <<>>)},
               St1);
event(#{type := alarm_cleared, task := T, alarm := A} = E, St) when T =/= cell ->
    held_trace(T, event_us(E), #{event => alarm_cleared, id => maps:get(id, A, <<>>),
                                 caption => maps:get(caption, A, <<>>),
                                 cleared => maps:get(cleared, A, undefined),
                                 who => maps:get(who, A, undefined)}, St);
event(#{type := task_crashed, task := T} = E, St) ->
    count([{T, crashes}], event_us(E), St);
event(_Other, St) ->
    St.

%% A task saved its product (or holds none any more).
saved(T, Serial, Product, At, #st{holding = Holding} = St) ->
    St1 = case maps:get(T, Holding, undefined) of
              Serial -> St;
              undefined -> St;
              Old -> let_go(Old, T, St)
          end,
    case Serial of
        undefined ->
            St1#st{holding = maps:remove(T, Holding)};
        _ ->
            St2 = St1#st{holding = maps:put(T, Serial, Holding)},
            case {maps:find(Serial, St2#st.products), St2#st.stale} of
                {error, #{Serial := T}} -> St2;           %% its stale copy: not again
                %% Whether the cell had it before is known once the database opens
                %% (see holders_now/2); a product taken is a record of the journal,
                %% applied then too.
                {error, _} when St2#st.db =:= closed -> St2;
                {error, _} -> enter(Serial, T, product_map(Product), At, St2);
                {{ok, P}, _} -> claim(Serial, T, P, product_map(Product), At, St2)
            end
    end.

product_map(P) when is_map(P) -> P;
product_map(_) -> #{}.

%% The task no longer holds the serial: handed over, sent out, or forgotten.
let_go(Serial, T, #st{products = Ps, stale = Stale} = St0) ->
    St = case Stale of
             #{Serial := T} -> St0#st{stale = maps:remove(Serial, Stale)};
             _ -> St0
         end,
    case maps:find(Serial, Ps) of
        {ok, #prod{holder = T} = P} ->
            St#st{products = Ps#{Serial := P#prod{holder = undefined, unheld = 0}}};
        _ ->
            St
    end.

enter(Serial, T, Product, At, St) ->
    Recipe = text(maps:get(recipe, Product, <<>>)),
    Failed = maps:get(failed, Product, false) =:= true,
    P = #prod{entered = At, recipe = Recipe, failed = Failed, entry = T, holder = T, by = T,
              last = Product},
    St1 = count_cell([in], At, St),
    St2 = St1#st{products = maps:put(Serial, P, St1#st.products)},
    St3 = write_open(Serial, P, St2),
    trace(Serial, At, T, #{event => entered, recipe => Recipe,
                           product => maps:without([serial], Product)}, St3).

claim(Serial, T, #prod{last = Last} = P0, Product, At, St) ->
    P = P0#prod{holder = T, by = T, unheld = 0, last = Product,
                failed = maps:get(failed, Product, P0#prod.failed) =:= true,
                recipe = text(maps:get(recipe, Product, P0#prod.recipe))},
    St1 = St#st{products = maps:put(Serial, P, St#st.products)},
    %% The product's row in the cell follows its verdict and recipe, also when the
    %% statistics restarted and have no saved fields to compare with.
    St2 = case P#prod.failed =/= P0#prod.failed orelse P#prod.recipe =/= P0#prod.recipe of
              true -> write_open(Serial, P, St1);
              false -> St1
          end,
    %% Restored after a restart, the product is known by what its row keeps.
    {Before, Fields} = case Last of
                           undefined -> {open_row(P0), maps:with([failed, recipe], Product)};
                           _ -> {Last, maps:without([serial], Product)}
                       end,
    Changes = maps:filter(fun(K, V) -> maps:get(K, Before, '$none') =/= V end, Fields),
    case map_size(Changes) of
        0 -> St2;
        _ -> changed(Serial, At, T, Changes, St2)
    end.

%% What changed since the task last saved the product. A record of the trace journal
%% (a task took a product the cell already knew) applied again after a crash knows
%% the product's fields only as the records and the books have them, not as its task
%% last saved them (those saves are not in the journal): its changes would differ
%% from those of its application as it was made, and the history would hold both.
%% What changed is written by that application alone; if the crash took it before it
%% was written, it is lost, as every save the journal does not keep.
changed(_Serial, _At, _T, _Changes, #st{applying = {_, _, replay}} = St) ->
    St;
changed(Serial, At, T, Changes, St) ->
    trace(Serial, At, T, #{event => changed, changes => Changes}, St).

%% The product left the cell through an exit task, failed or not as its exit record
%% says (`Failed', see cell_stats_trace:left_failed/2). One the statistics no longer
%% hold was counted before: taken for scrapped (its hand-out took longer than a
%% hand-over may), it is counted as left instead; already out, it is not counted again.
leave(Serial, T, At, Failed, #st{products = Ps, stale = Stale} = St) ->
    As = fun(#prod{failed = Known} = P) ->
                 P#prod{failed = cell_stats_trace:left_failed(Failed, Known)}
         end,
    case {maps:find(Serial, Ps), Stale} of
        {{ok, P}, _} ->
            left(Serial, T, At, As(P), St);
        {error, #{Serial := T}} ->
            %% Its stale copy sent out again: it left once.
            St#st{stale = maps:remove(Serial, Stale)};
        {error, _} ->
            Summary = left_summary(Serial, St),
            case cell_stats_trace:left_after_scrap(Summary) of
                count ->
                    left(Serial, T, At, As(#prod{entered = At, entry = T}), St);
                already_out ->
                    St;
                {uncount_scrap, By} ->
                    cell_log:warning(cell, "statistics: product ~ts was counted as scrapped "
                                     "but has left through ~ts; it is counted as left",
                                     [Serial, T]),
                    St1 = count_cell_by([scrapped], -1, At,
                                        case By of
                                            undefined -> St;
                                            _ -> count_by([{By, scrapped}], -1, At, St)
                                        end),
                    left(Serial, T, At, As(summary_prod(Summary, At, T)), St1)
            end
    end.

%% A product as the summary of one that left has it.
summary_prod(#{entered := E} = S, At, T) ->
    #prod{entered = case E of undefined -> At; _ -> E * 1000 end,
          recipe = maps:get(recipe, S, <<>>), failed = maps:get(failed, S, false),
          entry = maps:get(entry_task, S, T)}.

left(Serial, T, At, P, #st{products = Ps, gone = Gone} = St0) ->
    %% Kept only while the journal is read at start (see holders_now/2).
    St = case St0 of
             #st{attached = false, db = open} -> St0#st{gone = Gone#{Serial => T}};
             _ -> St0
         end,
    Quality = case P#prod.failed of true -> failed; false -> good end,
    St1 = count_cell([out, Quality], At, St),
    St2 = timing({cell, lead}, P#prod.entered, At, St1),
    St3 = timing({cell, cycle}, maps:get(cell, St2#st.last_out, undefined), At, St2),
    St4 = St3#st{last_out = maps:put(cell, At, St3#st.last_out),
                 products = maps:remove(Serial, Ps)},
    St5 = write_left(Serial, P, out, {T, At}, St4),
    trace(Serial, At, T, #{event => left, quality => Quality}, St5).

%% No task has held the product for two writes in a row: it was forgotten inside the
%% cell. The registry is asked too, so a product whose new holder's event is still
%% on its way is not taken for lost.
reconcile(Now, #st{products = Ps} = St) ->
    maps:fold(fun(Serial, #prod{holder = undefined, unheld = N} = P, Acc) ->
                      case cell_stats_trace:unheld(N, holders(Serial)) of
                          held ->
                              Acc#st{products = maps:put(Serial, P#prod{unheld = 0},
                                                         Acc#st.products)};
                          scrap ->
                              scrap(Serial, P, Now, Acc);
                          {wait, N1} ->
                              Acc#st{products = maps:put(Serial, P#prod{unheld = N1},
                                                         Acc#st.products)}
                      end;
                 (_, _, Acc) ->
                      Acc
              end, St, Ps).

holders(Serial) ->
    try cell_registry:holders(Serial)
    catch error:badarg -> [undefined]          %% the registry is restarting: wait
    end.

scrap(Serial, #prod{by = Task} = P, At, St) ->
    St1 = count_cell([scrapped], At, case Task of
                                         undefined -> St;
                                         _ -> count([{Task, scrapped}], At, St)
                                     end),
    St2 = St1#st{products = maps:remove(Serial, St1#st.products)},
    St3 = write_left(Serial, P, scrapped, {Task, At}, St2),
    trace(Serial, At, Task, #{event => scrapped, failed => P#prod.failed,
                              text => <<"no task holds it any more: it was forgotten in "
                                        "the cell (an operator's Reset) or taken out by hand">>},
          St3).

held_trace(T, At, Entry, #st{holding = Holding} = St) ->
    case maps:find(T, Holding) of
        {ok, Serial} -> trace(Serial, At, T, Entry, St);
        error -> St
    end.

trace_event(#{type := Type, task := T, item := S} = E, At, St) ->
    Detail = maps:with([scanner, pause_id, abort_id, zone, lane], E),
    trace(S, At, T, Detail#{event => Type}, St).

exit_task(_T, #st{exits = all}) -> true;
exit_task(T, #st{exits = Exits}) -> lists:member(T, Exits).

%% When a product reached a point in a task, for the times that end later.
at(Serial, Key, At, #st{products = Ps} = St) ->
    case maps:find(Serial, Ps) of
        {ok, #prod{at = M} = P} -> St#st{products = Ps#{Serial := P#prod{at = M#{Key => At}}}};
        error -> St
    end.

since(Serial, Key, #st{products = Ps}) ->
    case maps:find(Serial, Ps) of
        {ok, #prod{at = #{Key := T}}} -> T;
        _ -> undefined
    end.

%%====================================================================
%% Time per state
%%====================================================================

%% A step of the clock (cell_stats_clock), its counter operations applied.
clock(Fun, #st{clock = C} = St) ->
    {Ops, C1} = Fun(C),
    lists:foldl(fun({K, Op, V}, Acc) -> op(K, Op, V, Acc) end, St#st{clock = C1}, Ops).

%% What is counted so far written, with the time of the write.
flush(St0) ->
    Now = now_us(),
    St1 = clock(fun(C) -> cell_stats_clock:shift_ended(Now, fun shift_starts/0, C) end, St0),
    St2 = reconcile(Now, St1),
    St3 = case St2#st.db of
              closed when Now >= St2#st.retry_at -> open(St2);
              _ -> St2
          end,
    {Mark, St3a} = durable_history(St3),
    St4 = journal_bound(journal_trimmed(Mark, write_pending(Now, Mark, St3a))),
    case St4#st.db =:= open andalso Now >= St4#st.purge_at of
        true -> trim(purge(Now, St4#st{purge_at = Now + ?PURGE_MS * 1000}));
        false -> trim(St4)
    end.

%%====================================================================
%% Counters
%%====================================================================

count(Keys, At, St) ->
    count_by(Keys, 1, At, St).

count_by(Keys, N, At, St) ->
    clock(fun(C) -> cell_stats_clock:count(Keys, N, At, fun shift_starts/0, C) end, St).

count_cell(Metrics, At, St) ->
    count([{cell, M} || M <- Metrics], At, St).

count_cell_by(Metrics, N, At, St) ->
    count_by([{cell, M} || M <- Metrics], N, At, St).

%% A duration ending at `At' since `From' (nothing when there is no start).
timing(Key, From, At, St) ->
    clock(fun(C) -> cell_stats_clock:timing(Key, From, At, fun shift_starts/0, C) end, St).

op(Key, add, V, #st{pending = Pending} = St) ->
    _ = ets:update_counter(Pending, Key, {3, V}, {Key, add, 0}),
    St;
op(Key, Op, V, #st{pending = Pending} = St) ->
    New = case ets:lookup(Pending, Key) of
              [{_, Op, Old}] -> cell_stats_db:merge(Op, Old, V);
              [] -> V
          end,
    true = ets:insert(Pending, {Key, Op, New}),
    St.

%% Before the counters are written with the id of the last journal record applied,
%% what those records wrote to the histories is made durable: every write handed over
%% done, the history tables flushed to the disk (a table on disc only keeps writes in
%% memory for seconds). Answers the id to write, if any.
%% Histories written since the last flush (a product scrapped, say) are made durable
%% the same way before the counters that count them.
durable_history(#st{db = open, attached = Attached, applied = A, saved = S} = St) ->
    Mark = case Attached andalso A =/= S andalso A =/= undefined of
               true -> A;
               false -> undefined
           end,
    case Mark =/= undefined orelse St#st.unsynced of
        true ->
            St1 = history_written(St),
            case St1#st.db of
                open ->
                    case cell_stats_db:sync_histories() of
                        ok -> {Mark, St1#st{unsynced = false}};
                        {error, Why} -> {undefined, closed(Why, St1)}
                    end;
                closed ->
                    {undefined, St1}
            end;
        false ->
            {undefined, St}
    end;
durable_history(St) ->
    {undefined, St}.

%% The counters and the histories hold what the journal's records up to `Mark'
%% changed: the journal lets them go.
journal_trimmed(undefined, St) ->
    St;
journal_trimmed(Mark, #st{db = open} = St) ->
    ok = cell_trace_journal:trim(Mark),
    St#st{saved = Mark};
journal_trimmed(_Mark, St) ->
    St.

%% The journal is told its bound (the settings may have changed) and answers how much it
%% holds: near the bound, a warning the operator sees, and a line in the log.
journal_bound(#st{journal_warned = Warned} = St) ->
    case whereis(cell_trace_journal) of
        undefined ->
            St;
        _ ->
            #{journal_max_mb := Mb} = settings(),
            Max = Mb * 1024 * 1024,
            Bytes = cell_trace_journal:bound(Max),
            Pct = Bytes * 100 div Max,
            case cell_stats_trace:journal_level(Bytes, Max, Warned) of
                warn ->
                    Text = io_lib:format("The trace journal holds ~b % of its ~b MB of "
                                         "records the database has not taken. At 100 % "
                                         "no new record is kept and the tasks that must "
                                         "record a product's way stop. Make the database "
                                         "work again (see the log) or raise journal_max_mb "
                                         "in the statistics settings.", [Pct, Mb]),
                    cell_log:warning(cell, "statistics: ~ts", [Text]),
                    ok = cell_alarms:warning(cell, ?JOURNAL_WARNING,
                                             <<"Trace journal nearly full">>, Text),
                    St#st{journal_warned = true};
                clear ->
                    _ = Warned =:= true andalso
                        cell_log:notice(cell, "statistics: the trace journal holds ~b % of "
                                        "its ~b MB again; the warning is reset", [Pct, Mb]),
                    ok = cell_alarms:reset_warning(cell, ?JOURNAL_WARNING),
                    St#st{journal_warned = false};
                same ->
                    St
            end
    end.

%% One transaction a second: every counter and the time they cover, together, with the
%% id of the last journal record whose effects they hold.
write_pending(Now, Mark, #st{db = open, pending = Pending, book_open = Open,
                              book_left = Gone} = St) ->
    case cell_stats_db:write_counters(Pending, Open, Gone, Mark, Now) of
        ok ->
            true = ets:delete_all_objects(Pending),
            St#st{book_open = #{}, book_left = #{}};
        {error, Why} ->
            closed(Why, St)
    end;
write_pending(_Now, _Mark, St) ->
    %% Not before the database is open: the time of the last write tells how long
    %% the runtime was down.
    St.

%%====================================================================
%% The database
%%====================================================================

%% The database is opened here, before any event is taken: whether a product saved
%% now is new to the cell or one it held before a restart is only known once the
%% products in the cell have been read back. mnesia itself is normally running
%% already (the `cell' application starts it before the controller); if it could
%% not be, this tries again. What is read back (with the id of the last journal
%% record applied) is part of opening: if it cannot be read the database is not open
%% and this tries again, so the statistics never count with an unknown mark.
open(#st{db = closed} = St) ->
    Result = case cell_db:start() of
                 ok ->
                     case cell_db:ensure_tables(cell_stats_db:tables(), ?LOAD_MS) of
                         ok -> cell_stats_db:at_open();
                         {error, _} = E -> E
                     end;
                 {error, _} = E ->
                     E
             end,
    case Result of
        {ok, Read} -> opened(Read, St#st{db = open});
        {error, Why} -> closed(Why, St)
    end;
open(St) ->
    St.

closed(Why, #st{db = Was} = St) ->
    case Was of
        open -> cell_log:error(cell, "statistics: the database stopped working (~ts); "
                               "counting goes on in memory", [cell_db:format_error(Why)]);
        _ -> cell_log:error(cell, "statistics: the database cannot be opened (~ts); "
                                 "counting goes on in memory, trying again in ~b s",
                                 [cell_db:format_error(Why), ?RETRY_MS div 1000])
    end,
    %% Writes queued for the writer wait with the others: nothing is handed over
    %% while the database is closed.
    Queued = lists:reverse(St#st.queued),
    lists:foldl(fun keep/2, St#st{db = closed, retry_at = now_us() + ?RETRY_MS * 1000,
                                  queued = []}, Queued).

%% The database is open: each task's time in the state it was in at the last write
%% before a stop or crash is closed there, the time the runtime was not running is OFF;
%% the products the cell held are known again; what was kept in memory meanwhile is
%% written.
opened(#{flushed := Flushed, open := OpenRows, firsts := Firsts, products := Open,
         mark := Saved}, #st{started = Started} = St0) ->
    Closed = lists:foldl(fun({T, Was}, Acc) ->
                                 Acc1 = until_down(T, Was, Flushed, Acc),
                                 case maps:is_key(T, cell_stats_clock:tasks(Acc1#st.clock)) of
                                     true ->
                                         Acc1;
                                     false ->
                                         %% Not in this cell any more: nothing of it is open.
                                         Key = {meta, {open, T}},
                                         db(fun() -> cell_stats_db:delete_counter(Key) end, Acc1)
                                 end
                         end, St0, OpenRows),
    St1 = maps:fold(fun(T, {State, Since}, Acc0) ->
                            Acc = clock(fun(C) -> cell_stats_clock:counting(T, State, Since, C)
                                        end, Acc0),
                            case maps:find(T, Firsts) of
                                error ->
                                    clock(fun(C) -> {[cell_stats_clock:seen(T, Started)], C} end,
                                          Acc);
                                _ when is_integer(Flushed), Flushed < Started ->
                                    account(T, off, Flushed, Started, Acc);
                                _ ->
                                    Acc
                            end
                    end, Closed, cell_stats_clock:tasks(Closed#st.clock)),
    %% A product the books are still to write (one that left while the database was
    %% away, say) is as the statistics have it, not as its row was.
    Known = lists:foldl(
              fun({Serial, Info}, Acc) ->
                      case maps:is_key(Serial, Acc) orelse
                          maps:is_key(Serial, St1#st.book_open) of
                          true -> Acc;
                          false ->
                              Acc#{Serial => from_open(Info, Started)}
                      end
              end, St1#st.products, Open),
    %% What the journal holds that the database may not, then the holders now, as the
    %% registry knows them.
    St2 = holders_now(attach(Saved, St1#st{products = Known}), Started),
    Backlog = lists:reverse(St2#st.backlog),
    case {Backlog, St0#st.retry_at} of
        {[_ | _], _} ->
            cell_log:notice(cell, "statistics: the database is open; the ~b records kept "
                            "in memory meanwhile are written~ts",
                            [length(Backlog), case St2#st.backlog_dropped of
                                                  0 -> "";
                                                  D -> io_lib:format(" (the ~b oldest were "
                                                                     "dropped)", [D])
                                              end]);
        {[], 0} ->
            ok;
        {[], _} ->
            %% It could not be opened before: the log said so.
            cell_log:notice(cell, "statistics: the database is open; counting goes on "
                            "there", [])
    end,
    St3 = St2#st{backlog = [], backlog_len = 0, backlog_dropped = 0, retry_at = 0},
    lists:foldl(fun(F, Acc) -> db(F, Acc) end, St3, Backlog).

%% The records of the trace journal not yet durable in the database are applied (the
%% others are skipped by their ids, so none is counted twice), in the order of the
%% journal; from now on each new record comes from the journal as soon as it is
%% durable, and its event is skipped. `Saved': the id of the last record applied, as
%% the database has it.
attach(_Saved, #st{attached = true} = St) ->
    St;
attach(Saved, St) ->
    case whereis(cell_trace_journal) of
        undefined ->
            %% No journal (the statistics started alone): the events are all there is.
            St;
        _ ->
            Records = cell_trace_journal:attach(),
            St1 = St#st{saved = Saved, applied = cell_stats_trace:latest(Saved, St#st.applied)},
            Fresh = [R || #{id := Id} = R <- Records, cell_stats_trace:fresh(Id, Saved)],
            _ = Fresh =:= [] orelse
                cell_log:notice(cell, "statistics: ~b records of the products' way through "
                                "the cell were in the trace journal but not yet in the "
                                "database (made before the statistics started, or cut off "
                                "from it by a crash); they are taken from the journal",
                                [length(Fresh)]),
            St2 = lists:foldl(fun(R, Acc) -> journal_record(R, replay, Acc) end, St1, Fresh),
            St2#st{attached = true}
    end.

%% A record of the journal applied once: none at or before the last durable one.
journal_record(#{id := Id} = R, Mode, #st{saved = Saved} = St) ->
    case cell_stats_trace:fresh(Id, Saved) of
        true -> apply_record(Id, R, Mode, St);
        false -> St
    end.

%% `replay': a record taken from the journal when the database opens; a run before
%% this one may have applied it and written its history entries, its counts lost with
%% that run. `live': a record the journal sent as it was made.
apply_record(Id, Event, Mode, #st{applied = Applied} = St) ->
    St1 = event(Event, St#st{applying = {Id, 0, Mode}}),
    St1#st{applying = undefined, applied = cell_stats_trace:latest(Id, Applied)}.

%% Who holds what is the registry's to say: after the records are applied, each
%% product is held by the task the registry has holding it, or by none. A product a
%% task holds that the records never saw enter (its entry lost before the journal kept
%% such things) enters now with what its product file says, and the log says so.
holders_now(St, Started) ->
    Rows = try cell_registry:tasks() catch error:badarg -> [] end,
    Holding = maps:from_list([{Id, S} || #{id := Id, serial := S} <- Rows, is_binary(S)]),
    ByTask = maps:from_list([{S, Id} || {Id, S} <- maps:to_list(Holding)]),
    Products = maps:map(fun(Serial, #prod{} = P) ->
                                case maps:find(Serial, ByTask) of
                                    {ok, T} -> P#prod{holder = T, by = T, unheld = 0};
                                    error -> P#prod{holder = undefined}
                                end
                        end, St#st.products),
    Places = maps:from_list([{Id, Row} || #{id := Id} = Row <- Rows]),
    St1 = maps:fold(fun(T, Serial, Acc) ->
                            case {maps:is_key(Serial, Acc#st.products), Acc#st.gone} of
                                {true, _} -> Acc;
                                {false, #{Serial := T}} -> stale(Serial, T, Acc);
                                {false, _} -> unrecorded(Serial, T, maps:get(T, Places),
                                                         Started, Acc)
                            end
                    end, St#st{holding = Holding, products = Products}, Holding),
    St1#st{gone = #{}}.

%% The task's file still holds a product whose exit through it is recorded: it left
%% once; the task's copy is not counted again, whatever the task does with it.
stale(Serial, T, #st{stale = Stale} = St) ->
    cell_log:notice(cell, "statistics: product ~ts left the cell through ~ts before the "
                    "restart, and ~ts still holds it in its file; it is not counted again",
                    [Serial, T, T]),
    St#st{stale = Stale#{Serial => T}}.

unrecorded(Serial, T, Row, Started, St) ->
    Product = case Row of
                  #{zone := Z, lane := L} ->
                      case cell_product:load(cell_product:path(Z, L)) of
                          {ok, #{product := #{serial := Serial} = P}} -> P;
                          _ -> #{}
                      end;
                  _ -> #{}
              end,
    cell_log:warning(cell, "statistics: product ~ts is held by ~ts but its entry into the "
                     "cell was never recorded; it is counted as entered now~ts",
                     [Serial, T, case Product of
                                     #{} when map_size(Product) =:= 0 ->
                                         ", its recipe unknown (its product file could not "
                                         "be read)";
                                     _ -> ", with the recipe of its product file"
                                 end]),
    enter(Serial, T, Product, Started, St).

%% The time from where a task was last counted to the runtime's last write, in the
%% state it was in then.
until_down(T, {State, Upto}, Flushed, St) when is_atom(State), is_integer(Upto),
                                                 is_integer(Flushed), Upto < Flushed ->
    account(T, State, Upto, Flushed, St);
until_down(_T, _Was, _Flushed, St) ->
    St.

account(Scope, State, From, To, St) ->
    clock(fun(C) -> cell_stats_clock:account(Scope, State, From, To, fun shift_starts/0, C) end,
          St).

%% A write of the history: when the database is open, handed to the writer at once
%% if it is idle, else with what else comes until it is; when it is not, kept (up to
%% a limit) until it is.
db(Fun, #st{db = open, writing = false} = St) ->
    hand_over([Fun], St#st{unsynced = true});
db(Fun, #st{db = open, queued = Q} = St) ->
    St#st{queued = [Fun | Q], unsynced = true};
db(Fun, St) ->
    keep(Fun, St).

hand_over(Writes, #st{writer = Writer, batch = N} = St) ->
    ok = cell_stats_writer:write(Writer, N + 1, Writes),
    St#st{batch = N + 1, writing = true, queued = []}.

%% A batch written, or stopped by a database that went away: the rest of it kept until
%% the database is back (what was queued after it goes there too, see closed/2).
batch_done(done, #st{writing = false, queued = [_ | _] = Q} = St) ->
    hand_over(lists:reverse(Q), St);
batch_done(done, St) ->
    St;
batch_done({failed, Why, Rest}, St) ->
    St1 = keep_older(Rest, St),
    case St1#st.db of
        open -> closed(Why, St1);
        closed -> St1
    end.

%% Every write so far is in the database (or kept, if it went away): what is queued is
%% written now, after the batch under way.
history_written(#st{writer = Writer, queued = Q} = St) ->
    batch_done(cell_stats_writer:write_now(Writer, lists:reverse(Q)),
               St#st{queued = [], writing = false}).

keep(Fun, #st{backlog_len = N, backlog_dropped = D} = St) when N >= ?BACKLOG_MAX ->
    full(D),
    St#st{backlog = [Fun | lists:sublist(St#st.backlog, ?BACKLOG_MAX - 1)],
          backlog_dropped = D + 1};
keep(Fun, #st{backlog = B, backlog_len = N} = St) ->
    St#st{backlog = [Fun | B], backlog_len = N + 1}.

%% The rest of a batch the database stopped: older than every write kept meanwhile (the
%% database may have been found closed, and later writes kept, before the batch's
%% answer came), so it goes at the oldest end, and the oldest are what a full backlog
%% drops.
keep_older(Rest, #st{backlog = B, backlog_len = N, backlog_dropped = D} = St) ->
    All = B ++ lists:reverse(Rest),
    case N + length(Rest) of
        Len when Len > ?BACKLOG_MAX ->
            full(D),
            St#st{backlog = lists:sublist(All, ?BACKLOG_MAX), backlog_len = ?BACKLOG_MAX,
                  backlog_dropped = D + Len - ?BACKLOG_MAX};
        Len ->
            St#st{backlog = All, backlog_len = Len}
    end.

%% The backlog is full: said once, when the first record is dropped.
full(0) ->
    cell_log:warning(cell, "statistics: the database has been away so long that ~b history "
                     "records wait in memory for it; from now on the oldest are dropped to "
                     "make room (the counters are kept whole)", [?BACKLOG_MAX]);
full(_Dropped) ->
    ok.

trace(undefined, _At, _Task, _Entry, St) ->
    St;
%% An entry's sequence orders the entries of one millisecond by their microsecond and
%% then as they were taken (journal records and events come by different ways).
trace(Serial, At, Task, Entry, #st{applying = {Id, K, Mode}} = St) ->
    %% Of a journal record: the same entry each time it is applied (made of the
    %% record alone), which the bag keeps once.
    E = Entry#{task => Task},
    db(fun() -> cell_stats_db:write_history(Serial, At, {Id, K}, E) end,
       St#st{applying = {Id, K + 1, Mode}});
trace(Serial, At, Task, Entry, #st{seq = Seq} = St) ->
    E = Entry#{task => Task},
    db(fun() -> cell_stats_db:write_history(Serial, At, Seq, E) end, St#st{seq = Seq + 1}).

%% A product in the cell: its summary is its row of the products in the cell (a RAM
%% table with a log, cheap to write); the summary on disc only is written when it leaves.
%% Both are the books: which products are in the cell and how each one left go with the
%% counters that count them, in their transaction (see write_pending/3), never ahead of
%% them; a record applied again after a crash then finds the books as they were when
%% the counters were, and counts what they do not hold, once.
write_open(Serial, #prod{} = P, #st{book_open = Open} = St) ->
    St#st{book_open = Open#{Serial => open_row(P)}}.

open_row(#prod{} = P) ->
    #{entered => P#prod.entered, recipe => P#prod.recipe, failed => P#prod.failed,
      entry => P#prod.entry}.

%% A product as its row in the cell has it (`Entered' when the row lacks the time).
from_open(Row, Entered) ->
    #prod{entered = maps:get(entered, Row, Entered), recipe = maps:get(recipe, Row, <<>>),
          failed = maps:get(failed, Row, false), entry = maps:get(entry, Row, undefined)}.

%% The summary of a product that left (`out' or `scrapped', by which task and when)
%% replaces its row in the cell, in the books.
write_left(Serial, #prod{} = P, Status, Left, #st{book_open = Open, book_left = Gone} = St) ->
    Info = cell_stats_db:product_summary(Serial, open_row(P), Status, Left),
    St#st{book_open = Open#{Serial => delete}, book_left = Gone#{Serial => Info}}.

%% How a product that left did, as the books have it: what is still to write first.
left_summary(Serial, #st{book_left = Gone}) ->
    case maps:find(Serial, Gone) of
        {ok, Info} ->
            Info;
        error -> cell_stats_db:left_summary(Serial)
    end.

%% Records older than the settings keep are removed, once an hour.
purge(Now, St) ->
    #{trace_days := TraceDays, shift_days := ShiftDays} = settings(),
    {Keys, Old} = cell_stats_db:expired(Now, ShiftDays, TraceDays),
    St1 = lists:foldl(fun(K, Acc) -> db(fun() -> cell_stats_db:delete_counter(K) end, Acc) end,
                      St, Keys),
    forget(Old, St1).

forget(Serials, St) ->
    lists:foldl(fun(Serial, Acc) -> db(fun() -> cell_stats_db:forget(Serial) end, Acc) end,
                St, Serials).

%% The histories live in a dets file, which cannot pass 2 GB. Past the settings'
%% `trace_max_records' (checked at every write: the count costs nothing) the histories
%% of the products that left longest ago go, down to nine tenths of it, and the log
%% says so: a cell that makes products faster than `trace_days' allows keeps fewer
%% days, never stops recording.
trim(#st{db = open} = St) ->
    #{trace_max_records := Max} = settings(),
    case cell_stats_db:over_limit(Max) of
        [] ->
            St;
        Drop ->
            {Until, _} = lists:last(Drop),
            cell_log:warning(cell, "statistics: the product histories reached ~b "
                             "records; the histories of the ~b products that left "
                             "until ~ts were removed", [Max, length(Drop), time_text(Until)]),
            forget([S || {_, S} <- Drop], St)
    end;
trim(St) ->
    St.

time_text(Ms) ->
    {{Y, Mo, D}, {H, Mi, _}} = calendar:system_time_to_local_time(Ms, millisecond),
    io_lib:format("~4..0b-~2..0b-~2..0b ~2..0b:~2..0b", [Y, Mo, D, H, Mi]).

%%====================================================================
%% Time and shifts
%%====================================================================

now_us() ->
    erlang:system_time(microsecond).

%% An event's moment on this node's clock (its monotonic stamp, made comparable).
%% A record of the trace journal, or the event of one, is at the record's time: the
%% same either way, so its history entries are the same.
event_us(#{at := At}) when is_integer(At) -> At;
event_us(#{mono := Mono}) -> Mono + erlang:time_offset(microsecond);
event_us(_) -> now_us().

shift_starts() ->
    #{shifts := Texts} = settings(),
    case cell_stats_shift:parse_all(Texts) of
        {ok, Starts} -> Starts;
        {error, _} -> [0]
    end.

settings() ->
    Defaults = cell_settings_schema:defaults(cell_stats_settings),
    try maps:merge(Defaults, cell_settings:get(statistics))
    catch error:_ -> Defaults;
          exit:_ -> Defaults
    end.

text(B) when is_binary(B) -> B;
text(A) when is_atom(A) -> atom_to_binary(A, utf8);
text(Other) -> iolist_to_binary(io_lib:format("~tp", [Other])).
