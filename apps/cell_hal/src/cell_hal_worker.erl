%% @doc One worker per PLC connection: it owns the connection (through its driver, see
%% {@link cell_hal_driver}), polls the inputs of every group bound to it, publishes the
%% values that changed, writes outputs in order, and tells subscribers when the
%% connection is up or down.
%%
%% <table>
%% <tr><th>state</th><th>what happens</th><th>leaves for</th></tr>
%% <tr><td>`connecting'</td><td>the driver connects, then reads every point once, outputs
%%   included (the device's outputs may differ from what was last commanded: a PLC may
%%   have put them in a safe state while the link was down)</td><td>`connected' after
%%   that first complete read; `disconnected' on failure or when it takes longer than
%%   `connect_timeout_ms'</td></tr>
%% <tr><td>`connected'</td><td>the connection is up: inputs are polled every `poll_ms',
%%   changes published, outputs written in order</td><td>`disconnected' when the link
%%   drops, a request times out or a poll fails</td></tr>
%% <tr><td>`disconnected'</td><td>the connection is down: inputs read as
%%   `disconnected', writes are refused; the worker waits, `reconnect_ms' at first,
%%   twice as long after each failed attempt up to `max_reconnect_ms'</td>
%%   <td>`connecting' when the wait ends</td></tr>
%% </table>
%%
%% Only the first complete read after a (re)connect brings the connection up: points
%% bound while it was on its way (a group added as the connection came up) are read
%% before it, so that no input of an up connection reads as not yet read. The
%% wait goes back to `reconnect_ms' only then, so a device that accepts connections
%% and then fails is retried ever more slowly. A stale input is never presented as
%% fresh: values are stored before the connection is marked up, and it is marked down
%% before anyone is told. A worker killed cannot mark it down: readers take a
%% connection whose worker is gone for down ({@link cell_hal_store:is_up/1}) until its
%% successor marks it so and tells the subscribers.
%%
%% A point the driver reports unusable (a symbol the PLC lacks, or of another type; an
%% address a Modbus PLC refuses) reads as `{error, {unavailable, Why}}' while the rest
%% of its group and the connection work on; its watches end with that reason (see
%% {@link cell_hal:watch/3}); the worker logs it once, and again when it can be used. Points fed by device
%% notifications keep their newest `samples_kept' time-stamped samples for tasks
%% ({@link cell_hal:samples/3}); going down forgets them, as it forgets the
%% faults.
-module(cell_hal_worker).
-behaviour(gen_statem).

-include("cell_hal.hrl").

-export([start_link/1, reconfigure/1, await_read/2, write/4, request/4, reason_text/2]).
-export([callback_mode/0, init/1, connecting/3, connected/3, disconnected/3,
         terminate/3]).

-type key() :: {atom(), atom()}.
-type tag() :: non_neg_integer().



-record(pt, {dir :: in | out,
             type :: cell_hal_type:type(),
             field :: term(),
             value = none :: none | {ok, cell_hal_type:value()}}).

-record(data, {id :: atom(),
               source :: binary(),                     %% log source "hal/plc1"
               driver :: module(),
               ds :: term(),                           %% the driver's state
               endpoint :: binary(),
               poll_ms :: pos_integer(),
               reconnect_ms :: pos_integer(),
               max_reconnect_ms :: pos_integer(),
               connect_timeout_ms :: pos_integer(),
               backoff :: pos_integer(),               %% the next wait in disconnected
               points = #{} :: #{key() => #pt{}},
               plan :: term(),                         %% the inputs' read plan
               requests = 0 :: non_neg_integer(),      %% exchanges one poll takes
               pushed = 0 :: non_neg_integer(),        %% inputs fed by notifications
               samples_kept :: pos_integer(),          %% time-stamped samples a point keeps
               tag = 0 :: tag(),                       %% the next tag
               sync :: tag() | undefined,              %% the first read after connecting
               synced = [] :: [{key(), term()}],       %% its values that changed so far
               asked = #{} :: #{key() => true},        %% the points it read or reads
               poll :: tag() | undefined,              %% the poll in flight
               poll_due = false :: boolean(),          %% the period ended during a poll
               unread = #{} :: #{key() => tag()},      %% outputs being read back, by read
               pending = #{} :: #{tag() => pending()},
               %% callers of await_read/2, each waiting for the poll of that tag
               readers = [] :: [{gen_statem:from(), tag()}],
               reason :: term(),                       %% why it is not up
               was_up = false :: boolean(),            %% up before this failure
               logged :: term()}).                     %% the failure last logged

-type pending() :: {write, key(), cell_hal_type:value(), async | gen_statem:from()}
                 | {request, gen_statem:from()}.

%%====================================================================
%% API
%%====================================================================

%% @doc Starts the worker of a configured connection.
-spec start_link(atom()) -> gen_statem:start_ret().
start_link(Id) ->
    gen_statem:start_link(?MODULE, Id, []).

%% @doc The points bound to the connection changed: read them again.
-spec reconfigure(pid()) -> ok.
reconfigure(Pid) ->
    gen_statem:cast(Pid, reconfigure).

%% @doc Returns once every input bound to the connection has been read, or the
%% connection is not up (then its first read after connecting reads them before it
%% comes up): for a group just added to a connection that is up.
-spec await_read(pid(), timeout()) -> ok.
await_read(Pid, Timeout) ->
    gen_statem:call(Pid, await_read, Timeout).

%% @doc Queues an output write. `async' returns once the write is queued; `sync'
%% returns when the device confirmed it. A worker gone or not answering in time exits
%% the caller as any call does; {@link cell_hal} says what that is to a task.
-spec write(pid(), key(), cell_hal_type:value(), {async | sync, timeout()}) ->
          ok | {error, term()}.
