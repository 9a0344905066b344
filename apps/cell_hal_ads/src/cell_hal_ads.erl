%% @doc The HAL's Beckhoff TwinCAT ADS driver: IO groups of a TwinCAT PLC (or of an IO
%% device's image) read and written through the HAL exactly like Modbus ones. A thin
%% layer over {@link cell_hal_ads_client}, which does the ADS work: symbols checked by
%% name, handles, sum commands, notifications with the PLC's time stamps.
%%
%% ```
%% ok = cell_hal:add_connection(#{id => plc1, driver => cell_hal_ads,
%%                                opts => #{host => "10.0.0.5",
%%                                          target_net_id => "10.0.0.5.1.1"}}),
%% ok = cell_hal:add_group(#{id => general, module => general_io, connection => plc1,
%%                           opts => #{input_struct => <<"MAIN.GeneralInputs">>,
%%                                     output_struct => <<".GeneralOutputs">>}}).
%% '''
%%
%% == Connection options ==
%% <table>
%% <tr><th>option</th><th>default</th><th></th></tr>
%% <tr><td>`host'</td><td>(required)</td><td>the PLC's name or address</td></tr>
%% <tr><td>`target_net_id'</td><td>(required)</td><td>the PLC's AMS Net ID,
%%   "10.0.0.5.1.1"</td></tr>
%% <tr><td>`target_port'</td><td>851</td><td>the AMS port: 851 for the first TwinCAT 3
%%   PLC runtime (801 on TwinCAT 2), or an IO device's image port</td></tr>
%% <tr><td>`port'</td><td>48898</td><td>the TCP port of the PLC's AMS router</td></tr>
%% <tr><td>`source_net_id'</td><td>`auto'</td><td>our AMS Net ID (`auto': this machine's
%%   address on the PLC's network and ".1.1"); the PLC needs a route for it</td></tr>
%% <tr><td>`source_port'</td><td>32905</td><td>our AMS port</td></tr>
%% <tr><td>`timeout_ms'</td><td>1000</td><td>how long one read or write may go
%%   unanswered</td></tr>
%% <tr><td>`access'</td><td>`handle'</td><td>symbols reached by handle, or by index group
%%   and offset (`address', the usual way to IO images)</td></tr>
%% <tr><td>`sum_commands', `max_sum'</td><td>`true', 500</td><td>a group read in one sum
%%   command, split at `max_sum' points</td></tr>
%% <tr><td>`max_in_flight'</td><td>64</td><td>requests sent before the first answer</td></tr>
%% <tr><td>`symbol_version'</td><td>`watch'</td><td>how program changes are noticed
%%   (`watch', `read' when handles fail, `ignore')</td></tr>
%% <tr><td>`link_check', `max_frame', `handle_idle'</td><td></td><td>as
%%   {@link cell_hal_ads_client}</td></tr>
%% </table>
%%
%% The TwinCAT router takes one TCP connection from a host: give each PLC host one HAL
%% connection.
%%
%% == Group fields and options ==
%% A point's `field' is a structure member, `<<".StartButton">>', inside the group
%% instance's `input_struct' or `output_struct' (seed 000 §4.1.1: `<<".GeneralInputs">>'
%% for a VAR_GLOBAL, `<<"MAIN.GeneralInputs">>' under a program), or an IO image's
%% unique name with its wildcard, `<<"*ManipulatorInputs.FailPaletteIsIn">>' (§4.1.2;
%% the connection's `target_port' is then the image's ADS port, and `access =>
%% address' reads it by index group and offset). Group instance options for ADS:
%% <ul>
%% <li>`input_struct', `output_struct': as above;</li>
%% <li>`notify': `all' or a list of input names fed by device notifications instead of
%%   polling; their samples keep the PLC's time stamps ({@link cell_hal:samples/3});</li>
%% <li>`notify_opts': `#{mode => on_change | cyclic, cycle_us, max_delay_us}' for them
%%   (default on change, the PLC checking every 10 ms, sent at once).</li>
%% </ul>
%%
%% == How the HAL's work maps onto ADS ==
%% <ul>
%% <li>A read of a plan: its symbols are resolved once per connection (checked: they
%%   exist, one match for "*", their type and size fit the point's), then every polled
%%   point in one sum command (0xF080 by handles); notified points are answered from
%%   their last sample, the first read waiting for the first one.</li>
%% <li>A write: one ADS Write by handle (0xF005), in the order the HAL queued them,
%%   several in flight. The realtime trigger of seed 000 §2.3.7 (enabling a PLC
%%   variable just before an expected edge) is a `cell_hal:write/3' to an output
%%   point on that variable: two process hops and one round trip.</li>
%% <li>A symbol the PLC lacks, or of another type: its points are reported unusable
%%   (`{faults, ...}', read `{unavailable, Why}'), the rest of the group works on, and
%%   they are tried again after every program change (symbol version).</li>
%% <li>A program change (online change or download): the client takes new handles and
%%   notifications; the connection stays up.</li>
%% <li>A lost connection: the client stops with the reason, the worker logs it, waits
%%   and connects again with a new client; handles and notifications come back.</li>
%% </ul>
%% Raw requests (`cell_hal:request/3'): `read_device_info', `read_state', `symbols' (the
%% PLC's symbol table), `{read, Group, Offset, Length}', `{write, Group, Offset, Data}',
%% `{read_write, Group, Offset, Length, Data}'.
%%
%% Handles and notifications of a group removed while the connection is up stay until
%% the connection closes.
-module(cell_hal_ads).
-behaviour(cell_hal_driver).

-export([check_opts/1, check_point/4, init/2, endpoint/1, connect/1, plan/2, read/3,
         write/4, request/4, handle_info/2, disconnect/1, format_reason/1]).

-export_type([field/0]).

-type key() :: cell_hal_driver:key().
-type var() :: cell_hal_ads_client:var().
-type sub_opts() :: cell_hal_ads_client:sub_opts().
%% A point's field as check_point/4 resolves it.
-type field() :: #{symbol := binary(), notify := false | sub_opts()}.
%% How a point is read: polled (and written) by handle, or fed by a notification.
-type entry() :: {poll, var()} | {notify, var(), sub_opts()}.
-type plan() :: [{key(), in | out, entry()}].

%% An entry's state on this connection: not asked yet, being resolved (or
%% subscribed), usable, or not usable for a reason. `held': the client counts a use of
%% it by this connection.
-record(entry, {state = new :: new | resolving | ready | {fault, term()},
                held = false :: boolean()}).

-record(read, {points :: plan(),
               timer :: reference(),
               asked = false :: boolean(),          %% the read of polled points went out
               %% each polled entry's result: from the read's answer, or the fault it
               %% had when the read went out
               answer :: undefined | {asked, #{entry() => {error, term()}}}
                       | #{entry() => {ok, term()} | {error, term()}}}).

-record(ads, {id :: atom(),
              client_opts :: map(),
              timeout :: pos_integer(),
              gen = 0 :: non_neg_integer(),          %% one a connection, in every label
              client :: pid() | undefined,
              mref :: reference() | undefined,
              up = false :: boolean(),
              reqs = gen_statem:reqids_new() :: cell_hal_ads_client:request_ids(),
              entries = #{} :: #{entry() => #entry{}},
              keys = #{} :: #{entry() => [key()]},   %% the points each entry serves
              points = #{} :: #{key() => {in | out, entry()}},
              subs = #{} :: #{reference() => entry()},
              latest = #{} :: #{entry() => cell_hal_type:value()},
              faulted = #{} :: #{key() => term()},   %% as last reported
              reads = #{} :: #{term() => #read{}},
              writes = queue:new() :: queue:queue({term(), entry(), cell_hal_type:value()}),
              outbox = [] :: [cell_hal_driver:event()],   %% events for the next message
              kicked = false :: boolean()}).

%% Options of the client the driver sets itself.
-define(OWN_CLIENT_OPTS, [name, log_variables, request_timeout, connect_timeout]).
-define(DEFAULT_TIMEOUT_MS, 1000).
%% A read waits for resolving, the sum read and first samples: each within the
%% client's deadline, this only bounds what the client cannot (a sample that never
%% comes).
-define(READ_DEADLINES, 3).
%% Errors that say a point's symbol cannot be used, not that the connection failed.
-define(STALE_HANDLE_ERRORS, [16#710, 16#711, 16#714, 16#722]).

%%====================================================================
%% Options and fields
%%====================================================================

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    {Timeout, ClientOpts} = case maps:take(timeout_ms, Opts) of
                                {T, Rest} -> {T, Rest};
                                error -> {?DEFAULT_TIMEOUT_MS, Opts}
                            end,
    case [K || K <- ?OWN_CLIENT_OPTS, maps:is_key(K, ClientOpts)] of
        [Own | _] ->
            {error, {bad_option, Own}};
        [] when not (is_integer(Timeout) andalso Timeout > 0) ->
            {error, {bad_option, timeout_ms}};
        [] ->
            case cell_hal_ads_client:check_opts(ClientOpts) of
                {ok, Full} -> {ok, maps:without(?OWN_CLIENT_OPTS, Full#{timeout_ms => Timeout})};
                {error, _} = E -> E
            end
    end.

%% @private
-spec check_point(map(), atom(), map(), cell_hal_group:point_def()) ->
          {ok, field()} | {error, term()}.
check_point(_Opts, _Group, GroupOpts, #{name := Name, dir := Dir, field := Field}) ->
    case cell_hal_group:ads_symbol(Dir, Field, GroupOpts) of
        {ok, {symbol, Full}} -> with_notify(Full, Name, Dir, GroupOpts);
        {ok, {image, Image}} -> with_notify(<<"*", Image/binary>>, Name, Dir, GroupOpts);
        {error, _} = E -> E
    end.

with_notify(Symbol, Name, Dir, GroupOpts) ->
    case cell_hal_ads_symbols:check_name(Symbol) of
        ok ->
            case notified(Name, Dir, GroupOpts) of
                {ok, Notify} -> {ok, #{symbol => Symbol, notify => Notify}};
                {error, _} = E -> E
            end;
        {error, _} ->
            {error, bad_field}
    end.

%% Whether the group's options have the point fed by notifications, and how.
notified(Name, Dir, GroupOpts) ->
    Listed = case maps:get(notify, GroupOpts, []) of
                 all -> Dir =:= in;
                 Names when is_list(Names) -> lists:member(Name, Names);
                 _ -> bad
             end,
    case {Listed, Dir, sub_opts(maps:get(notify_opts, GroupOpts, #{}))} of
        {bad, _, _} -> {error, notify};
        {_, _, error} -> {error, notify_opts};
        {true, out, _} -> {error, {notify, output}};
        {true, in, {ok, O}} -> {ok, O};
        {false, _, _} -> {ok, false}
    end.

-define(MAX_US, (16#FFFFFFFF div 10)).
sub_opts(O) when is_map(O) ->
    Valid = fun(mode, M) -> M =:= on_change orelse M =:= cyclic;
               (K, Us) when K =:= cycle_us; K =:= max_delay_us ->
                    is_integer(Us) andalso Us >= 0 andalso Us =< ?MAX_US;
               (_, _) -> false
            end,
    case maps:fold(fun(K, V, Ok) -> Ok andalso Valid(K, V) end, true, O) of
        true -> {ok, O};
        false -> error
    end;
sub_opts(_) ->
    error.

%%====================================================================
%% Connection
%%====================================================================

%% @private
-spec init(atom(), map()) -> #ads{}.
init(Id, Opts) ->
    {Timeout, ClientOpts} = maps:take(timeout_ms, Opts),
    #ads{id = Id, timeout = Timeout,
         client_opts = ClientOpts#{name => <<"hal/", (atom_to_binary(Id))/binary>>,
                                   log_variables => false,
                                   request_timeout => Timeout}}.

%% @private
-spec endpoint(#ads{}) -> iodata().
endpoint(#ads{client_opts = #{host := Host, port := Port, target_net_id := Net,
                              target_port := TPort}}) ->
    HostText = case is_tuple(Host) of
                   true -> inet:ntoa(Host);
                   false -> Host
               end,
    [HostText, $:, integer_to_list(Port), ", AMS ", cell_hal_ads_codec:format_net_id(Net),
     $:, integer_to_list(TPort)].

%% @private
%% A client is one connection: it stops with the reason when the connection fails,
%% and the worker decides when to try again.
-spec connect(#ads{}) -> {ok, #ads{}}.
connect(#ads{client_opts = Opts} = S) ->
    case cell_hal_ads_client:start_link(Opts) of
        {ok, Pid} ->
            S1 = S#ads{client = Pid, mref = erlang:monitor(process, Pid)},
            {ok, ask(subscribe_status, status, S1)};
        {error, Why} ->
            %% Options were checked when the connection was added: not expected.
            self() ! {?MODULE, S#ads.gen, failed, Why},
            {ok, S}
    end.

%% @private
-spec disconnect(#ads{}) -> #ads{}.
disconnect(#ads{client = Client, mref = MRef, reads = Reads} = S) ->
    _ = is_reference(MRef) andalso erlang:demonitor(MRef, [flush]),
    %% Its parent's exit signal ends the client through its terminate/3, which gives
    %% the PLC its handles and notifications back.
    _ = is_pid(Client) andalso exit(Client, shutdown),
    maps:foreach(fun(_, #read{timer = T}) -> _ = erlang:cancel_timer(T) end, Reads),
    %% Requests still out keep their old generation: their answers are dropped.
    S#ads{gen = S#ads.gen + 1, client = undefined, mref = undefined, up = false,
          entries = #{}, subs = #{}, latest = #{}, faulted = #{}, reads = #{},
          writes = queue:new(), outbox = [], kicked = false}.

%%====================================================================
%% Plans, reads, writes
%%====================================================================

%% @private
-spec plan([cell_hal_driver:point()], #ads{}) ->
          {plan(), #{requests := non_neg_integer(), pushed := non_neg_integer()}}.
plan(Points, #ads{client_opts = Opts}) ->
    Plan = [{K, Dir, entry(Dir, T, F)}
            || #{key := K, dir := Dir, type := T, field := F} <- Points],
    Polled = length(lists:usort([V || {_, _, {poll, V}} <- Plan])),
    Pushed = length([K || {K, _, {notify, _, _}} <- Plan]),
    {Plan, #{requests => requests(Polled, Opts), pushed => Pushed}}.

entry(in, Type, #{symbol := Name, notify := Sub}) when is_map(Sub) ->
    {notify, {Name, Type}, Sub};
entry(_, Type, #{symbol := Name}) ->
    {poll, {Name, Type}}.

requests(0, _) -> 0;
requests(N, #{sum_commands := true, max_sum := Max}) -> (N + Max - 1) div Max;
requests(N, #{sum_commands := false}) -> N.

%% @private
-spec read(term(), plan(), #ads{}) -> {ok, #ads{}}.
read(Tag, Plan, #ads{timeout = T} = S) ->
    Timer = erlang:start_timer(?READ_DEADLINES * T, self(), {?MODULE, S#ads.gen, Tag}),
    S1 = learn(Plan, S#ads{reads = (S#ads.reads)#{Tag => #read{points = Plan, timer = Timer}}}),
    queued(advance(ensure([E || {_, _, E} <- Plan], S1))).

%% @private
-spec write(term(), cell_hal_driver:point(), cell_hal_type:value(), #ads{}) -> {ok, #ads{}}.
write(Tag, #{key := K, dir := Dir, type := T, field := F}, V, S) ->
    E = entry(Dir, T, F),
    S1 = learn([{K, Dir, E}], S#ads{writes = queue:in({Tag, E, V}, S#ads.writes)}),
    queued(advance(ensure([E], S1))).

%% @private
-spec request(term(), term(), pos_integer(), #ads{}) -> {ok, #ads{}} | {error, term()}.
request(Tag, Request, Timeout, #ads{client = Client, reqs = Reqs} = S)
  when is_pid(Client) ->
    Raw = Request =:= read_device_info orelse Request =:= read_state
        orelse Request =:= symbols orelse
        (is_tuple(Request) andalso lists:member(element(1, Request),
                                                [read, write, read_write])),
    case Raw andalso cell_hal_ads_client:send_request(Client, Request, Timeout,
                                                       {S#ads.gen, {request, Tag}}, Reqs) of
        {ok, Reqs1} -> {ok, S#ads{reqs = Reqs1}};
        {error, _} = E -> E;
        false -> {error, {bad_request, Request}}
    end;
request(_, _, _, _) ->
    {error, disconnected}.

%% The points an entry serves, for the events about them.
learn(Plan, S) ->
    lists:foldl(fun learn_point/2, S, Plan).

learn_point({K, Dir, E}, #ads{points = Points} = S) ->
    case Points of
        #{K := {Dir, E}} ->
            S;
        #{K := {_, Old}} ->
            %% A group added again under its old name, its point on another symbol: the
            %% old entry serves it no more.
            S1 = S#ads{keys = maps:update_with(Old, fun(Ks) -> lists:delete(K, Ks) end,
                                               S#ads.keys)},
            serve_point(K, Dir, E, S1);
        #{} ->
            serve_point(K, Dir, E, S)
    end.

serve_point(K, Dir, E, #ads{keys = Keys, points = Points} = S) ->
    S#ads{keys = maps:update_with(E, fun(Ks) -> [K | Ks] end, [K], Keys),
          points = Points#{K => {Dir, E}}}.

outputs_of(E, #ads{keys = Keys, points = Points}) ->
    [K || K <- maps:get(E, Keys, []), element(1, maps:get(K, Points)) =:= out].

%% Entries not asked for on this connection are resolved (polled ones, all in one
%% request) or subscribed to (notified ones, all in one request).
ensure(Entries, S) ->
    New = lists:usort([E || E <- Entries, state(E, S) =:= new]),
    Polled = [V || {poll, V} <- New],
    Notified = [{V, O} || {notify, V, O} <- New],
    S1 = case Polled of
             [] -> S;
             _ -> ask({resolve, Polled}, {resolve, Polled}, set_state(New, resolving, S))
         end,
    case Notified of
        [] -> S1;
        _ -> ask({subscribe, Notified}, {subscribe, Notified}, set_state(New, resolving, S1))
    end.

state(E, #ads{entries = Es}) ->
    case Es of
        #{E := #entry{state = State}} -> State;
        #{} -> new
    end.

set_state(Entries, State, #ads{entries = Es} = S) ->
    S#ads{entries = lists:foldl(fun(E, Acc) ->
                                        Old = maps:get(E, Acc, #entry{}),
                                        Acc#{E => Old#entry{state = State}}
                                end, Es, Entries)}.

settled(E, S) ->
    case state(E, S) of
        ready -> true;
        {fault, _} -> true;
        _ -> false
    end.

%% Sends a request to the client, labelled with this connection's generation.
ask(Request, Label, #ads{client = Client, reqs = Reqs, timeout = T, gen = Gen} = S) ->
    {ok, Reqs1} = cell_hal_ads_client:send_request(Client, Request, T, {Gen, Label}, Reqs),
    S#ads{reqs = Reqs1}.

%% Moves reads and writes on as far as what is known allows.
advance(S) ->
    advance_writes(advance_reads(S)).

advance_reads(#ads{reads = Reads} = S) ->
    maps:fold(fun(Tag, R, Acc) -> advance_read(Tag, R, Acc) end, S, Reads).

advance_read(Tag, #read{asked = false, points = Plan} = R, S) ->
    case lists:all(fun({_, _, E}) -> settled(E, S) end, Plan) of
        true ->
            Polled = lists:usort([E || {_, _, {poll, _} = E} <- Plan]),
            Faulted = maps:from_list([{E, {error, Why}} || E <- Polled,
                                                          {fault, Why} <- [state(E, S)]]),
            case [V || {poll, V} = E <- Polled, not is_map_key(E, Faulted)] of
                [] ->
                    finish_read(Tag, R#read{asked = true, answer = Faulted}, S);
                Vars ->
                    S1 = ask({read_vars, Vars}, {read, Tag, Vars}, S),
                    S1#ads{reads = (S1#ads.reads)#{Tag := R#read{asked = true,
                                                                  answer = {asked, Faulted}}}}
            end;
        false ->
            S
    end;
advance_read(Tag, #read{answer = Answer} = R, S) when is_map(Answer) ->
    finish_read(Tag, R, S);
advance_read(_, _, S) ->
    S.

%% A read whose polled points are answered completes once every notified point has
%% its first sample (or is unusable).
finish_read(Tag, #read{points = Plan, answer = Answer, timer = Timer}, S) ->
    Waiting = [E || {_, _, {notify, _, _} = E} <- Plan, state(E, S) =:= ready,
                    not is_map_key(E, S#ads.latest)],
    case Waiting of
        [] ->
            _ = erlang:cancel_timer(Timer),
            S1 = S#ads{reads = maps:remove(Tag, S#ads.reads)},
            result(Tag, [{K, point_result(E, Answer, S1)} || {K, _, E} <- Plan], S1);
        _ ->
            S#ads{reads = (S#ads.reads)#{Tag => #read{points = Plan, answer = Answer,
                                                        timer = Timer, asked = true}}}
    end.

point_result({poll, _} = E, Answer, _) ->
    maps:get(E, Answer);
point_result({notify, _, _} = E, _, S) ->
    case state(E, S) of
        {fault, Why} -> {error, Why};
        ready -> {ok, maps:get(E, S#ads.latest)}
    end.

%% The values of a read, the points it could not serve reported first. A read that
%% served no point because the PLC refused or did not answer has failed.
result(Tag, Results, S) ->
    Values = [{K, V} || {K, {ok, V}} <- Results],
    Errors = [{K, Why} || {K, {error, Why}} <- Results],
    case [Why || {_, Why} <- Errors, not symbol_error(Why)] of
        [Why | _] when Values =:= [] ->
            emit([{reply, Tag, {error, Why}}], S);
        _ ->
            served(Values, emit([{reply, Tag, {ok, Values}}], faults(Errors, S)))
    end.

%% Reports points newly unusable (before their values could be read as fresh).
faults(Errors, #ads{faulted = F} = S) ->
    case [{K, Why} || {K, Why} <- Errors, maps:get(K, F, none) =/= Why] of
        [] -> S;
        New -> emit([{faults, New}], S#ads{faulted = maps:merge(F, maps:from_list(New))})
    end.

%% Points that gave a value are usable again (after the value is stored).
served(Values, #ads{faulted = F} = S) ->
    case [K || {K, _} <- Values, is_map_key(K, F)] of
        [] -> S;
        Back -> emit([{faults, [{K, ok} || K <- Back]}], S#ads{faulted = maps:without(Back, F)})
    end.

symbol_error({unknown_symbol, _}) -> true;
symbol_error({ambiguous_symbol, _, _}) -> true;
symbol_error({type_mismatch, _, _}) -> true;
symbol_error({not_resolved, _}) -> true;
symbol_error({symbol_error, _, _}) -> true;
symbol_error({symbol_table, _}) -> true;
symbol_error({bad_size, _, _}) -> true;
symbol_error({ads_error, Code, _}) -> lists:member(Code, ?STALE_HANDLE_ERRORS);
symbol_error(_) -> false.

%% Writes go out in the order queued, each once its entry is settled.
advance_writes(#ads{writes = Q} = S) ->
    case queue:peek(Q) of
        {value, {Tag, E, V}} ->
            case state(E, S) of
                ready ->
                    {poll, Var} = E,
                    S1 = ask({write_vars, [{Var, V}]}, {write, Tag, E}, S),
                    advance_writes(S1#ads{writes = queue:drop(Q)});
                {fault, Why} ->
                    advance_writes(emit([{reply, Tag, {error, Why}}], S#ads{writes = queue:drop(Q)}));
                _ ->
                    S
            end;
        empty ->
            S
    end.

%% Events found while the worker called in wait for the next message: a kick to self.
emit(Events, #ads{outbox = Out} = S) ->
    S#ads{outbox = lists:reverse(Events, Out)}.

queued(#ads{outbox = [], kicked = _} = S) ->
    {ok, S};
queued(#ads{kicked = true} = S) ->
    {ok, S};
queued(S) ->
    self() ! {?MODULE, kick},
    {ok, S#ads{kicked = true}}.

%%====================================================================
%% Messages
%%====================================================================

%% @private
-spec handle_info(term(), #ads{}) -> {ok, [cell_hal_driver:event()], #ads{}} | unknown.
handle_info({?MODULE, kick}, S) ->
    events(S#ads{kicked = false});
handle_info({'DOWN', MRef, process, _, Why}, #ads{mref = MRef} = S) ->
    Reason = case Why of
                 {shutdown, R} -> R;
                 Other -> {client_exited, Other}
             end,
    {ok, outbox(S) ++ [{lost, Reason}], S#ads{outbox = [], mref = undefined}};
handle_info({cell_hal_ads, Client, Status}, #ads{client = Client} = S) when is_pid(Client) ->
    status(Status, S);
handle_info({cell_hal_ads, Ref, Msg}, #ads{subs = Subs} = S) when is_reference(Ref) ->
    case Subs of
        #{Ref := E} -> events(note(E, Msg, S));
        #{} -> {ok, [], S}          %% of a connection closed since
    end;
handle_info({cell_hal_ads, _, _}, S) ->
    {ok, [], S};
handle_info({timeout, _, {?MODULE, Gen, Tag}}, #ads{gen = Gen, reads = Reads} = S) ->
    case maps:take(Tag, Reads) of
        {_, Rest} ->
            Ms = ?READ_DEADLINES * S#ads.timeout,
            events(emit([{reply, Tag, {error, {no_answer, Ms}}}], S#ads{reads = Rest}));
        error ->
            {ok, [], S}
    end;
handle_info({?MODULE, Gen, failed, Why}, #ads{gen = Gen} = S) ->
    {ok, [{lost, Why}], S};
handle_info({timeout, _, {?MODULE, _, _}}, S) ->
    {ok, [], S};
handle_info({?MODULE, _, failed, _}, S) ->
    {ok, [], S};
handle_info(Msg, #ads{reqs = Reqs} = S) ->
    case cell_hal_ads_client:check_response(Msg, Reqs) of
        {Result, {Gen, Label}, Reqs1} when Gen =:= S#ads.gen ->
            events(answer(Label, Result, S#ads{reqs = Reqs1}));
        {_, _, Reqs1} ->
            {ok, [], S#ads{reqs = Reqs1}};   %% for a connection closed since
        _ ->
            unknown
    end.

events(S) ->
    S1 = advance(S),
    {ok, outbox(S1), S1#ads{outbox = []}}.

outbox(#ads{outbox = Out}) ->
    lists:reverse(Out).

status(up, #ads{up = false} = S) ->
    {ok, [connected], S#ads{up = true}};
status(symbols_changed, S) ->
    events(retry(S));
status(_, S) ->
    %% `{down, _}': its exit follows, and says why.
    {ok, [], S}.

%% After a program change the client has taken new handles and notifications for
%% what it holds; what could not be used before is asked for again: entries never
%% resolved, and outputs whose writes found their symbol gone (inputs tell by their
%% next read).
retry(#ads{entries = Es, faulted = F} = S) ->
    Again = [E || {E, #entry{state = State, held = Held}} <- maps:to_list(Es),
                  case {E, State, Held} of
                      {_, {fault, _}, false} -> true;
                      {{poll, _}, _, true} ->
                          lists:any(fun(K) -> is_map_key(K, F) end, outputs_of(E, S));
                      _ -> false
                  end],
    ensure(Again, set_state(Again, new, S)).

%%--------------------------------------------------------------------
%% Answers of the client
%%--------------------------------------------------------------------

answer(status, _, S) ->
    S;
answer(release, _, S) ->
    S;
answer({resolve, Vars}, {ok, Results}, S) ->
    resolved([{{poll, V}, R} || {V, R} <- lists:zip(Vars, Results)], S);
answer({subscribe, Subs}, {ok, Results}, S) ->
    resolved([{{notify, V, O}, R} || {{V, O}, R} <- lists:zip(Subs, Results)], S);
answer({Kind, Asked}, {error, {_, Client}}, S)
  when Kind =:= resolve orelse Kind =:= subscribe, is_pid(Client) ->
    %% The client exited: its monitor says why.
    set_state(asked_entries(Kind, Asked), new, S);
answer({Kind, Asked}, {error, Why}, S) when Kind =:= resolve orelse Kind =:= subscribe ->
    %% The PLC did not answer in time (or the connection closed): whatever waits on
    %% these fails, and they are asked for again by the next read.
    Entries = asked_entries(Kind, Asked),
    fail_waiting(Entries, Why, set_state(Entries, new, S));
answer({read, Tag, Vars}, {ok, Results}, #ads{reads = Reads} = S) ->
    case Reads of
        #{Tag := #read{answer = {asked, Faulted}} = R} ->
            Answer = maps:merge(Faulted, maps:from_list([{{poll, V}, Result}
                                                         || {V, Result} <- lists:zip(Vars, Results)])),
            S#ads{reads = Reads#{Tag := R#read{answer = Answer}}};
        #{} ->
            S
    end;
answer({read, Tag, _}, {error, Why}, #ads{reads = Reads} = S) ->
    case maps:take(Tag, Reads) of
        {#read{timer = T}, Rest} ->
            _ = erlang:cancel_timer(T),
            emit([{reply, Tag, {error, error_reason(Why)}}], S#ads{reads = Rest});
        error ->
            S
    end;
answer({write, Tag, E}, Result, S) ->
    case Result of
        {ok, [ok]} ->
            emit([{reply, Tag, ok}], S);
        {ok, [{error, Why}]} ->
            S1 = case symbol_error(Why) of
                     true -> faults([{K, Why} || K <- maps:get(E, S#ads.keys, [])],
                                    set_state([E], {fault, Why}, S));
                     false -> S
                 end,
            emit([{reply, Tag, {error, Why}}], S1);
        {error, Why} ->
            emit([{reply, Tag, {error, error_reason(Why)}}], S)
    end;
answer({request, Tag}, Result, S) ->
    Reply = case Result of
                ok -> {ok, ok};
                {ok, _} -> Result;
                {error, Why} -> {error, error_reason(Why)}
            end,
    emit([{reply, Tag, Reply}], S).

asked_entries(resolve, Vars) -> [{poll, V} || V <- Vars];
asked_entries(subscribe, Subs) -> [{notify, V, O} || {V, O} <- Subs].

%% `{Reason, Client}' of a client that exited: only the reason.
error_reason({Why, Client}) when is_pid(Client) -> {client_exited, Why};
error_reason(Why) -> Why.

%% Entries resolved (or subscribed to), or not usable, one result each.
resolved(Results, S) ->
    lists:foldl(fun({E, {ok, Ref}}, Acc) when is_reference(Ref) ->
                        ready(E, Acc#ads{subs = (Acc#ads.subs)#{Ref => E}});
                   ({E, {ok, _Info}}, Acc) ->
                        ready(E, Acc);
                   ({E, {error, Why}}, Acc) ->
                        #entry{held = Held} = maps:get(E, Acc#ads.entries, #entry{}),
                        Acc1 = Acc#ads{entries = (Acc#ads.entries)#{
                                                   E => #entry{state = {fault, Why},
                                                               held = Held}}},
                        faults([{K, Why} || K <- maps:get(E, Acc1#ads.keys, [])], Acc1)
                end, S, Results).

ready(E, #ads{entries = Es} = S) ->
    Old = maps:get(E, Es, #entry{}),
    S1 = S#ads{entries = Es#{E => Old#entry{state = ready, held = true}}},
    %% Asked again while held (an output after a program change): one use is enough.
    S2 = case {Old#entry.held, E} of
             {true, {poll, Var}} -> ask({release, [Var]}, release, S1);
             _ -> S1
         end,
    %% Outputs are not read by polls: usable again is said now (the worker reads
    %% them back). Inputs say so with their next value.
    Outputs = [K || K <- outputs_of(E, S2), is_map_key(K, S2#ads.faulted)],
    case Outputs of
        [] -> S2;
        _ -> emit([{faults, [{K, ok} || K <- Outputs]}],
                  S2#ads{faulted = maps:without(Outputs, S2#ads.faulted)})
    end.

%% Whatever waits on entries that could not be asked for fails.
fail_waiting(Entries, Why, #ads{reads = Reads, writes = Q} = S) ->
    Hit = fun(E) -> lists:member(E, Entries) end,
    {Failed, Kept} = maps:fold(fun(Tag, #read{points = Plan, timer = T} = R, {F, K}) ->
                                       case lists:any(fun({_, _, E}) -> Hit(E) end, Plan) of
                                           true -> _ = erlang:cancel_timer(T), {[Tag | F], K};
                                           false -> {F, K#{Tag => R}}
                                       end
                               end, {[], #{}}, Reads),
    {Writes, Left} = lists:partition(fun({_, E, _}) -> Hit(E) end, queue:to_list(Q)),
    emit([{reply, Tag, {error, Why}} || Tag <- lists:sort(Failed)] ++
             [{reply, Tag, {error, Why}} || {Tag, _, _} <- Writes],
         S#ads{reads = Kept, writes = queue:from_list(Left)}).

%% A subscription's samples, or its error (the symbol went with a program change).
note(E, {samples, Samples}, #ads{entries = Es} = S) ->
    {_, Last} = lists:last(Samples),
    Old = maps:get(E, Es, #entry{}),
    S1 = S#ads{latest = (S#ads.latest)#{E => Last},
               entries = Es#{E => Old#entry{state = ready}}},
    Keys = maps:get(E, S1#ads.keys, []),
    served([{K, Last} || K <- Keys], emit([{samples, [{K, Samples} || K <- Keys]}], S1));
note(E, {error, Why}, #ads{entries = Es} = S) ->
    Old = maps:get(E, Es, #entry{}),
    S1 = S#ads{latest = maps:remove(E, S#ads.latest),
               entries = Es#{E => Old#entry{state = {fault, Why}}}},
    faults([{K, Why} || K <- maps:get(E, S1#ads.keys, [])], S1).

%%====================================================================
%% Words for operators
%%====================================================================

%% @private
-spec format_reason(term()) -> iodata().
format_reason({no_answer, Ms}) ->
    io_lib:format("no answer within ~b ms", [Ms]);
format_reason({client_exited, Why}) ->
    io_lib:format("the ADS connection ended unexpectedly (~tp)", [Why]);
format_reason({notify, output}) ->
    "outputs cannot be fed by notifications";
format_reason(Why) ->
    cell_hal_ads_client:format_error(Why).
