%% @doc The __NAME__ application's supervisor: in simulation mode, the simulated line
%% ({@link __NAME___sim}); on the real machine nothing. Ten restarts a minute is a
%% fault that will not go away on its own: the application stops, and with it the
%% node, which the service manager starts afresh.
-module(__NAME___sup).
-behaviour(supervisor).

-export([start_link/1]).
-export([init/1]).

-spec start_link(boolean()) -> {ok, pid()} | ignore | {error, term()}.
start_link(Simulated) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, Simulated).

-spec init(boolean()) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(true) ->
    {ok, {#{strategy => one_for_one, intensity => 10, period => 60},
          [#{id => __NAME___sim, start => {__NAME___sim, start_link, []}, shutdown => 5000}]}};
init(false) ->
    {ok, {#{strategy => one_for_one}, []}}.
