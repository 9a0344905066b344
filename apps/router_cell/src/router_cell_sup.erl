%% @doc The router cell's supervisor: in simulation mode, the machine's physics
%% ({@link router_sim}); on the real machine (or when the router is not the cell the
%% runtime runs) nothing. The physics waits for a HAL taken down under it (the cell's
%% monitor restarting) rather than crash, so only its own faults count here. Ten
%% restarts a minute is a fault that will not go away on its own: the application
%% stops, and with it the node (a permanent application of the release), which heart
%% or the service manager then starts afresh: a simulated machine without its physics
%% would only mislead the operator.
-module(router_cell_sup).
-behaviour(supervisor).

-export([start_link/2]).
-export([init/1]).

%% @doc The physics of a router with these lanes, if it is simulated.
-spec start_link(boolean(), [front | rear]) -> {ok, pid()} | ignore | {error, term()}.
start_link(Simulated, Lanes) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, {Simulated, Lanes}).

-spec init({boolean(), [front | rear]}) ->
          {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init({true, Lanes}) ->
    %% The physics' own faults only (see the module doc).
    Flags = #{strategy => one_for_one, intensity => 10, period => 60},
    {ok, {Flags, [#{id => router_sim, start => {router_sim, start_link, [#{lanes => Lanes}]},
                    shutdown => 5000}]}};
init({false, _}) ->
    {ok, {#{strategy => one_for_one}, []}}.
