%% The model of prop_cell_hal_ads_conn for parallel runs: reads, writes and
%% notifications race each other, a kill of the connection's process and a cut of the
%% connection. A PLC restart stays in the sequential property: while it lasts, every
%% handle fails, which no serial order of the commands explains; the watcher's check
%% waits for a value that a racing write would change under it.
-module(prop_cell_hal_ads_conn_par).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).

initial_state() -> prop_cell_hal_ads_conn:initial_state().

command(M) ->
    ?SUCHTHAT({call, _, F, _}, prop_cell_hal_ads_conn:command(M),
              F =/= restart andalso F =/= watched).

precondition(_, {call, _, F, _}) when F =:= restart; F =:= watched -> false;
precondition(M, Call) -> prop_cell_hal_ads_conn:precondition(M, Call).

postcondition(M, Call, Res) -> prop_cell_hal_ads_conn:postcondition(M, Call, Res).

next_state(M, Res, Call) -> prop_cell_hal_ads_conn:next_state(M, Res, Call).
