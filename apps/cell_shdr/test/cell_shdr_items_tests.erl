%% The data items and their derivations from the cell.
-module(cell_shdr_items_tests).
-include_lib("eunit/include/eunit.hrl").

%% Every IPC-2541 state of seed 000 §2.2, read row by row from the table in the
%% module doc.
execution_test_() ->
    Table = [{off, <<"STOPPED">>, unavailable},
             {down, <<"INTERRUPTED">>, unavailable},
             {setup, <<"WAIT">>, <<"POWERING_UP">>},
             {{ready, idle, starved}, <<"READY">>, unavailable},
             {{ready, idle, blocked}, <<"WAIT">>, <<"PART_UNLOAD">>},
             {{ready, processing, active}, <<"ACTIVE">>, unavailable},
             {{ready, processing, executing}, <<"ACTIVE">>, unavailable}],
    ?assertEqual(lists:sort(cell_ipc:states()), lists:sort([S || {S, _, _} <- Table])),
    [?_assertEqual({E, W}, {cell_shdr_items:execution(S), cell_shdr_items:wait_state(S)})
     || {S, E, W} <- Table].

part_state_test_() ->
    [?_assertEqual(V, cell_shdr_items:part_state(E))
     || {E, V} <- [{item_transfer_in, <<"NEEDS_PROCESSING">>},
                   {item_work_start, <<"IN_PROCESS">>},
                   {item_work_pause, keep},
                   {item_work_resume, <<"IN_PROCESS">>},
                   {item_work_complete, <<"PROCESSING_ENDED_COMPLETE">>},
                   {item_work_abort, <<"PROCESSING_ENDED_ABORTED">>},
                   {equipment_blocked, <<"WAITING_FOR_TRANSIT">>},
                   {equipment_unblocked, <<"IN_TRANSIT">>},
                   {item_transfer_out, <<"TRANSIT_COMPLETE">>},
                   {equipment_starved, keep}, {equipment_unstarved, keep},
                   {item_identifier_read, keep}]].

modes_test_() ->
    [?_assertEqual(<<"MANUAL">>, cell_shdr_items:controller_mode(true)),
     ?_assertEqual(<<"AUTOMATIC">>, cell_shdr_items:controller_mode(false)),
     ?_assertEqual(<<"TRIGGERED">>, cell_shdr_items:estop(true)),
     ?_assertEqual(<<"ARMED">>, cell_shdr_items:estop(false))].

