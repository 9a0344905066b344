%% @doc The recipe buffer (seed 000 §3.2.3): recipes loaded once, read many times, so
%% reading a file never costs a device task its cycle time.
%%
%% `get(Name)' reads the buffer (an ETS table) directly. The first request for a
%% recipe goes to this process, which starts one loader for it; requests for the same
%% recipe that arrive meanwhile wait for that load instead of starting their own, and
%% requests for other recipes are never held up behind it. A recipe that fails to
%% load is not remembered: the next request tries the file again.
%%
%% The controller calls {@link clear/0} at every Start, so recipes changed while the
%% machine stood still are read afresh. A load still running across a clear answers
%% those who asked for it but is not kept.
-module(cell_recipe_buffer).
-behaviour(gen_server).

-export([start_link/0, start_link/1, child_spec/1]).
-export([get/1, get/2, clear/0, loaded/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([options/0]).

-type options() :: #{recipe => cell_recipe:options()}.  %% how recipes are loaded

-define(TAB, cell_recipe_buffer).
-define(TIMEOUT, 60000).

-record(load, {ref :: reference(), waiting :: [gen_server:from()]}).
-record(state, {recipe_opts :: cell_recipe:options(),
                generation = 0 :: non_neg_integer(),   %% bumped by every clear
                %% loads under way, by recipe and generation, and their loaders
                loads = #{} :: #{{cell_recipe:name(), non_neg_integer()} => #load{},
                                 pid() => {cell_recipe:name(), non_neg_integer()}}}).

%% get/1 here reads recipes; it is not the process dictionary BIF.
-compile({no_auto_import, [get/1]}).

%% @doc Starts the buffer with the default recipe options.
-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    start_link(#{}).

%% @doc Starts the buffer, registered as `cell_recipe_buffer'.
-spec start_link(options()) -> {ok, pid()} | {error, term()}.
start_link(Opts) ->
    case Opts of
        #{recipe := R} when not is_map(R) -> {error, {bad_option, recipe}};
        _ when is_map(Opts) ->
            case maps:keys(Opts) -- [recipe] of
                [] -> gen_server:start_link({local, ?MODULE}, ?MODULE, Opts, []);
                [K | _] -> {error, {bad_option, K}}
            end;
        _ -> {error, {bad_option, options}}
    end.

%% @doc A child spec for the controller's supervisor.
-spec child_spec(options()) -> supervisor:child_spec().
child_spec(Opts) ->
    #{id => ?MODULE, start => {?MODULE, start_link, [Opts]}}.

%% @doc The recipe, from the buffer or, the first time, from its file.
-spec get(cell_recipe:name()) -> {ok, cell_recipe:recipe()} | {error, term()}.
get(Name) ->
    get(Name, ?TIMEOUT).

%% @doc As {@link get/1}, waiting at most `Timeout' ms for a load: `{error, timeout}'.
-spec get(cell_recipe:name(), timeout()) -> {ok, cell_recipe:recipe()} | {error, term()}.
get(Name, Timeout) ->
    case ets:lookup(?TAB, Name) of
        [{_, Recipe}] ->
            {ok, Recipe};
        [] ->
            %% A late reply after a timeout is dropped (calls use process aliases).
            try cell_service_tables:call(?MODULE, {get, Name}, Timeout)
            catch exit:{timeout, _} -> {error, timeout}
            end
    end.

%% @doc Empties the buffer (the controller calls it at every Start).
-spec clear() -> ok.
clear() ->
    cell_service_tables:call(?MODULE, clear, 5000).

%% @doc The names of the recipes in the buffer.
-spec loaded() -> [cell_recipe:name()].
loaded() ->
    lists:sort([Name || {Name, _} <- ets:tab2list(?TAB)]).

%%====================================================================
%% gen_server
%%====================================================================

%% @private
-spec init(options()) -> {ok, #state{}}.
init(Opts) ->
    %% Restarted after a fault, the buffer keeps the recipes it had (see
    %% cell_service_tables); loads under way then are asked for again.
    _ = cell_service_tables:claim(?TAB, [protected, set, {read_concurrency, true}]),
    {ok, #state{recipe_opts = maps:get(recipe, Opts, #{})}}.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, term(), #state{}} | {noreply, #state{}}.
handle_call({get, Name}, From, #state{generation = Gen, loads = Loads} = State) ->
    case ets:lookup(?TAB, Name) of
        [{_, Recipe}] ->
            {reply, {ok, Recipe}, State};
        [] ->
            Key = {Name, Gen},
            case Loads of
                #{Key := #load{waiting = W} = L} ->
                    {noreply, State#state{loads = Loads#{Key := L#load{waiting = [From | W]}}}};
                _ ->
                    Opts = State#state.recipe_opts,
                    Server = self(),
                    {Pid, Ref} = spawn_monitor(fun() ->
                                                       Result = cell_recipe:load(Name, Opts),
                                                       Server ! {loaded, self(), Result}
                                               end),
                    {noreply, State#state{loads = Loads#{Key => #load{ref = Ref, waiting = [From]},
                                                         Pid => Key}}}
            end
    end;
handle_call(clear, _From, #state{generation = Gen} = State) ->
    true = ets:delete_all_objects(?TAB),
    {reply, ok, State#state{generation = Gen + 1}}.

%% @private
-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({loaded, Pid, Result}, State) ->
    {noreply, finish(Pid, Result, State)};
handle_info({'DOWN', _Ref, process, Pid, Reason}, State) ->
    %% Only a loader that crashed gets here: a finished one's 'DOWN' is flushed.
    cell_log:error(recipes, "a recipe loader crashed: ~tp", [Reason]),
    {noreply, finish(Pid, {error, {load_failed, Reason}}, State)}.

%% Answers everyone waiting for the load, and keeps the recipe unless a clear came
%% in between.
finish(Pid, Result, #state{loads = Loads, generation = Current} = State) ->
    {{Name, Gen} = Key, Loads1} = maps:take(Pid, Loads),
    {#load{ref = Ref, waiting = Waiting}, Loads2} = maps:take(Key, Loads1),
    true = erlang:demonitor(Ref, [flush]),
    case Result of
        {ok, Recipe} when Gen =:= Current -> true = ets:insert(?TAB, {Name, Recipe});
        _ -> ok
    end,
    lists:foreach(fun(From) -> gen_server:reply(From, Result) end, Waiting),
    State#state{loads = Loads2}.
