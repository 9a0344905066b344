%% @doc The HAL's tables and the few operations that touch them, shared by the
%% configuration server, the workers and the readers.
%%
%% The tables belong to `cell_hal_sup' (created in its `init/1'), so they live as long
%% as the HAL: a restarted server or worker finds the configuration, the last values
%% and every subscription where it left them. Who writes what:
%% <ul>
%% <li>`cell_hal_server' writes the configuration (connections, groups, point
%%   descriptions and their value rows) and the subscriptions;</li>
%% <li>a connection's worker writes its connection's status, its points' values and
%%   faults and the time-stamped samples of points fed by device notifications, and
%%   sends every notification;</li>
%% <li>a simulated PLC writes its process and its memory (image, rules, link) in the
%%   table of simulated PLCs, so a restarted one finds them;</li>
%% <li>readers (tasks) only read.</li>
%% </ul>
%% A watch fires exactly once: whoever takes its claim row first (the worker that saw
%% the value change, or the server that found it already true) sends the message.
-module(cell_hal_store).

-include("cell_hal.hrl").

-export([create_tables/0]).
-export([conn/1, conns/0, group/1, groups/0, groups_of/1, point/1, points_of_conn/1,
         points_of_group/1, value/1, is_up/1, as_seen/1, up_worker/1, read/1]).
-export([put_conn/1, delete_conn/1, put_group/2, delete_group/1]).
-export([set_worker/3, mark/3, announce/2, put_value/2, notify/2, fire_watches/2,
         set_fault/2, faults_of_conn/1]).
-export([add_samples/3, samples/2, clear_samples/1]).
-export([add_sub/2, delete_sub/2, add_conn_sub/2, delete_conn_sub/2, conn_subs/1,
         add_watch/4, cancel_watch/1, forget/1, subscribers/0]).
-export([add_waiter/2, take_waiter/1, take_waiters/0]).

-define(CONNS, cell_hal_conns).
-define(GROUPS, cell_hal_groups).
-define(POINTS, cell_hal_points).
-define(VALUES, cell_hal_values).
-define(SUBS, cell_hal_subs).
-define(CONN_SUBS, cell_hal_conn_subs).
-define(WATCHES, cell_hal_watches).
-define(CLAIMS, cell_hal_watch_claims).
-define(SIM, cell_hal_sim_devices).
-define(HW, cell_hal_hw_objects).
-define(SAMPLES, cell_hal_samples).
-define(WAITERS, cell_hal_waiters).

-type key() :: {atom(), atom()}.

%% @doc Creates the tables in the calling process, which owns them from then on.
-spec create_tables() -> ok.
create_tables() ->
    Read = [named_table, public, {read_concurrency, true}],
    ?CONNS = ets:new(?CONNS, [set, {keypos, #hal_conn.id} | Read]),
    ?GROUPS = ets:new(?GROUPS, [set, {keypos, #hal_group.id} | Read]),
    ?POINTS = ets:new(?POINTS, [ordered_set, {keypos, #hal_point.key} | Read]),
    ?VALUES = ets:new(?VALUES, [set, {keypos, #hal_value.key}, {write_concurrency, true}
                                | Read]),
    ?SUBS = ets:new(?SUBS, [bag | Read]),
    ?CONN_SUBS = ets:new(?CONN_SUBS, [bag | Read]),
    ?WATCHES = ets:new(?WATCHES, [bag | Read]),
    ?CLAIMS = ets:new(?CLAIMS, [set | Read]),
    ?SIM = ets:new(?SIM, [set | Read]),
    ?HW = ets:new(?HW, [set | Read]),
    %% {{Key, Seq}, TimeNs, Value}: a point's samples in arrival order, a range of keys
    ?SAMPLES = ets:new(?SAMPLES, [ordered_set | Read]),
    %% {Ref, Pid}: a process to tell when the server takes requests again
    ?WAITERS = ets:new(?WAITERS, [set | Read]),
    ok.

%%====================================================================
%% Configuration
%%====================================================================

-spec conn(atom()) -> {ok, #hal_conn{}} | error.
conn(Id) ->
    case ets:lookup(?CONNS, Id) of
        [C] -> {ok, C};
        [] -> error
    end.

-spec conns() -> [#hal_conn{}].
conns() -> ets:tab2list(?CONNS).

-spec group(atom()) -> {ok, #hal_group{}} | error.
group(Id) ->
    case ets:lookup(?GROUPS, Id) of
        [G] -> {ok, G};
        [] -> error
    end.

-spec groups() -> [#hal_group{}].
groups() -> ets:tab2list(?GROUPS).

%% @doc The groups bound to a connection.
-spec groups_of(atom()) -> [atom()].
groups_of(Conn) ->
    Pattern = pattern(hal_group, record_info(size, hal_group),
                      [{#hal_group.id, '$1'}, {#hal_group.conn, Conn}]),
    lists:sort(ets:select(?GROUPS, [{Pattern, [], ['$1']}])).

-spec point(key()) -> {ok, #hal_point{}} | error.
point(Key) ->
    case ets:lookup(?POINTS, Key) of
        [P] -> {ok, P};
        [] -> error
    end.

-spec points_of_conn(atom()) -> [#hal_point{}].
points_of_conn(Conn) ->
    ets:match_object(?POINTS, pattern(hal_point, record_info(size, hal_point),
                                      [{#hal_point.conn, Conn}])).

%% @doc A group's points in key order (its keys share the group id, so this is a range).
-spec points_of_group(atom()) -> [#hal_point{}].
points_of_group(Group) ->
    ets:match_object(?POINTS, pattern(hal_point, record_info(size, hal_point),
                                      [{#hal_point.key, {Group, '_'}}])).

%% A match pattern for a record (the record syntax with '_' would break its types).
pattern(Name, Size, Bound) ->
    erlang:make_tuple(Size, '_', [{1, Name} | Bound]).

-spec value(key()) -> {ok, #hal_value{}} | error.
value(Key) ->
    case ets:lookup(?VALUES, Key) of
        [V] -> {ok, V};
        [] -> error
    end.

%% @doc Whether a connection's inputs are fresh: it is marked up and the worker that
%% marked it so still runs. A worker killed leaves its connection marked up (it cannot
%% say otherwise); until its successor starts and marks it down the connection is down
%% all the same, so that nothing the dead worker read is presented as fresh. See
%% {@link as_seen/1}.
-spec is_up(atom()) -> boolean().
is_up(Conn) ->
    case ets:lookup(?CONNS, Conn) of
        [C] -> (as_seen(C))#hal_conn.status =:= up;
        [] -> false
    end.

%% @doc A connection's row as readers must see it: one marked up whose worker is gone
%% (killed; its successor not started yet) is down, for `worker_gone'. Its worker's
%% process is the one in the row: a worker marks its connection down before it
%% records itself there, so a row marked up names the worker that marked it. Asking
%% whether a local process is alive takes a fraction of a microsecond, which every read
%% of an input can afford.
-spec as_seen(#hal_conn{}) -> #hal_conn{}.
as_seen(#hal_conn{status = up, pid = Pid} = C) ->
    case is_pid(Pid) andalso is_process_alive(Pid) of
        true -> C;
        false -> C#hal_conn{status = down, reason = worker_gone}
    end;
as_seen(#hal_conn{} = C) ->
    C.

%% @doc The worker of a connection that is up (see {@link is_up/1}), to hand it a
%% write or a request.
-spec up_worker(atom()) -> {ok, pid()} | error.
up_worker(Conn) ->
    case ets:lookup(?CONNS, Conn) of
        [C] ->
            case as_seen(C) of
                #hal_conn{status = up, pid = Pid} when is_pid(Pid) -> {ok, Pid};
                #hal_conn{} -> error
            end;
        [] ->
            error
    end.

%% @doc A point's value as a task may see it: an input only while its connection is
%% up (a stale input is never presented as fresh; see {@link is_up/1}), an output as
%% last commanded or read back; neither while the driver reports it unusable.
-spec read(key()) -> {ok, cell_hal_type:value()}
                     | {error, disconnected | unknown_point | not_yet_read
                               | {unavailable, binary()}}.
read(Key) ->
    case ets:lookup(?VALUES, Key) of
        [#hal_value{fault = Why}] when is_binary(Why) -> {error, {unavailable, Why}};
        [#hal_value{dir = out, value = {ok, _} = V}] -> V;
        [#hal_value{conn = C, value = V}] ->
            case is_up(C) of
                false -> {error, disconnected};
                true when V =:= none -> {error, not_yet_read};
                true -> V
            end;
        [] ->
            {error, unknown_point}
    end.

-spec put_conn(#hal_conn{}) -> ok.
put_conn(C) ->
    true = ets:insert(?CONNS, C),
    ok.

-spec delete_conn(atom()) -> ok.
delete_conn(Id) ->
    true = ets:delete(?CONNS, Id),
    true = ets:delete(?CONN_SUBS, Id),
    ok.

%% @doc Stores a group instance with its points, their values not read yet.
-spec put_group(#hal_group{}, [#hal_point{}]) -> ok.
put_group(G, Points) ->
    true = ets:insert(?POINTS, Points),
    true = ets:insert(?VALUES, [#hal_value{key = K, conn = C, dir = D, type = T}
                                || #hal_point{key = K, conn = C, dir = D, type = T} <- Points]),
    true = ets:insert(?GROUPS, G),
    ok.

%% @doc Removes a group, its points, their values, and every subscription and watch
%% on them.
-spec delete_group(atom()) -> ok.
delete_group(Id) ->
    Keys = [K || #hal_point{key = K} <- points_of_group(Id)],
    lists:foreach(fun(K) ->
                          true = ets:delete(?POINTS, K),
                          true = ets:delete(?VALUES, K),
                          true = ets:delete(?SUBS, K),
                          [true = ets:delete(?CLAIMS, Ref)
                           || {_, Ref, _, _} <- ets:lookup(?WATCHES, K)],
                          true = ets:delete(?WATCHES, K),
                          ok = clear_samples([K])
                  end, Keys),
    true = ets:delete(?GROUPS, Id),
    ok.

%%====================================================================
%% Worker side
%%====================================================================

%% @doc Records the worker process of a connection and where it connects to. The
%% connection must be marked down first (see {@link as_seen/1}).
-spec set_worker(atom(), pid(), binary()) -> ok.
set_worker(Conn, Pid, Endpoint) ->
    true = ets:update_element(?CONNS, Conn, [{#hal_conn.pid, Pid},
                                             {#hal_conn.endpoint, Endpoint}]),
    ok.

%% @doc Marks a connection up or down (readers see it at once); `Reason' says why it
%% is down. Nobody is told yet: see {@link announce/2}.
-spec mark(atom(), up | down, term()) -> ok.
mark(Conn, Status, Reason) ->
    _ = ets:update_element(?CONNS, Conn, [{#hal_conn.status, Status},
                                          {#hal_conn.since, os:system_time(millisecond)},
                                          {#hal_conn.reason, Reason}]),
    ok.

%% @doc Tells a connection's subscribers it is up or down.
-spec announce(atom(), up | down) -> ok.
announce(Conn, Status) ->
    lists:foreach(fun({_, Pid}) -> Pid ! {cell_hal_conn, Conn, Status} end,
                  ets:lookup(?CONN_SUBS, Conn)).

%% @doc Stores a point's new value; false when the point is gone (its group was just
%% removed): nothing is then published.
-spec put_value(key(), cell_hal_type:value()) -> boolean().
put_value(Key, V) ->
    ets:update_element(?VALUES, Key, {#hal_value.value, {ok, V}}).

%% @doc Tells a point's subscribers its new value and fires the watches it satisfies.
-spec notify(key(), cell_hal_type:value()) -> ok.
notify(Key, V) ->
    lists:foreach(fun({_, Pid}) -> Pid ! {cell_hal, Key, V} end, ets:lookup(?SUBS, Key)),
    fire_watches(Key, V).

%% @doc Fires the watches of a point that its value satisfies, each at most once.
-spec fire_watches(key(), cell_hal_type:value()) -> ok.
fire_watches(Key, V) ->
    lists:foreach(fun(W) -> fire(W, V) end, ets:lookup(?WATCHES, Key)).

fire({_, Ref, Pid, Cond} = W, V) ->
    case cell_hal_type:holds(Cond, V) andalso ets:take(?CLAIMS, Ref) of
        [_] ->
            true = ets:delete_object(?WATCHES, W),
            Pid ! {cell_hal_watch, Ref, V},
            ok;
        _ ->
            ok
    end.

%% A watch ended by its point's fault, at most once as a fire is.
fail({_, Ref, Pid, _} = W, Why) ->
    case ets:take(?CLAIMS, Ref) of
        [_] ->
            true = ets:delete_object(?WATCHES, W),
            Pid ! {cell_hal_unavailable, Ref, Why},
            ok;
        [] ->
            ok
    end.

%% @doc Marks a point unusable (`Why' in words) or usable again (`undefined');
%% true when that changed anything. A point made unusable ends its watches: each
%% watcher gets `{cell_hal_unavailable, Ref, Why}' instead of a value, so that nobody
%% waits for a point that cannot be read. Its subscribers get `{cell_hal_fault, Key,
%% Why}', or `{cell_hal_fault, Key, cleared}' when it is usable again (then a read
%% gives its value), so that nobody shows a value the point no longer has.
-spec set_fault(key(), binary() | undefined) -> boolean().
set_fault(Key, Why) ->
    try ets:lookup_element(?VALUES, Key, #hal_value.fault) of
        Why -> false;
        _ ->
            Changed = ets:update_element(?VALUES, Key, {#hal_value.fault, Why}),
            _ = Changed andalso is_binary(Why) andalso
                lists:foreach(fun(W) -> fail(W, Why) end, ets:lookup(?WATCHES, Key)),
            Told = case Why of
                       undefined -> cleared;
                       _ -> Why
                   end,
            _ = Changed andalso
                lists:foreach(fun({_, Pid}) -> Pid ! {cell_hal_fault, Key, Told} end,
                              ets:lookup(?SUBS, Key)),
            Changed
    catch
        error:badarg -> false
    end.

%% @doc The points of a connection its driver reports unusable, with why.
-spec faults_of_conn(atom()) -> [{key(), binary()}].
faults_of_conn(Conn) ->
    Pattern = pattern(hal_value, record_info(size, hal_value),
                      [{#hal_value.key, '$1'}, {#hal_value.conn, Conn},
                       {#hal_value.fault, '$2'}]),
    lists:sort(ets:select(?VALUES, [{Pattern, [{is_binary, '$2'}], [{{'$1', '$2'}}]}])).

%%====================================================================
%% Time-stamped samples
%%====================================================================

%% @doc Appends a point's samples (oldest first) and keeps its newest `Keep'.
-spec add_samples(key(), [{integer(), cell_hal_type:value()}], pos_integer()) -> ok.
add_samples(_Key, [], _Keep) ->
    ok;
add_samples(Key, Samples, Keep) ->
    {First, Next} = sample_range(Key),
    {Rows, Last} = lists:mapfoldl(fun({T, V}, Seq) -> {{{Key, Seq}, T, V}, Seq + 1} end,
                                  Next, Samples),
    true = ets:insert(?SAMPLES, Rows),
    Oldest = max(First, Last - Keep),
    lists:foreach(fun(Seq) -> true = ets:delete(?SAMPLES, {Key, Seq}) end,
                  lists:seq(First, Oldest - 1)),
    ok.

%% The sequence numbers a point's samples use: the first kept and the next free.
sample_range(Key) ->
    %% Sequence numbers are integers, which sort before the atom `end'.
    case ets:prev(?SAMPLES, {Key, 'end'}) of
        {Key, Last} ->
            {Key, First} = ets:next(?SAMPLES, {Key, -1}),
            {First, Last + 1};
        _ ->
            {0, 0}
    end.

%% @doc A point's samples kept from `Since' on (nanoseconds, the PLC's stamps): the one
%% in force at `Since' (the last stamped at or before it) and every later one, oldest
%% first.
%% `not_kept' when the oldest kept sample is stamped after `Since' (the value at
%% `Since' is unknown: the connection was down meanwhile, or more samples came than
%% are kept); `not_sampled' when none is kept.
-spec samples(key(), integer()) ->
          {ok, [{integer(), cell_hal_type:value()}]}
        | {error, not_sampled | {not_kept, integer()}}.
samples(Key, Since) ->
    case ets:select(?SAMPLES, [{{{Key, '_'}, '$1', '$2'}, [], [{{'$1', '$2'}}]}]) of
        [] ->
            {error, not_sampled};
        [{Oldest, _} | _] when Oldest > Since ->
            {error, {not_kept, Oldest}};
        All ->
            {ok, from(Since, All)}
    end.

%% From the sample in force at Since (the last stamped at or before it) on; samples of
%% one PLC cycle share a stamp and come together.
from(Since, All) ->
    InForce = lists:foldl(fun({T, _}, _) when T =< Since -> T;
                             (_, Acc) -> Acc
                          end, Since, All),
    lists:dropwhile(fun({T, _}) -> T < InForce end, All).

%% @doc Forgets the samples of points (their connection went down, or they are gone).
-spec clear_samples([key()]) -> ok.
clear_samples(Keys) ->
    lists:foreach(fun(K) -> true = ets:match_delete(?SAMPLES, {{K, '_'}, '_', '_'}) end, Keys).

%%====================================================================
%% Subscriptions (server side)
%%====================================================================

-spec add_sub(key(), pid()) -> ok.
add_sub(Key, Pid) ->
    true = ets:insert(?SUBS, {Key, Pid}),
    ok.

-spec delete_sub(key(), pid()) -> ok.
delete_sub(Key, Pid) ->
    true = ets:delete_object(?SUBS, {Key, Pid}),
    ok.

-spec add_conn_sub(atom(), pid()) -> ok.
add_conn_sub(Conn, Pid) ->
    true = ets:insert(?CONN_SUBS, {Conn, Pid}),
    ok.

-spec delete_conn_sub(atom(), pid()) -> ok.
delete_conn_sub(Conn, Pid) ->
    true = ets:delete_object(?CONN_SUBS, {Conn, Pid}),
    ok.

-spec conn_subs(atom()) -> [pid()].
conn_subs(Conn) -> [Pid || {_, Pid} <- ets:lookup(?CONN_SUBS, Conn)].

%% @doc Registers a watch, then fires it at once if the current value (`none' when
%% there is no fresh one) already satisfies it, or ends it at once if the point is
%% unusable (see {@link set_fault/2}). Registering before looking closes the race with
%% a worker publishing (or marking the point) meanwhile: one of the two sees the other.
-spec add_watch(key(), reference(), pid(), cell_hal_type:condition()) -> ok.
add_watch(Key, Ref, Pid, Cond) ->
    true = ets:insert(?CLAIMS, {Ref, Key, Pid}),
    W = {Key, Ref, Pid, Cond},
    true = ets:insert(?WATCHES, W),
    case read(Key) of
        {ok, V} -> fire(W, V);
        {error, {unavailable, Why}} -> fail(W, Why);
        {error, _} -> ok
    end.

%% @doc Cancels a watch: true when it had not fired (no message will come).
-spec cancel_watch(reference()) -> boolean().
cancel_watch(Ref) ->
    case ets:take(?CLAIMS, Ref) of
        [{Ref, Key, Pid}] ->
            true = ets:match_delete(?WATCHES, {Key, Ref, Pid, '_'}),
            true;
        [] ->
            false
    end.

%% @doc Drops every subscription and watch of a process (it exited).
-spec forget(pid()) -> ok.
forget(Pid) ->
    true = ets:match_delete(?SUBS, {'_', Pid}),
    true = ets:match_delete(?CONN_SUBS, {'_', Pid}),
    [true = ets:delete(?CLAIMS, Ref) || {_, Ref, _, _} <- ets:match_object(?WATCHES, {'_', '_', Pid, '_'})],
    true = ets:match_delete(?WATCHES, {'_', '_', Pid, '_'}),
    ok.

%% @doc Every process holding a subscription or a watch (to monitor them again after
%% the server restarted).
-spec subscribers() -> [pid()].
subscribers() ->
    lists:usort([P || {_, P} <- ets:tab2list(?SUBS)] ++
                [P || {_, P} <- ets:tab2list(?CONN_SUBS)] ++
                [P || {_, _, P} <- ets:tab2list(?CLAIMS)]).

%%====================================================================
%% Waiting for the server
%%====================================================================

%% @doc Records a process to tell, under `Ref', when the server takes requests again.
-spec add_waiter(reference(), pid()) -> ok.
add_waiter(Ref, Pid) ->
    true = ets:insert(?WAITERS, {Ref, Pid}),
    ok.

%% @doc The process waiting under `Ref', taken: each is told once, by whoever takes it.
-spec take_waiter(reference()) -> [{reference(), pid()}].
take_waiter(Ref) ->
    ets:take(?WAITERS, Ref).

%% @doc Every process waiting, taken (by a server that starts).
-spec take_waiters() -> [{reference(), pid()}].
take_waiters() ->
    lists:append([ets:take(?WAITERS, Ref) || {Ref, _} <- ets:tab2list(?WAITERS)]).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% The tables of a HAL that is not running, owned by a process of their own.
with_tables(Tests) ->
    {setup,
     fun() ->
             Self = self(),
             Owner = spawn(fun() ->
                                   ok = create_tables(),
                                   Self ! {tables, self()},
                                   receive stop -> ok end
                           end),
             receive {tables, Owner} -> Owner end
     end,
     fun(Owner) ->
             Ref = monitor(process, Owner),
             Owner ! stop,
             receive {'DOWN', Ref, process, Owner, _} -> ok end
     end,
     Tests}.

%% Up only while the worker that marked it so runs; a row marked down stays down.
as_seen_test_() ->
    with_tables(
      fun() ->
              Dead = spawn(fun() -> ok end),
              Ref = monitor(process, Dead),
              receive {'DOWN', Ref, process, Dead, _} -> ok end,
              Up = #hal_conn{id = c, driver = cell_hal_sim, opts = #{}, worker_opts = #{},
                             status = up, pid = self(), since = 1},
              ?assertEqual(Up, as_seen(Up)),
              [?assertEqual(Gone#hal_conn{status = down, reason = worker_gone}, as_seen(Gone))
               || Gone <- [Up#hal_conn{pid = Dead}, Up#hal_conn{pid = undefined}]],
              Down = Up#hal_conn{status = down, reason = stopped},
              ?assertEqual(Down, as_seen(Down)),
              ?assertEqual(Down#hal_conn{pid = Dead}, as_seen(Down#hal_conn{pid = Dead})),
              ?assertNot(is_up(c)),
              ?assertEqual(error, up_worker(c)),
              ok = put_conn(Up),
              ?assert(is_up(c)),
              ?assertEqual({ok, self()}, up_worker(c)),
              ok = put_conn(Up#hal_conn{pid = Dead}),
              ?assertNot(is_up(c)),
              ?assertEqual(error, up_worker(c)),
              ok = put_conn(Down),
              ?assertNot(is_up(c)),
              ?assertEqual(error, up_worker(c))
      end).

samples_test_() ->
    K = {g, p},
    Other = {g, q},
    with_tables(
      fun() ->
              ?assertEqual({error, not_sampled}, samples(K, 0)),
              ok = add_samples(K, [{10, 1}, {20, 2}, {30, 3}], 4),
              ok = add_samples(Other, [{5, a}], 4),
              %% from a stamp between two samples: the one in force, then the later
              ?assertEqual({ok, [{20, 2}, {30, 3}]}, samples(K, 25)),
              %% from a sample's own stamp: that sample first
              ?assertEqual({ok, [{20, 2}, {30, 3}]}, samples(K, 20)),
              ?assertEqual({ok, [{10, 1}, {20, 2}, {30, 3}]}, samples(K, 10)),
              %% after the last: the last, still in force
              ?assertEqual({ok, [{30, 3}]}, samples(K, 99)),
              %% before the oldest kept: the value then is unknown
              ?assertEqual({error, {not_kept, 10}}, samples(K, 9)),
              %% only the newest four are kept, one batch or many
              ok = add_samples(K, [{40, 4}, {50, 5}], 4),
              ?assertEqual({error, {not_kept, 20}}, samples(K, 15)),
              ?assertEqual({ok, [{20, 2}, {30, 3}, {40, 4}, {50, 5}]}, samples(K, 20)),
              ok = add_samples(K, [{T, T div 10} || T <- lists:seq(60, 150, 10)], 4),
              ?assertEqual({ok, [{120, 12}, {130, 13}, {140, 14}, {150, 15}]}, samples(K, 120)),
              ?assertEqual(4, length(ets:select(?SAMPLES, [{{{K, '_'}, '_', '_'}, [], [true]}]))),
              %% equal stamps (one PLC cycle) keep their order
              ok = add_samples(Other, [{7, b}, {7, c}], 4),
              ?assertEqual({ok, [{7, b}, {7, c}]}, samples(Other, 7)),
              ?assertEqual({ok, [{5, a}, {7, b}, {7, c}]}, samples(Other, 6)),
              ok = clear_samples([K]),
              ?assertEqual({error, not_sampled}, samples(K, 0)),
              ?assertEqual({ok, [{7, b}, {7, c}]}, samples(Other, 8)),
              %% a point's samples go on after a clear
              ok = add_samples(K, [{200, 20}], 4),
              ?assertEqual({ok, [{200, 20}]}, samples(K, 200))
      end).
-endif.
