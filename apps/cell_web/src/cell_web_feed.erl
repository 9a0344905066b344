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
%% If the event fan-out or the log server restarts, this process stops with them and
%% its supervisor starts it again; the pages, which monitor it, reconnect and read a
%% fresh snapshot.
-module(cell_web_feed).
-behaviour(gen_server).

-export([start_link/0, join/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(state, {pages = #{} :: #{pid() => reference()},
                events :: reference(),
                log :: reference()}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc A page's websocket process gets the updates from now on, until it exits.
-spec join(pid()) -> ok.
join(Page) ->
    gen_server:call(?MODULE, {join, Page}).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    %% Bursts (a thousand tasks stopping) wait outside the heap.
    process_flag(message_queue_data, off_heap),
    ok = cell_events:subscribe(),
    ok = cell_log:subscribe(),
    {ok, #state{events = monitor(process, cell_events),
                log = monitor(process, cell_log_server)}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, ok, #state{}}.
handle_call({join, Page}, _From, #state{pages = Pages} = State) ->
    case maps:is_key(Page, Pages) of
        true -> {reply, ok, State};
        false -> {reply, ok, State#state{pages = Pages#{Page => monitor(process, Page)}}}
    end.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}} | {stop, term(), #state{}}.
handle_info({cell_event, _} = Msg, State) ->
    {noreply, send(Msg, State)};
handle_info({cell_log, _} = Msg, State) ->
    {noreply, send(Msg, State)};
handle_info({'DOWN', Ref, process, _, Reason}, #state{events = Ref} = State) ->
    {stop, {cell_events_down, Reason}, State};
handle_info({'DOWN', Ref, process, _, Reason}, #state{log = Ref} = State) ->
    {stop, {log_server_down, Reason}, State};
handle_info({'DOWN', _Ref, process, Page, _Reason}, #state{pages = Pages} = State) ->
    {noreply, State#state{pages = maps:remove(Page, Pages)}}.

send(_Msg, #state{pages = Pages} = State) when map_size(Pages) =:= 0 ->
    State;
send(Msg, #state{pages = Pages} = State) ->
    case cell_web_ws_h:messages(Msg) of
        [] ->
            State;
        Messages ->
            Json = iolist_to_binary(lists:join($,, [jsx:encode(M) || M <- Messages])),
            _ = maps:fold(fun(Page, _, ok) -> Page ! {cell_web_feed, Json}, ok end, ok, Pages),
            State
    end.
