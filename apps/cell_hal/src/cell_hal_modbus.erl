%% @doc The Modbus TCP driver: a client in pure Erlang, hosted by a HAL worker (or any
%% process that feeds it its messages, as the benchmark does).
%%
%% Connection options:
%% <table>
%% <tr><th>option</th><th>default</th><th></th></tr>
%% <tr><td>`host'</td><td>(required)</td><td>name or address of the device</td></tr>
%% <tr><td>`port'</td><td>502</td><td></td></tr>
%% <tr><td>`unit'</td><td>1</td><td>unit id of the device (a group may name another
%%   unit behind a gateway)</td></tr>
%% <tr><td>`word_order'</td><td>`big'</td><td>of values of 32 and 64 bits: `big'
%%   (most significant word first) or `little'</td></tr>
%% <tr><td>`timeout_ms'</td><td>1000</td><td>how long a request may go unanswered</td></tr>
%% <tr><td>`max_in_flight'</td><td>1</td><td>requests sent before the first answer
%%   (pipelining); only for devices that queue requests</td></tr>
%% <tr><td>`max_gap'</td><td>0</td><td>unused registers or bits a block read may span
%%   to join two points (only where the device answers for the gap)</td></tr>
%% <tr><td>`refused_group'</td><td>`fault'</td><td>what a poll in which the PLC refuses
%%   every request of an IO group means: `fault' (its points read unavailable, the rest
%%   of the connection goes on) or `disconnect' (the connection is lost, as on a
%%   transport failure, and is tried again at the worker's reconnect backoff)</td></tr>
%% <tr><td>`refused_retry_ms'</td><td>500</td><td>how long a read request the PLC refused
%%   rests before it is asked again (not at every poll), twice as long after each
%%   further refusal</td></tr>
%% <tr><td>`max_refused_retry_ms'</td><td>30000</td><td>the longest such rest</td></tr>
%% </table>
%%
%% Requests carry transaction ids 0..65535, wrapping around, never one still in
%% flight. Writes and raw requests go before the polls waiting to be sent, in their own
%% order. The socket delivers up to 64 packets before it is re-armed (one option call
%% per 64 answers rather than one per answer); frames are handed to the socket's port
%% without waiting (its confirmation comes back as a message); connecting happens in a
%% short-lived process, so the host process never blocks. Deadlines are kept with one
%% timer a connection, armed for the earliest deadline in flight, rather than one a
%% request: a round trip costs no timer operation.
%%
%% Faults: a Modbus exception is the PLC answering, so it never takes the connection
%% down. A write or raw request it refuses answers `{error, {modbus_exception, Code,
%% Name}}'. A read request of a poll it refuses leaves the inputs of that request
%% unusable (`{faults, ...}': they read `{error, {unavailable, Why}}', Why the
%% exception in words, see {@link cell_hal_modbus_codec:exception_text/1}) while the
%% rest of the poll is read as usual; the refused request rests `refused_retry_ms'
%% (doubling, at most `max_refused_retry_ms') before it is asked again, and its inputs
%% are usable again with the first value it answers. Outputs a refused read-back
%% request covers are not marked: they keep their commanded value and their writes go
%% to the PLC, which answers for itself. A poll in which the PLC refuses every request
%% of a group is the `refused_group' option's to decide. Transport failures alone close
%% the connection (`{lost, Why}'): a frame that is malformed, too long, answers no
%% request or answers for another unit, because nothing after it on that stream can be
%% trusted; a poll or write left unanswered past `timeout_ms'. A raw request that times
%% out just fails; its late answer is dropped.
-module(cell_hal_modbus).
-behaviour(cell_hal_driver).

%% Packets the socket delivers before it is re-armed.
-define(ACTIVE_N, 64).

-export([check_opts/1, check_point/4, init/2, endpoint/1, connect/1, plan/2, read/3,
         write/4, request/4, handle_info/2, disconnect/1, format_reason/1]).

-type tid() :: cell_hal_modbus_codec:tid().
-type unit_id() :: cell_hal_modbus_codec:unit_id().
-type key() :: cell_hal_driver:key().
-type exception() :: {modbus_exception, cell_hal_modbus_codec:exception_code(), atom()}.
%% The blocks of a read and the outputs among their points (a refusal leaves them
%% unmarked).
-type plan() :: {cell_hal_modbus_plan:plan(), #{key() => true}}.
-export_type([plan/0]).

%% A read of a plan on its way: requests still unanswered, values so far, and the
%% blocks the PLC refused (or that rest after an earlier refusal).
-record(rd, {left :: non_neg_integer(),
             outputs :: #{key() => true},
             blocks :: cell_hal_modbus_plan:plan(),
             values = [] :: [cell_hal_driver:values()],
             refused = [] :: [{cell_hal_modbus_plan:block(), unit_id(),
                               cell_hal_modbus_codec:request(), exception()}]}).

-record(req, {kind :: {poll, term(), cell_hal_modbus_plan:block()} | {write, term()}
                    | {raw, term()},
              unit :: unit_id(),
              request :: cell_hal_modbus_codec:request(),
              timeout :: pos_integer(),
              deadline = 0 :: integer()}).        %% monotonic ms, set when sent

-record(mb, {id :: atom(),
             host :: inet:hostname() | inet:ip_address(),
             port :: inet:port_number(),
             unit :: unit_id(),
             word_order :: cell_hal_type_codec:word_order(),
             timeout_ms :: pos_integer(),
             max_in_flight :: pos_integer(),
             max_gap :: non_neg_integer(),
             refused_group :: fault | disconnect,
             refused_retry_ms :: pos_integer(),
             max_refused_retry_ms :: pos_integer(),
             socket :: gen_tcp:socket() | undefined,
             connector :: {pid(), reference()} | undefined,
             buf = <<>> :: binary(),
             tid = 0 :: tid(),
             in_flight = #{} :: #{tid() => #req{}},
             urgent = queue:new() :: queue:queue(#req{}),     %% writes and raw requests
             polls = queue:new() :: queue:queue(#req{}),
             reads = #{} :: #{term() => #rd{}},
             %% read requests refused: when each is asked again, its next rest, why
             resting = #{} :: #{{unit_id(), cell_hal_modbus_codec:request()} =>
                                    {integer(), pos_integer(), exception()}},
             faulted = #{} :: #{key() => term()},          %% inputs reported unusable
             late = #{} :: #{tid() => true},                %% timed-out raw requests
             timer :: {reference(), integer()} | undefined,  %% earliest deadline
             flush = false :: boolean()}).                  %% a flush is on its way

%%====================================================================
%% Options and fields
%%====================================================================

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    Defaults = #{port => 502, unit => 1, word_order => big, timeout_ms => 1000,
                 max_in_flight => 1, max_gap => 0, refused_group => fault,
                 refused_retry_ms => 500, max_refused_retry_ms => 30000},
    Checks = #{host => fun is_host/1,
               port => fun(V) -> is_integer(V) andalso V > 0 andalso V =< 65535 end,
               unit => fun(V) -> is_integer(V) andalso V >= 0 andalso V =< 255 end,
               word_order => fun(V) -> V =:= big orelse V =:= little end,
               timeout_ms => fun(V) -> is_integer(V) andalso V > 0 end,
               max_in_flight => fun(V) -> is_integer(V) andalso V > 0 andalso V =< 1024 end,
               max_gap => fun(V) -> is_integer(V) andalso V >= 0 andalso V =< 124 end,
               refused_group => fun(V) -> V =:= fault orelse V =:= disconnect end,
               refused_retry_ms => fun(V) -> is_integer(V) andalso V > 0 end,
               max_refused_retry_ms => fun(V) -> is_integer(V) andalso V > 0 end},
    case [K || {K, V} <- maps:to_list(Opts),
               not (maps:is_key(K, Checks) andalso (maps:get(K, Checks))(V))] of
        [] when not is_map_key(host, Opts) -> {error, {bad_option, host}};
        [] ->
            Checked = maps:merge(Defaults, Opts),
            case maps:get(max_refused_retry_ms, Checked) < maps:get(refused_retry_ms, Checked) of
                true -> {error, {bad_option, max_refused_retry_ms}};
                false -> {ok, Checked}
            end;
        [Bad | _] -> {error, {bad_option, Bad}}
    end.

is_host(H) when is_binary(H) -> is_host(binary_to_list(H));
is_host(H) when is_list(H) -> H =/= [] andalso io_lib:printable_latin1_list(H);
is_host(H) when is_tuple(H) ->
    case inet:ntoa(H) of
        {error, einval} -> false;
        _ -> true
    end;
is_host(_) -> false.

%% @private
-spec check_point(map(), atom(), map(), cell_hal_group:point_def()) ->
          {ok, cell_hal_modbus_plan:field()} | {error, atom()}.
check_point(Opts, _Group, GroupOpts, #{dir := Dir, type := Type, field := Field}) ->
    Unit = maps:get(unit, GroupOpts, maps:get(unit, Opts)),
    Order = maps:get(word_order, GroupOpts, maps:get(word_order, Opts)),
    case {is_integer(Unit) andalso Unit >= 0 andalso Unit =< 255,
          Order =:= big orelse Order =:= little} of
        {false, _} -> {error, bad_unit};
        {_, false} -> {error, bad_word_order};
        _ -> cell_hal_modbus_plan:field(Dir, Type, Field, #{unit => Unit, word_order => Order})
    end.

%%====================================================================
%% Connection
%%====================================================================

%% @private
-spec init(atom(), map()) -> #mb{}.
init(Id, Opts) ->
    Host = case maps:get(host, Opts) of
               H when is_binary(H) -> binary_to_list(H);
               H -> H
           end,
    #mb{id = Id, host = Host, port = maps:get(port, Opts), unit = maps:get(unit, Opts),
        word_order = maps:get(word_order, Opts), timeout_ms = maps:get(timeout_ms, Opts),
        max_in_flight = maps:get(max_in_flight, Opts), max_gap = maps:get(max_gap, Opts),
        refused_group = maps:get(refused_group, Opts, fault),
        refused_retry_ms = maps:get(refused_retry_ms, Opts, 500),
        max_refused_retry_ms = maps:get(max_refused_retry_ms, Opts, 30000)}.

%% @private
-spec endpoint(#mb{}) -> iodata().
endpoint(#mb{host = Host, port = Port}) ->
    HostText = case is_tuple(Host) of
                   true -> inet:ntoa(Host);
                   false -> Host
               end,
    [HostText, $:, integer_to_list(Port)].

%% @private
%% gen_tcp:connect blocks its caller: a connector process does it and hands the socket
%% over, so the worker keeps answering while a device is slow to accept.
-spec connect(#mb{}) -> {ok, #mb{}}.
connect(#mb{host = Host, port = Port} = S) ->
    Parent = self(),
    Connector = spawn_monitor(fun() -> connector(Parent, Host, Port) end),
    {ok, S#mb{connector = Connector}}.

connector(Parent, Host, Port) ->
    Opts = [binary, {packet, raw}, {active, false}, {nodelay, true}, {keepalive, true}],
    case gen_tcp:connect(Host, Port, Opts) of
        {ok, Sock} ->
            case gen_tcp:controlling_process(Sock, Parent) of
                ok ->
                    Parent ! {?MODULE, connected, self(), Sock};
                {error, Why} ->
                    _ = gen_tcp:close(Sock),
                    Parent ! {?MODULE, connect_failed, self(), Why}
            end;
        {error, Why} ->
            Parent ! {?MODULE, connect_failed, self(), Why}
    end.

%% @private
-spec disconnect(#mb{}) -> #mb{}.
disconnect(#mb{socket = Sock, connector = Connector} = S) ->
    case Connector of
        {Pid, MRef} ->
            erlang:demonitor(MRef, [flush]),
            exit(Pid, kill);
        undefined ->
            ok
    end,
    _ = Sock =/= undefined andalso gen_tcp:close(Sock),
    ok = cancel(S#mb.timer),
    %% What the PLC refused held for that connection: the next one asks afresh.
    S#mb{socket = undefined, connector = undefined, buf = <<>>, in_flight = #{},
         urgent = queue:new(), polls = queue:new(), reads = #{}, late = #{},
         timer = undefined, flush = false, resting = #{}, faulted = #{}}.

%%====================================================================
%% Reads, writes, raw requests
%%====================================================================

%% @private
-spec plan([cell_hal_driver:point()], #mb{}) -> {plan(), #{requests := non_neg_integer()}}.
plan(Points, #mb{max_gap = Gap}) ->
    Plan = cell_hal_modbus_plan:plan([{K, T, F} || #{key := K, type := T, field := F} <- Points],
                                     Gap),
    {{Plan, maps:from_list([{K, true} || #{key := K, dir := out} <- Points])},
     #{requests => length(Plan)}}.

%% @private
%% A request resting after a refusal is not sent: its block counts as refused again.
-spec read(term(), plan(), #mb{}) -> {ok, #mb{}}.
read(Tag, {[], _}, S) ->
    self() ! {?MODULE, empty_read, Tag},
    {ok, S};
read(Tag, {Plan, Outputs}, #mb{polls = Q, reads = Reads, timeout_ms = T, resting = Resting} = S) ->
    Now = erlang:monotonic_time(millisecond),
    {Asked, Rest} =
        lists:partition(fun({_, UR}) ->
                                case Resting of
                                    #{UR := {At, _, _}} -> At =< Now;
                                    #{} -> true
                                end
                        end, lists:zip(Plan, cell_hal_modbus_plan:requests(Plan))),
    Rd = #rd{left = length(Asked), outputs = Outputs, blocks = Plan,
             refused = [{B, U, R, element(3, maps:get({U, R}, Resting))} || {B, {U, R}} <- Rest]},
    case Asked of
        [] ->
            self() ! {?MODULE, empty_read, Tag},
            {ok, S#mb{reads = Reads#{Tag => Rd}}};
        _ ->
            Reqs = [#req{kind = {poll, Tag, B}, unit = U, request = R, timeout = T}
                    || {B, {U, R}} <- Asked],
            pumped(S#mb{polls = queue:join(Q, queue:from_list(Reqs)), reads = Reads#{Tag => Rd}})
    end.

%% @private
-spec write(term(), cell_hal_driver:point(), cell_hal_type:value(), #mb{}) -> {ok, #mb{}}.
write(Tag, #{type := Type, field := Field}, V, #mb{timeout_ms = T} = S) ->
    {Unit, Req} = cell_hal_modbus_plan:write_request(Type, Field, V),
    urgent(#req{kind = {write, Tag}, unit = Unit, request = Req, timeout = T}, S).

%% @private
%% A request of the codec (see cell_hal_modbus_codec:request()), to the connection's
%% unit or, as `{Unit, Request}', to another.
-spec request(term(), term(), pos_integer(), #mb{}) -> {ok, #mb{}} | {error, term()}.
request(Tag, {Unit, Req}, Timeout, S) when is_integer(Unit), Unit >= 0,
                                                             Unit =< 255 ->
    case cell_hal_modbus_codec:check_request(Req) of
        ok ->
            urgent(#req{kind = {raw, Tag}, unit = Unit, request = Req, timeout = Timeout}, S);
        Error ->
            Error
    end;
request(Tag, Req, Timeout, #mb{unit = Unit} = S) ->
    request(Tag, {Unit, Req}, Timeout, S).

%% Sends what the window allows. A send error is reported through the mailbox: the
%% callers of read/write/request only queue.
pumped(S) ->
    {ok, pump(S)}.

%% A write or raw request goes out at once on an idle connection. With others in
%% flight it waits for the end of the host's turn, so that requests issued together
%% leave together, in one frame batch.
urgent(Req, #mb{urgent = Q, in_flight = InFlight} = S) when map_size(InFlight) =:= 0 ->
    pumped(S#mb{urgent = queue:in(Req, Q)});
urgent(Req, #mb{urgent = Q, flush = true} = S) ->
    {ok, S#mb{urgent = queue:in(Req, Q)}};
urgent(Req, #mb{urgent = Q, socket = Sock} = S) ->
    self() ! {?MODULE, flush, Sock},
    {ok, S#mb{urgent = queue:in(Req, Q), flush = true}}.

pump(#mb{socket = undefined} = S) ->
    S;
pump(#mb{socket = Sock} = S) ->
    case fill(S, erlang:monotonic_time(millisecond), []) of
        {[], S1} ->
            S1;
        {Frames, S1} ->
            %% The port confirms with {inet_reply, Sock, Status}: no wait here.
            try erlang:port_command(Sock, lists:reverse(Frames)) of
                true -> S1
            catch
                error:badarg -> self() ! {?MODULE, send_failed, Sock, closed}, S1
            end
    end.

fill(#mb{in_flight = InFlight, max_in_flight = Max} = S, _Now, Frames)
  when map_size(InFlight) >= Max ->
    {Frames, S};
fill(#mb{urgent = U, polls = P} = S, Now, Frames) ->
    case queue:out(U) of
        {{value, Req}, U1} -> fill_send(Req, S#mb{urgent = U1}, Now, Frames);
        {empty, _} ->
            case queue:out(P) of
                {{value, Req}, P1} -> fill_send(Req, S#mb{polls = P1}, Now, Frames);
                {empty, _} -> {Frames, S}
            end
    end.

fill_send(#req{unit = Unit, request = R, timeout = T} = Req, #mb{in_flight = InFlight} = S,
          Now, Frames) ->
    {Tid, S1} = next_tid(S),
    Frame = cell_hal_modbus_codec:adu(Tid, Unit, cell_hal_modbus_codec:request_pdu(R)),
    Deadline = Now + T,
    fill(arm(Deadline, S1#mb{in_flight = InFlight#{Tid => Req#req{deadline = Deadline}}}),
         Now, [Frame | Frames]).

%% The one deadline timer fires no later than the earliest deadline in flight.
arm(Deadline, #mb{timer = {_, At}} = S) when At =< Deadline ->
    S;
arm(Deadline, #mb{timer = Timer} = S) ->
    ok = cancel(Timer),
    TRef1 = erlang:start_timer(Deadline, self(), {?MODULE, deadline}, [{abs, true}]),
    S#mb{timer = {TRef1, Deadline}}.

cancel({TRef, _}) ->
    _ = erlang:cancel_timer(TRef),
    ok;
cancel(undefined) ->
    ok.

%% The timer fired: the requests past their deadline fail, and it is armed again for
%% the earliest one left.
expire(#mb{in_flight = InFlight} = S) ->
    Now = erlang:monotonic_time(millisecond),
    Deadlines = [{D, Tid} || {Tid, #req{deadline = D}} <- maps:to_list(InFlight)],
    Expired = lists:sort([E || {D, _} = E <- Deadlines, D =< Now]),
    Left = [D || {D, _} <- Deadlines, D > Now],
    S1 = case Left of
             [] -> S#mb{timer = undefined};
             _ -> arm(lists:min(Left), S#mb{timer = undefined})
         end,
    expire(Expired, S1, []).

expire([], S, Events) ->
    {ok, lists:reverse(Events), pump(S)};
expire([{_, Tid} | Rest], #mb{in_flight = InFlight} = S, Events) ->
    case maps:take(Tid, InFlight) of
        {#req{kind = {raw, Tag}}, Left} ->
            expire(Rest, S#mb{in_flight = Left, late = (S#mb.late)#{Tid => true}},
                   [{reply, Tag, {error, timeout}} | Events]);
        {#req{unit = U, request = R, timeout = T}, _} ->
            lost_after({no_answer, T, U, R}, S, lists:reverse(Events))
    end.

%% The next transaction id not in flight (at most max_in_flight are), wrapping around.
next_tid(#mb{tid = Tid, in_flight = InFlight, late = Late} = S) ->
    Next = (Tid + 1) band 16#FFFF,
    case InFlight of
        #{Tid := _} -> next_tid(S#mb{tid = Next});
        #{} -> {Tid, S#mb{tid = Next, late = maps:remove(Tid, Late)}}
    end.

%%====================================================================
%% Messages
%%====================================================================

%% @private
-spec handle_info(term(), #mb{}) -> {ok, [cell_hal_driver:event()], #mb{}} | unknown.
handle_info({tcp, Sock, Data}, #mb{socket = Sock, buf = <<>>} = S) ->
    frames(S#mb{buf = Data}, []);
handle_info({tcp, Sock, Data}, #mb{socket = Sock, buf = Buf} = S) ->
    frames(S#mb{buf = <<Buf/binary, Data/binary>>}, []);
handle_info({tcp_closed, Sock}, #mb{socket = Sock} = S) ->
    lost(closed, S);
handle_info({tcp_error, Sock, Why}, #mb{socket = Sock} = S) ->
    lost({network, Why}, S);
handle_info({?MODULE, send_failed, Sock, Why}, #mb{socket = Sock} = S) ->
    lost({network, Why}, S);
handle_info({?MODULE, flush, Sock}, #mb{socket = Sock} = S) ->
    {ok, [], pump(S#mb{flush = false})};
handle_info({inet_reply, Sock, ok}, #mb{socket = Sock} = S) ->
    {ok, [], S};
handle_info({inet_reply, Sock, {error, Why}}, #mb{socket = Sock} = S) ->
    lost({network, Why}, S);
handle_info({timeout, TRef, {?MODULE, deadline}}, #mb{timer = {TRef, _}} = S) ->
    expire(S);
handle_info({?MODULE, connected, Pid, Sock}, #mb{connector = {Pid, MRef}} = S) ->
    erlang:demonitor(MRef, [flush]),
    S1 = S#mb{socket = Sock, connector = undefined},
    case inet:setopts(Sock, [{active, ?ACTIVE_N}]) of
        ok -> {ok, [connected], pump(S1)};
        {error, Why} -> lost({network, Why}, S1)
    end;
handle_info({tcp_passive, Sock}, #mb{socket = Sock} = S) ->
    case inet:setopts(Sock, [{active, ?ACTIVE_N}]) of
        ok -> {ok, [], S};
        {error, Why} -> lost({network, Why}, S)
    end;
handle_info({?MODULE, connected, _OldPid, Sock}, S) ->
    _ = gen_tcp:close(Sock),
    {ok, [], S};
handle_info({?MODULE, connect_failed, Pid, Why}, #mb{connector = {Pid, MRef}} = S) ->
    erlang:demonitor(MRef, [flush]),
    lost({connect, Why}, S#mb{connector = undefined});
handle_info({'DOWN', MRef, process, Pid, Why}, #mb{connector = {Pid, MRef}} = S) ->
    lost({connect, Why}, S#mb{connector = undefined});
handle_info({?MODULE, empty_read, Tag}, #mb{reads = Reads} = S) ->
    case maps:take(Tag, Reads) of
        {Rd, Rest} -> finish_read(Tag, Rd, S#mb{reads = Rest});
        error -> {ok, [{reply, Tag, {ok, []}}], S}
    end;
handle_info({timeout, _, {?MODULE, deadline}}, S) ->
    %% A timer of a connection closed since.
    {ok, [], S};
handle_info(Msg, S) when element(1, Msg) =:= tcp; element(1, Msg) =:= tcp_closed;
                         element(1, Msg) =:= tcp_passive;
                         element(1, Msg) =:= tcp_error; element(1, Msg) =:= inet_reply;
                         element(1, Msg) =:= ?MODULE ->
    %% Of a connection closed since.
    {ok, [], S};
handle_info(_, _) ->
    unknown.

%% Every complete frame in the buffer answers a request in flight.
frames(#mb{buf = Buf} = S, Events) ->
    case cell_hal_modbus_codec:frame(Buf) of
        {ok, Tid, Unit, Pdu, Rest} ->
            case answer(Tid, Unit, Pdu, S#mb{buf = Rest}) of
                {ok, Es, S1} -> frames(S1, lists:reverse(Es, Events));
                {lost, Why} -> lost_after(Why, S, lists:reverse(Events))
            end;
        more ->
            {ok, lists:reverse(Events), pump(S)};
        {error, Why} ->
            lost_after({bad_frame, Why}, S, lists:reverse(Events))
    end.

answer(Tid, Unit, Pdu, #mb{in_flight = InFlight, late = Late} = S) ->
    case maps:take(Tid, InFlight) of
        {#req{unit = Unit, request = R} = Req, Rest} ->
            case cell_hal_modbus_codec:decode_response(R, Pdu) of
                {ok, Reply} -> completed(Req, {ok, Reply}, S#mb{in_flight = Rest});
                {exception, Code} ->
                    Exc = {modbus_exception, Code, cell_hal_modbus_codec:exception_name(Code)},
                    completed(Req, {error, Exc}, S#mb{in_flight = Rest});
                {error, Why} -> {lost, {bad_frame, Why}}
            end;
        {#req{unit = Asked}, _} ->
            {lost, {wrong_unit, Asked, Unit}};
        error when is_map_key(Tid, Late) ->
            {ok, [], S#mb{late = maps:remove(Tid, Late)}};
        error ->
            {lost, {unexpected_tid, Tid}}
    end.

completed(#req{kind = {write, Tag}}, {ok, ok}, S) ->
    {ok, [{reply, Tag, ok}], S};
completed(#req{kind = {write, Tag}}, Error, S) ->
    {ok, [{reply, Tag, Error}], S};
completed(#req{kind = {raw, Tag}}, Result, S) ->
    {ok, [{reply, Tag, Result}], S};
completed(#req{kind = {poll, Tag, Block}, unit = U, request = R}, Result,
          #mb{reads = Reads, resting = Resting} = S) ->
    case Reads of
        #{Tag := #rd{left = Left, values = Vs, refused = Refused} = Rd} ->
            {Rd1, S1} =
                case Result of
                    {ok, Reply} ->
                        {Rd#rd{values = [cell_hal_modbus_plan:decode(Block, Reply) | Vs]},
                         S#mb{resting = maps:remove({U, R}, Resting)}};
                    {error, Exc} ->
                        {Rd#rd{refused = [{Block, U, R, Exc} | Refused]}, rest(U, R, Exc, S)}
                end,
            case Left of
                1 -> finish_read(Tag, Rd1#rd{left = 0}, S1#mb{reads = maps:remove(Tag, Reads)});
                _ -> {ok, [], S1#mb{reads = Reads#{Tag := Rd1#rd{left = Left - 1}}}}
            end;
        #{} ->
            {ok, [], S}
    end.

%% A refused request rests before it is asked again, twice as long as last time.
rest(U, R, Exc, #mb{resting = Resting, refused_retry_ms = Min, max_refused_retry_ms = Max} = S) ->
    Wait = case Resting of
               #{{U, R} := {_, Last, _}} -> min(2 * Last, Max);
               #{} -> Min
           end,
    S#mb{resting = Resting#{{U, R} => {erlang:monotonic_time(millisecond) + Wait, Wait, Exc}}}.

%% A read whose requests are all answered (or refused): the inputs of refused requests
%% are reported unusable before the values go out, those read again usable after.
%% A group refused whole is the `refused_group' option's to decide.
finish_read(Tag, #rd{blocks = Plan, outputs = Outputs, values = Vs, refused = Refused},
            #mb{faulted = Faulted} = S) ->
    Values = lists:append(lists:reverse(Vs)),
    Why = maps:from_list([{K, {refused, U, R, Exc}}
                          || {B, U, R, Exc} <- Refused, K <- cell_hal_modbus_plan:keys(B)]),
    case S#mb.refused_group =:= disconnect andalso
             cell_hal_modbus_plan:refused_groups(Plan, maps:keys(Why), Outputs) of
        [G | _] ->
            [{refused, U, R, Exc} | _] = [W || {{G1, _}, W} <- maps:to_list(Why), G1 =:= G],
            {ok, [{reply, Tag, {error, {group_refused, G, U, R, Exc}}}], S};
        _ ->
            %% Said at every read, not only when it changes: the HAL marks (and logs)
            %% a point only when that changes, and a group removed and added again
            %% has its points unmarked.
            New = [{K, W} || {K, W} <- lists:sort(maps:to_list(Why)), not is_map_key(K, Outputs)],
            Back = [K || {K, _} <- Values, is_map_key(K, Faulted)],
            Faulted1 = maps:without(Back, maps:merge(Faulted, maps:from_list(New))),
            {ok, [{faults, New} || New =/= []] ++ [{reply, Tag, {ok, Values}}]
                 ++ [{faults, [{K, ok} || K <- Back]} || Back =/= []],
             S#mb{faulted = Faulted1}}
    end.

lost(Why, S) ->
    lost_after(Why, S, []).

lost_after(Why, S, Events) ->
    {ok, Events ++ [{lost, Why}], disconnect(S)}.

%%====================================================================
%% Words for operators
%%====================================================================

%% @private
-spec format_reason(term()) -> iodata().
format_reason({connect, econnrefused}) -> "connection refused";
format_reason({connect, Why}) -> ["cannot connect: ", network_error(Why)];
format_reason(closed) -> "the PLC closed the connection";
format_reason({network, Why}) -> ["network error: ", network_error(Why)];
format_reason({no_answer, Ms, Unit, Req}) ->
    io_lib:format("no answer within ~b ms to ~s (unit ~b)",
                  [Ms, cell_hal_modbus_codec:describe(Req), Unit]);
format_reason({bad_frame, Why}) ->
    ["the PLC sent a malformed frame: ", cell_hal_modbus_codec:format_error(Why)];
format_reason({unexpected_tid, Tid}) ->
    io_lib:format("the PLC answered transaction ~b, which was never asked or already "
                  "answered", [Tid]);
format_reason({wrong_unit, Asked, Got}) ->
    io_lib:format("the PLC answered for unit ~b to a request for unit ~b", [Got, Asked]);
format_reason({refused, Unit, Req, {modbus_exception, Code, _}}) ->
    [cell_hal_modbus_codec:exception_text(Code),
     io_lib:format(": ~s (unit ~b)", [cell_hal_modbus_codec:describe(Req), Unit])];
format_reason({group_refused, Group, Unit, Req, {modbus_exception, Code, _}}) ->
    [io_lib:format("the PLC refuses every request of IO group ~s, such as ~s (unit ~b): ",
                   [Group, cell_hal_modbus_codec:describe(Req), Unit]),
     cell_hal_modbus_codec:exception_text(Code)];
format_reason({modbus_exception, Code, _Name}) ->
    cell_hal_modbus_codec:exception_text(Code);
format_reason(timeout) -> "no answer in time";
format_reason({bad_request, What}) ->
    io_lib:format("the request is outside Modbus limits (~s)", [What]);
format_reason(Other) -> io_lib:format("~tp", [Other]).

network_error(nxdomain) -> "unknown host";
network_error(Why) when is_atom(Why) -> inet:format_error(Why);
network_error(Why) -> io_lib:format("~tp", [Why]).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% The requests of a read queued on a connection with no socket (nothing is sent),
%% answered here one by one: `Answers' maps a request to its reply or exception.
answer_read(Tag, Plan, Answers, S0) ->
    {ok, S1} = read(Tag, Plan, S0),
    Reqs = queue:to_list(S1#mb.polls),
    S2 = S1#mb{polls = queue:new()},
    case Reqs of
        [] ->
            receive {?MODULE, empty_read, Tag} = Msg -> handle_info(Msg, S2) end;
        _ ->
            lists:foldl(fun(#req{request = R} = Req, {ok, Es, Sx}) ->
                                Result = case maps:get(R, Answers) of
                                             {exception, C} ->
                                                 {error, {modbus_exception, C, exception_name(C)}};
                                             Reply ->
                                                 {ok, Reply}
                                         end,
                                {ok, Es1, Sx1} = completed(Req, Result, Sx),
                                {ok, Es ++ Es1, Sx1}
                        end, {ok, [], S2}, Reqs)
    end.

exception_name(C) -> cell_hal_modbus_codec:exception_name(C).

%% An exception for one request of a poll: the inputs it reads are reported unusable
%% (the output it covers is not), before the values of the other requests; the request
%% then rests and is not sent, its inputs reported again; answered again, they are
%% usable again after their values.
refused_request_test() ->
    Pt = fun(K, Dir, Field) ->
                 {ok, F} = cell_hal_modbus_plan:field(Dir, int16, Field, #{unit => 1, word_order => big}),
                 #{key => K, dir => Dir, type => int16, field => F}
         end,
    S0 = (init(plc, #{host => "h", port => 1, unit => 1, word_order => big, timeout_ms => 1000,
                      max_in_flight => 1, max_gap => 0}))#mb{refused_retry_ms = 100000,
                                                            max_refused_retry_ms = 100000},
    {Plan, #{requests := 2}} = plan([Pt({g, a}, in, {input_register, 0}),
                                     Pt({g, b}, in, {holding_register, 10}),
                                     Pt({g, c}, out, {holding_register, 11})], S0),
    IR = {read_input_registers, 0, 1},
    HR = {read_holding_registers, 10, 2},
    Why = {refused, 1, HR, {modbus_exception, 2, illegal_data_address}},
    {ok, Events, S1} = answer_read(1, Plan, #{IR => <<7:16>>, HR => {exception, 2}}, S0),
    ?assertEqual([{faults, [{{g, b}, Why}]}, {reply, 1, {ok, [{{g, a}, 7}]}}], Events),
    %% resting: not asked, its input reported again
    {ok, Events2, S2} = answer_read(2, Plan, #{IR => <<8:16>>}, S1),
    ?assertEqual([{faults, [{{g, b}, Why}]}, {reply, 2, {ok, [{{g, a}, 8}]}}], Events2),
    %% its rest over, it is asked again, and answered
    Over = erlang:monotonic_time(millisecond) - 1,
    S3 = S2#mb{resting = maps:map(fun(_, {_, W, E}) -> {Over, W, E} end, S2#mb.resting)},
    {ok, Events3, S4} = answer_read(3, Plan, #{IR => <<8:16>>, HR => <<5:16, 6:16>>}, S3),
    [{reply, 3, {ok, Values3}}, Back] = Events3,
    ?assertEqual([{{g, a}, 8}, {{g, b}, 5}, {{g, c}, 6}], lists:sort(Values3)),
    ?assertEqual({faults, [{{g, b}, ok}]}, Back),
    ?assertEqual(#{}, S4#mb.resting),
    %% a request refused again and again rests twice as long each time, up to the most
    Rests = lists:foldl(fun(_, {Sx, Acc}) ->
                                Sy = rest(1, HR, {modbus_exception, 6, server_device_busy}, Sx),
                                {_, W, _} = maps:get({1, HR}, Sy#mb.resting),
                                {Sy, [W | Acc]}
                        end, {S4#mb{refused_retry_ms = 500, max_refused_retry_ms = 3000}, []},
                        lists:seq(1, 5)),
    ?assertEqual([500, 1000, 2000, 3000, 3000], lists:reverse(element(2, Rests))),
    %% every request of a read refused: no value, the connection still answers
    {ok, Events5, _} = answer_read(5, Plan, #{IR => {exception, 2}, HR => {exception, 2}}, S0),
    ?assertMatch([{faults, [{{g, a}, _}, {{g, b}, _}]}, {reply, 5, {ok, []}}], Events5),
    %% refused_group => disconnect: a group refused whole is an error of the read
    {ok, Events6, _} = answer_read(6, Plan, #{IR => {exception, 2}, HR => {exception, 2}},
                                   S0#mb{refused_group = disconnect}),
    ?assertMatch([{reply, 6, {error, {group_refused, g, 1, _, {modbus_exception, 2, _}}}}],
                 Events6),
    %% ... but one input of it read keeps it
    {ok, Events7, _} = answer_read(7, Plan, #{IR => <<1:16>>, HR => {exception, 2}},
                                   S0#mb{refused_group = disconnect}),
    ?assertEqual([{faults, [{{g, b}, Why}]}, {reply, 7, {ok, [{{g, a}, 1}]}}], Events7).

%% Transaction ids run 0..65535 and on from 0, never taking one still in flight.
next_tid_test_() ->
    Req = #req{kind = {raw, x}, unit = 1, request = {read_coils, 0, 1}, timeout = 1},
    S = #mb{tid = 65534},
    {A, S1} = next_tid(S),
    {B, S2} = next_tid(S1),
    {C, _} = next_tid(S2),
    Busy = #mb{tid = 65535, in_flight = #{65535 => Req, 0 => Req, 1 => Req}},
    {D, _} = next_tid(Busy),
    {E, S3} = next_tid(#mb{tid = 5, late = #{5 => true, 6 => true}}),
    [?_assertEqual([65534, 65535, 0], [A, B, C]),
     ?_assertEqual(2, D),
     %% A late answer's id given to a new request is no longer late.
     ?_assertEqual({5, #{6 => true}}, {E, S3#mb.late})].

options_test_() ->
    [?_assertEqual({error, {bad_option, host}}, check_opts(#{})),
     ?_assertMatch({ok, #{port := 502, unit := 1, word_order := big, timeout_ms := 1000,
                          max_in_flight := 1, max_gap := 0}}, check_opts(#{host => "plc1"})),
     ?_assertMatch({ok, _}, check_opts(#{host => {10, 0, 0, 5}})),
     ?_assertMatch({ok, _}, check_opts(#{host => <<"10.0.0.5">>})),
     ?_assertEqual({error, {bad_option, host}}, check_opts(#{host => ""})),
     ?_assertEqual({error, {bad_option, host}}, check_opts(#{host => {1, 2, 3}})),
     ?_assertEqual({error, {bad_option, port}}, check_opts(#{host => "h", port => 0})),
     ?_assertEqual({error, {bad_option, port}}, check_opts(#{host => "h", port => 65536})),
     ?_assertEqual({error, {bad_option, unit}}, check_opts(#{host => "h", unit => 256})),
     ?_assertEqual({error, {bad_option, word_order}}, check_opts(#{host => "h", word_order => cdab})),
     ?_assertEqual({error, {bad_option, max_in_flight}}, check_opts(#{host => "h", max_in_flight => 0})),
     ?_assertEqual({error, {bad_option, max_gap}}, check_opts(#{host => "h", max_gap => 125})),
     ?_assertMatch({ok, #{refused_group := fault, refused_retry_ms := 500,
                          max_refused_retry_ms := 30000}}, check_opts(#{host => "h"})),
     ?_assertMatch({ok, #{refused_group := disconnect}},
                   check_opts(#{host => "h", refused_group => disconnect})),
     ?_assertEqual({error, {bad_option, refused_group}},
                   check_opts(#{host => "h", refused_group => ignore})),
     ?_assertEqual({error, {bad_option, refused_retry_ms}},
                   check_opts(#{host => "h", refused_retry_ms => 0})),
     ?_assertEqual({error, {bad_option, max_refused_retry_ms}},
                   check_opts(#{host => "h", refused_retry_ms => 1000,
                                max_refused_retry_ms => 999})),
     ?_assertEqual({error, {bad_option, colour}}, check_opts(#{host => "h", colour => red}))].

reasons_read_as_words_test_() ->
    [?_assertEqual("connection refused", lists:flatten(format_reason({connect, econnrefused}))),
     ?_assertEqual("cannot connect: unknown host",
                   lists:flatten(format_reason({connect, nxdomain}))),
     ?_assertEqual("no answer within 1000 ms to read holding registers 0..9 (unit 1)",
                   lists:flatten(format_reason({no_answer, 1000, 1, {read_holding_registers, 0, 10}}))),
     ?_assertEqual("the PLC refuses this address (illegal data address, Modbus exception 2): "
                   "read input registers 5 (unit 2)",
                   lists:flatten(format_reason({refused, 2, {read_input_registers, 5, 1},
                                                {modbus_exception, 2, illegal_data_address}}))),
     ?_assertEqual("the PLC refuses every request of IO group io, such as read coils 3..4 "
                   "(unit 1): the device behind the gateway did not answer (gateway target "
                   "failed to respond, Modbus exception 11)",
                   lists:flatten(format_reason({group_refused, io, 1, {read_coils, 3, 2},
                                                {modbus_exception, 11, gateway_target_failed_to_respond}}))),
     ?_assertEqual("the PLC does not offer this function (illegal function, Modbus exception 1)",
                   lists:flatten(format_reason({modbus_exception, 1, illegal_function}))),
     ?_assertEqual("the PLC answered for unit 3 to a request for unit 1",
                   lists:flatten(format_reason({wrong_unit, 1, 3})))].
-endif.
