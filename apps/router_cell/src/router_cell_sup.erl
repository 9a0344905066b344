%% @doc The router cell's supervisor: the HAL connection first, the simulated machine
%% after it (its physics moves the simulated PLC's points), rest_for_one. Ten restarts
%% a minute is a fault that will not go away on its own: the application stops and
%% the node reports it; the cell's tasks are not under this supervisor and run on.
-module(router_cell_sup).
-behaviour(supervisor).

-export([start_link/0, start_link/2]).
-export([init/1]).

%% @doc A supervisor with nothing to do: the router is not the configured cell.
-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, none).

%% @doc The router's HAL, and its physics in simulation mode.
-spec start_link(map(), boolean()) -> {ok, pid()} | ignore | {error, term()}.
start_link(Spec, Simulated) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, {Spec, Simulated}).

-spec init(none | {map(), boolean()}) ->
          {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(none) ->
    {ok, {#{strategy => one_for_one}, []}};
init({#{hal := Hal} = Spec, Simulated}) ->
    Flags = #{strategy => rest_for_one, intensity => 10, period => 60},
    Sim = case Simulated of
              true -> [#{id => router_sim,
                         start => {router_sim, start_link,
                                   [#{lanes => router_sim_lanes(Spec)}]}}];
              false -> []
          end,
    {ok, {Flags, [#{id => router_hal, start => {router_hal, start_link, [Hal]}} | Sim]}}.

router_sim_lanes(#{tasks := Tasks}) ->
    [L || #{module := router_loading_task, args := #{lane := L}} <- Tasks].
