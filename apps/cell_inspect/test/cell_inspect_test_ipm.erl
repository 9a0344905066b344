%% Image processing for tests: loading its workspace waits until the test releases
%% it (the loader tells `cell_inspect_test_gate' it is loading), so a test can hold a
%% block in WaitingForIPM, or have an image arrive while a workspace loads.
-module(cell_inspect_test_ipm).
-behaviour(cell_inspect_processing).

-export([load/1, process/3]).

load(W) ->
    cell_inspect_test_gate ! {?MODULE, loading, self()},
    receive release -> {ok, W} end.

process(_Image, _Job, _W) ->
    {pass, <<"gated">>}.
