%% @doc The core runtime application: starts the controller supervisor.
-module(cell_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    cell_log:notice(cell, "cellrt starting; cell root folder ~ts", [cell_config:root()]),
    cell_controller_sup:start_link().

-spec stop(term()) -> ok.
stop(_State) ->
    cell_log:notice(cell, "cellrt stopped", []).
