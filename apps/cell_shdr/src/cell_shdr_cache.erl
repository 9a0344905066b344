%% @doc The adapter's value cache: watches the cell, keeps the current value of every
%% data item, filters duplicates, sweeps conditions, and writes each change once into
%% a shared log the clients read at their own pace.
%%
%% <b>Watching.</b> It subscribes to `cell_events' and reads `cell_registry' and
%% `cell_alarms' tables; it never calls a device task. It monitors those services
%% and `cell_settings': when one of them restarts (its subscribers and registrations
%% are gone with it), the adapter reports AVAILABILITY UNAVAILABLE, attaches again
%% with a backoff like a reconnecting driver (10 ms doubling to 1 s), registers its
%% settings schema again, and recomputes every item from what it reads, so nothing
%% missed meanwhile stays wrong.
%%
%% <b>Values.</b> Plain items live in the ETS table `cell_shdr_values' (`{Key,
%% Value}'); a change equal to the current value is dropped, so each client sees a
%% value once. A value that lasted no time is not sent either: values are held until
%% the millisecond of their stamp is over, and of an item's changes within one
%% timestamp only the last goes out (MESSAGE points, which are no states, go at once).
%% The part counts go on from the statistics' totals when the adapter starts. A HAL
%% point's item is read again when its connection goes down or up and when the HAL
%% marks the point faulty or clears it: UNAVAILABLE at once while it cannot be read,
%% never its last value as if it were current. Each condition item holds its active native codes; on every alarm event
%% the item is marked from `cell_alarms:list/0' and swept: a new or changed code is
%% sent at its level, a code gone is sent NORMAL, and when none is left one NORMAL
%% with no code clears the item.
%%
%% <b>The log.</b> Each change becomes its SHDR lines once, appended to the ETS table
%% `cell_shdr_log' as `{Seq, Bytes, EndOffset}'; the head sequence number is an
%% atomic. A client registers with {@link register_client/1}, which answers the full
%% snapshot and the sequence number it stands for, then copies entries from the log
%% to its socket. A client that has caught up arms a flag; the cache wakes only armed
%% clients, with one message each, so a slow client costs the cache nothing and its
%% mailbox never grows. The log keeps the last `max_client_buffer' bytes: a client
%% further behind finds its next entry gone and is dropped (see {@link
%% cell_shdr_protocol}). Only this process writes the log and the values, so a
%% snapshot and its sequence number always agree.
-module(cell_shdr_cache).
-behaviour(gen_server).

-include_lib("kernel/include/file.hrl").

-export([start_link/0, register_client/1, alive/0, close_clients/0, settings/0, items/0, points/0,
         time_series/4, axes/0, axis/2, refresh_assets/0, clients/0, sync/0, log_tables/0]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-export_type([registration/0]).

-define(VALUES, cell_shdr_values).
-define(LOG, cell_shdr_log).
-define(SOURCE, shdr).
-define(BACKOFF_MIN, 10).
-define(BACKOFF_MAX, 1000).
-define(ITEMS_A_LINE, 24).
-define(REMOVED_KEPT, 256).
-define(HOLD, 2).
-define(WATCHED, [cell_registry, cell_events, cell_alarms, cell_settings]).

-type registration() :: #{preamble := iodata(), seq := non_neg_integer(),
                          offset := non_neg_integer(), head := atomics:atomics_ref(),
                          log := ets:tid() | atom(), limit := pos_integer(),
                          ping_period := pos_integer(), life_timeout := pos_integer()}.

-record(task, {serial :: binary() | undefined,
               program = unavailable :: binary() | unavailable,
               started :: integer() | undefined,     %% monotonic µs of work start
               count = 0 :: non_neg_integer()}).

%% A client: its monitor, its wake flag, whether it has shown life (a PING), and its
%% place in the order of connects.
-record(client, {ref :: reference(), flag :: atomics:atomics_ref(), alive = false :: boolean(),
                 since :: pos_integer()}).

-record(state, {head :: atomics:atomics_ref(),
                seq = 0 :: non_neg_integer(),
                offset = 0 :: non_neg_integer(),
                oldest = 1 :: pos_integer(),
                conds = #{} :: #{binary() => #{binary() => cell_shdr_codec:condition()}},
                assets = #{} :: #{binary() => {binary(), integer()}},  %% document, time
                removed = #{} :: #{binary() => integer()},             %% removal time
                clients = #{} :: #{pid() => #client{}},
                settings = #{} :: map(),
                prefixes = #{} :: #{atom() => binary()},
                %% Tasks that do no work (their spec's `work' is false): no part count
                %% and no cycle time of their own.
                idle = [] :: [atom()],
                tasks = #{} :: #{atom() => #task{}},
                counts = {0, 0} :: {non_neg_integer(), non_neg_integer()}, %% good, bad
                %% Each task's part count as the statistics had it when the adapter
                %% started (`undefined' until read).
                base :: #{atom() => non_neg_integer()} | undefined,
                points = [] :: [map()],
                %% The cell's axes (its spec's hardware objects of kind axis), by id,
                %% the name of each.
                axes = #{} :: #{atom() => {binary(), linear | rotary}},
                messages = #{} :: #{binary() => true},   %% keys of MESSAGE points
                watched = #{} :: #{reference() => atom()},
                attached = false :: boolean(),
                backoff = ?BACKOFF_MIN :: pos_integer(),
                retry :: reference() | undefined,
                closing = false :: boolean(),
                %% Values held until their millisecond is over: their stamp, the
                %% updates in order, the timer that sends them.
                pending = none :: none | {cell_shdr_codec:stamp(), [{binary(), term()}],
                                          reference()}}).

%%====================================================================
%% API
%%====================================================================

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Registers the calling client: it is monitored, woken through `Flag' (an
%% atomics array of one, set to 1 by the client when it waits), and receives the
%% snapshot to send first and the log position it stands for.
%%
%% At most `max_clients' are registered. When every place is taken, the oldest client
%% that has not shown life ({@link alive/0}) is sent `{cell_shdr, evicted}' and loses
%% its place to the caller; when every one has, the caller is refused.
-spec register_client(atomics:atomics_ref()) ->
          {ok, registration()} | {error, {full, pos_integer()} | closing}.
