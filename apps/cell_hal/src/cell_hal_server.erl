%% @doc Keeps the HAL's configuration and its subscribers: adds and removes connections
%% and group instances (checked at the door), registers subscriptions and watches, and
%% monitors every subscriber so that what a process asked for ends with it.
%%
%% It is on no hot path: reads go straight to the tables, notifications straight from
%% the workers. A restart finds the tables as they were (they belong to the
%% supervisor) and monitors the subscribers again.
-module(cell_hal_server).
-behaviour(gen_server).

-include("cell_hal.hrl").

-export([start_link/0, call/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(state, {monitors = #{} :: #{pid() => reference()}}).

%% Options the worker reads itself, with their defaults.
-define(WORKER_OPTS, #{poll_ms => 50,
                       reconnect_ms => 500,
                       max_reconnect_ms => 30000,
                       connect_timeout_ms => 5000,
                       samples_kept => 1000}).
-define(CALL_TIMEOUT, 15000).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc A request of the HAL's API (see {@link cell_hal}).
-spec call(term()) -> term().
call(Request) ->
    gen_server:call(?MODULE, Request, ?CALL_TIMEOUT).

%% @private
-spec init([]) -> {ok, #state{}}.
init([]) ->
    Monitors = maps:from_list([{P, erlang:monitor(process, P)}
                               || P <- cell_hal_store:subscribers()]),
    %% Those who found the server away are told it is back: the requests they send on
    %% this wait until init/1 has returned. The name is registered before init/1
    %% runs, so a waiter that did not find it recorded itself before this look.
    _ = [back(Ref, Pid) || {Ref, Pid} <- cell_hal_store:take_waiters()],
    %% The forces set under the server before end with it (cell_hal_force): its inputs
    %% here, its outputs written back by each connection's worker once up.
    ok = cell_hal_force:forget_ended_inputs(),
    {ok, #state{monitors = Monitors}}.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({add_connection, Spec}, _From, S) ->
    {reply, add_connection(Spec), S};
handle_call({remove_connection, Id}, _From, S) ->
    {reply, remove_connection(Id), S};
handle_call({add_group, Spec}, _From, S) ->
    {reply, add_group(Spec), S};
handle_call({remove_group, Id}, _From, S) ->
    {reply, remove_group(Id), S};
handle_call({subscribe, Key, Pid}, _From, S) ->
    case cell_hal_store:point(Key) of
        {ok, _} ->
            ok = cell_hal_store:add_sub(Key, Pid),
            {reply, ok, monitor_pid(Pid, S)};
        error ->
            {reply, {error, unknown_point}, S}
    end;
handle_call({watch, Key, Cond, Pid}, _From, S) ->
    case cell_hal_store:point(Key) of
        {ok, _} ->
            Ref = make_ref(),
            S1 = monitor_pid(Pid, S),
            ok = cell_hal_store:add_watch(Key, Ref, Pid, Cond),
            {reply, {ok, Ref}, S1};
        error ->
            {reply, {error, unknown_point}, S}
    end;
handle_call({subscribe_connection, Conn, Pid}, _From, S) ->
    case cell_hal_store:conn(Conn) of
        {ok, _} ->
            %% Subscribed first, status read after: a change in between is both in the
            %% reply and in a message, never in neither.
            ok = cell_hal_store:add_conn_sub(Conn, Pid),
            Status = case cell_hal_store:is_up(Conn) of true -> up; false -> down end,
            {reply, {ok, Status}, monitor_pid(Pid, S)};
        error ->
            {reply, {error, unknown_connection}, S}
    end.

%% @private
-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _S) ->
    error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({waiting, Ref}, S) ->
    %% A waiter that found this server running (the row is gone if init/1 took it).
    _ = [back(R, Pid) || {R, Pid} <- cell_hal_store:take_waiter(Ref)],
    {noreply, S};
handle_info({'DOWN', MRef, process, Pid, _}, #state{monitors = Ms} = S) ->
    case Ms of
        #{Pid := MRef} ->
            ok = cell_hal_store:forget(Pid),
            {noreply, S#state{monitors = maps:remove(Pid, Ms)}};
        #{} ->
            {noreply, S}
    end.

back(Ref, Pid) ->
    Pid ! {cell_hal_back, Ref}.

monitor_pid(Pid, #state{monitors = Ms} = S) ->
    case Ms of
        #{Pid := _} -> S;
        #{} -> S#state{monitors = Ms#{Pid => erlang:monitor(process, Pid)}}
    end.

%%====================================================================
%% Connections
%%====================================================================

add_connection(Spec) ->
    maybe_all(
      [fun() -> only_keys(Spec, [id, driver, opts], [id, driver]) end,
       fun() -> check(is_atom(maps:get(id, Spec)), id) end,
       fun() -> check(cell_hal_store:conn(maps:get(id, Spec)) =:= error,
                      {already_exists, maps:get(id, Spec)}) end,
       fun() -> check(is_driver(maps:get(driver, Spec)), driver) end,
       fun() -> check(is_map(maps:get(opts, Spec, #{})), opts) end],
      fun() ->
              #{id := Id, driver := Driver} = Spec,
              Opts = maps:get(opts, Spec, #{}),
              case worker_opts(Opts) of
                  {ok, W} ->
                      case Driver:check_opts(maps:without(maps:keys(?WORKER_OPTS), Opts)) of
                          {ok, DOpts} -> start_connection(Id, Driver, DOpts, W);
                          {error, {bad_option, _}} = Error -> Error
                      end;
                  Error ->
                      Error
              end
      end).

start_connection(Id, Driver, DOpts, W) ->
    ok = cell_hal_store:put_conn(#hal_conn{id = Id, driver = Driver, opts = DOpts,
                                           worker_opts = W,
                                           since = os:system_time(millisecond),
                                           reason = starting}),
    case cell_hal_conn_sup:start_worker(Id) of
        ok ->
            ok;
        {error, Why} ->
            ok = cell_hal_store:delete_conn(Id),
            {error, {worker, Why}}
    end.

worker_opts(Opts) ->
    W = maps:merge(?WORKER_OPTS, maps:with(maps:keys(?WORKER_OPTS), Opts)),
    case [K || {K, V} <- maps:to_list(W), not (is_integer(V) andalso V > 0)] of
        [] when map_get(max_reconnect_ms, W) < map_get(reconnect_ms, W) ->
            {error, {bad_option, max_reconnect_ms}};
        [] ->
            {ok, W};
        [K | _] ->
            {error, {bad_option, K}}
    end.

is_driver(Mod) ->
    is_atom(Mod) andalso code:ensure_loaded(Mod) =:= {module, Mod} andalso
        lists:all(fun({F, A}) -> erlang:function_exported(Mod, F, A) end,
                  cell_hal_driver:behaviour_info(callbacks)).

remove_connection(Id) ->
    case cell_hal_store:conn(Id) of
        {ok, _} ->
            case cell_hal_store:groups_of(Id) of
                [] ->
                    ok = cell_hal_conn_sup:stop_worker(Id),
                    cell_hal_store:delete_conn(Id);
                Groups ->
                    {error, {in_use, Groups}}
            end;
        error ->
            {error, unknown_connection}
    end.

%%====================================================================
%% Groups
%%====================================================================

add_group(Spec) ->
    maybe_all(
      [fun() -> only_keys(Spec, [id, module, connection, opts], [id, module, connection]) end,
       fun() -> check(is_atom(maps:get(id, Spec)), id) end,
       fun() -> check(cell_hal_store:group(maps:get(id, Spec)) =:= error,
                      {already_exists, maps:get(id, Spec)}) end,
       fun() -> check(is_group_module(maps:get(module, Spec)), module) end,
       fun() -> check(cell_hal_store:conn(maps:get(connection, Spec)) =/= error, connection) end,
       fun() -> check(is_map(maps:get(opts, Spec, #{})), opts) end],
      fun() ->
              #{id := Id, module := Mod, connection := Conn} = Spec,
              Opts = maps:get(opts, Spec, #{}),
              case points(Mod, Opts) of
                  {ok, Defs} -> bind_group(Id, Mod, Conn, Opts, Defs);
                  Error -> Error
              end
      end).

is_group_module(Mod) ->
    is_atom(Mod) andalso code:ensure_loaded(Mod) =:= {module, Mod} andalso
        erlang:function_exported(Mod, points, 1).

%% The group module is the cell's own code: a fault in it refuses the group with the
%% reason, and the HAL goes on.
points(Mod, Opts) ->
    try Mod:points(Opts) of
        Defs ->
            case cell_hal_group:check_points(Defs) of
                ok -> {ok, Defs};
                Error -> Error
            end
    catch
        Class:Reason:Stack ->
            cell_log:error(cell_hal, "the IO group module ~s failed to list its points: "
                           "~p:~tp ~tp", [Mod, Class, Reason, Stack]),
            {error, {bad_group, {Class, Reason}}}
    end.

bind_group(Id, Mod, Conn, Opts, Defs) ->
    {ok, #hal_conn{driver = Driver, opts = COpts, pid = Pid}} = cell_hal_store:conn(Conn),
    case resolve(Driver, COpts, Conn, Id, Opts, Defs, []) of
        {ok, Points} ->
            ok = cell_hal_store:put_group(#hal_group{id = Id, module = Mod, conn = Conn,
                                                     opts = Opts}, Points),
            reconfigure(Pid);
        Error ->
            Error
    end.

resolve(_, _, _, _, _, [], Acc) ->
    {ok, lists:reverse(Acc)};
resolve(Driver, COpts, Conn, Id, Opts, [#{name := Name} = Def | Defs], Acc) ->
    case Driver:check_point(COpts, Id, Opts, Def) of
        {ok, Field} ->
            #{dir := Dir, type := Type, address := Addr, caption := Caption,
              field := Declared} = Def,
            P = #hal_point{key = {Id, Name}, conn = Conn,
                           dir = Dir, type = Type, field = Field, declared = Declared,
                           address = Addr, caption = Caption,
                           unit = maps:get(unit, Def, <<>>), seq = length(Acc)},
            resolve(Driver, COpts, Conn, Id, Opts, Defs, [P | Acc]);
        {error, Why} ->
            {error, {bad_point, Name, {field, Why}}}
    end.

remove_group(Id) ->
    case cell_hal_store:group(Id) of
        {ok, #hal_group{conn = Conn}} ->
            ok = cell_hal_store:delete_group(Id),
            case cell_hal_store:conn(Conn) of
                {ok, #hal_conn{pid = Pid}} -> reconfigure(Pid);
                error -> ok
            end;
        error ->
            {error, unknown_group}
    end.

reconfigure(Pid) when is_pid(Pid) -> cell_hal_worker:reconfigure(Pid);
reconfigure(undefined) -> ok.

%%====================================================================
%% Checks at the door
%%====================================================================

%% Runs checks in order; the first that fails names what is wrong.
maybe_all([], Then) ->
    Then();
maybe_all([Check | Rest], Then) ->
    case Check() of
        ok -> maybe_all(Rest, Then);
        Error -> Error
    end.

only_keys(Spec, Allowed, Required) when is_map(Spec) ->
    case [K || K <- Required, not maps:is_key(K, Spec)] ++
         [K || K <- maps:keys(Spec), not lists:member(K, Allowed)] of
        [] -> ok;
        [K | _] -> {error, {bad_option, K}}
    end;
only_keys(_, _, _) ->
    {error, {bad_option, spec}}.

check(true, _) -> ok;
check(false, {already_exists, _} = Why) -> {error, Why};
check(false, Key) -> {error, {bad_option, Key}}.
