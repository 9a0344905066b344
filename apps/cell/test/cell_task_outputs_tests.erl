%% The outputs a task commanded and what is written again when a lost connection is
%% back (cell_task_outputs).
-module(cell_task_outputs_tests).
-include_lib("eunit/include/eunit.hrl").

-import(cell_task_outputs, [new/0, command/4, writes/3, text/1]).

image() ->
    lists:foldl(fun({G, P, V}, I) -> command(I, G, P, V) end, new(),
                [{conv, motor, false}, {conv, motor, true}, {conv, lamp, false},
                 {robot, move, 3}, {robot, grip, true}]).

last_command_wins_test() ->
    ?assertEqual(#{{conv, motor} => true, {conv, lamp} => false, {robot, move} => 3,
                   {robot, grip} => true}, maps:map(fun(_, {_, V}) -> V end, image())).

nothing_to_write_when_the_device_holds_the_image_test() ->
    Now = #{{conv, motor} => true, {conv, lamp} => false},
    ?assertEqual([], writes(image(), [conv], Now)).

an_output_the_device_lost_is_written_again_test() ->
    %% The move command never reached the PLC: it reads back 0.
    Now = #{{robot, move} => 0, {robot, grip} => true},
    ?assertEqual([{robot, move, 3}], writes(image(), [robot], Now)).

only_the_lost_connections_groups_test() ->
    %% conv's connection was not lost: a difference there is not this path's to undo.
    Now = #{{conv, motor} => false, {conv, lamp} => false, {robot, move} => 0,
            {robot, grip} => false},
    ?assertEqual([{robot, move, 3}, {robot, grip, true}], writes(image(), [robot], Now)),
    ?assertEqual([{conv, motor, true}, {robot, move, 3}, {robot, grip, true}],
                 writes(image(), [conv, robot], Now)).

%% A PLC restarted with every output at zero: the robot's target is written before the
%% command that starts the move, as the task wrote them, or the robot would move to
%% the stale target; an output commanded again takes the place of its last command.
in_the_order_the_task_commanded_test() ->
    I = lists:foldl(fun({G, P, V}, Acc) -> command(Acc, G, P, V) end, new(),
                    [{robot, target, 1}, {robot, command, 7}, {robot, grip, true}]),
    Zero = #{{robot, target} => 0, {robot, command} => 0, {robot, grip} => false},
    ?assertEqual([{robot, target, 1}, {robot, command, 7}, {robot, grip, true}],
                 writes(I, [robot], Zero)),
    I2 = command(command(I, robot, target, 4), robot, command, 8),
    ?assertEqual([{robot, grip, true}, {robot, target, 4}, {robot, command, 8}],
                 writes(I2, [robot], Zero)).

an_output_that_cannot_be_read_is_written_test() ->
    ?assertEqual([{conv, lamp, false}], writes(image(), [conv], #{{conv, motor} => true})).

numbers_compare_by_value_test() ->
    I = command(new(), robot, speed, 12),
    ?assertEqual([], writes(I, [robot], #{{robot, speed} => 12.0})),
    ?assertEqual([{robot, speed, 12}], writes(I, [robot], #{{robot, speed} => 12.5})).

an_empty_image_writes_nothing_test() ->
    ?assertEqual([], writes(new(), [conv, robot], #{{conv, motor} => false})).

text_names_each_write_test() ->
    ?assertEqual(<<"robot.move := 3, conv.motor := true, conv.name := \"P1\"">>,
                 iolist_to_binary(text([{robot, move, 3}, {conv, motor, true},
                                        {conv, name, <<"P1">>}]))).
