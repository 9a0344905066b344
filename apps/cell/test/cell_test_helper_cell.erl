%% A cell module whose spec declares a device task's module as a unit: the helper
%% refuses it while the spec is built.
-module(cell_test_helper_cell).

-export([cell_spec/0]).

cell_spec() ->
    #{tasks => [cell_spec_helpers:unit(picker, cell_test_task,
                                       #{zone => <<"Picker">>, lane => <<"Front">>})]}.
