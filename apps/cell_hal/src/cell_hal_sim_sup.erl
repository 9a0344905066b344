%% @doc Supervises the simulated PLCs, one child per device name. A simulated PLC
%% starts the first time a connection or a simulation needs it and keeps its image
%% across the HAL's reconnects, as a real PLC keeps its memory; restarted here after a
%% crash or a kill, it comes back at once with its image and its rules (kept in the
%% HAL's tables, see {@link cell_hal_sim_device}), as a real PLC after a reboot.
-module(cell_hal_sim_sup).
-behaviour(supervisor).

-export([start_link/0, ensure_device/2, stop_device/1]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

%% @doc The process of the simulated PLC `Name', started if it does not run.
-spec ensure_device(atom(), map()) -> pid().
ensure_device(Name, Opts) ->
    case cell_hal_sim_device:whereis(Name) of
        Pid when is_pid(Pid) ->
            Pid;
        undefined ->
            Spec = #{id => Name, start => {cell_hal_sim_device, start_link, [Name, Opts]}},
            case supervisor:start_child(?MODULE, Spec) of
                {ok, Pid} -> Pid;
                {error, {already_started, Pid}} -> Pid;
                {error, already_present} ->
                    _ = supervisor:delete_child(?MODULE, Name),
                    ensure_device(Name, Opts)
            end
    end.

%% @doc Stops a simulated PLC; its image and its rules are forgotten.
-spec stop_device(atom()) -> ok.
stop_device(Name) ->
    _ = supervisor:terminate_child(?MODULE, Name),
    _ = supervisor:delete_child(?MODULE, Name),
    cell_hal_sim_device:forget(Name).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% A simulated PLC crashing keeps crashing only through a bug in the simulator
    %% itself (rules are isolated): a few restarts a minute, then escalate.
    {ok, {#{strategy => one_for_one, intensity => 5, period => 60}, []}}.
