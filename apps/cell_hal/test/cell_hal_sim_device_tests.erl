%% The memory a simulated PLC keeps across its restarts, and what it runs again at a
%% start with it: pure, no process.
-module(cell_hal_sim_device_tests).
-include_lib("eunit/include/eunit.hrl").

-define(DEV, plc1).

recall_of_a_device_that_never_ran_test() ->
    ?assertEqual({#{}, #{}, up}, cell_hal_sim_device:recall(?DEV, [])),
    %% Only its own rows: another device's, and the devices' processes, are skipped.
    Rows = [{plc2, self()}, {?DEV, self()}, {{image, plc2, {io, a}}, 1},
            {{rules, plc2}, #{{io, a} => []}}, {{link, plc2}, down}],
    ?assertEqual({#{}, #{}, up}, cell_hal_sim_device:recall(?DEV, Rows)).

recall_gives_back_image_rules_and_link_test() ->
    Rule = {{io, out}, fun(V) -> [{0, {io, in}, V}] end},
    Rows = [{{image, ?DEV, {io, out}}, true}, {{image, ?DEV, {io, n}}, 7},
            {{image, plc2, {io, out}}, false}, {?DEV, self()},
            {{rules, ?DEV}, #{{io, out} => [Rule]}}, {{link, ?DEV}, silent}],
    ?assertEqual({#{{io, out} => true, {io, n} => 7}, #{{io, out} => [Rule]}, silent},
                 cell_hal_sim_device:recall(?DEV, Rows)).

replay_runs_each_rule_on_its_value_test() ->
    A = {{io, a}, fun(V) -> [{0, {io, a_in}, V}] end},
    A2 = {{io, a}, fun(V) -> [{10, {io, a_late}, V}] end},
    B = {{io, b}, fun(V) -> [{0, {io, b_in}, not V}] end},
    Image = #{{io, a} => 3, {io, b} => true, {io, c} => 1.5},
    %% Points in order, each point's rules in the order they were added.
    ?assertEqual([{{io, a}, A, 3}, {{io, a}, A2, 3}, {{io, b}, B, true}],
                 cell_hal_sim_device:replay(Image, #{{io, b} => [B], {io, a} => [A, A2]})).

replay_skips_points_never_written_test() ->
    A = {{io, a}, fun(V) -> [{0, {io, a_in}, V}] end},
    ?assertEqual([], cell_hal_sim_device:replay(#{}, #{{io, a} => [A]})),
    ?assertEqual([], cell_hal_sim_device:replay(#{{io, b} => false}, #{{io, a} => [A]})),
    %% A point written to zero is written: its rule runs.
    ?assertEqual([{{io, a}, A, 0}], cell_hal_sim_device:replay(#{{io, a} => 0}, #{{io, a} => [A]})),
    ?assertEqual([], cell_hal_sim_device:replay(#{{io, a} => 0}, #{})).
