%% @doc The top supervisor of the `cell' application: it holds the controller's tree
%% (see {@link cell_controller_sup}) and starts it again, whole, when the controller
%% gives up.
%%
%% The controller gives up when its children fail more than its intensity allows (a
%% burst of faults in one service: each restart of the service restarted the children
%% after it). Starting the controller's tree anew is what a node restart would do,
%% without stopping the HAL, the panel, the SHDR adapter or the inspection blocks,
%% which stay attached to the cell and follow it back. The tasks come back OFF and
%% the cell waits for the operator's Start (the log says so). Only a controller that
%% keeps giving up (more than three times in ten minutes: thirty-odd faults that
%% restarting does not cure) stops the `cell' application and with it the node; the
%% node's watchdog (heart, or the service manager) then starts it afresh.
-module(cell_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% One child; the intensity counts the controller's escalations (see above).
    Flags = #{strategy => one_for_one, intensity => 3, period => 600},
    %% Counts the controller's starts, so that a start after the first says why the
    %% cell stopped; shared by every start of the child through its arguments.
    Starts = counters:new(1, []),
    {ok, {Flags, [#{id => cell_controller_sup,
                    start => {cell_controller_sup, start_link, [Starts]},
                    type => supervisor, shutdown => infinity}]}}.
