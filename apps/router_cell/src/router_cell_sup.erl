%% @doc The router cell's supervisor: in simulation mode, the machine's physics
%% ({@link router_sim}); on the real machine (or when the router is not the cell the
%% runtime runs) nothing. Ten restarts a minute is a fault that will not go away on
%% its own: the application stops and the node reports it; the cell's tasks are not
%% under this supervisor and run on (their watchdogs then tell the operator).
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
    Flags = #{strategy => one_for_one, intensity => 10, period => 60},
    {ok, {Flags, [#{id => router_sim, start => {router_sim, start_link, [#{lanes => Lanes}]},
                    shutdown => 5000}]}};
init({false, _}) ->
    {ok, {#{strategy => one_for_one}, []}}.
