%% @doc The HAL (seed 000 §4): tasks read and write IO points by name and never talk
%% to a driver. A point is addressed `{Group, Point}': a configured group instance and a
%% name its group module declares ({@link cell_hal_group}).
%%
%% ```
%% ok = cell_hal:add_connection(#{id => plc1, driver => cell_hal_modbus,
%%                                opts => #{host => "10.0.0.5", poll_ms => 20}}),
%% ok = cell_hal:add_group(#{id => general, module => general_io, connection => plc1,
%%                           opts => #{base => 0}}),
%% {ok, true} = cell_hal:read(general, start_button),
%% ok = cell_hal:write(general, start_button_light, true),
%% {ok, Ref} = cell_hal:watch(general, door_closed, {eq, true}),
%% receive {cell_hal_watch, Ref, true} -> closed end.
%% '''
%%
%% Reads come straight from a table, without a process hop: an input only while its
%% connection is up, so a stale input is never presented as fresh. A connection whose
%% worker is gone (killed, not started again yet) is down, whatever its worker last
%% marked. Writes are checked at once and queued to the connection's worker in order;
%% `write/3' never waits for the device. Waiting is a subscription, never polling.
%%
%% Messages:
%% <ul>
%% <li>`{cell_hal_watch, Ref, Value}' once, when a watched condition holds;</li>
%% <li>`{cell_hal, {Group, Point}, Value}' on every change of a subscribed point (a
%%   change of an output is a new commanded value or a value read back after a
%%   reconnect);</li>
%% <li>`{cell_hal_fault, {Group, Point}, Why}' to the same subscribers when the driver
%%   reports the point unusable (`Why' in words: reads give `{error, {unavailable,
%%   Why}}'), and `{cell_hal_fault, {Group, Point}, cleared}' when it is usable again
%%   (a read gives its value);</li>
%% <li>`{cell_hal_conn, ConnId, up | down}' when a connection goes up (after its first
%%   complete read) or down (for a worker killed, when its successor starts).</li>
%% </ul>
%% Subscriptions and watches end when their process exits.
%%
%% <b>While the HAL's processes restart.</b> A connection's worker may be killed and
%% started again by its supervisor, and the server with every worker (`rest_for_one');
%% what was subscribed and watched lives in tables that outlive them. A request of the
%% IO API that finds the process serving it gone, sees it die, or waits for it in vain
%% gets what a lost connection gives: `{error, disconnected}' (a task raises "IO
%% connection lost" and goes on after Retry), never an exit; so does a change of the
%% configuration (adding or removing a connection or a group) while the server is
%% away. Cancelling a watch and unsubscribing touch only the caller's own rows,
%% without the server. A process that found the server away asks for
%% `{cell_hal_back, Ref}' with {@link notify_back/0} and subscribes again when it
%% comes: the monitor, the units and the inspection blocks do so.
%%
%% <b>Time-stamped samples</b> (seed 000 §2.3.7). A driver with device-side
%% notifications (ADS) stamps each sample with the PLC's time, the time of the PLC
%% cycle that took it. The HAL keeps the newest samples of each such point, so a task
%% can find what happened between two moments more precisely than any read could
%% tell it: the laser-beam latch reads the sensor's and the axis position's samples
%% and takes the position at the sensor's edge.
%% ```
%% Since = os:system_time(nanosecond),      %% the PLC's clock, on the same IPC
%% ok = cell_hal:write(tool_setter, axis_start, true),
%% {ok, Ref} = cell_hal:watch(tool_setter, axis_done, {eq, true}),
%% receive {cell_hal_watch, Ref, true} -> ok end,
%% {ok, Beam} = cell_hal:samples(tool_setter, beam, Since),
%% {ok, Pos} = cell_hal:samples(tool_setter, axis_pos, Since),
%% {ok, #{position := Diameter}} =
%%     cell_hal_ads_latch:position_at_edge(Beam, Pos, #{edge => rising, from => Since}).
%% '''
-module(cell_hal).

-include("cell_hal.hrl").

-export([add_connection/1, remove_connection/1, add_group/1, remove_group/1]).
-export([connections/0, groups/0, points/1, describe/2, connection_of/1]).
-export([read/2, write/3, write_sync/4, watch/3, cancel_watch/1, subscribe/2,
         unsubscribe/2]).
-export([subscribe_connection/1, unsubscribe_connection/1, status/1, info/1]).
-export([notify_back/0]).
-export([request/3, samples/3]).

-export_type([connection_spec/0, group_spec/0, point_info/0, conn_info/0]).

-type connection_spec() :: #{id := atom(), driver := module(), opts => map()}.
-type group_spec() :: #{id := atom(), module := module(), connection := atom(),
                        opts => map()}.
-type point_info() :: #{name := atom(), group := atom(), connection := atom(),
                        dir := in | out, type := cell_hal_type:type(),
                        address := binary(), caption := binary(), unit := binary(),
                        field := term()}.
