%% @doc The controller: the supervisor of the cell runtime, built from the cell spec
%% (see {@link cell_spec}), under {@link cell_sup}.
%%
%% rest_for_one, in dependency order: the registry owns the tables every later child
%% uses; the service tables keep what the services must not lose; the trace journal
%% is written by every writer of the product's way (the answers, the tasks) and read by
%% the statistics, so a restart of it restarts them all and the statistics read it
%% again whole; the services (events, alarms, settings, the recipe buffer, the peers,
%% under {@link cell_service_sup}) are used by the tasks and restart alone, without the
%% children after them; the handshake links connect the tasks; the monitor connects the
%% HAL the spec names and watches the general IO (the tasks read their IO only once
%% started); the controller drives the tasks; the statistics only listen to all of
%% them, and the guard (a product held twice, a cell that makes no progress) only
%% listens and asks the operator; it reads every table before it, and a restart of it
%% touches nothing else (it looks at what the tasks hold again when it starts). A child
%% that dies takes down only those started after it. Ten restarts a minute is a
%% fault that will not go away by restarting one service on an unattended machine:
%% beyond that the controller gives up and {@link cell_sup} starts its whole tree
%% again (a fresh registry, the tasks OFF), without stopping the node.
-module(cell_controller_sup).
-behaviour(supervisor).

-export([start_link/0, start_link/1]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    start_link(counters:new(1, [])).

%% @doc As {@link start_link/0}; `Starts' counts the starts under {@link cell_sup}: a
%% start after the first is the controller coming back after it gave up.
-spec start_link(counters:counters_ref()) -> {ok, pid()} | ignore | {error, term()}.
start_link(Starts) ->
    ok = counters:add(Starts, 1, 1),
    case counters:get(Starts, 1) of
        1 -> ok;
        N -> cell_log:error(cell, "the cell's controller was started again after repeated "
                            "internal faults (~s time since the node started); the tasks "
                            "are OFF: check the machine and press Start", [ordinal(N - 1)])
    end,
    case cell_spec:load() of
        {ok, Spec} ->
            ok = cell_spec:keep(Spec),
            supervisor:start_link({local, ?MODULE}, ?MODULE, Spec);
        {error, Reason} -> {error, {bad_cell_spec, Reason}}
    end.

-spec init(cell_spec:spec()) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(#{tasks := Tasks, settings := Schemas} = Spec) ->
    %% Ten restarts a minute restart this part; beyond that cell_sup starts it anew.
    Flags = #{strategy => rest_for_one, intensity => 10, period => 60},
    Services = [#{id => cell_events, start => {cell_events, start_link, []}},
                #{id => cell_alarms, start => {cell_alarms, start_link, []}},
                cell_settings:child_spec(#{schemas => [cell_machine_settings | Schemas]}),
                cell_recipe_buffer:child_spec(#{}),
                cell_peers:child_spec(Spec)],
    Children = [#{id => cell_registry, start => {cell_registry, start_link, []}},
                #{id => cell_service_tables, start => {cell_service_tables, start_link, []}},
                %% Before every writer of the product's way and its reader: see above.
                cell_trace_journal:child_spec(),
                #{id => cell_service_sup, start => {cell_service_sup, start_link, [Services]},
                  type => supervisor, shutdown => infinity},
                #{id => cell_handshake_sup,
                  start => {cell_handshake_sup, start_link, [cell_spec:hosted_links(Spec)]},
                  type => supervisor, shutdown => infinity},
                #{id => cell_task_sup, start => {cell_task_sup, start_link, [Tasks]},
                  type => supervisor, shutdown => infinity},
                cell_monitor:child_spec(Spec),
                #{id => cell_controller, start => {cell_controller, start_link, []}},
                %% It only listens, so its restart touches nothing but the guard.
                cell_stats:child_spec(Spec),
                #{id => cell_guard, start => {cell_guard, start_link, []}}],
    {ok, {Flags, Children}}.

ordinal(1) -> "first";
ordinal(2) -> "second";
ordinal(3) -> "third";
ordinal(N) -> integer_to_list(N) ++ "th".
