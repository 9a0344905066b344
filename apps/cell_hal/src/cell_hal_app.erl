%% @doc The HAL application: starts the HAL's supervisor. Connections and groups are
%% added at run time by the cell (see {@link cell_hal}).
-module(cell_hal_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    cell_hal_sup:start_link().

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
