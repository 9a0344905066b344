%% The model of prop_cell_task for parallel runs: the same commands except process
%% kills and crashes. A restart is not atomic (its old error is withdrawn before the
%% new one is raised), so racing it against answers has no linearisation; restarts are
%% covered by the sequential property, where each one completes before the next command.
%%
%% One more thing is not atomic, by design: an answer that makes a task initialise
%% again removes the error at once, and a failing init raises a new one a moment
%% later. Another answer to that task in between finds no error (two operators
%% answering one error: the first takes it). So an answer here may also be
%% `{error, not_found}'; every other result is checked as in the sequential model.
-module(prop_cell_task_par).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).

initial_state() -> prop_cell_task:initial_state().

command(M) ->
    ?SUCHTHAT({call, _, F, _}, prop_cell_task:command(M), F =/= kill andalso F =/= crash).

precondition(M, Call) -> prop_cell_task:precondition(M, Call).

postcondition(_M, {call, _, answer, _}, {error, not_found}) -> true;
postcondition(M, Call, Res) -> prop_cell_task:postcondition(M, Call, Res).

next_state(M, Res, Call) -> prop_cell_task:next_state(M, Res, Call).
