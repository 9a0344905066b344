%% @doc One AMS/TCP connection to a Beckhoff TwinCAT ADS server (a PLC runtime, or an
%% IO device's image server), with what a cell needs on top of the bare commands:
%% symbols resolved by name and checked, handles cached and renewed, whole IO groups in
%% one sum command, device notifications with the PLC's time stamps.
%%
%% No local AMS router is needed: the client speaks AMS/TCP to the PLC's router on port
%% 48898 with its own AMS Net ID and port (the PLC needs a route for that Net ID and
%% this machine's address, as for any ADS client).
%%
%% The connection is a process of {@link cell_hal_ads_conn}: its states, what it does
%% after a program change, and its end when the connection cannot be made or is lost,
%% are told there. A client is one connection: it does not connect again by itself;
%% its owner starts a new one (the HAL's worker, with its back-off). This module is its
%% interface: the calls, their arguments checked in the caller.
%%
%% == Variables ==
%% A variable is `{Name, Type}': a PLC symbol name ("MAIN.GeneralInputs.StartButton",
%% ".GeneralInputs.StopButton", or "*ManipulatorInputs.FailPaletteIsIn" for an IO image)
%% and a {@link cell_hal_ads_types} type. {@link resolve/3} checks each against the PLC
%% (symbol info by name, or the uploaded symbol table for "*" names) and takes a handle
%% (or, with `access => address', the symbol's index group and offset). Resolved
%% variables are cached per connection and shared by all callers; the last caller's
%% {@link release/2} (or exit) gives the handle back after `handle_idle' ms. Reads and
%% writes of many variables go out as sum commands split at `max_sum'. A read that
%% goes out as one request is written by the caller itself on the socket, without a
%% call to the client's process ({@link cell_hal_ads_direct}).
%%
%% == Without waiting ==
%% {@link send_request/5} starts a call without waiting for its answer, for a caller
%% that must stay responsive (the HAL's worker): the answer arrives as a message that
%% {@link check_response/2} recognizes, labelled as the caller chose. Every request
%% is answered, at the latest when its timeout passes (`{error, timeout}'), unless the
%% client exits (the caller's monitor, set up by `send_request', says so).
%%
%% == Messages ==
%% <ul>
%% <li>`{cell_hal_ads, Client, up}', `{cell_hal_ads, Client, {down, Reason}}' and
%%     `{cell_hal_ads, Client, symbols_changed}' (variables were resolved again after a
%%     program change) to processes that called {@link subscribe_status/1}.</li>
%% <li>`{cell_hal_ads, SubRef, {samples, [{Time, Value}]}}' for a subscription, `Time'
%%     being the PLC's time stamp in nanoseconds since the Unix epoch (exact: the
%%     PLC's 100 ns FILETIME times 100), samples in the PLC's order.</li>
%% <li>`{cell_hal_ads, SubRef, {error, Reason}}' when a subscription could not be added
%%     again after a program change; it is tried again at the next one.</li>
%% </ul>
-module(cell_hal_ads_client).

-export([start_link/1, start/1, stop/1, check_opts/1]).
-export([status/1, subscribe_status/1, unsubscribe_status/1]).
-export([read_device_info/1, read_device_info/2, read_state/1, read_state/2,
         write_control/3, write_control/5, read/4, read/5, write/4, write/5,
         read_write/5, read_write/6, sum_read/2, sum_read/3, sum_write/2, sum_write/3,
         sum_read_write/2, sum_read_write/3]).
-export([resolve/2, resolve/3, release/2, read_vars/2, read_vars/3, write_vars/2,
         write_vars/3, read_by_name/3, read_by_name/4, write_by_name/4,
         write_by_name/5, subscribe/2, subscribe/3, unsubscribe/2, symbols/1, symbols/2]).
-export([send_request/5, check_response/2]).
-export([format_error/1]).

-export_type([client/0, opts/0, var/0, var_info/0, sub_opts/0, reason/0, status/0,
              async_request/0, request_ids/0]).

-type client() :: pid() | atom().
-type u32() :: 0..16#FFFFFFFF.

-type opts() :: #{host := inet:hostname() | inet:ip_address() | binary(),
                  target_net_id := cell_hal_ads_codec:net_id() | binary() | string(),
                  port => inet:port_number(),           %% 48898
                  target_port => 1..65535,              %% 851, the first TwinCAT 3 PLC
                  source_net_id => auto | cell_hal_ads_codec:net_id() | binary() | string(),
                  source_port => 1..65535,              %% 32905
                  name => binary() | atom(),            %% log source
                  request_timeout => pos_integer(),     %% ms, the client's own requests
                  connect_timeout => pos_integer(),     %% ms
                  sum_commands => boolean(),            %% true
                  max_sum => pos_integer(),             %% 500 sub-commands per sum
                  max_in_flight => pos_integer(),       %% 64 requests, direct reads too
                  access => handle | address,           %% handle
                  symbol_version => watch | read | ignore,  %% watch
                  handle_idle => non_neg_integer(),     %% ms, 5000
                  link_check => pos_integer() | infinity,   %% ms, 5000
                  max_frame => pos_integer(),           %% bytes, 16 MiB
                  log_variables => boolean()}.          %% true

-type var() :: {Name :: binary(), cell_hal_ads_types:type()}.

-type var_info() :: #{symbol := binary(), plc_type := binary(), size := non_neg_integer(),
                      group := u32(), offset := u32()}.

%% Times in microseconds; the PLC gets them in its unit, 100 ns.
-type sub_opts() :: #{mode => on_change | cyclic,   %% on_change
                      cycle_us => non_neg_integer(),  %% how often the PLC looks, 10 ms
                      max_delay_us => non_neg_integer()}.  %% 0: at once

-type reason() :: term().

%% Calls that can be made without waiting (see send_request/5); each is answered as
%% its function of the same name answers.
-type async_request() :: {resolve, [var()]}
                       | {release, [var()]}
                       | {read_vars, [var()]}
                       | {write_vars, [{var(), cell_hal_ads_types:value()}]}
                       | {subscribe, [{var(), sub_opts()}]}
                       | {unsubscribe, [reference()]}
                       | subscribe_status | symbols
                       | read_device_info | read_state
                       | {read, u32(), u32(), u32()}
                       | {write, u32(), u32(), iodata()}
                       | {read_write, u32(), u32(), u32(), iodata()}.

-type request_ids() :: gen_statem:request_id_collection().

-type status() :: #{state := up | restoring | connecting,
                    name := binary(), peer := binary(), target := binary(),
                    source := binary() | undefined,
                    device => #{name := binary(), version := {byte(), byte(), 0..65535}},
                    ads_state => cell_hal_ads_codec:ads_state(),
                    symbol_version => byte() | undefined,
                    variables := non_neg_integer(), failed := [binary()],
                    subscriptions := non_neg_integer(), in_flight := non_neg_integer(),
                    reason => binary()}.

-define(DEFAULT_TIMEOUT, 5000).

%%====================================================================
%% Starting and stopping
%%====================================================================

%% @doc Starts a client linked to the caller; it connects at once. Options are checked
%% first: `{error, {bad_option, Key}}' names the first one that is missing, unknown or
%% malformed (`reconnect' and `backoff' too: a client does not connect again by
%% itself, see {@link cell_hal_ads_opts}). It ends with `{shutdown, Reason}' when the
%% connection cannot be made or is lost.
-spec start_link(opts()) -> {ok, pid()} | {error, {bad_option, atom()} | term()}.
start_link(Opts) ->
    case check_opts(Opts) of
        {ok, Full} -> gen_statem:start_link(cell_hal_ads_conn, Full, []);
        {error, _} = E -> E
    end.

%% @doc As {@link start_link/1}, without a link.
-spec start(opts()) -> {ok, pid()} | {error, {bad_option, atom()} | term()}.
start(Opts) ->
    case check_opts(Opts) of
        {ok, Full} -> gen_statem:start(cell_hal_ads_conn, Full, []);
        {error, _} = E -> E
    end.

%% @doc Stops a client: notifications are deleted and handles released on the way out.
-spec stop(client()) -> ok.
stop(Client) ->
    gen_statem:stop(Client).

%% @doc The options with their defaults, or the first bad one.
-spec check_opts(term()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    cell_hal_ads_opts:check(Opts).

%%====================================================================
%% Status
%%====================================================================

%% @doc Where the connection stands, for people and for the cell's status pages.
-spec status(client()) -> status().
status(Client) ->
    gen_statem:call(Client, status).

%% @doc The caller gets `{cell_hal_ads, Client, up | {down, Reason} | symbols_changed}'
%% from now on, starting with the present state (`up' or `{down, Reason}').
-spec subscribe_status(client()) -> ok.
subscribe_status(Client) ->
    gen_statem:call(Client, subscribe_status).

%% @doc Ends a {@link subscribe_status/1}.
-spec unsubscribe_status(client()) -> ok.
unsubscribe_status(Client) ->
    gen_statem:call(Client, unsubscribe_status).

%%====================================================================
%% ADS commands
%%====================================================================

%% @doc The ADS server's name and version.
-spec read_device_info(client()) ->
          {ok, #{name := binary(), version := {byte(), byte(), 0..65535}}} | {error, reason()}.
read_device_info(Client) ->
    read_device_info(Client, ?DEFAULT_TIMEOUT).

%% @doc As {@link read_device_info/1}, waiting at most `Timeout' ms.
-spec read_device_info(client(), timeout()) ->
          {ok, #{name := binary(), version := {byte(), byte(), 0..65535}}} | {error, reason()}.
read_device_info(Client, Timeout) ->
    request(Client, read_device_info, Timeout).

%% @doc The ADS state (`run', `stop', `config' ...) and the device state.
-spec read_state(client()) ->
          {ok, #{ads_state := cell_hal_ads_codec:ads_state(), device_state := 0..65535}}
        | {error, reason()}.
read_state(Client) ->
    read_state(Client, ?DEFAULT_TIMEOUT).

%% @doc As {@link read_state/1}, waiting at most `Timeout' ms.
-spec read_state(client(), timeout()) ->
          {ok, #{ads_state := cell_hal_ads_codec:ads_state(), device_state := 0..65535}}
        | {error, reason()}.
read_state(Client, Timeout) ->
    request(Client, read_state, Timeout).

%% @doc Asks the ADS server to change state (`run', `stop' ...).
-spec write_control(client(), cell_hal_ads_codec:ads_state(), 0..65535) -> ok | {error, reason()}.
write_control(Client, AdsState, DeviceState) ->
    write_control(Client, AdsState, DeviceState, <<>>, ?DEFAULT_TIMEOUT).

%% @doc As {@link write_control/3}, with data and a timeout.
-spec write_control(client(), cell_hal_ads_codec:ads_state(), 0..65535, iodata(), timeout()) ->
          ok | {error, reason()}.
write_control(Client, AdsState, DeviceState, Data, Timeout) ->
    request(Client, {write_control, AdsState, DeviceState, Data}, Timeout).

%% @doc Reads `Length' bytes at an index group and offset.
-spec read(client(), u32(), u32(), u32()) -> {ok, binary()} | {error, reason()}.
read(Client, Group, Offset, Length) ->
    read(Client, Group, Offset, Length, ?DEFAULT_TIMEOUT).

%% @doc As {@link read/4}, waiting at most `Timeout' ms.
-spec read(client(), u32(), u32(), u32(), timeout()) -> {ok, binary()} | {error, reason()}.
read(Client, Group, Offset, Length, Timeout) ->
    request(Client, {read, Group, Offset, Length}, Timeout).

%% @doc Writes bytes at an index group and offset.
-spec write(client(), u32(), u32(), iodata()) -> ok | {error, reason()}.
write(Client, Group, Offset, Data) ->
    write(Client, Group, Offset, Data, ?DEFAULT_TIMEOUT).

%% @doc As {@link write/4}, waiting at most `Timeout' ms.
-spec write(client(), u32(), u32(), iodata(), timeout()) -> ok | {error, reason()}.
write(Client, Group, Offset, Data, Timeout) ->
    request(Client, {write, Group, Offset, Data}, Timeout).

%% @doc Writes `Data' and reads up to `ReadLength' bytes back, in one request.
-spec read_write(client(), u32(), u32(), u32(), iodata()) -> {ok, binary()} | {error, reason()}.
read_write(Client, Group, Offset, ReadLength, Data) ->
    read_write(Client, Group, Offset, ReadLength, Data, ?DEFAULT_TIMEOUT).

%% @doc As {@link read_write/5}, waiting at most `Timeout' ms.
-spec read_write(client(), u32(), u32(), u32(), iodata(), timeout()) ->
          {ok, binary()} | {error, reason()}.
read_write(Client, Group, Offset, ReadLength, Data, Timeout) ->
    request(Client, {read_write, Group, Offset, ReadLength, Data}, Timeout).

%% @doc Reads of `{Group, Offset, Length}' in one sum command (several where `max_sum'
%% requires it; one request each without sum commands): one result per item.
-spec sum_read(client(), [{u32(), u32(), u32()}]) ->
          {ok, [{ok, binary()} | {error, reason()}]} | {error, reason()}.
sum_read(Client, Items) ->
    sum_read(Client, Items, ?DEFAULT_TIMEOUT).

%% @doc As {@link sum_read/2}, waiting at most `Timeout' ms.
-spec sum_read(client(), [{u32(), u32(), u32()}], timeout()) ->
          {ok, [{ok, binary()} | {error, reason()}]} | {error, reason()}.
sum_read(Client, Items, Timeout) ->
    call(Client, {batch, reads, Items}, Timeout).

%% @doc Writes of `{Group, Offset, Data}' as {@link sum_read/2} does reads.
-spec sum_write(client(), [{u32(), u32(), iodata()}]) ->
          {ok, [ok | {error, reason()}]} | {error, reason()}.
sum_write(Client, Items) ->
    sum_write(Client, Items, ?DEFAULT_TIMEOUT).

%% @doc As {@link sum_write/2}, waiting at most `Timeout' ms.
-spec sum_write(client(), [{u32(), u32(), iodata()}], timeout()) ->
          {ok, [ok | {error, reason()}]} | {error, reason()}.
sum_write(Client, Items, Timeout) ->
    call(Client, {batch, writes, Items}, Timeout).

%% @doc ReadWrites of `{Group, Offset, ReadLength, Data}' as {@link sum_read/2} does reads.
-spec sum_read_write(client(), [{u32(), u32(), u32(), iodata()}]) ->
          {ok, [{ok, binary()} | {error, reason()}]} | {error, reason()}.
sum_read_write(Client, Items) ->
    sum_read_write(Client, Items, ?DEFAULT_TIMEOUT).

%% @doc As {@link sum_read_write/2}, waiting at most `Timeout' ms.
-spec sum_read_write(client(), [{u32(), u32(), u32(), iodata()}], timeout()) ->
          {ok, [{ok, binary()} | {error, reason()}]} | {error, reason()}.
sum_read_write(Client, Items, Timeout) ->
    call(Client, {batch, read_writes, Items}, Timeout).

%%====================================================================
%% Variables
%%====================================================================

%% @doc Resolves variables for the caller, in as few round trips as the PLC allows:
%% each is checked against the PLC's symbol (it must exist, "*" names must match one
%% symbol, the type and size must fit) and gets a handle, which is kept for every
%% caller until released. One result per variable, in order; an error names the
%% symbol: `{unknown_symbol, Name}', `{ambiguous_symbol, Pattern, Candidates}',
%% `{type_mismatch, Name, #{expected, plc_type, size}}', `{bad_name, Name}' ...
-spec resolve(client(), [var()]) ->
          {ok, [{ok, var_info()} | {error, reason()}]} | {error, reason()}.
resolve(Client, Vars) ->
    resolve(Client, Vars, ?DEFAULT_TIMEOUT).

%% @doc As {@link resolve/2}, waiting at most `Timeout' ms.
-spec resolve(client(), [var()], timeout()) ->
          {ok, [{ok, var_info()} | {error, reason()}]} | {error, reason()}.
resolve(Client, Vars, Timeout) ->
    case cell_hal_ads_args:vars(Vars) of
        ok -> call(Client, {resolve, Vars}, Timeout);
        Error -> Error
    end.

%% @doc The caller no longer uses these variables (one use each). A handle nobody
%% uses goes back to the PLC after `handle_idle' ms.
-spec release(client(), [var()]) -> ok | {error, reason()}.
release(Client, Vars) ->
    case cell_hal_ads_args:shapes(Vars) of
        ok -> gen_statem:call(Client, {release, Vars});
        Error -> Error
    end.

%% @doc Reads resolved variables, all in one round trip (sum commands): one value or
%% error per variable, in order.
-spec read_vars(client(), [var()]) ->
          {ok, [{ok, cell_hal_ads_types:value()} | {error, reason()}]} | {error, reason()}.
read_vars(Client, Vars) ->
    read_vars(Client, Vars, ?DEFAULT_TIMEOUT).

%% @doc As {@link read_vars/2}, waiting at most `Timeout' ms.
-spec read_vars(client(), [var()], timeout()) ->
          {ok, [{ok, cell_hal_ads_types:value()} | {error, reason()}]} | {error, reason()}.
read_vars(Client, Vars, Timeout) ->
    %% The caller sends the request itself when it can (cell_hal_ads_direct); what it
    %% cannot read so goes through the client's process, checked first.
    case cell_hal_ads_direct:read_vars(Client, Vars, Timeout) of
        {slow, Left} ->
            case cell_hal_ads_args:shapes(Vars) of
                ok -> call(Client, {read_vars, Vars}, Left);
                Error -> Error
            end;
        {down, Reason} ->
            exit({Reason, {?MODULE, read_vars, [Client, Vars, Timeout]}});
        Result ->
            Result
    end.

%% @doc Writes resolved variables, all in one round trip: `ok' or an error per
%% variable, in order. A value that does not fit its type is not sent.
-spec write_vars(client(), [{var(), cell_hal_ads_types:value()}]) ->
          {ok, [ok | {error, reason()}]} | {error, reason()}.
write_vars(Client, Pairs) ->
    write_vars(Client, Pairs, ?DEFAULT_TIMEOUT).

%% @doc As {@link write_vars/2}, waiting at most `Timeout' ms.
-spec write_vars(client(), [{var(), cell_hal_ads_types:value()}], timeout()) ->
          {ok, [ok | {error, reason()}]} | {error, reason()}.
write_vars(Client, Pairs, Timeout) ->
    case cell_hal_ads_args:pairs(Pairs) of
        ok -> call(Client, {write_vars, Pairs}, Timeout);
        Error -> Error
    end.

%% @doc Reads one variable by name: resolved (the handle stays cached for a while),
%% read, released.
-spec read_by_name(client(), binary(), cell_hal_ads_types:type()) ->
          {ok, cell_hal_ads_types:value()} | {error, reason()}.
read_by_name(Client, Name, Type) ->
    read_by_name(Client, Name, Type, ?DEFAULT_TIMEOUT).

%% @doc As {@link read_by_name/3}, waiting at most `Timeout' ms in all.
-spec read_by_name(client(), binary(), cell_hal_ads_types:type(), timeout()) ->
          {ok, cell_hal_ads_types:value()} | {error, reason()}.
read_by_name(Client, Name, Type, Timeout) ->
    with_var(Client, {Name, Type}, Timeout,
             fun(Left) ->
                     case read_vars(Client, [{Name, Type}], Left) of
                         {ok, [Result]} -> Result;
                         {error, _} = E -> E
                     end
             end).

%% @doc Writes one variable by name, as {@link read_by_name/3} reads.
-spec write_by_name(client(), binary(), cell_hal_ads_types:type(), cell_hal_ads_types:value()) ->
          ok | {error, reason()}.
write_by_name(Client, Name, Type, Value) ->
    write_by_name(Client, Name, Type, Value, ?DEFAULT_TIMEOUT).

%% @doc As {@link write_by_name/4}, waiting at most `Timeout' ms in all.
-spec write_by_name(client(), binary(), cell_hal_ads_types:type(), cell_hal_ads_types:value(),
                    timeout()) -> ok | {error, reason()}.
write_by_name(Client, Name, Type, Value, Timeout) ->
    with_var(Client, {Name, Type}, Timeout,
             fun(Left) ->
                     case write_vars(Client, [{{Name, Type}, Value}], Left) of
                         {ok, [Result]} -> Result;
                         {error, _} = E -> E
                     end
             end).

with_var(Client, Var, Timeout, Fun) ->
    Deadline = deadline(Timeout),
    case resolve(Client, [Var], Timeout) of
        {ok, [{ok, _}]} ->
            Result = Fun(left(Deadline)),
            ok = release(Client, [Var]),
            Result;
        {ok, [{error, _} = E]} ->
            E;
        {error, _} = E ->
            E
    end.

%% @doc Device notifications for variables, resolved for the caller as by
%% {@link resolve/2}. The caller gets `{cell_hal_ads, SubRef, {samples, Samples}}'
%% messages (see the module doc). `on_change' sends a value when it changes (and the
%% present value at once); `cyclic' sends one every `cycle_us'. One result per
%% subscription, in order.
-spec subscribe(client(), [{var(), sub_opts()}]) ->
          {ok, [{ok, reference()} | {error, reason()}]} | {error, reason()}.
subscribe(Client, Subs) ->
    subscribe(Client, Subs, ?DEFAULT_TIMEOUT).

%% @doc As {@link subscribe/2}, waiting at most `Timeout' ms.
-spec subscribe(client(), [{var(), sub_opts()}], timeout()) ->
          {ok, [{ok, reference()} | {error, reason()}]} | {error, reason()}.
subscribe(Client, Subs, Timeout) ->
    case cell_hal_ads_args:subs(Subs) of
        {ok, Checked} -> call(Client, {subscribe, Checked}, Timeout);
        Error -> Error
    end.

%% @doc Ends subscriptions of the caller.
-spec unsubscribe(client(), [reference()]) -> ok | {error, reason()}.
unsubscribe(Client, Refs) ->
    case cell_hal_ads_args:refs(Refs) of
        ok -> gen_statem:call(Client, {unsubscribe, Refs});
        Error -> Error
    end.

%% @doc The PLC's symbol table (top-level symbols, as uploaded), sorted by name.
-spec symbols(client()) -> {ok, [cell_hal_ads_codec:symbol()]} | {error, reason()}.
symbols(Client) ->
    symbols(Client, ?DEFAULT_TIMEOUT).

%% @doc As {@link symbols/1}, waiting at most `Timeout' ms.
-spec symbols(client(), timeout()) -> {ok, [cell_hal_ads_codec:symbol()]} | {error, reason()}.
symbols(Client, Timeout) ->
    call(Client, symbols, Timeout).

%% @doc Starts a call without waiting for its answer and adds it to `ReqIds' under
%% `Label'. The arguments are checked here as the waiting functions check them; a bad
%% one is `{error, Reason}' at once and nothing is sent. The answer, at the latest
%% after `Timeout' ms, is found by {@link check_response/2}.
-spec send_request(client(), async_request(), timeout(), term(), request_ids()) ->
          {ok, request_ids()} | {error, reason()}.
send_request(Client, Request, Timeout, Label, ReqIds) ->
    case async_message(Request, Timeout) of
        {ok, Msg} -> {ok, gen_statem:send_request(Client, Msg, Label, ReqIds)};
        {error, _} = E -> E
    end.

async_message({resolve, Vars}, T) -> checked(cell_hal_ads_args:vars(Vars), {resolve, Vars}, T);
async_message({read_vars, Vars}, T) ->
    checked(cell_hal_ads_args:shapes(Vars), {read_vars, Vars}, T);
async_message({write_vars, Pairs}, T) ->
    checked(cell_hal_ads_args:pairs(Pairs), {write_vars, Pairs}, T);
async_message({subscribe, Subs}, T) ->
    case cell_hal_ads_args:subs(Subs) of
        {ok, Checked} -> {ok, {req, {subscribe, Checked}, deadline(T)}};
        Error -> Error
    end;
async_message({release, Vars}, _) ->
    case cell_hal_ads_args:shapes(Vars) of
        ok -> {ok, {release, Vars}};
        Error -> Error
    end;
async_message({unsubscribe, Refs}, _) ->
    case cell_hal_ads_args:refs(Refs) of
        ok -> {ok, {unsubscribe, Refs}};
        Error -> Error
    end;
async_message(subscribe_status, _) ->
    {ok, subscribe_status};
async_message(symbols, T) ->
    {ok, {req, symbols, deadline(T)}};
async_message(Request, T) ->
    case cell_hal_ads_args:request(Request) of
        true -> {ok, {req, {request, Request}, deadline(T)}};
        false -> {error, {bad_argument, Request}}
    end.

checked(ok, Request, T) -> {ok, {req, Request, deadline(T)}};
checked(Error, _, _) -> Error.

%% @doc Whether a message answers a request of `ReqIds': `{Result, Label, Rest}'
%% with the answer as the waiting function gives it (`{error, {Reason, Client}}' if
%% the client exited first), `no_request' when none is outstanding, `no_reply' for
%% another message.
-spec check_response(term(), request_ids()) ->
          {term(), term(), request_ids()} | no_request | no_reply.
check_response(Msg, ReqIds) ->
    case gen_statem:check_response(Msg, ReqIds, true) of
        {{reply, Reply}, Label, Rest} -> {Reply, Label, Rest};
        {{error, _} = E, Label, Rest} -> {E, Label, Rest};
        Other -> Other
    end.

%% A request is checked in the caller: a bad argument never reaches the client.
request(Client, Request, Timeout) ->
    case cell_hal_ads_args:request(Request) of
        true -> call(Client, {request, Request}, Timeout);
        false -> {error, {bad_argument, Request}}
    end.

call(Client, Request, Timeout) ->
    Deadline = deadline(Timeout),
    try
        gen_statem:call(Client, {req, Request, Deadline}, Timeout)
    catch
        exit:{timeout, _} -> {error, timeout}
    end.

deadline(infinity) -> infinity;
deadline(Timeout) -> now_ms() + Timeout.

left(infinity) -> infinity;
left(Deadline) -> max(0, Deadline - now_ms()).

now_ms() ->
    erlang:monotonic_time(millisecond).

%%====================================================================
%% Errors for people
%%====================================================================

%% @doc Any reason this client gives, in words for the people running the machine.
-spec format_error(reason()) -> binary().
format_error(Reason) ->
    cell_hal_ads_errors:format_error(Reason).
