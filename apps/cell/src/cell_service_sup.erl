%% @doc The services of the controller the tasks use (the event fan-out, the alarms,
%% the settings, the recipe buffer, the peers), under {@link cell_controller_sup}.
%%
%% one_for_one: a service that dies restarts alone, and with what it knew, because its
%% tables stay with {@link cell_service_tables} meanwhile. The tasks, the handshake
%% links, the monitor and the controller after it in the controller's chain keep
%% running: a line in production keeps moving, an error waiting for its answer is still
%% shown and still reaches its task. Subscribers do not notice: their subscriptions are
%% in the kept tables.
-module(cell_service_sup).
-behaviour(supervisor).

-export([start_link/1]).
-export([init/1]).

-spec start_link([supervisor:child_spec()]) -> {ok, pid()} | ignore | {error, term()}.
start_link(Children) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, Children).

-spec init([supervisor:child_spec()]) ->
          {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(Children) ->
    %% A restart here costs the cell nothing, so a burst of twenty a minute is still
    %% cured by restarting; beyond, the controller restarts the services afresh and,
    %% after them, the tasks (OFF), as for any other of its children.
    Flags = #{strategy => one_for_one, intensity => 20, period => 60},
    {ok, {Flags, Children}}.
