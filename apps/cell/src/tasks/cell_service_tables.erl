%% @doc The keeper of the tables a service of the controller must not lose when it
%% restarts (the subscribers of {@link cell_events}, the active errors of {@link
%% cell_alarms}, the objects and subscribers of {@link cell_settings}, the loaded
%% recipes of {@link cell_recipe_buffer}).
%%
%% A service claims its table in `init/1': the first time the keeper makes it and gives
%% it to the service, naming itself the table's heir. When the service dies the table
%% comes back to the keeper whole (ETS hands it over as part of the owner's exit), and
%% the service started again claims it back and reads what its predecessor knew. A claim
%% that arrives before the table is back (the new service started before the old one's
%% exit was complete) waits for it.
%%
%% The keeper sits in the controller's rest_for_one chain before the services: while it
%% runs, a service's restart loses nothing; when the controller's tree is started anew,
%% the keeper goes with it, and the services start from empty tables as at boot. Started
%% alone (in a unit test, a tool), a service makes its table itself: {@link claim/2}
%% says `new'.
%%
%% Between a service's death and its successor's start its name is not registered: a
%% call then exits with `noproc' and a cast is lost. Its callers that must not fail
%% for that (a task raising an error, the controller setting the emergency stop's
%% alarm) go through {@link call/3} and {@link cast/2}: they wait until the service
%% has claimed its table again (it is registered by then), told by the keeper, not
%% found by polling.
-module(cell_service_tables).
-behaviour(gen_server).

-export([start_link/0, claim/2, await/2, call/3, cast/2]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(state, {waiting = #{} :: #{atom() => {pid(), gen_server:from()}},
                %% callers waiting for a service by its registered name
                awaiting = #{} :: #{atom() => [gen_server:from()]}}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The caller's named table `Name', made with `Opts' (`named_table' and the heir
%% are added) if the keeper has none yet (`new'), or the one its predecessor left
%% (`kept'). Either way the caller owns it when this returns.
-spec claim(atom(), [term()]) -> new | kept.
claim(Name, Opts) when is_atom(Name), is_list(Opts) ->
    case whereis(?MODULE) of
        undefined ->
            Name = ets:new(Name, [named_table | Opts]),
            new;
        Keeper ->
            Result = gen_server:call(Keeper, {claim, Name, Opts, self()}, infinity),
            %% The keeper gave the table away before it answered: its notice is here.
            receive {'ETS-TRANSFER', Name, Keeper, Name} -> Result end
    end.

%% @doc Returns once a process is registered as `Name', at most `Timeout'
%% milliseconds: at once if it is, or when a service of that name claims its table.
%% `timeout' if it did not come back in time or there is no keeper to tell.
-spec await(atom(), timeout()) -> ok | timeout.
await(Name, Timeout) when is_atom(Name) ->
    case {whereis(Name), whereis(?MODULE)} of
        {Pid, _} when is_pid(Pid) -> ok;
        {undefined, undefined} -> timeout;
        {undefined, Keeper} ->
            try gen_server:call(Keeper, {await, Name}, Timeout)
            catch exit:{_, {gen_server, call, _}} -> timeout
            end
    end.

%% @doc `gen_server:call(Name, Request, Timeout)', through a restart of the service:
%% a request that found no process (so was never handled) is sent again once the
%% service is back. Any other exit is the caller's, as for gen_server:call/3.
-spec call(atom(), term(), timeout()) -> term().
call(Name, Request, Timeout) ->
    try gen_server:call(Name, Request, Timeout)
    catch
        exit:{noproc, _} ->
            _ = await(Name, Timeout),
            gen_server:call(Name, Request, Timeout)
    end.

%% @doc `gen_server:cast(Name, Msg)', waiting first for a service that is restarting
%% (at most five seconds; then the message is lost, as a cast to no process is).
-spec cast(atom(), term()) -> ok.
cast(Name, Msg) ->
    _ = case whereis(Name) of
            undefined -> await(Name, 5000);
            _ -> ok
        end,
    gen_server:cast(Name, Msg).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, new | kept | ok, #state{}} | {noreply, #state{}}.
handle_call({claim, Name, Opts, Pid}, From, #state{waiting = W} = State0) ->
    Self = self(),
    State = back(Pid, State0),
    case ets:info(Name, owner) of
        undefined ->
            Name = ets:new(Name, [named_table, {heir, Self, Name} | Opts]),
            {reply, give(Name, Pid, new), State};
        Self ->
            {reply, give(Name, Pid, kept), State};
        _Dying ->
            %% Its previous owner has not finished exiting: answered when it is back.
            {noreply, State#state{waiting = W#{Name => {Pid, From}}}}
    end;
handle_call({await, Name}, From, #state{awaiting = A} = State) ->
    case whereis(Name) of
        undefined -> {noreply, State#state{awaiting = A#{Name => [From | maps:get(Name, A, [])]}}};
        _ -> {reply, ok, State}
    end.

%% A service claims its table from its init: it is registered already (gen_server
%% registers before init), and those waiting for it can call it now.
back(Pid, #state{awaiting = A} = State) ->
    case process_info(Pid, registered_name) of
        {registered_name, Name} when is_map_key(Name, A) ->
            {Waiting, A1} = maps:take(Name, A),
            _ = [gen_server:reply(From, ok) || From <- Waiting],
            State#state{awaiting = A1};
        _ ->
            State
    end.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'ETS-TRANSFER', Name, _From, Name}, #state{waiting = W} = State) ->
    case maps:take(Name, W) of
        {{Pid, Claim}, W1} ->
            gen_server:reply(Claim, give(Name, Pid, kept)),
            {noreply, State#state{waiting = W1}};
        error ->
            {noreply, State}
    end.

%% A claimer gone meanwhile (its start failed) leaves the table here, for the next.
give(Name, Pid, Result) ->
    try ets:give_away(Name, Pid, Name) of
        true -> Result
    catch
        error:badarg -> Result
    end.
