%% @doc The virtual PLC's supervisor: the simulation's own supervisor first, then the
%% PLC ({@link cell_vplc}), which puts the cell's IO in the HAL, starts the simulation
%% under the first and serves it. `rest_for_one': a simulation supervisor that gave up
%% takes the PLC with it, which sets everything up again; the PLC crashing leaves the
%% physics running (its world is what the clients saw). A few restarts a minute, then
%% the node stops: a virtual PLC that cannot stay up should say so, not limp.
-module(cell_vplc_sup).
-behaviour(supervisor).

-export([start_link/0, start_simulation/1]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, top).

%% @doc Starts one child of the cell's simulation.
-spec start_simulation(supervisor:child_spec()) -> {ok, pid()} | {error, term()}.
start_simulation(Spec) ->
    case supervisor:start_child(cell_vplc_sim_sup, Spec) of
        {ok, Pid} -> {ok, Pid};
        {ok, Pid, _} -> {ok, Pid};
        {error, {already_started, Pid}} -> {ok, Pid};
        {error, _} = Error -> Error
    end.

-spec init(top | simulation) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(top) ->
    {ok, {#{strategy => rest_for_one, intensity => 5, period => 60},
          [#{id => cell_vplc_sim_sup, type => supervisor,
             start => {supervisor, start_link, [{local, cell_vplc_sim_sup}, ?MODULE, simulation]}},
           #{id => cell_vplc, start => {cell_vplc, start_link, []}, shutdown => 5000}]}};
init(simulation) ->
    %% The cell's own physics, restarted as its cell's supervisor would.
    {ok, {#{strategy => one_for_one, intensity => 10, period => 60}, []}}.
