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
-module(cell_service_tables).
-behaviour(gen_server).

-export([start_link/0, claim/2]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(state, {waiting = #{} :: #{atom() => {pid(), gen_server:from()}}}).

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

-spec init([]) -> {ok, #state{}}.
init([]) ->
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, new | kept, #state{}} | {noreply, #state{}}.
handle_call({claim, Name, Opts, Pid}, From, #state{waiting = W} = State) ->
    Self = self(),
    case ets:info(Name, owner) of
        undefined ->
            Name = ets:new(Name, [named_table, {heir, Self, Name} | Opts]),
            {reply, give(Name, Pid, new), State};
        Self ->
            {reply, give(Name, Pid, kept), State};
        _Dying ->
            %% Its previous owner has not finished exiting: answered when it is back.
            {noreply, State#state{waiting = W#{Name => {Pid, From}}}}
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
