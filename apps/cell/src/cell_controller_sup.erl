%% @doc The controller: the top-level supervisor of the cell runtime, built from the
%% cell spec (see {@link cell_spec}).
%%
%% rest_for_one, in dependency order: the registry owns the tables every later child
%% uses; events, the trace journal, alarms, settings and the recipe buffer are used by
%% the tasks; the peers and the handshake links connect the tasks; the monitor connects
%% the HAL the spec names and watches the general IO (the tasks read their IO only once
%% started); the controller drives the tasks; the statistics only listen to all of them
%% (and read the trace journal). A child
%% that dies takes down only those started after it. Ten restarts a minute is a
%% fault that will not go away by itself on an unattended machine: beyond that the node
%% reports it instead of spinning.
-module(cell_controller_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    case cell_spec:load() of
        {ok, Spec} -> supervisor:start_link({local, ?MODULE}, ?MODULE, Spec);
        {error, Reason} -> {error, {bad_cell_spec, Reason}}
    end.

-spec init(cell_spec:spec()) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(#{tasks := Tasks, settings := Schemas} = Spec) ->
    Flags = #{strategy => rest_for_one, intensity => 10, period => 60},
    Children = [#{id => cell_registry, start => {cell_registry, start_link, []}},
                #{id => cell_events, start => {cell_events, start_link, []}},
                %% Before every writer of the product's way (answers, tasks) and its
                %% reader (the statistics): a restart of it restarts them all, so the
                %% statistics read it again whole.
                cell_trace_journal:child_spec(),
                #{id => cell_alarms, start => {cell_alarms, start_link, []}},
                cell_settings:child_spec(#{schemas => [cell_machine_settings | Schemas]}),
                cell_recipe_buffer:child_spec(#{}),
                cell_peers:child_spec(Spec),
                #{id => cell_handshake_sup,
                  start => {cell_handshake_sup, start_link, [cell_spec:hosted_links(Spec)]},
                  type => supervisor, shutdown => infinity},
                #{id => cell_task_sup, start => {cell_task_sup, start_link, [Tasks]},
                  type => supervisor, shutdown => infinity},
                cell_monitor:child_spec(Spec),
                #{id => cell_controller, start => {cell_controller, start_link, []}},
                %% Last: it only listens, so its restart touches nothing else.
                cell_stats:child_spec(Spec)],
    {ok, {Flags, Children}}.
