%% What the inspection suites and their test modules share: the longest wait for the
%% block, the test modules' short names, and the simulated camera of the suites' block
%% settings.
-define(WAIT, 20000).
-define(P, cell_inspect_plc).
-define(T, cell_inspect_test_cell).
-define(S, cell_inspect_steps).
-define(CAM, <<"cam1">>).
