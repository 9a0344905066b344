%% @doc The HAL's top supervisor. It owns the HAL's tables (created in `init/1'), so
%% the configuration, the last values and the subscriptions survive a restart of any
%% child.
%%
%% `rest_for_one' in dependency order: the server registers what the workers serve;
%% the simulated PLCs must run before a worker connects to one; hardware objects come
%% last, independent of the rest.
-module(cell_hal_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    ok = cell_hal_store:create_tables(),
    ok = cell_hal_force:create_table(),
    %% Each child restarts on its own terms below; five escalations a minute mean the
    %% HAL cannot run: stop it so the node reports it rather than spin.
    Flags = #{strategy => rest_for_one, intensity => 5, period => 60},
    Children = [#{id => cell_hal_server, start => {cell_hal_server, start_link, []}},
                sup(cell_hal_sim_sup),
                sup(cell_hal_conn_sup),
                sup(cell_hal_hw_sup)],
    {ok, {Flags, Children}}.

sup(Mod) ->
    #{id => Mod, start => {Mod, start_link, []}, type => supervisor, shutdown => infinity}.