-type conn_info() :: #{status := up | down, driver := module(), endpoint := binary(),
                       since := integer() | undefined, reason := binary(),
                       groups := [atom()],
                       faults := [#{point := {atom(), atom()}, reason := binary()}]}.
-type error(Why) :: {error, Why}.

%% How long `write/3' may take to hand a write to the worker (it is never blocked on
%% the device, so this only bounds a worker that is itself stuck).
-define(QUEUE_TIMEOUT, 5000).
%% How long `add_group/1' waits for a new group's first read at most: a worker whose
%% device does not answer has the connection down well before.
-define(READ_TIMEOUT, 30000).

%% The behaviours of the processes serving the IO API: the server, the workers.
-define(HAL_PROCESS(B), (B =:= gen_server orelse B =:= gen_statem)).

%%====================================================================
%% Configuration
%%====================================================================

%% @doc Adds a connection to a PLC and starts its worker. `opts' holds the driver's
%% options and the worker's: `poll_ms' (default 50), `reconnect_ms' (first wait after
%% a failure, default 500), `max_reconnect_ms' (default 30000), `connect_timeout_ms'
%% (for connecting and the first read, default 5000), `samples_kept' (time-stamped
%% samples kept of each point fed by device notifications, default 1000; see
%% {@link samples/3}).
-spec add_connection(connection_spec()) ->
          ok | error({bad_option, atom()} | {already_exists, atom()} | {worker, term()}
                     | disconnected).
add_connection(Spec) ->
    server({add_connection, Spec}).

%% @doc Removes a connection once no group is bound to it; its worker closes it.
-spec remove_connection(atom()) ->
          ok | error(unknown_connection | {in_use, [atom()]} | disconnected).
remove_connection(Id) ->
    server({remove_connection, Id}).

%% @doc Adds a group instance bound to a connection: its module lists the points for
%% its options, and the connection's driver checks every field first. On a connection
%% that is up it returns once the group's inputs have been read (or the connection
%% went down meanwhile), so that none reads as `not_yet_read' after it; on one that is
%% down the connection's first read after connecting reads them before it comes up.
-spec add_group(group_spec()) ->
          ok | error({bad_option, atom()} | {already_exists, atom()}
                     | {bad_point, term(), term()} | {bad_group, term()} | disconnected).
add_group(#{connection := Conn} = Spec) ->
    case server({add_group, Spec}) of
        ok ->
            case cell_hal_store:up_worker(Conn) of
                {ok, Pid} ->
                    %% The group is there whatever this wait ends with (the worker
                    %% gone: its successor reads every point before it comes up).
                    _ = served(fun() -> cell_hal_worker:await_read(Pid, ?READ_TIMEOUT) end,
                               timeout),
                    ok;
                error ->
                    ok
            end;
        Error ->
            Error
    end;
add_group(Spec) ->
    server({add_group, Spec}).

%% @doc Removes a group instance; its subscriptions and watches end.
-spec remove_group(atom()) -> ok | error(unknown_group | disconnected).
remove_group(Id) ->
    server({remove_group, Id}).

%% @doc The ids of the configured connections.
-spec connections() -> [atom()].
connections() ->
    lists:sort([Id || #hal_conn{id = Id} <- cell_hal_store:conns()]).

%% @doc The ids of the configured IO group instances.
-spec groups() -> [atom()].
groups() ->
    lists:sort([Id || #hal_group{id = Id} <- cell_hal_store:groups()]).

%% @doc A group's points as its IO page shows them: in the order its module lists them.
-spec points(atom()) -> {ok, [point_info()]} | error(unknown_group).
points(Group) ->
    case cell_hal_store:group(Group) of
        {ok, _} -> {ok, [info_of(P) || P <- lists:keysort(#hal_point.seq,
                                                          cell_hal_store:points_of_group(Group))]};
        error -> {error, unknown_group}
    end.

%% @doc One point's description.
-spec describe(atom(), atom()) -> {ok, point_info()} | error(unknown_point).
describe(Group, Point) ->
    case cell_hal_store:point({Group, Point}) of
        {ok, P} -> {ok, info_of(P)};
        error -> {error, unknown_point}
    end.

%% @doc The connection a group instance is bound to.
-spec connection_of(atom()) -> {ok, atom()} | error(unknown_group).
connection_of(Group) ->
    case cell_hal_store:group(Group) of
        {ok, #hal_group{conn = Conn}} -> {ok, Conn};
        error -> {error, unknown_group}
    end.

info_of(#hal_point{key = {G, N}, conn = C, dir = D, type = T, declared = F, address = A,
                   caption = Cap, unit = U}) ->
    #{name => N, group => G, connection => C, dir => D, type => T, address => A,
      caption => Cap, unit => U, field => F}.

%%====================================================================
%% IO
%%====================================================================

%% @doc A point's value, from the table (no process hop). An input reads
%% `disconnected' while its connection is down and `not_yet_read' before the first
%% read of its group; an output reads its last commanded value (or the value read back
%% from the device after a (re)connect). A point the driver cannot read or write (a
%% symbol the PLC lacks, an address a Modbus PLC refuses) reads `{unavailable, Why}',
%% Why in an operator's words; the rest of its group and the connection go on.
-spec read(atom(), atom()) ->
          {ok, cell_hal_type:value()}
        | error(disconnected | unknown_point | not_yet_read | {unavailable, binary()}).
read(Group, Point) ->
    cell_hal_store:read({Group, Point}).

%% @doc Commands an output. The value is checked against the point's type at once and
%% queued to the connection's worker, which writes in order; this returns without
%% waiting for the device (a write the device then refuses is logged). A worker that
%% is restarting, or does not take the write within 5 s, is a lost connection:
%% `disconnected'.
-spec write(atom(), atom(), cell_hal_type:value()) ->
          ok | error(unknown_point | not_an_output | {bad_value, term()} | disconnected
                     | {unavailable, binary()}).
write(Group, Point, Value) ->
    command({Group, Point}, Value, {async, ?QUEUE_TIMEOUT}).

%% @doc Commands an output and waits until the device confirmed it, at most `Timeout'
%% ms. After `{error, timeout}' the write may still reach the device.
-spec write_sync(atom(), atom(), cell_hal_type:value(), timeout()) ->
          ok | error(unknown_point | not_an_output | {bad_value, term()} | disconnected
                     | {unavailable, binary()} | timeout | term()).
write_sync(Group, Point, Value, Timeout) ->
    command({Group, Point}, Value, {sync, Timeout}).

command(Key, Value, Mode) ->
    case cell_hal_store:value(Key) of
        {ok, #hal_value{dir = out, fault = Why}} when is_binary(Why) ->
            {error, {unavailable, Why}};
        {ok, #hal_value{dir = out, type = T, conn = C}} ->
            case cell_hal_type:check(T, Value) of
                {ok, V} ->
                    %% A forced output keeps the value for its release.
                    case cell_hal_force:held(Key, V) orelse cell_hal_store:up_worker(C) of
                        true ->
                            ok;
                        {ok, Pid} ->
                            Lapse = case Mode of
                                        {async, _} -> disconnected;
                                        {sync, _} -> timeout
                                    end,
                            served(fun() -> cell_hal_worker:write(Pid, Key, V, Mode) end,
                                   Lapse);
                        error ->
                            {error, disconnected}
                    end;
                error ->
                    {error, {bad_value, Value}}
            end;
        {ok, #hal_value{}} ->
            {error, not_an_output};
        error ->
            {error, unknown_point}
    end.

%% @doc Sends `{cell_hal_watch, Ref, Value}' once, when the point's value satisfies
%% `Cond' — at once if it already does. An input satisfies nothing while its
%% connection is down. A point the driver cannot serve (see {@link read/2}) ends the
%% watch instead, at once or when that happens: `{cell_hal_unavailable, Ref, Why}',
%% Why in an operator's words, and no value follows. A condition that cannot hold for
%% the point's type is refused.
%% While the server restarts (with the connections' workers) a watch cannot be placed:
%% `{error, disconnected}'.
-spec watch(atom(), atom(), cell_hal_type:condition()) ->
          {ok, reference()} | error(unknown_point | {bad_condition, term()} | disconnected).
watch(Group, Point, Cond) ->
    Key = {Group, Point},
    case cell_hal_store:value(Key) of
        {ok, #hal_value{type = T}} ->
            case cell_hal_type:check_cond(T, Cond) of
                {ok, C} -> server({watch, Key, C, self()});
                error -> {error, {bad_condition, Cond}}
            end;
        error ->
            {error, unknown_point}
    end.

%% @doc Cancels a watch: `true' if it had not fired (no message will come), `false'
%% if it had (its message is in the mailbox or on its way). It takes the watch's claim
%% as the worker firing it would, so it needs no process and works while the server
%% restarts.
-spec cancel_watch(reference()) -> boolean().
cancel_watch(Ref) ->
    cell_hal_store:cancel_watch(Ref).

%% @doc Sends `{cell_hal, {Group, Point}, Value}' to the caller on every change, and
%% `{cell_hal_fault, {Group, Point}, Why | cleared}' when the point becomes unusable
%% or usable again.
%% `{error, disconnected}' while the server restarts.
-spec subscribe(atom(), atom()) -> ok | error(unknown_point | disconnected).
subscribe(Group, Point) ->
    server({subscribe, {Group, Point}, self()}).

%% @doc Ends the caller's subscription to a point (see {@link subscribe/2}).
-spec unsubscribe(atom(), atom()) -> ok.
unsubscribe(Group, Point) ->
    cell_hal_store:delete_sub({Group, Point}, self()).

%%====================================================================
%% Connectivity
%%====================================================================

%% @doc Sends `{cell_hal_conn, ConnId, up | down}' to the caller on every change from
%% now on, and returns the status now. A message right after may repeat it.
%% `{error, disconnected}' while the server restarts: nothing was subscribed.
-spec subscribe_connection(atom()) -> {ok, up | down} | error(unknown_connection | disconnected).
subscribe_connection(Conn) ->
    server({subscribe_connection, Conn, self()}).

%% @doc Ends the caller's subscription to a connection's status (see
%% {@link subscribe_connection/1}).
-spec unsubscribe_connection(atom()) -> ok.
unsubscribe_connection(Conn) ->
    cell_hal_store:delete_conn_sub(Conn, self()).

%% @doc Sends `{cell_hal_back, Ref}' to the caller once, when the HAL's server takes
%% requests again: for a process whose subscription (or change of the configuration)
%% got `{error, disconnected}' because the server was away, so that it asks again on
%% that message rather than by polling. If the server is there now the message comes
%% at once; if it is away, from the next server as it starts. The wait is kept in a
%% table that outlives the server.
-spec notify_back() -> reference().
notify_back() ->
    Ref = make_ref(),
    ok = cell_hal_store:add_waiter(Ref, self()),
    %% Recorded first, looked for after: a server that starts from here on finds the
    %% record; one found here is asked to answer (if it dies first, its successor
    %% finds the record).
    _ = case whereis(cell_hal_server) of
            undefined -> ok;
            Pid -> Pid ! {waiting, Ref}
        end,
    Ref.

%% @doc Whether a connection is up (its inputs are fresh). A connection whose worker
%% is gone (killed, not started again yet) is down.
-spec status(atom()) -> up | down | error(unknown_connection).
status(Conn) ->
    case cell_hal_store:conn(Conn) of
        {ok, C} -> (cell_hal_store:as_seen(C))#hal_conn.status;
        error -> {error, unknown_connection}
    end.

%% @doc A connection for the operator's panel: status, since when (system time, ms),
%% why it is down in words, where it goes, the groups bound to it. A connection whose
%% worker is gone is down; its `since' is then when it was last marked up (the moment
%% the worker died is not recorded).
-spec info(atom()) -> {ok, conn_info()} | error(unknown_connection).
info(Conn) ->
    case cell_hal_store:conn(Conn) of
        {ok, C} ->
            #hal_conn{status = Status, driver = Driver, endpoint = Ep, since = Since,
                      reason = Why} = cell_hal_store:as_seen(C),
            Reason = case Status of
                         up -> <<>>;
                         down -> iolist_to_binary(cell_hal_worker:reason_text(Driver, Why))
                     end,
            Faults = [#{point => K, reason => Text}
                      || {K, Text} <- cell_hal_store:faults_of_conn(Conn)],
            {ok, #{status => Status, driver => Driver, endpoint => Ep, since => Since,
                   reason => Reason, groups => cell_hal_store:groups_of(Conn),
                   faults => Faults}};
        error ->
            {error, unknown_connection}
    end.

%% @doc A raw request of the connection's protocol, for diagnostics and functions the
%% HAL does not model (Modbus: a {@link cell_hal_modbus_codec:request()}, or
%% `{Unit, Request}' for another unit). Only while the connection is up.
-spec request(atom(), term(), pos_integer()) -> {ok, term()} | error(term()).
request(Conn, Request, Timeout) when is_integer(Timeout), Timeout > 0 ->
    case cell_hal_store:up_worker(Conn) of
        {ok, Pid} ->
            served(fun() -> cell_hal_worker:request(Pid, Request, Timeout, Timeout + 1000) end,
                   timeout);
        error ->
            {error, disconnected}
    end.

%% @doc The time-stamped samples of a point fed by device notifications, from `Since'
%% on (nanoseconds since 1970 in the PLC's clock, as the samples are stamped): the
%% sample in force at `Since' (the last stamped before it), then every later one,
%% oldest first. Errors: `disconnected' while the connection is down; `not_sampled'
%% for a point no notification feeds; `{not_kept, Oldest}' when the value at `Since'
%% is unknown because the oldest sample kept is stamped later (the connection was down
%% meanwhile, which forgets the samples, or more came than `samples_kept').
-spec samples(atom(), atom(), integer()) ->
          {ok, [{integer(), cell_hal_type:value()}]}
        | error(unknown_point | disconnected | not_sampled | {not_kept, integer()}).
samples(Group, Point, Since) when is_integer(Since) ->
    Key = {Group, Point},
    case cell_hal_store:value(Key) of
        {ok, #hal_value{conn = C}} ->
            Result = cell_hal_store:samples(Key, Since),
            %% Going down forgets samples: a result taken meanwhile may lack some.
            case cell_hal_store:is_up(C) of
                true -> Result;
                false -> {error, disconnected}
            end;
        error ->
            {error, unknown_point}
    end.

%% A request of the IO API to the server. It restarts with the connections' workers
%% (rest_for_one), so its absence is theirs: a lost connection to the caller.
server(Request) ->
    served(fun() -> cell_hal_server:call(Request) end, disconnected).

%% The one place where a HAL process that is not there to answer becomes what a lost
%% connection gives: gone before the call (noproc), dying during it (killed, shutdown,
%% normal, a crash), or not answering in time. `Lapse' is what no answer in time means:
%% `disconnected' where the process only queues (a stuck or restarting process),
%% `timeout' where the device's confirmation is awaited.
served(Call, Lapse) ->
    try
        Call()
    catch
        exit:{timeout, {Behaviour, call, _}} when ?HAL_PROCESS(Behaviour) ->
            {error, Lapse};
        exit:{_Gone, {Behaviour, call, _}} when ?HAL_PROCESS(Behaviour) ->
            {error, disconnected}
    end.