write(Pid, Key, V, {Mode, Timeout}) ->
    gen_statem:call(Pid, {write, Key, V, Mode}, Timeout).

%% @doc A raw request of the driver's protocol.
-spec request(pid(), term(), pos_integer(), timeout()) -> {ok, term()} | {error, term()}.
request(Pid, Req, DeviceTimeout, Timeout) ->
    gen_statem:call(Pid, {request, Req, DeviceTimeout}, Timeout).

%%====================================================================
%% gen_statem
%%====================================================================

%% @private
-spec callback_mode() -> [state_functions | state_enter].
callback_mode() -> [state_functions, state_enter].

%% @private
-spec init(atom()) -> {ok, connecting, #data{}}.
init(Id) ->
    %% terminate/3 runs on shutdown: the connection is closed and marked down.
    process_flag(trap_exit, true),
    {ok, #hal_conn{driver = Driver, opts = Opts, worker_opts = W, status = Old}} =
        cell_hal_store:conn(Id),
    DS = Driver:init(Id, Opts),
    Endpoint = iolist_to_binary(Driver:endpoint(DS)),
    %% A worker that crashed while up: nothing it read is fresh any more. Marked down
    %% before this worker records itself, so that the row never names a live worker
    %% with its predecessor's `up' (cell_hal_store:as_seen/1).
    ok = cell_hal_store:mark(Id, down, restarted),
    ok = cell_hal_store:set_worker(Id, self(), Endpoint),
    _ = Old =:= up andalso cell_hal_store:announce(Id, down),
    D = #data{id = Id, source = <<"hal/", (atom_to_binary(Id))/binary>>,
              driver = Driver, ds = DS, endpoint = Endpoint,
              poll_ms = maps:get(poll_ms, W), reconnect_ms = maps:get(reconnect_ms, W),
              max_reconnect_ms = maps:get(max_reconnect_ms, W),
              connect_timeout_ms = maps:get(connect_timeout_ms, W),
              samples_kept = maps:get(samples_kept, W),
              backoff = maps:get(reconnect_ms, W)},
    {ok, connecting, load_points(D)}.

%%--------------------------------------------------------------------
%% connecting: the driver connects, then the first complete read
%%--------------------------------------------------------------------

%% @private
-spec connecting(gen_statem:event_type(), term(), #data{}) -> gen_statem:state_function_result().
connecting(enter, _Old, _D) ->
    {keep_state_and_data, [{state_timeout, 0, connect}]};
connecting(state_timeout, connect, #data{driver = Driver, ds = DS, connect_timeout_ms = T} = D) ->
    {ok, DS1} = Driver:connect(DS),
    {keep_state, D#data{ds = DS1}, [{state_timeout, T, {no_connection, T}}]};
connecting(state_timeout, {no_connection, T}, #data{sync = Sync} = D) ->
    %% One deadline covers connecting and the first read.
    Why = case Sync of
              undefined -> {no_connection, T};
              _ -> {no_first_read, T}
          end,
    {next_state, disconnected, D#data{reason = Why}};
connecting(info, Msg, D) ->
    driver_info(Msg, connecting, D);
connecting(Type, Event, D) ->
    common(Type, Event, connecting, D).

%%--------------------------------------------------------------------
%% connected: up; polls, writes
%%--------------------------------------------------------------------

%% @private
-spec connected(gen_statem:event_type(), term(), #data{}) -> gen_statem:state_function_result().
connected(enter, _Old, #data{poll_ms = P}) ->
    {keep_state_and_data, [{{timeout, poll}, P, poll}]};
connected({timeout, poll}, poll, #data{poll_ms = P, poll = Polling} = D) ->
    D1 = case Polling of
             undefined -> start_poll(D);
             _ -> D#data{poll_due = true}
         end,
    {keep_state, D1, [{{timeout, poll}, P, poll}]};
connected({call, From}, {write, Key, V, Mode}, D) ->
    case queue_write(Key, V, Mode, From, D) of
        {ok, D1} when Mode =:= async -> {keep_state, D1, [{reply, From, ok}]};
        {ok, D1} -> {keep_state, D1};
        {error, _} = Error -> {keep_state_and_data, [{reply, From, Error}]}
    end;
connected({call, From}, await_read,
          #data{poll = Polling, poll_due = Due, tag = Next} = D) ->
    %% New inputs are read by the poll in flight, or by the one due after it (see
    %% read_new_inputs/1); one that gave no value (a fault) is not waited for again.
    case unread_inputs(D) of
        true when Due -> {keep_state, D#data{readers = [{From, Next} | D#data.readers]}};
        true when Polling =/= undefined ->
            {keep_state, D#data{readers = [{From, Polling} | D#data.readers]}};
        _ -> {keep_state_and_data, [{reply, From, ok}]}
    end;
connected({call, From}, {request, Req, Timeout}, #data{driver = Driver, ds = DS} = D) ->
    Tag = D#data.tag,
    case Driver:request(Tag, Req, Timeout, DS) of
        {ok, DS1} ->
            {keep_state, pend(Tag, {request, From}, D#data{ds = DS1, tag = Tag + 1})};
        {error, _} = Error ->
            {keep_state_and_data, [{reply, From, Error}]}
    end;
connected(info, Msg, D) ->
    driver_info(Msg, connected, D);
connected(Type, Event, D) ->
    common(Type, Event, connected, D).

%%--------------------------------------------------------------------
%% disconnected: down; waits, then tries again
%%--------------------------------------------------------------------

%% @private
-spec disconnected(gen_statem:event_type(), term(), #data{}) -> gen_statem:state_function_result().
disconnected(enter, _Old, #data{id = Id, driver = Driver, ds = DS, reason = Why} = D) ->
    DS1 = Driver:disconnect(DS),
    ok = cell_hal_store:mark(Id, down, Why),
    _ = D#data.was_up andalso cell_hal_store:announce(Id, down),
    %% What the driver said of single points held for that connection only; samples
    %% with a gap are no record to latch a position from.
    Keys = maps:keys(D#data.points),
    _ = [cell_hal_store:set_fault(K, undefined) || K <- Keys],
    ok = cell_hal_store:clear_samples(Keys),
    D1 = readers_down(fail_pending(D#data{ds = DS1})),
    Wait = D#data.backoff,
    D2 = log_failure(Wait, D1),
    {keep_state, D2#data{backoff = min(2 * Wait, D#data.max_reconnect_ms), was_up = false,
                         sync = undefined, synced = [], asked = #{}, poll = undefined,
                         poll_due = false,
                         unread = #{}},
     [{state_timeout, Wait, reconnect}, {{timeout, poll}, cancel}]};
disconnected(state_timeout, reconnect, D) ->
    {next_state, connecting, D};
disconnected(info, Msg, D) ->
    driver_info(Msg, disconnected, D);
disconnected(Type, Event, D) ->
    common(Type, Event, disconnected, D).

%%--------------------------------------------------------------------
%% Every state
%%--------------------------------------------------------------------

common({call, From}, {write, _, _, _}, _, _) ->
    {keep_state_and_data, [{reply, From, {error, disconnected}}]};
common({call, From}, {request, _, _}, _, _) ->
    {keep_state_and_data, [{reply, From, {error, disconnected}}]};
common({call, From}, await_read, _, _) ->
    {keep_state_and_data, [{reply, From, ok}]};
common(cast, reconfigure, State, D) ->
    D1 = load_points(D),
    {keep_state, case State of
                     connected -> start_readback(read_new_inputs(D1));
                     _ -> D1
                 end}.

%% @private
-spec terminate(term(), atom(), #data{}) -> ok.
terminate(_Reason, State, #data{id = Id, driver = Driver, ds = DS} = D) ->
    %% Outputs stay as the PLC holds them: the HAL never writes on its own, and a PLC
    %% takes its outputs to their safe state when its watchdog sees the link gone.
    _ = Driver:disconnect(DS),
    ok = cell_hal_store:mark(Id, down, stopped),
    _ = State =:= connected andalso cell_hal_store:announce(Id, down),
    _ = fail_pending(D),
    ok.

%%====================================================================
%% Driver events
%%====================================================================

driver_info({'EXIT', _, _}, _, _) ->
    %% A closed socket's port: the driver learns of it from its own messages.
    keep_state_and_data;
driver_info(Msg, State, #data{driver = Driver, ds = DS} = D) ->
    case Driver:handle_info(Msg, DS) of
        {ok, Events, DS1} ->
            events(Events, State, D#data{ds = DS1});
        unknown ->
            cell_log:trace(D#data.source, "unexpected message ~tp", [Msg]),
            keep_state_and_data
    end.

events([], State, D) ->
    {next_state, State, D};
events([E | Es], State, D) ->
    case event(E, State, D) of
        {disconnected, D1} -> {next_state, disconnected, D1};  %% the rest is stale
        {Next, D1} -> events(Es, Next, D1)
    end.

event(connected, connecting, D) ->
    start_sync(D);
event({lost, Why}, State, D) when State =/= disconnected ->
    {disconnected, D#data{reason = Why}};
event({reply, Tag, {ok, Values}}, connecting, #data{sync = Tag} = D) ->
    sync_read(Values, D);
event({reply, Tag, {ok, Values}}, connected, #data{poll = Tag} = D) ->
    D1 = readers_done(Tag, publish(Values, fun(#pt{dir = Dir}, _) -> Dir =:= in end,
                                   D#data{poll = undefined})),
    {connected, case D1#data.poll_due of
                    true -> start_poll(D1#data{poll_due = false});
                    false -> D1
                end};
event({reply, Tag, {error, Why}}, State, #data{sync = S, poll = P} = D)
  when State =/= disconnected, Tag =:= S orelse Tag =:= P ->
    {disconnected, D#data{reason = Why}};
event({reply, Tag, Result}, State, #data{pending = P, unread = U} = D) ->
    case maps:take(Tag, P) of
        {Pending, Rest} ->
            {State, complete(Pending, Result, D#data{pending = Rest})};
        error ->
            case State =:= connected andalso lists:member(Tag, maps:values(U)) of
                true -> read_back(Tag, Result, D);
                false -> {State, D}
            end
    end;
event({push, Values}, connected, D) ->
    {connected, publish(Values, fun(#pt{dir = Dir}, _) -> Dir =:= in end, D)};
event({samples, PerPoint}, State, D) when State =/= disconnected ->
    Known = [{K, Ss} || {K, [_ | _] = Ss} <- PerPoint, is_map_key(K, D#data.points)],
    lists:foreach(fun({K, Ss}) -> cell_hal_store:add_samples(K, Ss, D#data.samples_kept) end,
                  Known),
    case State of
        connected ->
            %% Every change, in the device's order: a bit that rose and fell between
            %% two notifications is seen rising by subscribers and watches.
            Each = [{K, V} || {K, Ss} <- Known, {_, V} <- Ss],
            {connected, publish(Each, fun(#pt{dir = Dir}, _) -> Dir =:= in end, D)};
        _ ->
            {State, D}
    end;
event({faults, Faults}, State, D) when State =/= disconnected ->
    Cleared = [K || {K, ok} <- Faults, fault(K, ok, D),
                    is_map_key(K, D#data.points)],
    _ = [fault(K, Why, D) || {K, Why} <- Faults, Why =/= ok],
    %% An input that can be used again is news to its subscribers even if its value
    %% is the one it had: they are told the value it has, or the next one read. An
    %% output shows what the device holds, as after a connect.
    {Inputs, Outputs} = lists:partition(
                          fun(K) -> (maps:get(K, D#data.points))#pt.dir =:= in end, Cleared),
    Unknown = [K || K <- Inputs, not tell_value(K)],
    D1 = forget_values(Unknown, D),
    case State =:= connected andalso Outputs =/= [] of
        true -> {connected, start_readback(forget_values(Outputs, D1))};
        false -> {State, D1}
    end;
event(_, State, D) ->
    %% An answer for an earlier connection.
    {State, D}.

%% The first read after connecting: every point, so that nothing is presented as fresh
%% that was not read on this connection.
start_sync(#data{points = Pts} = D) ->
    sync(maps:to_list(Pts), D#data{synced = [], asked = #{}}).

sync(Points, D) ->
    case plan(Points, D) of
        {_, 0, 0} ->
            {connected, go_up(D)};
        {Plan, _, _} ->
            {Tag, D1} = read(Plan, D),
            Asked = maps:merge(D#data.asked, maps:from_keys([K || {K, _} <- Points], true)),
            {connecting, D1#data{sync = Tag, asked = Asked}}
    end.

%% A part of the first read answered: its values stored (readers see them once the
%% connection is up), then the points bound since it was planned read too, before the
%% connection goes up.
sync_read(Values, D) ->
    {Changed, D1} = store(Values, fun(_, _) -> true end, D#data{sync = undefined}),
    D2 = D1#data{synced = D1#data.synced ++ Changed},
    #data{points = Pts, asked = Asked} = D2,
    case [P || {K, _} = P <- maps:to_list(Pts), not is_map_key(K, Asked)] of
        [] -> {connected, go_up(D2)};
        New -> sync(New, D2)
    end.

go_up(#data{id = Id, points = Pts, synced = Changed} = D) ->
    D1 = D#data{synced = [], asked = #{}},
    ok = cell_hal_store:mark(Id, up, undefined),
    ChangedKeys = maps:from_list(Changed),
    lists:foreach(fun({K, V}) -> cell_hal_store:notify(K, V) end, Changed),
    %% Watches placed while down were not fired; an unchanged value may satisfy them.
    maps:foreach(fun(K, #pt{}) when is_map_key(K, ChangedKeys) -> ok;
                    (K, #pt{}) ->
                         case maps:get(K, D1#data.points) of
                             #pt{value = {ok, V}} -> cell_hal_store:fire_watches(K, V);
                             #pt{value = none} -> ok
                         end
                 end, Pts),
    ok = cell_hal_store:announce(Id, up),
    Pushed = case D#data.pushed of
                 0 -> "";
                 N -> [", ", plural(N, "input"), " by notification"]
             end,
    cell_log:notice(D#data.source, "connection to ~s (~s) up: ~s, ~s a poll~s",
                    [Id, D#data.endpoint, plural(maps:size(Pts), "point"),
                     plural(D#data.requests, "request"), Pushed]),
    D2 = release_ended(D1),
    %% Outputs the first read gave no value of are read back now.
    start_readback(D2#data{backoff = D#data.reconnect_ms, reason = undefined, was_up = true,
                           logged = undefined, unread = #{}}).

%% The outputs whose force a restart of the HAL's server ended are written back to
%% the value the cell wants, first of all (see cell_hal_force), and said so.
release_ended(#data{points = Pts} = D) ->
    maps:fold(fun(Key, #pt{dir = out}, Acc) ->
                      release_ended(Key, cell_hal_force:take_ended(Key), Acc);
                 (_, #pt{}, Acc) ->
                      Acc
              end, D, Pts).

release_ended(_Key, no, D) ->
    D;
release_ended(Key, {ok, {ok, V}}, D) ->
    cell_log:warning(D#data.source, "force of ~s ended: the IO service restarted; written "
                     "back to ~s, the value the cell wants", [point_name(Key), value_text(Key, V, D)]),
    case queue_write(Key, V, async, undefined, D) of
        {ok, D1} -> D1;
        {error, _} -> D
    end;
release_ended(Key, {ok, none}, D) ->
    cell_log:warning(D#data.source, "force of ~s ended: the IO service restarted; no value "
                     "of the cell's is known for it, so it keeps the one it has", [point_name(Key)]),
    D.

start_poll(#data{requests = 0} = D) ->
    %% Device notifications feed every input: nothing to poll, but inputs never read
    %% (a group added while up) are read once, which sets their notifications up.
    case unread_inputs(D) of
        true -> read_inputs(D);
        false -> D
    end;
start_poll(D) ->
    read_inputs(D).

read_inputs(#data{plan = Plan} = D) ->
    {Tag, D1} = read(Plan, D),
    D1#data{poll = Tag}.

%% The inputs of a group added while up are read at once, not at the next poll
%% period; after the poll in flight if there is one (it reads the plan of before).
read_new_inputs(#data{poll = Polling} = D) ->
    case unread_inputs(D) of
        true when Polling =:= undefined -> start_poll(D);
        true -> D#data{poll_due = true};
        false -> D
    end.

%% The poll of tag `Tag' answered: those waiting for it (or an earlier one) are told.
readers_done(_Tag, #data{readers = []} = D) ->
    D;
readers_done(Tag, #data{readers = Readers} = D) ->
    {Done, Waiting} = lists:partition(fun({_, T}) -> T =< Tag end, Readers),
    _ = [gen_statem:reply(From, ok) || {From, _} <- Done],
    D#data{readers = Waiting}.

%% Those waiting for a poll are told when the connection goes down: its first read
%% after connecting reads every input.
readers_down(D) ->
    _ = [gen_statem:reply(From, ok) || {From, _} <- D#data.readers],
    D#data{readers = []}.

unread_inputs(#data{points = Pts}) ->
    lists:any(fun(#pt{dir = Dir, value = V}) -> Dir =:= in andalso V =:= none end,
              maps:values(Pts)).


%% The answer to reading back outputs: only those no write has commanded since count.
read_back(Tag, {ok, Values}, #data{unread = U} = D) ->
    D1 = publish(Values, fun(#pt{dir = Dir}, K) -> Dir =:= out andalso maps:get(K, U, none) =:= Tag end,
                 D),
    {connected, D1#data{unread = maps:filter(fun(_, T) -> T =/= Tag end, U)}};
read_back(_Tag, {error, Why}, D) ->
    {disconnected, D#data{reason = Why}}.

%% Outputs of a group added while up are read once, so they show what the device holds;
%% each group change reads the outputs it brought, whatever reads are in flight.
start_readback(#data{points = Pts, unread = U} = D) ->
    New = maps:filter(fun(K, #pt{dir = Dir, value = V}) ->
                              Dir =:= out andalso V =:= none andalso not is_map_key(K, U)
                      end, Pts),
    case plan(maps:to_list(New), D) of
        {_, 0, 0} ->
            D;
        {Plan, _, _} ->
            {Tag, D1} = read(Plan, D),
            D1#data{unread = maps:merge(U, maps:map(fun(_, _) -> Tag end, New))}
    end.

read(Plan, #data{driver = Driver, ds = DS, tag = Tag} = D) ->
    {ok, DS1} = Driver:read(Tag, Plan, DS),
    {Tag, D#data{ds = DS1, tag = Tag + 1}}.

%% A plan, the exchanges one read of it takes, and how many of its points device
%% notifications feed (a read of those alone sends nothing, but is still a read).
plan(Points, #data{driver = Driver, ds = DS}) ->
    {Plan, #{requests := N} = Info} =
        Driver:plan([#{key => K, dir => Dir, type => T, field => F}
                     || {K, #pt{dir = Dir, type = T, field = F}} <- Points], DS),
    {Plan, N, maps:get(pushed, Info, 0)}.

%%====================================================================
%% Values
%%====================================================================

%% Stores the values that changed among those `Keep' accepts; returns them.
store(Values, Keep, #data{points = Pts} = D) ->
    {Changed, Pts1} =
        lists:foldl(
          fun({K, V}, {Acc, Ps} = Unchanged) ->
                  case Ps of
                      #{K := #pt{value = {ok, V}}} ->
                          Unchanged;
                      #{K := Pt} ->
                          case Keep(Pt, K) andalso cell_hal_store:put_value(K, V) of
                              true -> {[{K, V} | Acc], Ps#{K := Pt#pt{value = {ok, V}}}};
                              false -> Unchanged
                          end;
                      #{} ->
                          Unchanged
                  end
          end, {[], Pts}, Values),
    {lists:reverse(Changed), D#data{points = Pts1}}.

publish(Values, Keep, D) ->
    {Changed, D1} = store(Values, Keep, D),
    lists:foreach(fun({K, V}) -> cell_hal_store:notify(K, V) end, Changed),
    D1.

%% Points bound to this connection, keeping the values already known.
load_points(#data{id = Id, points = Old} = D) ->
    Pts = maps:from_list(
            [{K, #pt{dir = Dir, type = T, field = F, value = known_value(K, Old)}}
             || #hal_point{key = K, dir = Dir, type = T, field = F}
                    <- cell_hal_store:points_of_conn(Id)]),
    Inputs = [P || {_, #pt{dir = in}} = P <- maps:to_list(Pts)],
    D1 = D#data{points = Pts},
    {Plan, N, Pushed} = plan(Inputs, D1),
    D1#data{plan = Plan, requests = N, pushed = Pushed}.

known_value(K, Old) ->
    case Old of
        #{K := #pt{value = V}} -> V;
        #{} ->
            case cell_hal_store:value(K) of
                {ok, #hal_value{value = V}} -> V;
                error -> none
            end
    end.

%%====================================================================
%% Faults of single points
%%====================================================================

%% Marks a point unusable (`Why', the driver's reason) or usable again (`ok'), logged
%% when that changes; true when it changed.
fault(K, Why, #data{driver = Driver} = D) ->
    Text = case Why of
               ok -> undefined;
               _ -> iolist_to_binary(Driver:format_reason(Why))
           end,
    case cell_hal_store:set_fault(K, Text) of
        true when Why =:= ok ->
            cell_log:notice(D#data.source, "~ts can be used again", [point_text(K)]),
            true;
        true ->
            cell_log:error(D#data.source, "~ts cannot be used: ~ts", [point_text(K), Text]),
            true;
        false ->
            false
    end.

%% Tells a point's subscribers the value it has, if it has one.
tell_value(K) ->
    case cell_hal_store:value(K) of
        {ok, #hal_value{value = {ok, V}}} ->
            ok = cell_hal_store:notify(K, V),
            true;
        _ ->
            false
    end.

%% An output's value is read from the device again.
forget_values(Keys, #data{points = Pts} = D) ->
    D#data{points = lists:foldl(fun(K, Acc) -> Acc#{K := (maps:get(K, Acc))#pt{value = none}} end,
                                Pts, Keys)}.

%% A point as the IO page shows it: "general.start_button (A1.01.06 Start button)".
point_text(K) ->
    case cell_hal_store:point(K) of
        {ok, #hal_point{address = A, caption = C}} ->
            [point_name(K), " (", A, " ", C, ")"];
        error ->
            point_name(K)
    end.

%%====================================================================
%% Writes and requests
%%====================================================================

queue_write(Key, V, Mode, From, #data{points = Pts, driver = Driver, ds = DS, tag = Tag} = D) ->
    case Pts of
        #{Key := #pt{dir = out, type = T, field = F} = Pt} ->
            case cell_hal_type:check(T, V) of
                {ok, V1} ->
                    {ok, DS1} = Driver:write(Tag, #{key => Key, dir => out, type => T,
                                                    field => F}, V1, DS),
                    Waiter = case Mode of async -> async; sync -> From end,
                    D1 = pend(Tag, {write, Key, V1, Waiter},
                              D#data{ds = DS1, tag = Tag + 1,
                                     unread = maps:remove(Key, D#data.unread)}),
                    {ok, commanded(Key, V1, Pt, D1)};
                error ->
                    {error, {bad_value, V}}
            end;
        #{Key := #pt{dir = in}} ->
            {error, not_an_output};
        #{} ->
            {error, unknown_point}
    end.

%% The commanded value is what a read of the output returns from now on.
commanded(_Key, V, #pt{value = {ok, V}}, D) ->
    D;
commanded(Key, V, Pt, #data{points = Pts} = D) ->
    _ = cell_hal_store:put_value(Key, V) andalso cell_hal_store:notify(Key, V),
    D#data{points = Pts#{Key := Pt#pt{value = {ok, V}}}}.

pend(Tag, What, #data{pending = P} = D) ->
    D#data{pending = P#{Tag => What}}.

complete({write, _, _, async}, ok, D) ->
    D;
complete({write, Key, V, async}, {error, Why}, D) ->
    cell_log:error(D#data.source, "writing ~s := ~s on ~s failed: ~s",
                   [point_name(Key), value_text(Key, V, D), D#data.id, why_text(Why, D)]),
    D;
complete({write, _, _, From}, Result, D) ->
    gen_statem:reply(From, Result),
    D;
complete({request, From}, Result, D) ->
    gen_statem:reply(From, Result),
    D.

%% Whatever was in flight when the connection went down has no answer.
fail_pending(#data{pending = P} = D) ->
    maps:foreach(fun(_, {write, Key, V, async}) ->
                         cell_log:warning(D#data.source,
                                          "~s := ~s may not have reached ~s: the connection "
                                          "went down before the PLC confirmed it",
                                          [point_name(Key), value_text(Key, V, D), D#data.id]);
                    (_, {write, _, _, From}) -> gen_statem:reply(From, {error, disconnected});
                    (_, {request, From}) -> gen_statem:reply(From, {error, disconnected})
                 end, P),
    D#data{pending = #{}}.

%%====================================================================
%% Words for operators
%%====================================================================

log_failure(Wait, #data{id = Id, endpoint = Ep, reason = Why, was_up = WasUp, logged = Last} = D) ->
    Text = why_text(Why, D),
    Retry = retry_text(Wait),
    if
        WasUp ->
            cell_log:warning(D#data.source, "connection to ~s (~s) lost: ~s; retrying in ~s",
                             [Id, Ep, Text, Retry]);
        Last =:= Why ->
            cell_log:debug(D#data.source, "still no connection to ~s (~s): ~s; retrying in ~s",
                           [Id, Ep, Text, Retry]);
        true ->
            cell_log:warning(D#data.source, "cannot connect to ~s (~s): ~s; retrying in ~s",
                             [Id, Ep, Text, Retry])
    end,
    D#data{logged = Why}.

why_text(Why, #data{driver = Driver}) ->
    reason_text(Driver, Why).

%% @doc Why a connection is down, in an operator's words.
-spec reason_text(module(), term()) -> iodata().
reason_text(_, {no_connection, Ms}) ->
    io_lib:format("no connection within ~b ms", [Ms]);
reason_text(_, {no_first_read, Ms}) ->
    io_lib:format("the first read of the IO image took more than ~b ms", [Ms]);
reason_text(_, starting) ->
    "not connected yet";
reason_text(_, restarted) ->
    "reconnecting after a restart of the connection's worker";
reason_text(_, worker_gone) ->
    "the connection's worker is gone; it is being started again";
reason_text(_, stopped) ->
    "the connection was stopped";
reason_text(Driver, Why) ->
    Driver:format_reason(Why).

retry_text(Ms) when Ms < 1000 -> [integer_to_list(Ms), " ms"];
retry_text(Ms) when Ms rem 1000 =:= 0 -> [integer_to_list(Ms div 1000), " s"];
retry_text(Ms) -> [io_lib:format("~.1f", [Ms / 1000]), " s"].

plural(1, One) -> ["1 ", One];
plural(N, One) -> [integer_to_list(N), $\s, One, $s].

point_name({G, P}) -> [atom_to_list(G), $., atom_to_list(P)].

value_text(Key, V, #data{points = Pts}) ->
    #{Key := #pt{type = T}} = Pts,
    cell_hal_type:format(T, V).
