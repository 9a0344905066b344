%% A device task module written without a restart reconciliation: the cell spec must
%% refuse it by name.
-module(cell_unreconciled_task).

-export([init/1, step/1, uninit/1]).

-spec init(term()) -> {ok, term()}.
init(T) -> {ok, T}.

-spec step(term()) -> {wait, [], term()}.
step(T) -> {wait, [], T}.

-spec uninit(term()) -> term().
uninit(T) -> T.