register_client(Flag) ->
    gen_server:call(?MODULE, {register, self(), Flag}, 30000).

%% @doc The adapter stops: `avail' goes UNAVAILABLE, the cell is no longer watched, new
%% clients are refused, and each client is told to send what is left of the log and
%% close. Returns the clients told.
-spec close_clients() -> [pid()].
close_clients() ->
    gen_server:call(?MODULE, close_clients).

%% @doc The calling client has shown life (its first PING): it keeps its place.
-spec alive() -> ok.
alive() ->
    gen_server:cast(?MODULE, {alive, self()}).

%% @doc The adapter's settings in force.
-spec settings() -> map().
settings() ->
    gen_server:call(?MODULE, settings).

%% @doc Every data item the adapter emits now, in the order of `Devices.xml'.
-spec items() -> [cell_shdr_items:item()].
items() ->
    gen_server:call(?MODULE, items).

%% @doc The HAL points configured as time series.
-spec points() -> [map()].
points() ->
    gen_server:call(?MODULE, points).

%% @doc A batch of samples of a time series item, the last taken at `LastMs' (UTC)
%% and `LastMono' (monotonic, µs).
-spec time_series(binary(), {integer(), integer()}, number(), [number()]) -> ok.
time_series(Key, {LastMs, LastMono}, Rate, Values) ->
    gen_server:cast(?MODULE, {time_series, Key, {LastMs, LastMono}, Rate, Values}).

%% @doc The cell's axes, as the cache read them from the cell's spec.
-spec axes() -> [atom()].
axes() ->
    gen_server:call(?MODULE, axes).

%% @doc An axis's status as it was read (cell_shdr_axes), or why it cannot be.
-spec axis(atom(), {ok, map()} | {error, term()}) -> ok.
axis(Id, Status) ->
    gen_server:cast(?MODULE, {axis, Id, Status}).

%% @doc Reads the recipes again and sends the assets that changed.
-spec refresh_assets() -> ok.
refresh_assets() ->
    gen_server:call(?MODULE, refresh_assets, 60000).

%% @doc The connected clients.
-spec clients() -> [pid()].
clients() ->
    gen_server:call(?MODULE, clients).

%% @doc Returns once the cache has handled what was sent to it before.
-spec sync() -> ok.
sync() ->
    gen_server:call(?MODULE, sync).

%% @doc The log table and its head counter (for the benchmark and tests).
-spec log_tables() -> {atom(), atomics:atomics_ref()}.
log_tables() ->
    gen_server:call(?MODULE, log_tables).

%%====================================================================
%% gen_server
%%====================================================================

-spec init([]) -> {ok, #state{}, {continue, attach}}.
init([]) ->
    ?VALUES = ets:new(?VALUES, [named_table, protected, {read_concurrency, true}]),
    ?LOG = ets:new(?LOG, [named_table, protected, set, {read_concurrency, true}]),
    true = ets:insert(?VALUES, {<<"avail">>, unavailable}),
    {ok, #state{head = atomics:new(1, []),
                settings = cell_settings_schema:defaults(cell_shdr_settings)},
     {continue, attach}}.

