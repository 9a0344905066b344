%% @doc The latest lines of the task log, kept in memory for the panel: a page that
%% connects shows them at once, without reading the day's log file.
%%
%% Subscribed to `cell_log'; the lines sit in an ETS table that websockets read
%% directly. If the log server restarts, this process keeps its lines and subscribes
%% again once the server is back (see {@link cell_attach}).
-module(cell_web_recent).
-behaviour(gen_server).

-export([start_link/0, lines/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(TAB, cell_web_recent_lines).
-define(KEEP, 200).

-record(state, {watch = #{} :: cell_attach:watch(),
                retry :: reference() | undefined,
                backoff = cell_attach:first() :: pos_integer()}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The latest lines, oldest first.
-spec lines() -> [cell_log:line()].
lines() ->
    [L || {_, L} <- ets:tab2list(?TAB)].

-spec init([]) -> {ok, #state{}}.
init([]) ->
    ?TAB = ets:new(?TAB, [named_table, ordered_set, protected, {read_concurrency, true}]),
    {ok, attach(#state{})}.

-spec handle_call(term(), gen_server:from(), #state{}) -> no_return().
handle_call(Msg, _From, _State) ->
    erlang:error({unexpected_call, Msg}).

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_log, Line}, State) ->
    true = ets:insert(?TAB, {erlang:unique_integer([monotonic]), Line}),
    case ets:info(?TAB, size) > ?KEEP of
        true -> true = ets:delete(?TAB, ets:first(?TAB));
        false -> ok
    end,
    {noreply, State};
handle_info({'DOWN', Ref, process, _, _}, #state{watch = W} = State) when is_map_key(Ref, W) ->
    ok = cell_attach:unwatch(W),
    {noreply, attach(State#state{watch = #{}})};
handle_info({timeout, TRef, cell_attach}, #state{retry = TRef, backoff = B} = State) ->
    {noreply, attach(State#state{retry = undefined, backoff = cell_attach:next(B)})}.

attach(#state{retry = undefined, backoff = B} = State) ->
    case cell_attach:watch([cell_log_server], fun cell_log:subscribe/0) of
        {ok, Watch} -> State#state{watch = Watch, backoff = cell_attach:first()};
        retry -> State#state{retry = cell_attach:retry_after(B)}
    end.
