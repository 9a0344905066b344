%% @doc The router cell's application: when the router is the cell the runtime runs
%% (the `cell' application's `cell_module'), it puts the demo recipes in place if they
%% are missing, connects the cell's HAL and, in simulation mode, starts the machine's
%% physics. Otherwise it starts and does nothing.
%%
%% It starts before the `cell' application and stops after it, as the seed's
%% controller creates its hardware objects before its device tasks and disposes of
%% them last: the tasks find their IO at their first Start and secure their outputs
%% through it when they stop.
-module(router_cell_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    case router_cell:is_configured() of
        true ->
            ok = router_recipes:ensure_demo(),
            Machine = router_cell:machine_settings(),
            router_cell_sup:start_link(router_cell:cell_spec(Machine, router_cell:router_settings()),
                                       maps:get(simulation_mode, Machine, true));
        false ->
            router_cell_sup:start_link()
    end.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