condition_test_() ->
    A = #{id => <<"robot:lost">>, local_id => <<"lost">>, kind => error, task => robot,
          caption => <<"Product lost">>, description => <<"Check the gripper">>,
          solutions => [retry], raised => 0},
    [?_assertEqual(#{level => fault, code => <<"robot.lost">>, severity => <<"error">>,
                     text => <<"Product lost: Check the gripper">>},
                   cell_shdr_items:condition(A)),
     ?_assertMatch(#{level := fault, severity := <<"alarm">>},
                   cell_shdr_items:condition(A#{kind => alarm})),
     ?_assertMatch(#{level := warning, text := <<"Product lost">>},
                   cell_shdr_items:condition(A#{kind => warning, description => <<>>})),
     ?_assertEqual(<<"a.b.c">>, cell_shdr_items:native_code(<<"a:b:c">>))].

names_test_() ->
    V = fun cell_shdr_items:valid_name/1,
    [?_assert(V(<<"avail">>)), ?_assert(V(<<"_x.y-1">>)), ?_assert(V(binary:copy(<<"a">>, 64))),
     ?_assertNot(V(binary:copy(<<"a">>, 65))), ?_assertNot(V(<<>>)), ?_assertNot(V(<<"1a">>)),
     ?_assertNot(V(<<"a b">>)), ?_assertNot(V(<<"a|b">>)), ?_assertNot(V(<<"a:b">>)),
     ?_assertNot(V(<<"@ASSET@">>)), ?_assertNot(V(<<"a--multiline--b">>)),
     ?_assert(V(<<"a--multi-line--b">>))].

prefixes_test() ->
    P = cell_shdr_items:prefixes(['robot', 'Robot 1', 'Robot_1', '1st', 'a:b',
                                  'x--multiline--y']),
    ?assertEqual(<<"robot">>, maps:get(robot, P)),
    ?assertEqual(<<"x_multiline_y">>, maps:get('x--multiline--y', P)),
    ?assertEqual(<<"t_1st">>, maps:get('1st', P)),
    ?assertEqual(<<"a_b">>, maps:get('a:b', P)),
    %% two ids that write the same get distinct prefixes
    ?assertEqual(lists:sort([<<"Robot_1">>, <<"Robot_1_2">>]),
                 lists:sort([maps:get('Robot 1', P), maps:get('Robot_1', P)])),
    [?assert(cell_shdr_items:valid_name(X)) || X <- maps:values(P)].

%% Keys are unique and valid ids, for any set of tasks and points.
items_unique_test() ->
    Tasks = [robot, load, 'part', 'cycle', 'a_part', 'load 2'],
    Points = [#{name => <<"temp">>, type => <<"TEMPERATURE">>, category => sample,
                sub_type => <<>>, units => <<"CELSIUS">>, time_series => false},
              #{name => <<"current">>, type => <<"AMPERAGE">>, category => sample,
                sub_type => <<"ACTUAL">>, units => <<"AMPERE">>, time_series => true,
                rate => 10.0}],
    Items = cell_shdr_items:items(Tasks, Points),
    Keys = [K || #{key := K} <- Items],
    ?assertEqual(length(Keys), length(lists:usort(Keys))),
    [?assert(cell_shdr_items:valid_name(K)) || K <- Keys],
    ?assertEqual(11 + 8 * length(Tasks) + 2, length(Items)),
    ?assertMatch([#{time_series := true, rate := 10.0, sub_type := <<"ACTUAL">>}],
                 [I || #{key := <<"current">>} = I <- Items]).

%% A task that does no work has no part count and no cycle time of its own.
items_of_idle_tasks_test() ->
    Keys = fun(Idle) -> [K || #{key := K} <- cell_shdr_items:items([load, robot], Idle, [])] end,
    All = Keys([]),
    ?assertEqual(All, [K || #{key := K} <- cell_shdr_items:items([load, robot], [])]),
    ?assertEqual(All -- [<<"load_part_count">>, <<"load_cycle_time">>], Keys([load])),
    ?assertEqual(All -- [<<"load_part_count">>, <<"load_cycle_time">>,
                         <<"robot_part_count">>, <<"robot_cycle_time">>],
                 Keys([robot, load])).

%% A sample is what an agent reads as a number, or UNAVAILABLE; an event is text.
point_value_test_() ->
    Sample = #{category => sample},
    Event = #{category => event},
    [?_assertEqual(21.5, cell_shdr_items:point_value(Sample, 21.5)),
     ?_assertEqual(-3, cell_shdr_items:point_value(Sample, -3)),
     ?_assertEqual(1, cell_shdr_items:point_value(Sample, true)),
     ?_assertEqual(0, cell_shdr_items:point_value(Sample, false)),
     ?_assertEqual(<<"12.5">>, cell_shdr_items:point_value(Sample, <<" 12.5 ">>)),
     ?_assertEqual(<<"7">>, cell_shdr_items:point_value(Sample, <<"7">>)),
     ?_assertEqual(unavailable, cell_shdr_items:point_value(Sample, <<"open">>)),
     ?_assertEqual(unavailable, cell_shdr_items:point_value(Sample, <<>>)),
     ?_assertEqual(unavailable, cell_shdr_items:point_value(Sample, {2026, 1, 2})),
     ?_assertEqual(<<"true">>, cell_shdr_items:point_value(Event, true)),
     ?_assertEqual(<<"false">>, cell_shdr_items:point_value(Event, false)),
     ?_assertEqual(<<"OPEN">>, cell_shdr_items:point_value(Event, <<"OPEN">>)),
     ?_assertEqual(3, cell_shdr_items:point_value(Event, 3)),
     ?_assertEqual(<<"2026-01-02">>, cell_shdr_items:point_value(Event, {2026, 1, 2})),
     ?_assertEqual(<<"{a,1}">>, cell_shdr_items:point_value(Event, {a, 1}))].

is_message_test_() ->
    [?_assert(cell_shdr_items:is_message(#{type => <<"MESSAGE">>})),
     ?_assertNot(cell_shdr_items:is_message(#{type => <<"PROGRAM">>})),
     ?_assertNot(cell_shdr_items:is_message(#{type => <<"TEMPERATURE">>}))].

%% A point configured on an axis is an item of that axis's Linear or Rotary component;
%% the settings refuse one that names no axis.
axis_point_test_() ->
    Point = #{name => <<"x_pos">>, type => <<"POSITION">>, category => sample,
              sub_type => <<"ACTUAL">>, units => <<"MILLIMETER">>},
    Items = fun(P) -> [I || #{key := <<"x_pos">>} = I <- cell_shdr_items:items([], [P])] end,
    Check = fun(P) ->
                    cell_shdr_point_settings:check(
                      maps:merge(#{time_series => false, component => device, axis => <<>>},
                                 P))
            end,
    [?_assertMatch([#{component := {axis, linear, <<"X">>}}],
                   Items(Point#{component => linear, axis => <<"X">>})),
     ?_assertMatch([#{component := {axis, rotary, <<"C">>}}],
                   Items(Point#{component => rotary, axis => <<"C">>})),
     ?_assertMatch([#{component := device}], Items(Point#{component => device, axis => <<>>})),
     ?_assertMatch([#{component := device}], Items(Point)),
     ?_assertEqual(ok, Check(Point#{component => linear, axis => <<"X">>})),
     ?_assertEqual({error, [axis], {an_axis_needs_a_name, <<>>}},
                   Check(Point#{component => linear})),
     ?_assertEqual({error, [axis], {an_axis_needs_a_name, <<"X Y">>}},
                   Check(Point#{component => rotary, axis => <<"X Y">>}))].

%% An axis of the cell is a Linear component with its position, feedrate and state (a
%% Rotary one, for an axis that turns, with its angle and angular velocity); its
%% values follow its status, UNAVAILABLE when it cannot be read.
cell_axis_test_() ->
    Axes = maps:map(fun(_, Name) -> {Name, linear} end,
                    cell_shdr_items:prefixes([lower_x, 'y axis'])),
    Items = cell_shdr_items:items([], [], [], Axes#{table => {<<"table">>, rotary}}),
    Of = fun(Name) -> [{K, T, C} || #{key := K, type := T, category := C,
                                      component := {axis, linear, N}} <- Items, N =:= Name]
         end,
    Moving = #{state => synchronized_motion, position => 12.5, velocity => -40.0},
    [?_assertEqual([{<<"lower_x_position">>, <<"POSITION">>, sample},
                    {<<"lower_x_feedrate">>, <<"AXIS_FEEDRATE">>, sample},
                    {<<"lower_x_state">>, <<"AXIS_STATE">>, event}], Of(<<"lower_x">>)),
     %% A name an item may have.
     ?_assertEqual(3, length(Of(<<"y_axis">>))),
     ?_assertMatch([#{sub_type := <<"ACTUAL">>, units := <<"MILLIMETER">>}],
                   [I || #{key := <<"lower_x_position">>} = I <- Items]),
     ?_assertMatch([#{type := <<"ANGLE">>, sub_type := <<"ACTUAL">>, units := <<"DEGREE">>,
                      component := {axis, rotary, <<"table">>}},
                    #{type := <<"ANGULAR_VELOCITY">>, units := <<"DEGREE/SECOND">>,
                      component := {axis, rotary, <<"table">>}},
                    #{type := <<"AXIS_STATE">>, component := {axis, rotary, <<"table">>}}],
                   [I || #{key := <<"table_", _/binary>>} = I <- Items]),
     ?_assertEqual([], [I || #{key := <<"table_feedrate">>, sub_type := _} = I <- Items]),
     ?_assertEqual([{<<"x_position">>, 12.5}, {<<"x_feedrate">>, 40.0},
                    {<<"x_state">>, <<"TRAVEL">>}],
                   cell_shdr_items:axis_values(<<"x">>, {ok, Moving})),
     ?_assertEqual([{<<"x_position">>, 0.0}, {<<"x_feedrate">>, 0.0},
                    {<<"x_state">>, <<"STOPPED">>}],
                   cell_shdr_items:axis_values(<<"x">>, {ok, Moving#{state => standstill,
                                                                    position => 0.0,
                                                                    velocity => 0.0}})),
     ?_assertEqual([{<<"x_position">>, unavailable}, {<<"x_feedrate">>, unavailable},
                    {<<"x_state">>, unavailable}],
                   cell_shdr_items:axis_values(<<"x">>, {error, not_present})),
     %% Coming to rest after a fault: still moving.
     ?_assertMatch([_, _, {<<"x_state">>, <<"TRAVEL">>}],
                   cell_shdr_items:axis_values(<<"x">>, {ok, Moving#{state => error_stop}}))].
