%% The model of prop_cell_task for parallel runs: the same commands except process
%% kills and crashes. A restart is not atomic (its old error is withdrawn before the
%% new one is raised), so racing it against answers has no linearisation; restarts are
%% covered by the sequential property, where each one completes before the next command.
-module(prop_cell_task_par).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).

initial_state() -> prop_cell_task:initial_state().

command(M) ->
    ?SUCHTHAT({call, _, F, _}, prop_cell_task:command(M), F =/= kill andalso F =/= crash).

precondition(M, Call) -> prop_cell_task:precondition(M, Call).

postcondition(M, Call, Res) -> prop_cell_task:postcondition(M, Call, Res).

next_state(M, Res, Call) -> prop_cell_task:next_state(M, Res, Call).
