%% @doc A per-task settings object for the tests: every field type the schema knows,
%% nested objects, lists of objects and a retired field.
-module(cell_test_robot_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, obsolete/0]).

-spec name() -> robot.
name() -> robot.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => enabled, type => boolean, default => true},
     #{name => speed, type => {float, 0.5, 2500.0}, default => 100.0, unit => <<"mm/s">>},
     #{name => retries, type => {integer, 0, 10}, default => 3},
     #{name => counter, type => integer, default => -5},
     #{name => gain, type => float, default => 1.0},
     #{name => label, type => {string, 8}, default => <<"R1">>},
     #{name => note, type => string, default => <<>>},
     #{name => tool, type => {enum, [gripper, vacuum, none]}, default => none},
     #{name => waypoints, type => {list, {integer, -1000, 1000}, 5}},
     #{name => axes, type => {list, {object, cell_test_axis_settings}}},
     #{name => home, type => {object, cell_test_axis_settings}, default => #{id => z}},
     #{name => camera, type => {optional, {object, cell_test_axis_settings}}},
     #{name => offset, type => {optional, {float, -10, 10}}}].

-spec obsolete() -> [atom()].
obsolete() -> [old_mode].
