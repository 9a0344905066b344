%% @doc Supervises the device tasks of the cell: one gen_statem each (cell_task_proc, or
%% cell_unit_proc for a unit), one_for_one, so one task's crash never disturbs another.
%% A restarted task goes on by itself only where its reconcile agrees with what it
%% finds, and comes back DOWN with an error naming the crash where reconcile cannot
%% decide (a crash in init or reconcile, or again before its first wait after going on
%% by itself; a unit: in Init, with such an error), so restarts cannot run away on
%% their own; the intensity below stops a task that crashes over and over anyway.
-module(cell_task_sup).
-behaviour(supervisor).

-export([start_link/1, start_task/1, stop_task/1]).
-export([init/1]).

-spec start_link([cell_task:spec()]) -> {ok, pid()} | ignore | {error, term()}.
start_link(Tasks) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, Tasks).

%% @doc Adds a task to the running cell (it starts OFF unless the cell runs).
-spec start_task(cell_task:spec()) -> {ok, pid()} | {error, term()}.
start_task(Spec) ->
    case cell_spec:validate(#{tasks => [Spec]}) of
        {ok, #{tasks := [Checked]}} ->
            case supervisor:start_child(?MODULE, child_spec(Checked)) of
                {ok, Pid} -> {ok, Pid};
                {error, _} = Error -> Error
            end;
        {error, _} = Error ->
            Error
    end.

%% @doc Removes a task: it stops (uninit runs) and is forgotten.
-spec stop_task(atom()) -> ok | {error, not_found}.
stop_task(Id) ->
    case supervisor:terminate_child(?MODULE, Id) of
        ok -> supervisor:delete_child(?MODULE, Id);
        {error, _} = Error -> Error
    end.

-spec init([cell_task:spec()]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(Tasks) ->
    case cell_registry:control(request) of
        stop ->
            ok;
        _ ->
            %% The tasks' subtree is restarting while the cell was running (an internal
            %% fault below the controller). The tasks come back OFF and wait for the
            %% operator's Start rather than move on their own; the controller tells the
            %% operator why with an alarm until then.
            ok = cell_registry:stopped_by_fault(services),
            cell_log:error(cell, "the cell's tasks were restarted after an internal fault; "
                           "check the machine and press Start", [])
    end,
    Known = cell_settings:names(),
    _ = [erlang:error({unknown_settings_object, Id, Name})
         || #{id := Id, settings := Name} <- Tasks, is_atom(Name),
            not lists:member(Name, Known)],
    %% A task that keeps crashing comes back DOWN and waits for the operator, so
    %% restarts do not run away; twenty a minute (a cell of many tasks hit by one fault
    %% at once) is spent
    %% only by tasks crashing as they boot, then the controller's tree restarts.
    Flags = #{strategy => one_for_one, intensity => 20, period => 60},
    {ok, {Flags, [child_spec(T) || T <- Tasks]}}.

child_spec(#{module := Mod} = Spec) ->
    case cell_unit:is_unit_module(Mod) of
        true -> cell_unit_proc:child_spec(Spec);
        false -> cell_task_proc:child_spec(Spec)
    end.
