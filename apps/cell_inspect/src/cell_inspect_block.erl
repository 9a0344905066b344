%% @doc One inspection block (seed 004): the PLC's I/O block on a HAL connection, its
%% camera clients, its image processing and its traceability records. The decisions
%% are {@link cell_inspect_status}'s; this process feeds it what happens and carries out
%% what it decides: writes to the PLC through the HAL, requests to cameras, processing
%% and database jobs in processes of their own.
%%
%% <table>
%% <tr><th>state</th><th>what happens</th><th>leaves for</th></tr>
%% <tr><td>`starting'</td><td>the block's IO group is added to its HAL connection, its
%%   settings loaded, its workspaces loading, its clients started and asked whether
%%   they are connected</td><td>`online' or `offline' once every client answered (or
%%   after 1 s), so that a command raised while the block was away finds its cameras</td></tr>
%% <tr><td>`online'</td><td>the PLC's connection is up: every change the HAL reports is
%%   echoed and a command's rising edge acted on; the outputs are written</td>
%%   <td>`offline' when the connection goes down</td></tr>
%% <tr><td>`offline'</td><td>the connection is down: nothing is written; inspections
%%   and messages under way go on; once up, the whole block is read again and what the
%%   PLC holds differently is written again</td><td>`online' when it comes up</td></tr>
%% </table>
%%
%% A tag the PLC does not have (a member missing from its structure, or of another
%% type) is an alarm of the block naming it; commands wait until the block can read the
%% PLC whole again, then the alarm is cleared.
%%
%% The block never polls: it subscribes to its input points and its connection in the
%% HAL, whose worker polls the PLC (or receives its notifications). Subscriptions the
%% HAL's server cannot take while it is away (restarting) leave the block `offline', as
%% a lost link does, until the HAL's `{cell_hal_back, Ref}' ({@link
%% cell_hal:notify_back/0}); a group the HAL already holds for the block is taken as it
%% is, without the server. The Heartbeat
%% toggles every `heartbeat_ms' in every state. A block that stops (or crashes) writes
%% nothing more: the PLC sees the Heartbeat stop; the block that starts again takes
%% over from what the PLC holds (see {@link cell_inspect_status}).
-module(cell_inspect_block).
-behaviour(gen_statem).

-compile({no_auto_import, [whereis/1]}).

-export([start_link/1, check_spec/1, create_table/0, whereis/1, running/0, view/1, views/0,
         subscribe/0, unsubscribe/0]).
-export([client_state/4, image/4, answer/4]).
-export([callback_mode/0, init/1, starting/3, online/3, offline/3, terminate/3]).

-export_type([spec/0]).

-type spec() :: #{id := atom(), connection := atom(), io := cell_inspect_io:opts()}.
-type ref() :: cell_inspect_status:ref().

-define(TABLE, cell_inspect_blocks).
-define(SCOPE, cell_inspect).             %% the pg scope of view subscribers
-define(HELLO_MS, 1000).          %% longest wait for the clients at start
-define(OVERRIDE_MS, 10000).      %% longest override lookup
-define(RETRY_MS, 1000).
-define(FAULTS_ALARM, <<"plc_tags">>).

-record(data, {id :: atom(),
               source :: binary(),
               conn :: atom(),
               io :: cell_inspect_io:opts(),
               logic :: cell_inspect_status:state(),
               settings = #{} :: map(),
               kinds = #{} :: #{binary() => none | {ipm, module()} | {misconfigured, iolist()}},
               workspaces = #{} :: #{binary() => {loading | ready | failed, {module(), binary()},
                                                  term()}},
               clients = #{} :: #{binary() => {pid(), reference()}},
               waiting = [] :: [binary()],
               jobs = #{} :: #{reference() => {pid(), job(), reference() | undefined}},
               settings_mon :: reference() | undefined,
               version = 0 :: non_neg_integer(),   %% settings applied so far
               synced = false :: boolean(),        %% the PLC read whole since it came up
               %% tags the PLC does not have as the block needs them (a member missing
               %% or of another type), with why: the operator sees them in an alarm
               faults = #{} :: #{cell_inspect_tags:tag() => binary()},
               last_view :: map() | undefined,
               retry = ?RETRY_MS :: pos_integer(),
               %% the HAL's server was away (it restarts): what it could not take is
               %% asked again when it says it is back
               back :: reference() | undefined}).

-type job() :: {process, ref()} | {override, ref()} | {load, binary(), {module(), binary()}}.

%%====================================================================
%% API
%%====================================================================

%% @doc Checks a block's spec (from the `cell_inspect' variable `blocks'): `id' (also
%% its HAL group's id), `connection' (a HAL connection), `io' (see {@link
%% cell_inspect_io:check_opts/1}).
-spec check_spec(term()) -> {ok, spec()} | {error, {bad_option, atom()}}.
check_spec(#{id := Id, connection := Conn} = S) when is_atom(Id), is_atom(Conn) ->
    case maps:keys(maps:without([id, connection, io], S)) of
        [] ->
            case cell_inspect_io:check_opts(maps:get(io, S, #{})) of
                {ok, Io} -> {ok, #{id => Id, connection => Conn, io => Io}};
                {error, _} = E -> E
            end;
        [K | _] when is_atom(K) -> {error, {bad_option, K}};
        _ -> {error, {bad_option, block}}
    end;
check_spec(#{id := Id}) when is_atom(Id) ->
    {error, {bad_option, connection}};
check_spec(_) ->
    {error, {bad_option, id}}.

-spec start_link(spec()) -> gen_statem:start_ret().
start_link(Spec) ->
    gen_statem:start_link(?MODULE, Spec, []).

%% @doc Creates the table blocks publish their state in (its owner: the app's supervisor).
-spec create_table() -> ok.
create_table() ->
    ?TABLE = ets:new(?TABLE, [named_table, public, {read_concurrency, true}]),
    ok.

%% @doc A block's process.
-spec whereis(atom()) -> pid() | undefined.
whereis(Id) ->
    try ets:lookup(?TABLE, Id) of
        [{Id, Pid, _}] -> Pid;
        [] -> undefined
    catch error:badarg -> undefined
    end.

%% @doc The blocks running.
-spec running() -> [{atom(), pid()}].
running() ->
    try [{Id, Pid} || {Id, Pid, _} <- ets:tab2list(?TABLE)]
    catch error:badarg -> []
    end.

%% @doc What a block shows: its PLC, InspectionStatus, ErrorCode, MessageStatus, the
%% inspection and message under way, its clients (read from a table, no process hop).
-spec view(atom()) -> {ok, map()} | {error, unknown_block}.
view(Id) ->
    try ets:lookup(?TABLE, Id) of
        [{Id, _, View}] -> {ok, View};
        [] -> {error, unknown_block}
    catch error:badarg -> {error, unknown_block}
    end.

-spec views() -> [map()].
views() ->
    try lists:sort([V || {_, _, V} <- ets:tab2list(?TABLE)])
    catch error:badarg -> []
    end.

%% @doc The caller receives `{cell_inspect, view, View}' whenever a block's view
%% changes, until it exits or unsubscribes.
-spec subscribe() -> ok.
subscribe() ->
    pg:join(?SCOPE, views, self()).

-spec unsubscribe() -> ok.
unsubscribe() ->
    _ = pg:leave(?SCOPE, views, self()),
    ok.

%% @doc A client says whether it is connected (see {@link cell_inspect_client}).
-spec client_state(pid(), binary(), pid(), connected | disconnected) -> ok.
client_state(Block, Id, Pid, State) ->
    gen_statem:cast(Block, {client_state, Id, Pid, State}).

%% @doc A client sends the image it was asked for.
-spec image(pid(), binary(), ref(), cell_inspect_processing:image()) -> ok.
image(Block, Id, Ref, Image) ->
    gen_statem:cast(Block, {image, Id, Ref, Image}).

%% @doc A client's user answers a message: refused when the message is no longer
%% waiting, was not shown to this client, or the answer is not one it offers (or a
%% text the PLC cannot hold: too long, or characters outside Latin-1).
-spec answer(pid(), binary(), ref(), cell_inspect_status:answer()) -> ok | {error, term()}.
answer(Block, Id, Ref, Answer) ->
    try gen_statem:call(Block, {answer, Id, Ref, Answer}, 5000)
    catch exit:{noproc, _} -> {error, no_block};
          exit:{timeout, _} -> {error, timeout}
    end.

%%====================================================================
%% gen_statem
%%====================================================================

%% @private
-spec callback_mode() -> [state_functions | state_enter].
callback_mode() -> [state_functions, state_enter].

%% @private
-spec init(spec()) -> gen_statem:init_result(starting).
init(#{id := Id, connection := Conn, io := Io}) ->
    %% terminate/3 runs on shutdown: the block's row leaves the table.
    process_flag(trap_exit, true),
    Inc = erlang:unique_integer([positive]),
    D = #data{id = Id, source = <<"inspect/", (atom_to_binary(Id))/binary>>, conn = Conn,
              io = Io, logic = cell_inspect_status:new(Inc, #{points => #{}, messages => #{}})},
    {ok, starting, D, [{next_event, internal, start}]}.

%%--------------------------------------------------------------------
%% starting: group, settings, workspaces, clients
%%--------------------------------------------------------------------

%% @private
-spec starting(gen_statem:event_type(), term(), #data{}) -> gen_statem:state_function_result().
starting(enter, _, _) ->
    keep_state_and_data;
starting(internal, start, D) ->
    start(D);
starting(state_timeout, start, D) ->
    start(D);
starting(state_timeout, go, D) ->
    go(D);
starting(info, {cell_hal_back, Ref}, #data{back = Ref} = D) ->
    start(D#data{back = undefined});
starting(cast, {client_state, Id, _, _} = Msg, #data{waiting = W} = D) ->
    {keep_state, D1} = common(cast, Msg, starting, D),
    case W -- [Id] of
        [] when W =/= [] -> go(D1#data{waiting = []});
        W1 -> {keep_state, D1#data{waiting = W1}}
    end;
starting(Type, Event, D) ->
    common(Type, Event, starting, D).

start(#data{id = Id, source = Src} = D) ->
    ets:insert(?TABLE, {Id, self(), view_of(starting, D)}),
    case ensure_group(D) of
        ok ->
            case attach_settings(D) of
                {ok, D1} ->
                    D2 = load_settings(starting, D1),
                    case D2#data.waiting of
                        [] -> go(D2);
                        _ -> {keep_state, D2, [{state_timeout, ?HELLO_MS, go}]}
                    end;
                {error, Why} ->
                    cell_log:warning(Src, "settings not available yet (~0tp); trying again",
                                     [Why]),
                    retry(D)
            end;
        {error, disconnected} ->
            cell_log:warning(Src, "the HAL is restarting: the block is added to connection "
                             "~s when it is back", [D#data.conn]),
            {keep_state, D#data{back = cell_hal:notify_back()}};
        {error, Why} ->
            cell_log:error(Src, "cannot add the block to connection ~s: ~0tp; trying again",
                           [D#data.conn, Why]),
            retry(D)
    end.

retry(#data{retry = R} = D) ->
    {keep_state, D#data{retry = min(2 * R, 30000)}, [{state_timeout, R, start}]}.

%% A group the HAL holds already (left by the block's previous run: the HAL keeps its
%% configuration across its own restarts) is taken as it is, without the HAL's server.
ensure_group(#data{id = Id, conn = Conn, io = Io}) ->
    case cell_hal:connection_of(Id) of
        {ok, Conn} ->
            ok;
        {ok, _} = Other ->
            {error, {group_taken, Id, Other}};
        {error, unknown_group} ->
            case cell_hal:add_group(#{id => Id, module => cell_inspect_io, connection => Conn,
                                      opts => Io}) of
                ok -> ok;
                {error, {already_exists, Id}} ->
                    case cell_hal:connection_of(Id) of
                        {ok, Conn} -> ok;
                        Other -> {error, {group_taken, Id, Other}}
                    end;
                {error, _} = E -> E
            end
    end.

%% Subscribes to the PLC's connection and inputs, then reads the PLC if it is up.
%% InspectionStatus is watched too: the HAL reads a new group's outputs back once, and
%% its change says that read is done.
go(#data{conn = Conn, source = Src} = D) ->
    Heartbeat = {{timeout, heartbeat}, maps:get(heartbeat_ms, D#data.settings), tick},
    case subscribe(D) of
        {ok, Status} ->
            cell_log:info(Src, "started on connection ~s (~s)", [Conn, Status]),
            case Status of
                up -> {next_state, online, plc_up(D), [Heartbeat]};
                down -> {next_state, offline, D, [Heartbeat]}
            end;
        disconnected ->
            {next_state, offline, hal_away(D), [Heartbeat]}
    end.

%% The HAL's server is away (it restarts) as the block subscribes: the PLC is taken as
%% lost (offline: nothing written, commands wait) until the HAL says it is back.
hal_away(#data{conn = Conn, source = Src} = D) ->
    cell_log:warning(Src, "the HAL is restarting: the PLC on connection ~s is taken as lost "
                     "until it is back", [Conn]),
    D#data{back = cell_hal:notify_back()}.

%% The HAL's server is back: subscribed again, and online if the PLC's connection is up.
back(State, #data{conn = Conn, source = Src} = D0) ->
    D = D0#data{back = undefined},
    Subscribed = subscribe(D),
    _ = [cell_log:info(Src, "the HAL is back: the PLC on connection ~s is followed again (~s)",
                       [Conn, Status]) || {ok, Status} <- [Subscribed]],
    case {Subscribed, State} of
        {{ok, up}, online} -> {keep_state, plc_up(D)};
        {{ok, up}, offline} -> {next_state, online, plc_up(D)};
        {{ok, down}, online} -> {next_state, offline, feed(plc_down, offline, D#data{synced = false})};
        {{ok, down}, offline} -> {keep_state, D};
        {disconnected, _} -> {keep_state, hal_away(D)}
    end.

%% Subscribes to the block's inputs and connection (again: the HAL keeps one
%% subscription of a process to a point): the connection's status, or `disconnected'
%% when the HAL's server is away.
subscribe(#data{id = Id, conn = Conn, io = Io}) ->
    subscribe(Id, Conn, [inspection_status | cell_inspect_io:input_points(Io)]).

subscribe(Id, Conn, [P | Points]) ->
    case cell_hal:subscribe(Id, P) of
        ok -> subscribe(Id, Conn, Points);
        {error, disconnected} -> disconnected
    end;
subscribe(_Id, Conn, []) ->
    case cell_hal:subscribe_connection(Conn) of
        {ok, Status} -> {ok, Status};
        {error, disconnected} -> disconnected
    end.

%%--------------------------------------------------------------------
%% online: the PLC's connection is up
%%--------------------------------------------------------------------

%% @private
-spec online(gen_statem:event_type(), term(), #data{}) -> gen_statem:state_function_result().
online(enter, _, D) ->
    {keep_state, publish(online, D)};
online(info, {cell_hal, {Id, _}, _}, #data{id = Id, synced = false} = D) ->
    %% The group was added while the connection was up: read whole once it has been.
    {keep_state, plc_up(D)};
online(info, {cell_hal, {Id, Point}, Value}, #data{id = Id} = D) ->
    {keep_state, input(Point, Value, D)};
online(info, {cell_hal_conn, Conn, up}, #data{conn = Conn} = D) ->
    {keep_state, plc_up(D)};
online(info, {cell_hal_conn, Conn, down}, #data{conn = Conn} = D) ->
    {next_state, offline, feed(plc_down, offline, D#data{synced = false})};
online(Type, Event, D) ->
    common(Type, Event, online, D).

%%--------------------------------------------------------------------
%% offline: the PLC's connection is down
%%--------------------------------------------------------------------

%% @private
-spec offline(gen_statem:event_type(), term(), #data{}) -> gen_statem:state_function_result().
offline(enter, _, D) ->
    {keep_state, publish(offline, D)};
offline(info, {cell_hal, _, _}, _D) ->
    %% Read again, all at once, when the connection is up.
    keep_state_and_data;
offline(info, {cell_hal_conn, Conn, up}, #data{conn = Conn} = D) ->
    {next_state, online, plc_up(D)};
offline(info, {cell_hal_conn, Conn, down}, #data{conn = Conn}) ->
    keep_state_and_data;
offline(Type, Event, D) ->
    common(Type, Event, offline, D).

%%--------------------------------------------------------------------
%% Every state
%%--------------------------------------------------------------------

common(info, {cell_hal_back, Ref}, State, #data{back = Ref} = D) ->
    back(State, D);
common({timeout, heartbeat}, tick, State, D) ->
    {keep_state, feed(heartbeat, State, D),
     [{{timeout, heartbeat}, maps:get(heartbeat_ms, D#data.settings), tick}]};
common(cast, {client_state, Id, Pid, What}, State, D) ->
    {keep_state, client_state(Id, Pid, What, State, D)};
common(cast, {image, Client, Ref, Image}, State, D) ->
    {keep_state, feed({image, Client, Ref, Image}, State, D)};
common({call, From}, {answer, Client, Ref, Answer}, State, #data{logic = L, io = Io} = D) ->
    Checked = case cell_inspect_status:check_answer(L, Client, Ref, Answer) of
                  ok -> plc_text(Answer, Io);
                  E -> E
              end,
    case Checked of
        {ok, A} -> {keep_state, feed({answer, Client, Ref, A}, State, D), [{reply, From, ok}]};
        {error, _} = Error -> {keep_state_and_data, [{reply, From, Error}]}
    end;
common(info, {?MODULE, result, Pid, Result}, State, D) ->
    {keep_state, result(Pid, Result, State, D)};
common(info, {'DOWN', Mon, process, _, Reason}, State, D) ->
    {keep_state, down(Mon, Reason, State, D)};
common(info, {timeout, _, {job, Mon}}, State, D) ->
    {keep_state, job_timeout(Mon, State, D)};
common(info, {cell_settings, changed, inspect}, State, D) ->
    {keep_state, load_settings(State, D)};
common(info, {cell_settings, changed, _}, _State, _D) ->
    keep_state_and_data;
common(info, {timeout, _, settings}, State, D) ->
    case attach_settings(D) of
        {ok, D1} ->
            %% The settings restarted: if the controller's tree restarted with them, the
            %% alarms are empty, so the block's alarm, if it has one, is set again (kept
            %% alarms see the same alarm and announce nothing).
            D2 = faults(D1#data.faults, D1#data{faults = #{}}),
            {keep_state, load_settings(State, D2#data{retry = ?RETRY_MS})};
        {error, _} ->
            R = D#data.retry,
            _ = erlang:start_timer(R, self(), settings),
            {keep_state, D#data{retry = min(2 * R, 30000)}}
    end;
common(info, {cell_hal_fault, {Id, _}, _}, _State, #data{id = Id}) ->
    %% A point the PLC cannot serve: the block's requests to it fail and say so.
    keep_state_and_data;
common(info, {cell_inspect, Id, panel_up, _}, _State, #data{id = Id, settings = S}) ->
    cell_inspect_panel:block(Id, self(), maps:get(panel_messages, S, false)),
    keep_state_and_data;
common(info, {'EXIT', _, Reason}, _State, _D) ->
    %% Our supervisor stops us (trap_exit is on for terminate/3).
    {stop, Reason}.

%% @private
-spec terminate(term(), atom(), #data{}) -> ok.
terminate(_Reason, _State, #data{id = Id, jobs = Jobs}) ->
    %% Jobs die with the block: their results would have no one to go to. The PLC sees
    %% the Heartbeat stop; the next block takes over from what the PLC holds.
    _ = [exit(Pid, kill) || {Pid, _, _} <- maps:values(Jobs)],
    _ = ets:delete(?TABLE, Id),
    ok.

%%====================================================================
%% The PLC
%%====================================================================

%% The whole block, read at once from the HAL's table (once the HAL has read it all:
%% a group added while its connection is up is read at the next poll). Tags the PLC
%% does not have (see faults/2) keep the block from going on until it has them: the
%% HAL tries them again at every change of the PLC's program, and their values then
%% bring the block here again.
plc_up(#data{id = Id, io = Io} = D) ->
    Read = fun(Tags) -> [{T, cell_inspect_io:read(Io, Id, T)} || T <- Tags] end,
    In = Read(cell_inspect_tags:inputs()),
    Out = Read(cell_inspect_tags:outputs()),
    Values = fun(Rs) -> maps:from_list([{T, V} || {T, {ok, V}} <- Rs]) end,
    Faults = [{T, Why} || {T, {error, {unavailable, Why}}} <- In ++ Out],
    Unread = [T || {T, {error, _}} <- In ++ Out],
    if
        Faults =/= [] ->
            faults(maps:from_list(Faults), D#data{synced = false});
        Unread =/= [] ->
            %% Not read yet: a change or a connection message follows.
            D#data{synced = false};
        true ->
            D1 = faults(#{}, D#data{synced = true}),
            feed({plc_up, #{inputs => Values(In), outputs => Values(Out)}}, online, D1)
    end.

%% A tag found unusable while the block works: the block is read whole again at the
%% next change of the PLC.
fault(Tag, Why, #data{faults = Faults} = D) ->
    faults(Faults#{Tag => Why}, D#data{synced = false}).

%% The tags the PLC does not have as the block needs them, as the operator sees them:
%% one alarm of the block naming them all, set while there are any.
faults(Same, #data{faults = Same} = D) ->
    D;
faults(Faults, #data{id = Id, io = #{layout := Layout}, conn = Conn, source = Src} = D)
  when map_size(Faults) =:= 0 ->
    ok = cell_alarms:clear_alarm(Id, ?FAULTS_ALARM),
    cell_log:notice(Src, "the PLC on ~s has every tag of the block again (~s)", [Conn, Layout]),
    D#data{faults = Faults};
faults(Faults, #data{id = Id, io = #{layout := Layout}, conn = Conn, source = Src} = D) ->
    Names = lists:join(", ", [[tag_name(Layout, T), " (", Why, ")"]
                              || {T, Why} <- lists:sort(maps:to_list(Faults))]),
    Text = io_lib:format("The PLC on connection ~s lacks tags the block needs, or holds "
                         "them with another type: ~ts. Inspections wait until its program "
                         "has them.", [Conn, Names]),
    ok = cell_alarms:alarm(Id, ?FAULTS_ALARM, "Inspection block: PLC tags missing", Text),
    cell_log:error(Src, "~ts", [Text]),
    D#data{faults = Faults}.

tag_name(ads, Tag) -> cell_inspect_tags:ab_name(Tag);
tag_name(s7, Tag) -> cell_inspect_tags:seed_name(Tag).

%% A changed input point. A command bit is taken with the value the change carries
%% (see cell_inspect_io:change/3), so a pulse over by now still rises. A command's
%% edge comes after the values it works on: those are read again first, so a value
%% written on the same PLC scan is not missed.
input(Point, Value, #data{io = Io} = D) ->
    case cell_inspect_io:change(Io, Point, Value) of
        {command, Tag, true} ->
            D1 = lists:foldl(fun(T, Dx) -> refresh(T, Dx) end, D,
                             cell_inspect_tags:data_inputs()),
            case D1#data.synced of
                true -> feed({input, Tag, true}, online, D1);
                %% Its values cannot all be read: the command waits, as the PLC
                %% holds it, for the block to be read whole again.
                false -> D1
            end;
        {command, Tag, false} ->
            feed({input, Tag, false}, online, D);
        {value, Tag} ->
            refresh(Tag, D);
        ignore ->
            D
    end.

refresh(Tag, #data{id = Id, io = Io} = D) ->
    case cell_inspect_io:read(Io, Id, Tag) of
        {ok, V} -> feed({input, Tag, V}, online, D);
        {error, {unavailable, Why}} -> fault(Tag, Why, D);
        {error, _} -> D
    end.

%% A text answer as the PLC will hold it: refused if it would not read back the same.
plc_text({text, T}, Io) when is_binary(T) ->
    Max = maps:get(result, cell_inspect_io:lengths(Io)),
    case cell_inspect_io:normalize(Io, message_result, T) of
        T -> {ok, {text, T}};
        _ ->
            case unicode:characters_to_list(T) of
                L when is_list(L), length(L) > Max -> {error, {too_long, Max}};
                _ -> {error, not_latin1}
            end
    end;
plc_text(A, _) ->
    {ok, A}.

%%====================================================================
%% The status machine and its effects
%%====================================================================

feed(Event, State, #data{logic = L} = D) ->
    {L1, Effects} = cell_inspect_status:handle(Event, L),
    D1 = lists:foldl(fun(E, Dx) -> effect(E, State, Dx) end, D#data{logic = L1}, Effects),
    publish(State, D1).

effect({write, Tag, V}, online, #data{id = Id, io = Io, source = Src} = D) ->
    lists:foldl(fun({P, HV}, Dx) ->
                        case cell_hal:write(Id, P, HV) of
                            ok ->
                                Dx;
                            {error, {unavailable, Why}} ->
                                fault(Tag, Why, Dx);
                            {error, Why} ->
                                cell_log:debug(Src, "~s not written: ~0tp",
                                               [cell_inspect_tags:seed_name(Tag), Why]),
                                Dx
                        end
                end, D, cell_inspect_io:writes(Io, Tag, V));
effect({write, _, _}, _State, D) ->
    D;                                  %% written again when the PLC is back
effect({request_image, Cs, Req}, _, D) ->
    send(Cs, request_image, Req, D);
effect({cancel_image, Cs, Ref}, _, D) ->
    send(Cs, cancel, Ref, D);
effect({show_message, Cs, Msg}, _, #data{io = Io} = D) ->
    %% A text answer must fit MessageResult: clients say so to their users.
    send(Cs, show_message, Msg#{max_length => maps:get(result, cell_inspect_io:lengths(Io))}, D);
effect({withdraw_message, Cs, Ref}, _, D) ->
    send(Cs, withdraw_message, Ref, D);
effect({process, Ref, Job}, _, D) ->
    start_processing(Ref, Job, D);
effect({log_override, Ref, Ov}, _, #data{id = Id} = D) ->
    job({override, Ref}, fun() -> cell_inspect_db:log_override(Ov#{block => Id}) end,
        ?OVERRIDE_MS, D);
effect({log, Level, Fmt, Args}, _, #data{source = Src} = D) ->
    cell_log:log(Level, Src, Fmt, Args),
    D.

send(Clients, What, Arg, #data{id = Id, clients = C} = D) ->
    _ = [Pid ! {cell_inspect, Id, What, Arg} || Client <- Clients,
                                                {ok, {Pid, _}} <- [maps:find(Client, C)]],
    D.

%% The view, when it changed: in the table, and to the subscribers.
publish(State, #data{id = Id, last_view = Last} = D) ->
    case view_of(State, D) of
        Last -> D;
        View ->
            true = ets:insert(?TABLE, {Id, self(), View}),
            _ = [P ! {cell_inspect, view, View} || P <- pg:get_members(?SCOPE, views)],
            D#data{last_view = View}
    end.

view_of(State, #data{id = Id, conn = Conn, logic = L, io = #{layout := Layout},
                     version = V, settings = S}) ->
    (cell_inspect_status:view(L))#{id => Id, connection => Conn, layout => Layout,
                                   state => State, settings_version => V,
                                   points => [P || #{id := P} <- maps:get(points, S, [])]}.

%%====================================================================
%% Jobs: processing, the database, loading workspaces
%%====================================================================

%% Each job runs in a process of its own and sends its result before it ends; a job
%% that crashes ends without one (its monitor says so).
job(Job, Fun, Timeout, #data{jobs = Jobs} = D) ->
    Block = self(),
    {Pid, Mon} = spawn_monitor(fun() -> Block ! {?MODULE, result, self(), Fun()} end),
    TRef = case Timeout of
               infinity -> undefined;
               _ -> erlang:start_timer(Timeout, self(), {job, Mon})
           end,
    D#data{jobs = Jobs#{Mon => {Pid, Job, TRef}}}.

start_processing(Ref, #{point := P, serial := S, client := Client, image := Image,
                        mode := Mode}, #data{id = Id, workspaces = Ws, settings = Set} = D) ->
    Run = case Mode of
              none -> none;
              {error, Code} -> {error, Code};
              ipm ->
                  case maps:get(P, Ws, undefined) of
                      {ready, {Mod, _}, Loaded} -> {ipm, Mod, Loaded};
                      _ -> {error, processing_not_available}
                  end
          end,
    Name = ref_name(Ref),
    Fun = fun() -> process(Id, Name, #{point => P, serial => S, client => Client}, Image, Run) end,
    job({process, Ref}, Fun, maps:get(processing_timeout_ms, Set), D).

ref_name({Inc, N}) -> iolist_to_binary([integer_to_list(Inc), $-, integer_to_list(N)]).

%% In the job's process: the image saved, processed, the inspection recorded.
process(Block, Name, #{point := P, serial := S, client := Client} = Job, Image, Run) ->
    Source = <<"inspect/", (atom_to_binary(Block))/binary>>,
    Saved = cell_inspect_images:save(Block, Name, Image),
    Result = case Run of
                 none -> {pass, <<>>};
                 {error, Code} -> {error, Code};
                 {ipm, Mod, Loaded} ->
                     try Mod:process(Image, maps:with([point, serial], Job), Loaded) of
                         {Verdict, Text} when (Verdict =:= pass orelse Verdict =:= fail),
                                              is_binary(Text) -> {Verdict, Text};
                         {error, Why} ->
                             cell_log:warning(Source, "processing of ~ts failed: ~0tp", [P, Why]),
                             {error, processing_error};
                         Other ->
                             cell_log:warning(Source, "processing of ~ts gave ~0tp", [P, Other]),
                             {error, processing_error}
                     catch
                         C:R:Stack ->
                             cell_log:warning(Source, "processing of ~ts crashed", [P]),
                             cell_log:trace(Source, "processing of ~ts: ~0tp:~0tp ~0tp",
                                            [P, C, R, Stack]),
                             {error, processing_error}
                     end
             end,
    {Result1, ImageRef} = case Saved of
                              {ok, Ref} -> {Result, Ref};
                              {error, Why2} ->
                                  cell_log:error(Source, "the image of ~ts could not be saved: "
                                                 "~0tp", [P, Why2]),
                                  {{error, internal_error}, <<>>}
                          end,
    Record = #{block => Block, point => P, serial => S, client => Client, image => ImageRef,
               result => case Result1 of {V, _} when V =/= error -> V; _ -> error end,
               code => case Result1 of {error, C2} -> C2; _ -> no_error end,
               text => case Result1 of {_, T} when is_binary(T) -> T; _ -> <<>> end},
    case cell_inspect_db:record_inspection(Record) of
        {ok, _} -> Result1;
        {error, Why3} ->
            cell_log:error(Source, "the inspection of ~ts could not be recorded: ~0tp",
                           [P, Why3]),
            {error, internal_error}
    end.

result(Pid, Result, State, #data{jobs = Jobs} = D) ->
    case [Mon || {Mon, {P, _, _}} <- maps:to_list(Jobs), P =:= Pid] of
        [Mon] ->
            demonitor(Mon, [flush]),
            {{_, Job, TRef}, Rest} = maps:take(Mon, Jobs),
            _ = TRef =/= undefined andalso erlang:cancel_timer(TRef, [{async, true}, {info, false}]),
            job_done(Job, {ok, Result}, State, D#data{jobs = Rest});
        [] ->
            D                                   %% stopped already (too late)
    end.

down(Mon, Reason, State, #data{jobs = Jobs} = D) ->
    case maps:take(Mon, Jobs) of
        {{_, Job, TRef}, Rest} ->
            _ = TRef =/= undefined andalso erlang:cancel_timer(TRef, [{async, true}, {info, false}]),
            job_done(Job, {crashed, Reason}, State, D#data{jobs = Rest});
        error ->
            down_other(Mon, State, D)
    end.

down_other(Mon, State, #data{clients = C, settings_mon = SM} = D) ->
    case [Id || {Id, {_, M}} <- maps:to_list(C), M =:= Mon] of
        [Id] ->
            feed({client_down, Id}, State, D#data{clients = maps:remove(Id, C)});
        [] when Mon =:= SM ->
            %% cell_settings restarted: our subscription and registration are gone.
            _ = erlang:start_timer(D#data.retry, self(), settings),
            D#data{settings_mon = undefined};
        [] ->
            D
    end.

job_done({process, Ref}, {ok, Result}, State, #data{io = Io} = D) ->
    R = case Result of
            {V, Text} when V =:= pass; V =:= fail ->
                {V, cell_inspect_io:normalize(Io, inspection_string, Text)};
            {error, _} = E -> E
        end,
    feed({processed, Ref, R}, State, D);
job_done({process, Ref}, Crash, State, #data{source = Src} = D) ->
    cell_log:warning(Src, "the processing job ended: ~0tp", [Crash]),
    feed({processed, Ref, {error, processing_error}}, State, D);
job_done({override, Ref}, {ok, Result}, State, D) ->
    R = case Result of
            {ok, _} -> logged;
            not_found -> not_found;
            {error, _} = E -> E
        end,
    feed({override_logged, Ref, R}, State, D);
job_done({override, Ref}, Crash, State, D) ->
    feed({override_logged, Ref, {error, Crash}}, State, D);
job_done({load, P, Key}, Result, State, #data{workspaces = Ws, source = Src} = D) ->
    case maps:get(P, Ws, undefined) of
        {loading, Key, _} ->
            {Status, Loaded} = case Result of
                                   {ok, {ok, L}} -> {ready, L};
                                   Other ->
                                       cell_log:warning(Src, "the workspace of ~ts could not "
                                                        "be loaded: ~0tp", [P, Other]),
                                       {failed, undefined}
                               end,
            feed({workspace, P, Status}, State, D#data{workspaces = Ws#{P => {Status, Key, Loaded}}});
        _ ->
            D                                   %% replaced since: a new load is under way
    end.

job_timeout(Mon, State, #data{jobs = Jobs, source = Src} = D) ->
    case maps:take(Mon, Jobs) of
        {{Pid, Job, _}, Rest} ->
            exit(Pid, kill),
            demonitor(Mon, [flush]),
            cell_log:warning(Src, "a job took too long and was stopped", []),
            D1 = D#data{jobs = Rest},
            case Job of
                {process, Ref} -> feed({processed, Ref, {error, processing_error}}, State, D1);
                {override, Ref} -> feed({override_logged, Ref, {error, timeout}}, State, D1);
                {load, _, _} -> D1
            end;
        error ->
            D
    end.

%%====================================================================
%% Clients
%%====================================================================

client_state(Id, Pid, What, State, #data{clients = C, source = Src} = D) ->
    case caps(Id, D) of
        undefined when What =:= disconnected; not is_map_key(Id, C) ->
            _ = What =:= connected andalso
                cell_log:warning(Src, "~ts is not a client of this block: ignored", [Id]),
            case maps:find(Id, C) of
                {ok, {_, Mon}} ->
                    demonitor(Mon, [flush]),
                    feed({client_down, Id}, State, D#data{clients = maps:remove(Id, C)});
                error -> D
            end;
        undefined ->
            client_state(Id, Pid, disconnected, State, D);
        Caps when What =:= connected ->
            C1 = case maps:find(Id, C) of
                     {ok, {Pid, _}} -> C;
                     {ok, {_, Old}} -> demonitor(Old, [flush]),
                                       C#{Id => {Pid, monitor(process, Pid)}};
                     error -> C#{Id => {Pid, monitor(process, Pid)}}
                 end,
            feed({client_up, Id, Caps}, State, D#data{clients = C1});
        _ when What =:= disconnected ->
            case maps:find(Id, C) of
                {ok, {Pid, Mon}} ->
                    demonitor(Mon, [flush]),
                    feed({client_down, Id}, State, D#data{clients = maps:remove(Id, C)});
                _ ->
                    D
            end
    end.

caps(Id, #data{settings = S}) ->
    case cell_inspect_panel:client_id() of
        Id ->
            case maps:get(panel_messages, S, false) of
                true -> #{points => all, images => false, messages => true};
                false -> undefined
            end;
        _ ->
            case [Cl || #{id := I} = Cl <- maps:get(clients, S, []), I =:= Id] of
                [#{points := Ps, images := Im, messages := Me} | _] ->
                    #{points => case Ps of [] -> all; _ -> Ps end, images => Im, messages => Me};
                [] ->
                    undefined
            end
    end.

%%====================================================================
%% Settings
%%====================================================================

attach_settings(D) ->
    try
        case cell_inspect_settings:register() of
            ok -> ok;
            {error, {name_taken, inspect, cell_inspect_settings}} -> ok;
            {error, Why} -> throw(Why)
        end,
        ok = cell_settings:subscribe(),
        {ok, D#data{settings_mon = monitor(process, cell_settings)}}
    catch
        throw:Why2 -> {error, Why2};
        exit:{noproc, _} -> {error, settings_not_running}
    end.

%% The block's settings, applied: points and messages to the status machine,
%% workspaces loaded where they changed, clients matched to the settings.
load_settings(State, #data{id = Id, source = Src} = D) ->
    S = cell_inspect_settings:block(Id),
    Kinds = maps:from_list([{P, cell_inspect_processing:kind(Proc, Ws)}
                            || #{id := P, processing := Proc, workspace := Ws}
                                   <- maps:get(points, S)]),
    _ = [cell_log:warning(Src, "inspection point ~ts is not properly configured: ~ts",
                          [P, Why])
         || {P, {misconfigured, Why}} <- maps:to_list(Kinds),
            maps:get(P, D#data.kinds, undefined) =/= {misconfigured, Why}],
    Config = #{points => maps:map(fun(_, none) -> none;
                                     (_, {ipm, _}) -> ipm;
                                     (_, {misconfigured, _}) -> misconfigured
                                  end, Kinds),
               messages => maps:from_list([{MId, #{text => T, kind => K}}
                                           || #{id := MId, text := T, kind := K}
                                                  <- maps:get(messages, S)])},
    D1 = feed({config, Config}, State, D#data{settings = S, kinds = Kinds,
                                              version = D#data.version + 1}),
    D2 = workspaces(S, State, D1),
    D3 = clients(S, State, D2),
    cell_inspect_panel:block(Id, self(), maps:get(panel_messages, S)),
    case maps:get(panel_messages, S) andalso erlang:whereis(cell_inspect_panel) =/= undefined
         andalso State =:= starting of
        true -> D3#data{waiting = D3#data.waiting ++ [cell_inspect_panel:client_id()]};
        false -> D3
    end.

workspaces(S, State, #data{kinds = Kinds, workspaces = Ws, jobs = Jobs} = D) ->
    Wanted = maps:from_list([{P, {Mod, W}} || #{id := P, workspace := W} <- maps:get(points, S),
                                              {ipm, Mod} <- [maps:get(P, Kinds)]]),
    %% Loads for points gone or changed are stopped.
    Stale = [Mon || {Mon, {_, {load, P, Key}, _}} <- maps:to_list(Jobs),
                    maps:get(P, Wanted, undefined) =/= Key],
    D1 = lists:foldl(fun(Mon, Dx) ->
                             {{Pid, _, _}, J} = maps:take(Mon, Dx#data.jobs),
                             exit(Pid, kill),
                             demonitor(Mon, [flush]),
                             Dx#data{jobs = J}
                     end, D, Stale),
    Kept = maps:filter(fun(P, {_, Key, _}) -> maps:get(P, Wanted, undefined) =:= Key end, Ws),
    maps:fold(fun(P, {Mod, W} = Key, Dx) ->
                      case maps:is_key(P, Kept) of
                          true -> Dx;
                          false ->
                              Dx1 = job({load, P, Key}, fun() -> Mod:load(W) end, infinity, Dx),
                              Ws1 = Dx1#data.workspaces,
                              feed({workspace, P, loading}, State,
                                   Dx1#data{workspaces = Ws1#{P => {loading, Key, undefined}}})
                      end
              end, D1#data{workspaces = Kept}, Wanted).

clients(S, State, #data{id = Id, source = Src} = D) ->
    Specs = lists:append(
              [case cell_inspect_client:module(Type) of
                   {ok, Mod} ->
                       [#{id => C, block => Id, module => Mod,
                          opts => maps:with([delay_ms, manual, scene, fail_rate], Cl)}];
                   error ->
                       cell_log:error(Src, "camera client ~ts has an unknown type \"~ts\"",
                                      [C, Type]),
                       []
               end || #{id := C, type := Type} = Cl <- maps:get(clients, S)]),
    Running = cell_inspect_client_sup:reconcile(Id, Specs),
    _ = [Pid ! {cell_inspect, Id, block_up, self()} || {_, Pid} <- Running],
    %% Clients connected now: their capabilities as the settings say now.
    D1 = maps:fold(fun(C, {Pid, _}, Dx) ->
                           case caps(C, Dx) of
                               undefined -> client_state(C, Pid, disconnected, State, Dx);
                               Caps -> feed({client_up, C, Caps}, State, Dx)
                           end
                   end, D, D#data.clients),
    D1#data{waiting = [C || {C, _} <- Running]}.
