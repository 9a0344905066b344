%% @doc The __NAME__ application: when it is the cell the runtime runs (the `cell'
%% application's `cell_module'), it puts the demo recipe in place if it is missing
%% and, in simulation mode, starts the simulated line behind the simulated PLC.
%% Otherwise it starts and does nothing.
-module(__NAME___app).
-behaviour(application).

-export([start/2, prep_stop/1, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    case cell_spec_helpers:is_configured_cell(__NAME__) of
        true ->
            ok = __NAME___recipes:ensure_demo(),
            __NAME___sup:start_link(cell_spec_helpers:simulated(
                                      cell_spec_helpers:machine_settings()));
        false ->
            __NAME___sup:start_link(false)
    end.

%% @doc As the node stops, the cell's tasks come to rest first, while the simulation
%% still runs: a part moving from the infeed into the press arrives. (This application
%% stops before cellrt's `cell', which would otherwise stop the tasks after the
%% simulation had gone.)
-spec prep_stop(term()) -> term().
prep_stop(State) ->
    ok = cell_app:rest(),
    State.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