-spec handle_continue(attach, #state{}) -> {noreply, #state{}}.
handle_continue(attach, State) ->
    {noreply, attach(State)}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({register, _, _}, _From, #state{closing = true} = State) ->
    {reply, {error, closing}, State};
handle_call({register, Pid, Flag}, _From, State0) ->
    case make_room(flush(State0)) of
        {ok, #state{clients = Clients} = State} ->
            Ref = monitor(process, Pid),
            Reg = #{preamble => snapshot(State), seq => State#state.seq,
                    offset => State#state.offset, head => State#state.head, log => ?LOG,
                    limit => setting(max_client_buffer, State),
                    ping_period => setting(ping_period, State),
                    life_timeout => setting(life_timeout, State)},
            Client = #client{ref = Ref, flag = Flag, since = erlang:unique_integer([positive,
                                                                                    monotonic])},
            {reply, {ok, Reg}, State#state{clients = Clients#{Pid => Client}}};
        full ->
            {reply, {error, {full, setting(max_clients, State0)}}, flush(State0)}
    end;
handle_call(settings, _From, State) ->
    {reply, State#state.settings, State};
handle_call(items, _From, State) ->
    {reply, all_items(State), State};
handle_call(points, _From, State) ->
    {reply, State#state.points, State};
handle_call(refresh_assets, _From, State) ->
    {reply, ok, assets(State)};
handle_call(clients, _From, State) ->
    {reply, maps:keys(State#state.clients), State};
handle_call(axes, _From, #state{axes = Axes} = State) ->
    {reply, lists:sort(maps:keys(Axes)), State};
handle_call(sync, _From, State) ->
    {reply, ok, flush(State)};
handle_call(close_clients, _From, #state{retry = Retry} = State0) ->
    _ = Retry =/= undefined andalso erlang:cancel_timer(Retry),
    %% What the cell's tables say now, its Stop at a node's shutdown included: a task
    %% writes its state there before it publishes it, and the event may not be here yet.
    Now = case State0#state.attached of
              true -> read_again(State0);
              false -> State0
          end,
    State1 = detach_quietly(Now#state{retry = undefined, closing = true}),
    State = flush(set([{<<"avail">>, unavailable}], now_stamp(), State1)),
    Pids = maps:keys(State#state.clients),
    _ = [Pid ! {cell_shdr, closing} || Pid <- Pids],
    {reply, Pids, State};
handle_call(log_tables, _From, State) ->
    {reply, {?LOG, State#state.head}, flush(State)}.

-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({alive, Pid}, #state{clients = Clients} = State) ->
    case Clients of
        #{Pid := C} -> {noreply, State#state{clients = Clients#{Pid => C#client{alive = true}}}};
        _ -> {noreply, State}   %% gone, or given its place meanwhile
    end;
handle_cast({axis, Id, Status}, #state{axes = Axes} = State) ->
    case Axes of
        #{Id := {Name, _Kind}} ->
            {noreply, set(cell_shdr_items:axis_values(Name, Status), now_stamp(), State)};
        #{} ->
            %% An axis the cell no longer has.
            {noreply, State}
    end;
handle_cast({time_series, Key, {Ms, Mono}, Rate, Values}, State) ->
    Line = cell_shdr_codec:time_series_line(stamp(Ms, Mono, State), Key, length(Values),
                                            Rate, Values),
    {noreply, emit([Line], State)}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_event, Event}, State) ->
    {noreply, event(Event, State)};
handle_info({cell_hal, {Group, Point}, Value}, State) ->
    {noreply, hal_value(Group, Point, Value, State)};
handle_info({cell_hal_fault, {Group, Point}, _Why}, State) ->
    {noreply, hal_reread(Group, Point, State)};
handle_info({cell_hal_conn, _Conn, _Status}, State) ->
    %% The points of that connection read as unavailable, or read again.
    {noreply, resync_points(State)};
handle_info({cell_settings, changed, shdr}, State) ->
    {noreply, settings_changed(State)};
handle_info({cell_settings, changed, _}, State) ->
    {noreply, State};
handle_info({'DOWN', Ref, process, Pid, _}, #state{clients = Clients} = State)
  when is_map_key(Pid, Clients) ->
    demonitor(Ref, [flush]),
    {noreply, State#state{clients = maps:remove(Pid, Clients)}};
handle_info({'DOWN', Ref, process, _, Reason}, #state{watched = W} = State)
  when is_map_key(Ref, W) ->
    Name = maps:get(Ref, W),
    cell_log:warning(?SOURCE, "the cell's ~ts stopped (~ts); MTConnect availability is "
                     "UNAVAILABLE until it is back", [Name, reason(Reason)]),
    {noreply, detach(State)};
handle_info({timeout, TRef, attach}, #state{retry = TRef} = State) ->
    {noreply, attach(State#state{retry = undefined})};
handle_info({timeout, _, attach}, #state{closing = true} = State) ->
    {noreply, State};
handle_info({timeout, TRef, flush}, #state{pending = {_, _, TRef}} = State) ->
    {noreply, flush(State)};
handle_info({timeout, _, flush}, State) ->
    %% Sent meanwhile with something else.
    {noreply, State}.

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, _State) ->
    ok.

%% A place for one more client (see cell_shdr_admission): a free one, or the place of
%% the oldest client that has not shown life, which is told to go.
make_room(#state{clients = Clients} = State) ->
    Known = [{Since, Alive, Pid} || {Pid, #client{alive = Alive, since = Since}}
                                        <- maps:to_list(Clients)],
    case cell_shdr_admission:admit(Known, setting(max_clients, State)) of
        admit ->
            {ok, State};
        {evict, Pid} ->
            #client{ref = Ref} = maps:get(Pid, Clients),
            demonitor(Ref, [flush]),
            Pid ! {cell_shdr, evicted},
            {ok, State#state{clients = maps:remove(Pid, Clients)}};
        full ->
            full
    end.

reason(normal) -> "normal stop";
reason(shutdown) -> "shut down";
reason({shutdown, _}) -> "shut down";
reason(killed) -> "killed";
reason(Other) -> io_lib:format("~0tp", [Other]).

%%====================================================================
%% Attaching to the cell
%%====================================================================

%% Monitors the cell's services, subscribes, registers the settings schema, and
%% recomputes everything. Any of them missing: try again after the backoff.
attach(State0) ->
    State = detach_quietly(State0),
    Pids = [{N, whereis(N)} || N <- ?WATCHED],
    case [N || {N, undefined} <- Pids] of
        [] ->
            Watched = maps:from_list([{monitor(process, P), N} || {N, P} <- Pids]),
            try
                ok = cell_events:subscribe(),
                ok = ensure_registered(),
                ok = cell_settings:subscribe(),
                S1 = load_settings(State#state{watched = Watched}),
                S2 = resync(S1#state{attached = true, backoff = ?BACKOFF_MIN}),
                cell_log:info(?SOURCE, "watching the cell", []),
                S2
            catch
                %% A service not there, or gone (killed, stopped) while it was asked.
                exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                                   Why =:= killed; element(1, Why) =:= shutdown ->
                    retry(State#state{watched = Watched});
                %% The registry went (its tables with it) while they were read: its
                %% 'DOWN' is on its way, and the next try finds it back.
                error:badarg -> retry(State#state{watched = Watched})
            end;
        _Missing ->
            retry(State)
    end.

%% The cell's tables read once more before the adapter stops; a service of the cell
%% gone meanwhile (its 'DOWN' still on its way) leaves the values as they are.
read_again(State) ->
    try resync(State)
    catch
        error:badarg -> State;
        exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                           Why =:= killed; element(1, Why) =:= shutdown -> State
    end.

retry(#state{backoff = B} = State) ->
    TRef = erlang:start_timer(B, self(), attach),
    State#state{retry = TRef, backoff = min(B * 2, ?BACKOFF_MAX), attached = false}.

detach(State) ->
    S1 = detach_quietly(State),
    S2 = set([{<<"avail">>, unavailable}], now_stamp(), S1),
    case S2#state.retry of
        undefined -> retry(S2);
        _ -> S2
    end.

detach_quietly(#state{watched = W} = State) ->
    _ = [demonitor(R, [flush]) || R <- maps:keys(W)],
    State#state{watched = #{}, attached = false}.

ensure_registered() ->
    case cell_settings:register(cell_shdr_settings) of
        ok -> ok;
        {error, Why} -> erlang:error({shdr_settings_refused, Why})
    end.

%%====================================================================
%% Settings
%%====================================================================

load_settings(State) ->
    S0 = cell_settings:get(shdr),
    S = case maps:get(uuid, S0) of
            <<>> ->
                Uuid = uuid4(),
                case cell_settings:put(shdr, #{uuid => Uuid}, <<"cellrt">>) of
                    ok -> ok;
                    {error, Why} ->
                        cell_log:error(?SOURCE, "could not save the new device uuid: ~ts",
                                       [cell_settings_schema:format_error(Why)])
                end,
                S0#{uuid => Uuid};
            _ ->
                S0
        end,
    Points = usable_points(maps:get(points, S), State#state.axes),
    State#state{settings = S, points = Points,
                messages = maps:from_list([{N, true} || #{name := N} = P <- Points,
                                                        cell_shdr_items:is_message(P)])}.

settings_changed(#state{settings = Old} = State) ->
    S1 = load_settings(State),
    New = S1#state.settings,
    Identity = [cell_shdr_codec:command(Name, maps:get(F, New))
                || {F, Name} <- identity_fields(), maps:get(F, New) =/= maps:get(F, Old)],
    S2 = emit(Identity, S1),
    case maps:with([port, bind], New) =:= maps:with([port, bind], Old) of
        true -> ok;
        false -> ok = cell_shdr_listener:restart()
    end,
    case maps:with([points], New) =:= maps:with([points], Old) of
        true -> ok;
        false -> cell_shdr_sampler:reconfigure()
    end,
    S3 = case maps:get(recipes_as_assets, New) =:= maps:get(recipes_as_assets, Old) of
             true -> S2;
             false -> assets(S2)
         end,
    hal_subscribe(S3#state.points),
    resync_points(S3).

identity_fields() ->
    [{uuid, <<"uuid">>}, {manufacturer, <<"manufacturer">>}, {station, <<"station">>},
     {serial_number, <<"serialNumber">>}, {description, <<"description">>}].

setting(Key, #state{settings = S}) ->
    maps:get(Key, S).

%% Points whose names meet a cell item or an axis's are left out, with a log line.
usable_points(Points, Axes) ->
    Taken = maps:from_list([{K, true} || #{key := K} <- cell_shdr_items:items([], [], [], Axes)]),
    [P || #{name := N} = P <- Points,
          case Taken of
              #{N := _} ->
                  cell_log:warning(?SOURCE, "HAL point item \"~ts\" has the name of a cell "
                                   "item; left out", [N]),
                  false;
              _ ->
                  true
          end].

uuid4() ->
    <<A:32, B:16, _:4, C:12, _:2, D:14, E:48>> = crypto:strong_rand_bytes(16),
    Hex = fun(N, W) -> string:lowercase(iolist_to_binary(io_lib:format("~*.16.0b", [W, N]))) end,
    iolist_to_binary([Hex(A, 8), $-, Hex(B, 4), $-, Hex(16#4000 bor C, 4), $-,
                      Hex(16#8000 bor D, 4), $-, Hex(E, 12)]).

%%====================================================================
%% Recomputing everything from the cell
%%====================================================================

resync(State000) ->
    Stamp = now_stamp(),
    State00 = axes_of_the_cell(State000),
    State0 = load_counts(State00),
    Rows = cell_registry:tasks(),
    Ids = [Id || #{id := Id} <- Rows],
    State1 = State0#state{prefixes = cell_shdr_items:prefixes(Ids),
                          idle = [Id || #{id := Id, work := false} <- Rows]},
    P = State1#state.prefixes,
    {TaskUpdates, State2} =
        lists:foldl(fun(#{id := Id, state := S} = Row, {Acc, St}) ->
                            {U, St1} = refresh_product(Id, Row, St),
                            {[{key(P, Id, <<"execution">>), cell_shdr_items:execution(S)},
                              {key(P, Id, <<"wait_state">>), cell_shdr_items:wait_state(S)}
                              | U] ++ Acc, St1}
                    end, {[], State1}, Rows),
    Cell = cell_registry:control(cell_state),
    Updates = [{<<"avail">>, <<"AVAILABLE">>},
               {<<"estop">>, cell_shdr_items:estop(cell_registry:control(estop))},
               {<<"mode">>, cell_shdr_items:controller_mode(
                               cell_registry:control(service_mode))},
               {<<"execution">>, cell_shdr_items:execution(Cell)},
               {<<"wait_state">>, cell_shdr_items:wait_state(Cell)}
               | TaskUpdates] ++ initial(State2),
    State3 = set(Updates, Stamp, State2),
    State4 = sweep_all(Stamp, State3),
    hal_subscribe(State4#state.points),
    State5 = resync_points(State4),
    assets(State5).

%% The axes of the cell's spec, each named as an item may be; they are watched (by
%% cell_shdr_axes), and a configured point named like one of their items is left out.
axes_of_the_cell(#state{settings = Settings} = State) ->
    #{hal := #{hardware := Hw}} = cell_spec:running(),
    Kinds = maps:from_list([{Id, case Opts of
                                     #{rotary := true} -> rotary;
                                     _ -> linear
                                 end} || #{id := Id, kind := axis} = A <- Hw,
                                         Opts <- [maps:get(opts, A, #{})]]),
    Axes = maps:map(fun(Id, Name) -> {Name, maps:get(Id, Kinds)} end,
                    cell_shdr_items:prefixes(maps:keys(Kinds))),
    ok = cell_shdr_axes:watch(maps:keys(Axes)),
    State#state{axes = Axes, points = usable_points(maps:get(points, Settings), Axes)}.

%% The part counts go on from the statistics the cell keeps (work completed and
%% aborted, per task, in total), read once when the adapter starts: an agent must not
%% see them start again from zero at every restart. Without statistics (none in the
%% cell, or not answering) they start from zero.
load_counts(#state{base = undefined} = State) ->
    Counters = try
                   _ = cell_stats:flush(),
                   cell_stats:counters(total)
               catch
                   exit:{Why, _} when Why =:= noproc; Why =:= timeout; Why =:= normal;
                                      Why =:= shutdown; Why =:= killed ->
                       cell_log:warning(?SOURCE, "the statistics do not answer; part "
                                        "counts start from zero", []),
                       #{}
               end,
    Tasks = maps:filter(fun(K, _) -> K =/= cell end, Counters),
    Good = lists:sum([maps:get(completed, C, 0) || C <- maps:values(Tasks)]),
    Bad = lists:sum([maps:get(aborted, C, 0) || C <- maps:values(Tasks)]),
    State#state{counts = {Good, Bad},
                base = maps:map(fun(_, C) -> maps:get(completed, C, 0) + maps:get(aborted, C, 0)
                                end, Tasks)};
load_counts(State) ->
    State.

%% What the adapter knows of a task (its count from the statistics at first).
task(Task, #state{tasks = Tasks, base = Base}) ->
    case Tasks of
        #{Task := T} -> T;
        _ -> #task{count = maps:get(Task, Base, 0)}
    end.

%% Items that start UNAVAILABLE or at zero until something happens, set once.
initial(#state{prefixes = P, counts = {Good, Bad}, idle = Idle, axes = Axes} = State) ->
    Keys = [{<<"program">>, unavailable}, {<<"cycle_time">>, unavailable},
            {<<"part_count">>, Good + Bad}, {<<"part_count_good">>, Good},
            {<<"part_count_bad">>, Bad}]
        ++ lists:append(
             [[{key(P, T, <<"part_state">>), unavailable}
               | case lists:member(T, Idle) of
                     true -> [];
                     false -> [{key(P, T, <<"cycle_time">>), unavailable},
                               {key(P, T, <<"part_count">>), (task(T, State))#task.count}]
                 end]
              || T <- maps:keys(P)])
        ++ lists:append([cell_shdr_items:axis_values(Name, {error, not_read})
                         || {Name, _Kind} <- maps:values(Axes)]),
    [KV || {K, _} = KV <- Keys, ets:lookup(?VALUES, K) =:= []].

resync_points(#state{points = Points} = State) ->
    Stamp = now_stamp(),
    Plain = [P || #{time_series := false} = P <- Points],
    Updates = [{N, hal_read(P)} || #{name := N} = P <- Plain],
    set(Updates, Stamp, State).

%%====================================================================
%% Events
%%====================================================================

event(#{type := Type} = Ev, #state{attached = true} = State) ->
    Stamp = {maps:get(time, Ev), maps:get(mono, Ev)},
    event(Type, Ev, Stamp, State);
event(_Ev, State) ->
    %% Not attached: a resync follows the attach and reads everything again.
    State.

event(cell_state, #{state := S}, Stamp, State) ->
    set([{<<"execution">>, cell_shdr_items:execution(S)},
         {<<"wait_state">>, cell_shdr_items:wait_state(S)}], Stamp, State);
event(estop, #{active := On}, Stamp, State) ->
    set([{<<"estop">>, cell_shdr_items:estop(On)}], Stamp, State);
event(service_mode, #{active := On}, Stamp, State) ->
    set([{<<"mode">>, cell_shdr_items:controller_mode(On)}], Stamp, State);
event(Type, #{alarm := #{task := Task}}, Stamp, State)
  when Type =:= alarm_raised; Type =:= alarm_cleared ->
    Key = cell_shdr_items:condition_owner(State#state.prefixes, Task),
    sweep(Key, alarms_by_owner(State), Stamp, State);
event(request, #{request := start}, _Stamp, State) ->
    %% Recipes are read at Start (seed 000 §3.2.3): the moment to publish changes.
    assets(State);
event(_Type, #{task := cell}, _Stamp, State) ->
    State;
event(Type, #{task := Task} = Ev, Stamp, #state{prefixes = P} = State0) ->
    State = case P of
                #{Task := _} -> State0;
                _ -> resync(State0)   %% a task the adapter did not know yet
            end,
    task_event(Type, Task, Ev, Stamp, State).

task_event(task_state, Task, #{state := S}, Stamp, State) ->
    P = State#state.prefixes,
    {U, State1} = refresh_product(Task, State),
    set([{key(P, Task, <<"execution">>), cell_shdr_items:execution(S)},
         {key(P, Task, <<"wait_state">>), cell_shdr_items:wait_state(S)} | U], Stamp, State1);
task_event(Type, Task, _Ev, {_, Mono} = Stamp, State0) ->
    P = State0#state.prefixes,
    {U, State1} = refresh_product(Task, State0),
    PartState = case cell_shdr_items:part_state(Type) of
                    keep -> [];
                    V -> [{key(P, Task, <<"part_state">>), V}]
                end,
    {Work, State2} = work(Type, Task, Mono, State1),
    set(U ++ PartState ++ Work, Stamp, State2).

%% Work start and end: cycle time, part counts, the cell's program.
work(item_work_start, Task, Mono, #state{tasks = Tasks} = State) ->
    T = task(Task, State),
    {[{<<"program">>, T#task.program}],
     State#state{tasks = Tasks#{Task => T#task{started = Mono}}}};
work(Type, Task, Mono, #state{tasks = Tasks, prefixes = P, counts = {Good, Bad}} = State)
  when Type =:= item_work_complete; Type =:= item_work_abort ->
    T = task(Task, State),
    Count = T#task.count + 1,
    {G1, B1} = case Type of
                   item_work_complete -> {Good + 1, Bad};
                   item_work_abort -> {Good, Bad + 1}
               end,
    Cycle = case {Type, T#task.started} of
                {item_work_complete, Started} when is_integer(Started) ->
                    Secs = round((Mono - Started) / 1000) / 1000,
                    [{key(P, Task, <<"cycle_time">>), Secs}, {<<"cycle_time">>, Secs}];
                _ ->
                    []
            end,
    Updates = [{key(P, Task, <<"part_count">>), Count}, {<<"part_count">>, G1 + B1},
               {<<"part_count_good">>, G1}, {<<"part_count_bad">>, B1} | Cycle],
    {own_work_items(Task, Updates, State),
     State#state{tasks = Tasks#{Task => T#task{count = Count, started = undefined}},
                 counts = {G1, B1}}};
work(_Type, _Task, _Mono, State) ->
    {[], State}.

%% A task declared to do no work has no part count or cycle time of its own, none
%% declared: should it work all the same, only the cell's go on.
own_work_items(Task, Updates, #state{idle = Idle, prefixes = P}) ->
    case lists:member(Task, Idle) of
        true ->
            Own = [key(P, Task, <<"part_count">>), key(P, Task, <<"cycle_time">>)],
            [U || {K, _} = U <- Updates, not lists:member(K, Own)];
        false ->
            Updates
    end.

%% The product a task holds, from the registry (the task writes it there before it
%% publishes): its serial, and its recipe from the product file when the serial
%% changed.
refresh_product(Task, State) ->
    case cell_registry:task(Task) of
        {ok, Row} -> refresh_product(Task, Row, State);
        {error, not_found} -> {[], State}
    end.

refresh_product(Task, Row, #state{tasks = Tasks, prefixes = P} = State) ->
    T = task(Task, State),
    Serial = maps:get(serial, Row, undefined),
    case Serial =:= T#task.serial andalso is_map_key(Task, Tasks) of
        true ->
            {[], State};
        false ->
            Program = program(Serial, Row),
            {[{key(P, Task, <<"serial">>), value_or_unavailable(Serial)},
              {key(P, Task, <<"program">>), Program}],
             State#state{tasks = Tasks#{Task => T#task{serial = Serial, program = Program}}}}
    end.

program(undefined, _Row) ->
    unavailable;
program(_Serial, #{zone := Zone, lane := Lane}) ->
    case cell_product:load(cell_product:path(Zone, Lane)) of
        {ok, #{product := #{recipe := Recipe}}} when Recipe =/= <<>> -> Recipe;
        _ -> unavailable
    end;
program(_Serial, _Row) ->
    unavailable.

value_or_unavailable(undefined) -> unavailable;
value_or_unavailable(V) -> V.

key(P, Task, Suffix) ->
    cell_shdr_items:task_key(P, Task, Suffix).

%%====================================================================
%% Plain values: duplicate filtering
%%====================================================================

%% Sets values; those that changed go out on shared lines stamped `Stamp'.
%%
%% A value that lasted no time is not sent: values are held until the millisecond of
%% their stamp is over (?HOLD ms after the change, or until anything else is sent, or
%% a change of another millisecond comes), and of the changes
%% of an item with the same stamp only the last goes out; none when it is back to what
%% was sent. A MESSAGE is not a state: each goes out at once.
set(Updates, {Ms, Mono}, State0) ->
    S = stamp(Ms, Mono, State0),
    Messages = State0#state.messages,
    {Msgs, Values} = lists:partition(fun({K, _}) -> is_map_key(K, Messages) end, Updates),
    State = case Msgs of
                [] -> State0;
                _ -> put_values(Msgs, S, flush(State0))
            end,
    hold(Values, S, Mono, State).

hold([], _S, _Mono, State) ->
    State;
hold(Values, S, _Mono, #state{pending = {S, Held, TRef}} = State) ->
    State#state{pending = {S, Held ++ Values, TRef}};
hold(Values, S, Mono, State0) ->
    State = flush(State0),
    %% ?HOLD ms after the change's own instant its millisecond is over, however late
    %% the cache reads it.
    Due = erlang:convert_time_unit(Mono, microsecond, millisecond) + ?HOLD,
    State#state{pending = {S, Values, erlang:start_timer(Due, self(), flush, [{abs, true}])}}.

%% Sends the values held.
flush(#state{pending = none} = State) ->
    State;
flush(#state{pending = {S, Held, TRef}} = State) ->
    _ = erlang:cancel_timer(TRef),
    put_values(Held, S, State#state{pending = none}).

put_values(Updates, S, State) ->
    case changed(Updates, #{}, []) of
        [] ->
            State;
        Changed ->
            true = ets:insert(?VALUES, Changed),
            append(value_lines(S, Changed, State), State)
    end.

%% The last update of a key wins; unchanged keys drop out.
changed([], _Seen, Acc) ->
    lists:reverse(Acc);
changed([{K, V} | Rest], Seen, Acc) ->
    Last = case lists:keyfind(K, 1, Rest) of
               false -> V;
               {K, _} -> skip
           end,
    case Last =:= skip orelse is_map_key(K, Seen) of
        true ->
            changed(Rest, Seen, Acc);
        false ->
            case ets:lookup(?VALUES, K) of
                [{K, V}] -> changed(Rest, Seen#{K => true}, Acc);
                _ -> changed(Rest, Seen#{K => true}, [{K, V} | Acc])
            end
    end.

%% Plain values share lines; a MESSAGE takes a line of its own, `key|code|text' (seed
%% 003), since an agent reads two fields after a message's key: on a shared line its
%% text would be taken for the next key.
value_lines(Stamp, Pairs, #state{messages = Messages}) ->
    {Msgs, Plain} = lists:partition(fun({K, _}) -> is_map_key(K, Messages) end, Pairs),
    [cell_shdr_codec:data_line(Stamp, Chunk) || Plain =/= [], Chunk <- chunks(Plain)]
        ++ [cell_shdr_codec:message_line(Stamp, K, <<>>, V) || {K, V} <- Msgs].

chunks(L) when length(L) =< ?ITEMS_A_LINE -> [L];
chunks(L) ->
    {A, B} = lists:split(?ITEMS_A_LINE, L),
    [A | chunks(B)].

%%====================================================================
%% Conditions: mark and sweep
%%====================================================================

%% Active alarms grouped by the condition item they show on.
alarms_by_owner(#state{prefixes = P}) ->
    lists:foldl(fun(#{task := T} = A, Acc) ->
                        K = cell_shdr_items:condition_owner(P, T),
                        C = cell_shdr_items:condition(A),
                        maps:update_with(K, fun(M) -> M#{maps:get(code, C) => C} end,
                                         #{maps:get(code, C) => C}, Acc)
                end, #{}, safe_alarms()).

safe_alarms() ->
    try cell_alarms:list()
    catch error:badarg -> []   %% the registry is restarting; its 'DOWN' follows
    end.

sweep_all(Stamp, #state{prefixes = P} = State) ->
    Active = alarms_by_owner(State),
    Keys = [<<"system">> | [<<V/binary, "_system">> || V <- maps:values(P)]],
    lists:foldl(fun(K, St) -> sweep(K, Active, Stamp, St) end, State, lists:usort(Keys)).

%% Marks the codes active on one condition item, sweeps those that are not.
sweep(Key, ActiveByOwner, {Ms, Mono}, #state{conds = Conds} = State) ->
    Active = maps:get(Key, ActiveByOwner, #{}),
    Old = maps:get(Key, Conds, undefined),
    S = stamp(Ms, Mono, State),
    Lines = case {Old, map_size(Active)} of
                {undefined, 0} -> [cell_shdr_codec:condition_line(S, Key, #{level => normal})];
                {Empty, 0} when map_size(Empty) =:= 0 -> [];
                {_, 0} -> [cell_shdr_codec:condition_line(S, Key, #{level => normal})];
                _ ->
                    Prev = case Old of undefined -> #{}; _ -> Old end,
                    [cell_shdr_codec:condition_line(S, Key, C)
                     || {Code, C} <- lists:sort(maps:to_list(Active)),
                        maps:get(Code, Prev, none) =/= C]
                        ++ [cell_shdr_codec:condition_line(S, Key, #{level => normal,
                                                                     code => Code})
                            || Code <- lists:sort(maps:keys(Prev)),
                               not is_map_key(Code, Active)]
            end,
    emit(Lines, State#state{conds = Conds#{Key => Active}}).

%%====================================================================
%% Assets: each recipe a File asset, marked and swept like conditions
%%====================================================================

assets(State) ->
    Wanted = case setting(recipes_as_assets, State) of
                 true -> recipe_assets(State);
                 false -> #{}
             end,
    #state{assets = Old, removed = Removed0} = State,
    Now = os:system_time(millisecond),
    Type = cell_shdr_assets:type(),
    Gone = [Id || Id <- lists:sort(maps:keys(Old)), not is_map_key(Id, Wanted)],
    Lines = [cell_shdr_codec:asset_line(asset_stamp(Ms, State), Id, Type, Doc)
             || {Id, {Doc, Ms} = A} <- lists:sort(maps:to_list(Wanted)),
                maps:get(Id, Old, none) =/= A]
        ++ [cell_shdr_codec:remove_asset_line(asset_stamp(Now, State), Id) || Id <- Gone],
    Removed = maps:without(maps:keys(Wanted),
                           maps:merge(Removed0, maps:from_list([{Id, Now} || Id <- Gone]))),
    emit(Lines, State#state{assets = Wanted, removed = forget_oldest(Removed)}).

%% The removals a new client is told of are the latest ?REMOVED_KEPT.
forget_oldest(Removed) when map_size(Removed) =< ?REMOVED_KEPT ->
    Removed;
forget_oldest(Removed) ->
    Sorted = lists:keysort(2, maps:to_list(Removed)),
    maps:from_list(lists:nthtail(map_size(Removed) - ?REMOVED_KEPT, Sorted)).

%% Each recipe with the time of its file: an agent records an asset as changed at the
%% time its line carries, so an unchanged file must always carry the same time.
recipe_assets(State) ->
    Uuid = setting(uuid, State),
    Dir = cell_config:dir(products),
    maps:from_list([{Name, {cell_shdr_assets:recipe(Info#{modified => Ms}, Uuid), Ms}}
                    || Name <- cell_recipe:list(), {ok, Info} <- [cell_recipe:info(Name)],
                       Ms <- [file_time(Dir, Name, Info)]]).

file_time(Dir, Name, #{modified := Modified}) ->
    File = filename:join(Dir, unicode:characters_to_list(<<Name/binary, ".zprd">>)),
    case file:read_file_info(File, [{time, posix}]) of
        {ok, #file_info{mtime = Secs}} -> Secs * 1000;
        {error, _} -> Modified
    end.

%% An asset's line carries the asset's own time (in relative-time mode, which counts
%% from the VM's start, the time it is sent).
asset_stamp(Ms, State) ->
    case setting(relative_time, State) of
        true -> stamp_now(State);
        false -> {utc, Ms}
    end.

%%====================================================================
%% HAL points
%%====================================================================

hal_subscribe(Points) ->
    _ = [cell_shdr_hal:subscribe(G, P) || #{time_series := false, group := G, point := P}
                                              <- Points],
    ok.

hal_read(#{group := Group, point := Point} = P) ->
    case cell_shdr_hal:read(Group, Point) of
        {ok, V} -> cell_shdr_items:point_value(P, V);
        {error, _} -> unavailable
    end.

%% A point's fault set (it reads as unavailable) or cleared (it reads its value).
hal_reread(Group, Point, #state{points = Points} = State) ->
    Updates = [{N, hal_read(P)} || #{time_series := false, name := N} = P <- Points,
                                   cell_shdr_hal:same_point(P, Group, Point)],
    set(Updates, now_stamp(), State).

hal_value(Group, Point, Value, #state{points = Points} = State) ->
    Updates = [{N, cell_shdr_items:point_value(P, Value)}
               || #{time_series := false, name := N} = P <- Points,
                  cell_shdr_hal:same_point(P, Group, Point)],
    set(Updates, now_stamp(), State).

%%====================================================================
%% The snapshot a new client starts from
%%====================================================================

snapshot(State) ->
    S = stamp_now(State),
    Settings = State#state.settings,
    Commands = [cell_shdr_codec:command(<<"shdrVersion">>, <<"2">>),
                cell_shdr_codec:command(<<"adapterVersion">>, adapter_version()),
                cell_shdr_codec:command(<<"device">>, maps:get(device_name, Settings,
                                                               <<"cell">>))]
        ++ [cell_shdr_codec:command(Name, V)
            || {F, Name} <- identity_fields(), V <- [maps:get(F, Settings, <<>>)], V =/= <<>>]
        ++ case setting(relative_time, State) of
               true -> [cell_shdr_codec:command(<<"relativeTime">>, <<"true">>)];
               false -> []
           end,
    Values = lists:sort(ets:tab2list(?VALUES)),
    Data = value_lines(S, Values, State),
    Conds = lists:append(
              [case maps:size(Codes) of
                   0 -> [cell_shdr_codec:condition_line(S, K, #{level => normal})];
                   _ -> [cell_shdr_codec:condition_line(S, K, C)
                         || {_, C} <- lists:sort(maps:to_list(Codes))]
               end || {K, Codes} <- lists:sort(maps:to_list(State#state.conds))]),
    %% Assets as they are, each with its own time: removing all and sending them again
    %% would have an agent record every one as removed and changed at each connect.
    %% Those removed lately are removed again, for an agent that was away then.
    Type = cell_shdr_assets:type(),
    Assets = [cell_shdr_codec:remove_asset_line(asset_stamp(Ms, State), Id)
              || {Id, Ms} <- lists:keysort(2, maps:to_list(State#state.removed))]
        ++ [cell_shdr_codec:asset_line(asset_stamp(Ms, State), Id, Type, Doc)
            || {Id, {Doc, Ms}} <- lists:sort(maps:to_list(State#state.assets))],
    [Commands, Data, Conds, Assets].

adapter_version() ->
    case application:get_key(cell_shdr, vsn) of
        {ok, V} -> list_to_binary(V);
        undefined -> <<"0">>
    end.

all_items(#state{prefixes = P, idle = Idle, points = Points, axes = Axes}) ->
    cell_shdr_items:items(lists:sort(maps:keys(P)), Idle, Points, Axes).

%%====================================================================
%% The log
%%====================================================================

%% Lines other than values: after the values held, which came first.
emit(Lines, State) ->
    append(Lines, flush(State)).

append([], State) ->
    State;
append(Lines, #state{seq = Seq0, offset = Off0} = State) ->
    Bin = iolist_to_binary(Lines),
    Seq = Seq0 + 1,
    Off = Off0 + byte_size(Bin),
    true = ets:insert(?LOG, {Seq, Bin, Off}),
    ok = atomics:put(State#state.head, 1, Seq),
    wake(State#state.clients),
    trim(State#state{seq = Seq, offset = Off}).

%% Wakes the clients that said they wait; a busy client finds the entry itself.
wake(Clients) ->
    maps:foreach(fun(Pid, #client{flag = Flag}) ->
                         case atomics:compare_exchange(Flag, 1, 1, 0) of
                             ok -> Pid ! {cell_shdr, wake};
                             _ -> ok
                         end
                 end, Clients).

%% Drops entries no client within its limit can still need.
trim(#state{oldest = Oldest, seq = Seq, offset = Off} = State) when Oldest < Seq ->
    Limit = setting(max_client_buffer, State),
    case ets:lookup(?LOG, Oldest) of
        [{_, _, End}] when Off - End > Limit ->
            true = ets:delete(?LOG, Oldest),
            trim(State#state{oldest = Oldest + 1});
        _ ->
            State
    end;
trim(State) ->
    State.

%%====================================================================
%% Time
%%====================================================================

now_stamp() ->
    {os:system_time(millisecond), erlang:monotonic_time(microsecond)}.

stamp_now(State) ->
    {Ms, Mono} = now_stamp(),
    stamp(Ms, Mono, State).

%% UTC, or in relative-time mode milliseconds since the VM started (a clock that
%% never goes back, and the same for every client).
stamp(Ms, Mono, State) ->
    case setting(relative_time, State) of
        true ->
            Start = erlang:convert_time_unit(erlang:system_info(start_time), native,
                                             microsecond),
            {relative, max(0, (Mono - Start) div 1000)};
        false ->
            {utc, Ms}
    end.
