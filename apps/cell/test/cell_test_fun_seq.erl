%% A sequence for the runner's tests: its steps are funs in its args,
%% `#{first => Step, steps => #{Step => fun((Seq) -> Result)}}'. Steps whose names
%% start with `busy_' are not resumable points (Halt does not hold before them).
-module(cell_test_fun_seq).
-behaviour(cell_sequence).

-export([init/2, step/2, resumable/1]).

init(#{first := First} = Args, Seq) ->
    case maps:find(init, Args) of
        {ok, F} -> {ok, First, F(Seq)};
        error -> {ok, First, Seq}
    end.

step(Step, Seq) ->
    case maps:find(Step, cell_sequence:arg(Seq, steps, #{})) of
        {ok, F} -> F(Seq);
        error -> cell_sequence:abort(Seq, {unhandled_step, Step})
    end.

resumable(Step) ->
    not lists:prefix("busy_", atom_to_list(Step)).
