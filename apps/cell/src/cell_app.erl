%% @doc The core runtime application: starts the cell's database and the controller
%% (under {@link cell_sup}).
-module(cell_app).
-behaviour(application).

-export([start/2, prep_stop/1, stop/1]).
%% For a cell's application that stops before `cell' (see rest/0).
-export([rest/0]).


-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    %% The folders may be new since cell_base started (another root, or removed).
    case cell_config:ensure_root() of
        ok ->
            cell_log:notice(cell, "cellrt starting; cell root folder ~ts", [cell_config:root()]),
            _ = cell_file:cleanup(cell_config:dir(data)),
            %% Before anything else of the cell: whether the last run ended cleanly.
            Previous = cell_node_run:boot(),
            %% The database in Databases/ (statistics, traceability), started here
            %% where the application controller is free to start mnesia; if it cannot
            %% be, the statistics say why and try again (cell_stats).
            _ = cell_db:start(),
            %% Nothing of an earlier run of the application (a request, a stop after a
            %% fault) is taken for a restart inside this one.
            ok = cell_registry:new_run(),
            %% A run that never reached its orderly stop (the power cut, the node
            %% killed): the operator is told why the cell stands, until Start.
            ok = case Previous of
                     {unexpected, _} -> cell_registry:node_stopped();
                     _ -> ok
                 end,
            case cell_sup:start_link() of
                {ok, Pid} ->
                    {ok, Pid};
                {error, {shutdown, {failed_to_start_child, cell_controller_sup, Why}}} ->
                    {error, Why};
                {error, _} = Error ->
                    Error
            end;
        {error, Reason} ->
            {error, {cell_root_folder, Reason}}
    end.

%% @doc Before the controller's tree goes down, the cell stops as at an operator's Stop:
%% every task comes to rest through its uninit (outputs secured, product saved) while the
%% HAL is still connected. The supervisor stops its children in reverse order, so the
%% monitor, which disconnects the HAL, would otherwise go before the tasks.
%%
%% It waits at most `shutdown_wait_ms' of the `cell' environment (the release sets 10 s;
%% 0, the default, stops the tree at once: tests that drive the tasks' sequences
%% themselves stop and start the cell many times).
-spec prep_stop(term()) -> term().
prep_stop(_State) ->
    ok = rest(),
    %% An orderly stop (only then is prep_stop called): stop/1 records it as clean.
    stopping.

%% @doc What the cell does as the node stops (see {@link prep_stop/1}): a Stop, and
%% the wait of at most `shutdown_wait_ms' for every task to come to rest; at once when
%% they are. A cell's own application stops before `cell' (it depends on it): one whose
%% processes the tasks need until they rest (the simulation of its machine, which must
%% finish a transfer under way) calls this from its own `prep_stop/1', so the tasks
%% come to rest while the simulation still runs.
-spec rest() -> ok.
rest() ->
    case application:get_env(cell, shutdown_wait_ms, 0) of
        Wait when is_integer(Wait), Wait > 0 -> stop_tasks(Wait);
        _ -> ok
    end.

stop_tasks(Wait) ->
    try
        ok = cell_events:subscribe([task_state]),
        case cell_controller:state() of
            %% Stopped already (a cell's application had it rest first).
            off ->
                ok;
            _ ->
                ok = cell_controller:stop(<<"shutdown">>),
                ok = cell_controller:sync(),
                await_rest(Wait, erlang:monotonic_time(millisecond) + Wait)
        end,
        ok = cell_events:unsubscribe()
    catch
        exit:Why ->
            cell_log:error(cell, "the cell could not be stopped before shutting down: ~0tp",
                           [Why])
    end.

%% Every task at rest after the Stop: a device task OFF (or DOWN, waiting for an
%% operator nobody asks now); a unit in a state a Stop leaves it in (Idle is a unit's
%% rest as much as Stopped, and Booting finishes its own sequence whatever is asked).
await_rest(Wait, Deadline) ->
    case [Id || #{id := Id} = Row <- cell_registry:tasks(), not at_rest(Row)] of
        [] ->
            ok;
        Busy ->
            receive
                {cell_event, #{type := task_state}} -> await_rest(Wait, Deadline)
            after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                cell_log:error(cell, "~s did not stop within ~b s; shutting down anyway",
                               [lists:join(", ", [atom_to_list(I) || I <- Busy]),
                                Wait div 1000])
            end
    end.

at_rest(#{kind := unit, unit_state := S}) ->
    lists:member(S, [booting, init, idle, stopped, fault]);
at_rest(#{state := State}) ->
    State =:= off orelse State =:= down.

%% @doc After the tree stopped: an orderly stop is recorded as the end of the run (see
%% {@link cell_node_run}); the application given up by its supervisor is not.
-spec stop(term()) -> ok.
stop(stopping) ->
    ok = cell_node_run:stopped(),
    cell_log:notice(cell, "cellrt stopped", []);
stop(_State) ->
    cell_log:error(cell, "cellrt stopped after its supervisors gave up", []).
