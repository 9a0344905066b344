%% @doc The core runtime application: starts the cell's database and the controller
%% supervisor.
-module(cell_app).
-behaviour(application).

-export([start/2, stop/1]).

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

-spec stop(term()) -> ok.
stop(_State) ->
    cell_log:notice(cell, "cellrt stopped", []).
