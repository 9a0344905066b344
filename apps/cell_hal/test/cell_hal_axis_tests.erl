%% What an axis's status says of its motion (cell_hal_axis:moving/1): a display reads a
%% moving axis again at its pace and a resting one only when told it changed.
-module(cell_hal_axis_tests).
-include_lib("eunit/include/eunit.hrl").

moving_test_() ->
    At = fun(State, V) -> #{state => State, position => 1.0, velocity => V, error => 0,
                            homed => true, powered => true, override => 100} end,
    [?_assert(cell_hal_axis:moving(At(S, 0.0)))
     || S <- [homing, discrete_motion, synchronized_motion, stopping]]
        ++ [?_assertNot(cell_hal_axis:moving(At(S, 0.0)))
            || S <- [disabled, standstill, error_stop]]
        %% A fault's stop still coming to rest.
        ++ [?_assert(cell_hal_axis:moving(At(error_stop, -12.0)))].
