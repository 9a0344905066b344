%% @doc The router cell's application: when the router is the cell the runtime runs
%% (the `cell' application's `cell_module'), it puts the demo recipes in place if they
%% are missing, declares the machine's inspection blocks and cameras ({@link
%% router_camera}) and, in simulation mode, starts the machine's physics behind the
%% simulated PLC. Otherwise it starts and does nothing.
%%
%% It starts after the `cell' application, whose monitor connects the HAL of the cell
%% spec (the router's PLC, simulated or real, and its IO groups): the physics finds
%% the simulated PLC's points in place, and stops before the monitor takes them down.
-module(router_cell_app).
-behaviour(application).

-export([start/2, prep_stop/1, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    case cell_spec_helpers:is_configured_cell(router_cell) of
        true ->
            ok = router_recipes:ensure_demo(),
            Machine = cell_spec_helpers:machine_settings(),
            ok = router_camera:configure(router_cell:lanes(Machine)),
            router_cell_sup:start_link(cell_spec_helpers:simulated(Machine),
                                       router_cell:lanes(Machine));
        false ->
            router_cell_sup:start_link(false, [])
    end.

%% @doc As the node stops, the cell's tasks come to rest first, while the physics still
%% runs: a panel moving between two segments arrives ({@link cell_app:rest/0}).
-spec prep_stop(term()) -> term().
prep_stop(State) ->
    ok = cell_app:rest(),
    State.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
