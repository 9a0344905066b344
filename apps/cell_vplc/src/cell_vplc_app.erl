%% @doc The virtual PLC's application: started alone on a node of its own by
%% `scripts/vplc' (never beside a running cell), it serves one cell's simulated machine
%% over Modbus TCP ({@link cell_vplc}).
-module(cell_vplc_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    cell_vplc_sup:start_link().

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
