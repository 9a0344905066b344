%% @doc The live updates of the connected pages, made once for all of them.
%%
%% Subscribed to every cell event and every task log line, this process turns each
%% into the page's messages (see {@link cell_web_ws_h}) and encodes them as JSON once;
%% every page that joined gets the same binary, shared, not copied. Ten pages cost one
%% encoding an event, not ten.
%%
%% A page joins with {@link join/1} and is monitored; it gets `{cell_web_feed, Json}'
%% where `Json' is one or more JSON objects separated by commas, to be framed into an
%% array. With no page connected the events are taken and dropped unencoded.
%%
%% If the event fan-out or the log server restarts, this process stays: it monitors
%% both, attaches again once they are back (see {@link cell_attach}: a backoff timer,
%% no polling), and then tells every page to read a fresh snapshot
%% (`cell_web_feed_resync'), since changes made while it was detached never reached
%% it. So a burst of restarts of the cell's services neither closes the pages nor
%% counts against the panel's supervisor.
-module(cell_web_feed).
-behaviour(gen_server).

-export([start_link/0, join/1, publish/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(state, {pages = #{} :: #{pid() => reference()},
                counters :: reference() | undefined,
                watch = #{} :: cell_attach:watch(),
                retry :: reference() | undefined,
                backoff = cell_attach:first() :: pos_integer()}).

-define(SERVICES, [cell_events, cell_log_server]).
%% How long after an item's event the shift's counters are read again (the statistics
%% write what they counted every second).
-define(COUNTERS_MS, 1500).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc A page's websocket process gets the updates from now on, until it exits.
-spec join(pid()) -> ok.
join(Page) ->
    gen_server:call(?MODULE, {join, Page}).

%% @doc Sends messages made elsewhere in the panel (forces, IO values, counters) to
%% every page, encoded once; never waits.
-spec publish([map()]) -> ok.
publish(Messages) ->
    gen_server:cast(?MODULE, {publish, Messages}).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    %% Bursts (a thousand tasks stopping) wait outside the heap.
    process_flag(message_queue_data, off_heap),
    {ok, attach(#state{})}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, ok, #state{}}.
handle_call({join, Page}, _From, #state{pages = Pages} = State) ->
    case maps:is_key(Page, Pages) of
        true -> {reply, ok, State};
        false -> {reply, ok, State#state{pages = Pages#{Page => monitor(process, Page)}}}
    end.

-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({publish, Messages}, State) ->
    {noreply, send_json(Messages, State)};
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_event, #{type := Type}} = Msg, State) ->
    {noreply, counters_later(Type, send(Msg, State))};
handle_info({timeout, TRef, counters}, #state{counters = TRef} = State) ->
    Counters = #{<<"type">> => <<"counters">>,
                 <<"counters">> => cell_web_json:term(cell_web_layout_h:counters())},
    {noreply, send_json([Counters], State#state{counters = undefined})};
handle_info({cell_log, _} = Msg, State) ->
    {noreply, send(Msg, State)};
handle_info({'DOWN', Ref, process, _, Reason}, #state{watch = W} = State)
  when is_map_key(Ref, W) ->
    cell_log:warning(web, "the panel lost the cell's ~ts (~0tp); the pages are brought up "
                     "to date when it is back", [service(maps:get(Ref, W)), Reason]),
    ok = cell_attach:unwatch(W),
    {noreply, attach(State#state{watch = #{}})};
handle_info({'DOWN', _Ref, process, Page, _Reason}, #state{pages = Pages} = State) ->
    {noreply, State#state{pages = maps:remove(Page, Pages)}};
handle_info({timeout, TRef, cell_attach}, #state{retry = TRef, backoff = B} = State) ->
    {noreply, attach(State#state{retry = undefined, backoff = cell_attach:next(B)})}.

%% The shift's counters change with the items that come, go and are worked; the
%% statistics write them within a second, so the pages get them anew then, once for a
%% burst of events.
counters_later(_Type, #state{pages = Pages} = State) when map_size(Pages) =:= 0 ->
    State;
counters_later(Type, #state{counters = undefined} = State)
  when Type =:= item_transfer_in; Type =:= item_transfer_out; Type =:= item_work_complete;
       Type =:= item_work_abort; Type =:= task_state ->
    State#state{counters = erlang:start_timer(?COUNTERS_MS, self(), counters)};
counters_later(_Type, State) ->
    State.

%% Subscribes to the events and the log lines; when both are back after a loss, every
%% page reads a fresh snapshot (at the first attach there is no page yet).
attach(#state{retry = undefined, backoff = B} = State) ->
    Subscribe = fun() -> ok = cell_events:subscribe(), cell_log:subscribe() end,
    case cell_attach:watch(?SERVICES, Subscribe) of
        {ok, Watch} ->
            ok = resync(State#state.pages),
            State#state{watch = Watch, backoff = cell_attach:first()};
        retry ->
            State#state{retry = cell_attach:retry_after(B)}
    end;
attach(State) ->
    %% A try is already armed.
    State.

service(cell_events) -> "events";
service(cell_log_server) -> "log server".

send(_Msg, #state{pages = Pages} = State) when map_size(Pages) =:= 0 ->
    State;
send(Msg, #state{pages = Pages} = State) ->
    case messages(Msg) of
        [] ->
            State;
        resync ->
            ok = resync(Pages),
            State;
        Messages ->
            send_json(Messages, State)
    end.

send_json(_Messages, #state{pages = Pages} = State) when map_size(Pages) =:= 0 ->
    State;
send_json(Messages, #state{pages = Pages} = State) ->
    Json = iolist_to_binary(lists:join($,, [jsx:encode(M) || M <- Messages])),
    _ = maps:fold(fun(Page, _, ok) -> Page ! {cell_web_feed, Json}, ok end, ok, Pages),
    State.

%% A message is made from the cell's tables as they are now. An event that comes while
%% the services owning them restart (the tables gone, the owner not there) cannot be
%% made: the pages read a fresh snapshot instead, once the cell answers again.
messages(Msg) ->
    try cell_web_ws_h:messages(Msg)
    catch
        error:badarg -> resync;
        %% A service not there, or gone (killed, stopped) while it was asked.
        exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                           Why =:= killed; element(1, Why) =:= shutdown -> resync
    end.

resync(Pages) ->
    _ = maps:fold(fun(Page, _, ok) -> Page ! cell_web_feed_resync, ok end, ok, Pages),
    ok.
