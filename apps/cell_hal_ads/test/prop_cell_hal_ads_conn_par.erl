%% The model of prop_cell_hal_ads_conn for parallel runs: reads, writes and
%% notifications race each other, a kill of the connection's process and a cut of the
%% connection. A PLC restart stays in the sequential property: while it lasts, every
%% handle fails, which no serial order of the commands explains; the watcher's check
%% waits for a value that a racing write would change under it.
%%
%% A write whose answer a racing kill or cut took away may have reached the PLC before
%% the kill, and been read there: in the serial order that explains the run it comes
%% before the kill, failed (see postcondition/3).
-module(prop_cell_hal_ads_conn_par).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).

initial_state() -> prop_cell_hal_ads_conn:initial_state().

command(M) ->
    ?SUCHTHAT({call, _, F, _}, prop_cell_hal_ads_conn:command(M),
              F =/= restart andalso F =/= watched).

precondition(_, {call, _, F, _}) when F =:= restart; F =:= watched -> false;
precondition(M, Call) -> prop_cell_hal_ads_conn:precondition(M, Call).

%% A write cut short by a racing kill or cut may have reached the PLC, and a racing
%% read may have seen it, before the kill in any serial order: it may fail while the
%% connection is still up in that order (its value is then possible, not certain).
%% Reads have no effect: they fail only where the connection is down.
postcondition(#{conn := up}, {call, _, F, _}, {error, _}) when F =:= write; F =:= notify ->
    true;
postcondition(M, Call, Res) -> prop_cell_hal_ads_conn:postcondition(M, Call, Res).

next_state(M, Res, Call) -> prop_cell_hal_ads_conn:next_state(M, Res, Call).
