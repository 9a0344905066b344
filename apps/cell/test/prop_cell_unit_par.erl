%% The model of prop_cell_unit for parallel runs: the unit's buttons, Halt and the
%% cell's commands race each other. Completing and aborting sequences, answers and
%% kills stay in the sequential property: each names what the unit waits for at the
%% moment it is sent, which a race changes under it.
-module(prop_cell_unit_par).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).

initial_state() -> prop_cell_unit:initial_state().

command(M) ->
    ?SUCHTHAT({call, _, F, _}, prop_cell_unit:command(M),
              lists:member(F, [button, halt, controller, estop])).

precondition(M, Call) -> prop_cell_unit:precondition(M, Call).

postcondition(M, Call, Res) -> prop_cell_unit:postcondition(M, Call, Res).

next_state(M, Res, Call) -> prop_cell_unit:next_state(M, Res, Call).
