%% @doc Owns the per-source log thresholds and the list of live log subscribers (both
%% in one ETS table that callers read without a process hop), and installs the task
%% log and trace log file handlers into lager.
-module(cell_log_server).
-behaviour(gen_server).

-export([start_link/0, set_level/2, reset_level/1, verbose_for/2,
         subscribe/1, unsubscribe/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2, terminate/2]).

-define(TAB, cell_log_levels).
-define(SUBS_KEY, '$subscribers').
-define(HANDLERS, [{{cell_log_file, task}, task}, {{cell_log_file, trace}, trace}]).

-record(state, {monitors = #{} :: #{pid() => reference()},
                %% Sources at Verbose for a while: the timer, and the level after it.
                timers = #{} :: #{binary() => {reference(), cell_log:threshold() | default}}}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

-spec set_level(binary() | '$default', cell_log:threshold()) -> ok.
set_level(Source, Level) -> gen_server:call(?MODULE, {set_level, Source, Level}).

-spec reset_level(binary()) -> ok.
reset_level(Source) -> gen_server:call(?MODULE, {reset_level, Source}).

-spec verbose_for(binary(), pos_integer()) -> ok.
verbose_for(Source, Ms) -> gen_server:call(?MODULE, {verbose_for, Source, Ms}).

-spec subscribe(pid()) -> ok.
subscribe(Pid) -> gen_server:call(?MODULE, {subscribe, Pid}).

-spec unsubscribe(pid()) -> ok.
unsubscribe(Pid) -> gen_server:call(?MODULE, {unsubscribe, Pid}).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    process_flag(trap_exit, true),
    ?TAB = ets:new(?TAB, [named_table, protected, {read_concurrency, true}]),
    true = ets:insert(?TAB, [{?SUBS_KEY, []}, {'$default', cell_log:default_level()}]),
    %% A new table: what callers kept of the old one's thresholds is out of date.
    ok = cell_log:levels_changed(),
    ok = install_handlers(),
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, ok, #state{}}.
handle_call({set_level, Source, Level}, _From, State) ->
    true = ets:insert(?TAB, {Source, Level}),
    ok = cell_log:levels_changed(),
    {reply, ok, cancel_timer(Source, State)};
handle_call({reset_level, Source}, _From, State) ->
    true = ets:delete(?TAB, Source),
    ok = cell_log:levels_changed(),
    {reply, ok, cancel_timer(Source, State)};
handle_call({verbose_for, Source, Ms}, _From, State0) ->
    %% Asked again while at Verbose for a while: the new time counts, and afterwards
    %% the level is the one from before the first ask.
    Previous = case {maps:find(Source, State0#state.timers), ets:lookup(?TAB, Source)} of
                   {{ok, {_, Before}}, _} -> Before;
                   {error, [{_, L}]} -> L;
                   {error, []} -> default
               end,
    State = cancel_timer(Source, State0),
    true = ets:insert(?TAB, {Source, verbose}),
    ok = cell_log:levels_changed(),
    Ref = erlang:start_timer(Ms, self(), {restore, Source}),
    {reply, ok, State#state{timers = maps:put(Source, {Ref, Previous}, State#state.timers)}};
handle_call({subscribe, Pid}, _From, #state{monitors = Mons} = State) ->
    case maps:is_key(Pid, Mons) of
        true ->
            {reply, ok, State};
        false ->
            Mons1 = maps:put(Pid, monitor(process, Pid), Mons),
            ok = store_subscribers(Mons1),
            {reply, ok, State#state{monitors = Mons1}}
    end;
handle_call({unsubscribe, Pid}, _From, State) ->
    {reply, ok, drop_subscriber(Pid, State)}.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({timeout, Ref, {restore, Source}}, #state{timers = Timers} = State) ->
    case maps:find(Source, Timers) of
        {ok, {Ref, Previous}} ->
            true = case Previous of
                       default -> ets:delete(?TAB, Source);
                       Level -> ets:insert(?TAB, {Source, Level})
                   end,
            ok = cell_log:levels_changed(),
            {noreply, State#state{timers = maps:remove(Source, Timers)}};
        _ ->
            {noreply, State}
    end;
handle_info({'DOWN', _Ref, process, Pid, _Reason}, State) ->
    {noreply, drop_subscriber(Pid, State)};
handle_info({gen_event_EXIT, _Handler, _Reason}, State) ->
    {noreply, State}.

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, _State) ->
    _ = [gen_event:delete_handler(lager_event, Id, remove) || {Id, _} <- ?HANDLERS],
    %% The table goes with this process: callers fall back to the default threshold.
    true = ets:delete(?TAB),
    cell_log:levels_changed().

install_handlers() ->
    Dir = cell_config:dir(logs),
    Installed = gen_event:which_handlers(lager_event),
    _ = [lager_app:start_handler(lager_event, Id, [{dir, Dir}, {kind, Kind}])
         || {Id, Kind} <- ?HANDLERS, not lists:member(Id, Installed)],
    _ = lager:update_loglevel_config(lager_event),
    ok.

drop_subscriber(Pid, #state{monitors = Mons} = State) ->
    case maps:take(Pid, Mons) of
        {Ref, Mons1} ->
            demonitor(Ref, [flush]),
            ok = store_subscribers(Mons1),
            State#state{monitors = Mons1};
        error ->
            State
    end.

store_subscribers(Mons) ->
    true = ets:insert(?TAB, {?SUBS_KEY, maps:keys(Mons)}),
    ok.

cancel_timer(Source, #state{timers = Timers} = State) ->
    case maps:take(Source, Timers) of
        {{Ref, _}, Timers1} ->
            _ = erlang:cancel_timer(Ref),
            State#state{timers = Timers1};
        error ->
            State
    end.
