%% @doc The foundation application: creates the cell root folder, then starts the log
%% server and installs the daily task log and trace log.
-module(cell_base_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    case cell_config:ensure_root() of
        ok ->
            cell_base_sup:start_link();
        {error, Reason} ->
            {error, {cell_root_folder, Reason}}
    end.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
