%% @doc The core runtime application: starts the cell's database and the controller
%% supervisor.
-module(cell_app).
-behaviour(application).

-export([start/2, prep_stop/1, stop/1]).

-define(STOP_MS, 10000).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    %% The folders may be new since cell_base started (another root, or removed).
    case cell_config:ensure_root() of
        ok ->
            cell_log:notice(cell, "cellrt starting; cell root folder ~ts", [cell_config:root()]),
            _ = cell_file:cleanup(cell_config:dir(data)),
            %% The database in Databases/ (statistics, traceability), started here
            %% where the application controller is free to start mnesia; if it cannot
            %% be, the statistics say why and try again (cell_stats).
            _ = cell_db:start(),
            cell_controller_sup:start_link();
        {error, Reason} ->
            {error, {cell_root_folder, Reason}}
    end.

%% @doc Before the controller's tree goes down, the cell stops as at an operator's Stop:
%% every running task ends in OFF through its uninit (outputs secured, product saved)
%% while the HAL is still connected. The supervisor stops its children in reverse
%% order, so the monitor, which disconnects the HAL, would otherwise go before the
%% tasks. A task finishing a transfer is waited for, up to ten seconds; one DOWN (an
%% error, a pause) holds as it is.
-spec prep_stop(term()) -> term().
prep_stop(State) ->
    try
        ok = cell_events:subscribe([task_state]),
        ok = cell_controller:stop(<<"shutdown">>),
        ok = cell_controller:sync(),
        await_settled(erlang:monotonic_time(millisecond) + ?STOP_MS),
        cell_events:unsubscribe()
    catch
        exit:Why ->
            cell_log:error(cell, "the cell could not be stopped before shutting down: ~0tp",
                           [Why])
    end,
    State.

await_settled(Deadline) ->
    case [Id || #{id := Id, state := {ready, _, _}} <- cell_controller:tasks()] of
        [] ->
            ok;
        Running ->
            receive
                {cell_event, #{type := task_state}} -> await_settled(Deadline)
            after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                cell_log:error(cell, "~ts did not stop within ~b s; shutting down anyway",
                               [lists:join(", ", [atom_to_list(Id) || Id <- Running]),
                                ?STOP_MS div 1000])
            end
    end.

-spec stop(term()) -> ok.
stop(_State) ->
    cell_log:notice(cell, "cellrt stopped", []).
