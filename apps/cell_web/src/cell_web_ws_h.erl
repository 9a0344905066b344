%% @doc `/api/ws' — live updates for the panel: the page never polls.
%%
%% At connect the page gets a snapshot (the cell, every task, the active errors,
%% alarms and warnings, the latest log lines), then every change as it happens. Each
%% frame is a JSON array of messages:
%%
%% <ul>
%% <li>`{"type": "snapshot", "cell", "tasks", "alarms", "log", "forces", "session",
%%     "resync"}'</li>
%% <li>`{"type": "cell", "cell": Cell}' — state or flags changed</li>
%% <li>`{"type": "task", "task": Task}' — a task's state (or product serial) changed</li>
%% <li>`{"type": "alarm", "alarm": Alarm}' — an error, alarm or warning raised or updated</li>
%% <li>`{"type": "alarm_cleared", "alarm": Alarm}' — answered, closed, cleared or
%%     withdrawn (`cleared' and `who' say which and by whom)</li>
%% <li>`{"type": "event", "event": Event}' — an IPC-2541 item event and the like</li>
%% <li>`{"type": "log", "line": Line}' — a task log line</li>
%% <li>`{"type": "link", "link": {"link", "phase", "serial"}}' — a handshake link's
%%     phase changed</li>
%% <li>`{"type": "counters", "counters": Counters}' — this shift's counters, read again
%%     after items came, went or were worked</li>
%% <li>`{"type": "forces", "forces": [Force]}' — the forced IO points, at every change</li>
%% <li>`{"type": "io", "points": [Point]}' and `{"type": "io_conn", ...}' — IO values
%%     and PLC connections changed (see `cell_web_io')</li>
%% <li>`{"type": "hardware", "hardware": [Object]}' — axes and interpolation channels
%%     that moved or changed, each as `GET /api/io' has it (see `cell_web_io')</li>
%% <li>the messages of the extensions' feeds (`cell_web_extension'), as
%%     `{"type": "inspect_messages", "messages": [Message]}' of the inspection blocks</li>
%% </ul>
%%
%% Each extension with a feed is joined as the page connects; what it names to watch
%% (the inspection panel's process) is monitored like the others.
%%
%% The changes come already encoded from {@link cell_web_feed}, which makes them once
%% for every page. A slow browser never slows the cell: the feed sends to this process
%% without waiting, and when more than `?MAX_BACKLOG' messages wait here, they are
%% dropped and a fresh snapshot (`"resync": true') is sent instead. A browser that stops
%% reading altogether is dropped by the socket's send timeout. When a service of the
%% cell restarts, the feed attaches again and the page gets a fresh snapshot
%% (`"resync": true') without reconnecting. The socket closes with 4001 when the
%% session ends, 1012 when the feed itself (or an extension's feed) restarts; the page
%% connects again.
-module(cell_web_ws_h).
-behaviour(cowboy_websocket).

-export([init/2, websocket_init/1, websocket_handle/2, websocket_info/2]).
-export([messages/1]).

-define(MAX_BACKLOG, 2000).
-define(BATCH, 256).
-define(PING_MS, 30000).
%% A snapshot asked while the cell's services restart is read again this much later.
-define(RESYNC_RETRY_MS, 100).

-record(state, {caller :: cell_web_req:caller(),
                feed :: reference() | undefined,
                %% The extensions whose feeds this page joined, by their monitors.
                extensions = #{} :: #{reference() => module()}}).

-spec init(cowboy_req:req(), map()) ->
          {cowboy_websocket, cowboy_req:req(), #state{}, map()} | {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    try
        ok = cell_web_req:check_origin(Req),
        Caller = cell_web_req:require(cell_web_req:caller(Req), view),
        case cowboy_req:header(<<"upgrade">>, Req) of
            U when is_binary(U) ->
                {cowboy_websocket, Req, #state{caller = Caller},
                 #{idle_timeout => 3 * ?PING_MS, max_frame_size => 4096, compress => false}};
            undefined ->
                cell_web_req:fail(426, upgrade_required, "this is a websocket")
        end
    catch
        throw:{cell_web_error, Status, Code, Message, Extra} ->
            {ok, cell_web_req:reply_error(Status, Code, Message, Extra, Req), Opts}
    end.

-spec websocket_init(#state{}) -> {[cow_ws:frame()], #state{}}.
websocket_init(#state{caller = Caller} = State) ->
    %% Join the feed first, then read the snapshot: nothing that happens in between is
    %% missed (a change seen twice is harmless, the page applies it again).
    Feed = monitor(process, cell_web_feed),
    ok = cell_web_feed:join(self()),
    ok = cell_web_io:watch(),
    ok = cell_web_sessions:attach(case Caller of
                                      #{session := undefined} -> anonymous;
                                      #{session := Id} -> Id
                                  end),
    _ = erlang:start_timer(?PING_MS, self(), ping),
    {Extensions, Messages} = join_extensions(),
    {[snapshot(false, State) | Messages],
     State#state{feed = Feed, extensions = Extensions}}.

%% The feeds of the extensions that have one and run.
join_extensions() ->
    Joined = [{Mod, Watch, Ms} || Mod <- cell_web_extension:modules(),
                                  erlang:function_exported(Mod, feed_join, 1),
                                  {ok, Watch, Ms} <- [Mod:feed_join(self())]],
    {maps:from_list([{monitor(process, Watch), Mod} || {Mod, Watch, _} <- Joined]),
     [frame(Ms) || {_, _, Ms} <- Joined, Ms =/= []]}.

frame(Messages) ->
    {text, jsx:encode(Messages)}.

%% What the joined extensions make of a message the page's process does not know
%% itself; a message none of them takes is a bug.
extension_info(Info, Extensions) ->
    Results = [Mod:feed_info(Info) || Mod <- lists:usort(maps:values(Extensions))],
    case [Ms || {ok, Ms} <- Results] of
        [] -> erlang:error({unexpected_message, Info});
        Taken -> [frame(Ms) || Ms <- Taken, Ms =/= []]
    end.

-spec websocket_handle(cow_ws:frame(), #state{}) ->
          {[cow_ws:frame()], #state{}}.
websocket_handle({text, <<"resync">>}, #state{extensions = Extensions} = State) ->
    {[snapshot(true, State) | [frame(Ms) || Mod <- lists:usort(maps:values(Extensions)),
                                            Ms <- [Mod:feed_resync()], Ms =/= []]],
     State};
websocket_handle({text, _}, State) ->
    {[{close, 1003, <<"the panel sends nothing but resync">>}], State};
websocket_handle(_Frame, State) ->
    {[], State}.

-spec websocket_info(term(), #state{}) -> {[cow_ws:frame()], #state{}}.
websocket_info({cell_web_feed, Json}, State) ->
    batch(Json, State);
websocket_info(cell_web_feed_resync, State) ->
    %% The feed was detached from the cell for a moment: what changed meanwhile never
    %% came, so the page reads everything anew. The cell's services and tables may
    %% still be coming back: then it tries again a moment later, the page connected.
    try snapshot(true, State) of
        Snapshot -> {[Snapshot], State}
    catch
        error:badarg ->
            {[], resync_later(State)};
        %% A service not there, or gone (killed, stopped) while it was asked.
        exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                           Why =:= killed; element(1, Why) =:= shutdown ->
            {[], resync_later(State)}
    end;
websocket_info({timeout, _, ping}, State) ->
    _ = erlang:start_timer(?PING_MS, self(), ping),
    {[ping], State};
websocket_info({cell_web_session, ended}, State) ->
    {[{close, 4001, <<"session ended">>}], State};
websocket_info({'DOWN', Ref, process, _, _}, #state{feed = F, extensions = Es} = State)
  when Ref =:= F; is_map_key(Ref, Es) ->
    {[{close, 1012, <<"the cell restarted">>}], State};
websocket_info(Info, #state{extensions = Es} = State) ->
    {extension_info(Info, Es), State}.

resync_later(State) ->
    _ = erlang:send_after(?RESYNC_RETRY_MS, self(), cell_web_feed_resync),
    State.

%% The first message, and what waits behind it, in one frame; or, when the browser
%% has fallen too far behind, a fresh snapshot in place of the backlog.
batch(First, State) ->
    case process_info(self(), message_queue_len) of
        {message_queue_len, N} when N > ?MAX_BACKLOG ->
            drop(),
            {[snapshot(true, State)], State};
        _ ->
            {[{text, [$[, lists:join($,, [First | drain(?BATCH)]), $]]}], State}
    end.

drain(0) ->
    [];
drain(N) ->
    receive
        {cell_web_feed, Json} -> [Json | drain(N - 1)]
    after 0 ->
        []
    end.

drop() ->
    receive
        {cell_web_feed, _} -> drop()
    after 0 ->
        ok
    end.

%% @doc The messages for the page of one event or log line.
-spec messages({cell_event, map()} | {cell_log, cell_log:line()}) -> [map()].
messages({cell_log, Line}) ->
    [#{<<"type">> => <<"log">>, <<"line">> => cell_web_json:line(Line)}];
messages({cell_event, #{type := Type} = E}) ->
    case Type of
        task_state -> task(E);
        T when T =:= cell_state; T =:= request; T =:= estop; T =:= service_mode ->
            [cell()];
        link_phase ->
            [#{<<"type">> => <<"link">>,
               <<"link">> => cell_web_json:term(maps:with([link, phase, serial], E))}];
        alarm_raised ->
            [#{<<"type">> => <<"alarm">>, <<"alarm">> => cell_web_json:alarm(maps:get(alarm, E))},
             cell()];
        alarm_cleared ->
            [#{<<"type">> => <<"alarm_cleared">>,
               <<"alarm">> => cell_web_json:alarm(maps:get(alarm, E))},
             cell()];
        _ ->
            [#{<<"type">> => <<"event">>, <<"event">> => cell_web_json:event(E)} | task(E)]
    end.

%% The task as the registry has it now, in the state the event announced, so the page
%% sees every change in order; its product serial is read fresh.
task(#{task := cell}) ->
    [];
task(#{task := Id} = E) ->
    case cell_registry:task(Id) of
        {ok, Row} ->
            Row1 = case E of
                       #{type := task_state, state := S} -> Row#{state => S};
                       _ -> Row
                   end,
            [#{<<"type">> => <<"task">>, <<"task">> => cell_web_json:task(Row1#{id => Id})}];
        {error, not_found} ->
            []
    end.

cell() ->
    #{<<"type">> => <<"cell">>, <<"cell">> => cell_web_cell_h:cell()}.

snapshot(Resync, #state{caller = #{user := User, role := Role}}) ->
    {text, jsx:encode(
             [#{<<"type">> => <<"snapshot">>,
                <<"resync">> => Resync,
                <<"cell">> => cell_web_cell_h:cell(),
                <<"tasks">> => [cell_web_json:task(T) || T <- cell_controller:tasks()],
                <<"alarms">> => [cell_web_json:alarm(A) || A <- cell_alarms:list()],
                <<"log">> => [cell_web_json:line(L) || L <- cell_web_recent:lines()],
                <<"forces">> => cell_web_forces:json(),
                <<"session">> => #{<<"user">> => User,
                                   <<"role">> => atom_to_binary(Role, utf8)}}])}.
