%% @doc The MTConnect SHDR adapter application: starts its supervisor.
-module(cell_shdr_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    cell_shdr_sup:start_link().

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
