%% @doc The behaviour of a PLC driver: what a HAL worker ({@link cell_hal_worker}) needs
%% from a protocol. A driver is a callback module whose state lives inside the worker
%% process that owns the connection; it never blocks that process. Everything a driver
%% does with the device is asynchronous: the worker asks (connect, read, write,
%% request), the driver sends, and the answers come back as messages to the worker,
%% which hands each one to {@link handle_info/2}; the driver turns them into events.
%%
%% <b>Reading an image.</b> When the configured points change the worker calls
%% `plan/2' with every point to poll; the driver decides how to read them with the
%% fewest exchanges its protocol allows (Modbus: block reads of adjacent addresses;
%% ADS: one sum read of many symbols, or device-side notifications). `read/3' starts
%% one complete read of a plan, however many requests that takes; it ends with exactly
%% one `{reply, Tag, {ok, Values}}' holding a value for every point of the plan, or
%% `{reply, Tag, {error, Why}}', or `{lost, Why}'. A driver with device-side
%% notifications sets them up in `read/3' (it counts the points they feed as
%% `pushed' in its plan, so a plan of such points alone is still read once) and
%% reports later changes as `{push, Values}' or, stamped with the device's time,
%% `{samples, PerPoint}' events; its first `read/3' still answers with the full image,
%% so the worker knows when every value is fresh.
%%
%% <b>Single points.</b> A point the driver cannot serve while the connection works (a
%% PLC symbol that is missing, or of another type than configured; an address a Modbus
%% PLC refuses) is reported as `{faults, [{Key, Why}]}' and left out of the values, and
%% as `{faults, [{Key, ok}]}' once it can be served again; the rest of the plan is read
%% as usual. A read in which not one point could be served for another reason (the
%% device did not answer) is an `{error, Why}', and so is one the driver's own
%% settings count as a lost connection (Modbus: `refused_group => disconnect').
%%
%% <b>Writing.</b> `write/4' queues one output write; writes reach the device in the
%% order they were queued. A driver may merge queued writes into one exchange (an ADS
%% sum write) as long as their order is kept. Each ends with `{reply, Tag, ok}' or
%% `{reply, Tag, {error, Why}}'.
%%
%% <b>Time.</b> Every exchange has a deadline the driver keeps with its own timer
%% messages; a reply never waits forever. A driver decides when a silent device means
%% a lost connection (`{lost, Why}'); after `lost', nothing it was asked is answered,
%% and the worker fails whatever was pending.
%%
%% <b>Fields.</b> `check_point/4' checks a point's driver field when a group is bound
%% to a connection, before anything runs, and returns the resolved field the driver
%% will get back in `plan/2' and `write/4'.
-module(cell_hal_driver).

-export_type([conn_id/0, key/0, point/0, tag/0, event/0, values/0]).

-type conn_id() :: atom().
-type key() :: {Group :: atom(), Point :: atom()}.
-type tag() :: term().
%% A point as the driver sees it, with its field as `check_point/4' resolved it.
-type point() :: #{key := key(), dir := in | out, type := cell_hal_type:type(),
                   field := term()}.
-type values() :: [{key(), cell_hal_type:value()}].
-type event() :: connected
               | {lost, Why :: term()}
               | {reply, tag(), {ok, values()} | ok | {ok, term()} | {error, term()}}
               | {push, values()}
               | {samples, [{key(), [{TimeNs :: integer(), cell_hal_type:value()}]}]}
               | {faults, [{key(), Why :: term() | ok}]}.

%% Checks the connection's options (the `opts' of `cell_hal:add_connection/1') and
%% fills in defaults. Keys the worker itself reads (`poll_ms', `reconnect_ms',
%% `max_reconnect_ms', `connect_timeout_ms') are removed before this is called.
-callback check_opts(Opts :: map()) -> {ok, map()} | {error, {bad_option, atom()}}.

%% Checks one point of a group instance bound to a connection of this driver and
%% resolves its field (a relative symbol against the group's structure, a unit and
%% word order from the group's options ...). `Opts' are the connection's checked
%% options, `GroupOpts' the group instance's options.
-callback check_point(Opts :: map(), Group :: atom(), GroupOpts :: map(),
                      cell_hal_group:point_def()) -> {ok, Field :: term()} | {error, term()}.

%% The driver's state for a connection. No I/O.
-callback init(conn_id(), Opts :: map()) -> State :: term().

%% Where the connection goes, in an operator's words: "10.0.0.5:502".
-callback endpoint(State :: term()) -> iodata().

%% Starts connecting; the outcome arrives later as `connected' or `{lost, Why}'.
-callback connect(State :: term()) -> {ok, State :: term()}.

%% The read plan of the given points; `requests' is how many exchanges one read takes,
%% `pushed' (default 0) how many of the points device notifications feed.
-callback plan([point()], State :: term()) ->
    {Plan :: term(), #{requests := non_neg_integer(), pushed => non_neg_integer()}}.

%% Starts one complete read of a plan.
-callback read(tag(), Plan :: term(), State :: term()) -> {ok, State :: term()}.

%% Queues one output write (in order with the writes before it).
-callback write(tag(), point(), cell_hal_type:value(), State :: term()) -> {ok, State :: term()}.

%% A raw protocol request (diagnostics, functions the HAL does not model), answered
%% with `{reply, Tag, {ok, Reply}}' or `{reply, Tag, {error, Why}}'.
-callback request(tag(), Request :: term(), Timeout :: pos_integer(), State :: term()) ->
    {ok, State :: term()} | {error, term()}.

%% A message that arrived at the worker: the driver's own (socket data, its timers,
%% a connector's result) become events; a stale one of an earlier connection is
%% dropped with `{ok, [], State}'; `unknown' means it is not the driver's. Samples are
%% `{TimeNs, Value}', oldest first, stamped in nanoseconds since 1970 by the device.
-callback handle_info(Msg :: term(), State :: term()) ->
    {ok, [event()], State :: term()} | unknown.

%% Closes the connection and forgets everything in flight. Never fails.
-callback disconnect(State :: term()) -> State :: term().

%% A reason of `lost' or `{error, Why}' in an operator's words.
-callback format_reason(Why :: term()) -> iodata().
