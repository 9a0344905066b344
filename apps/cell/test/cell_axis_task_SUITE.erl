%% A device task moving axes and an interpolation channel in a running cell
%% (cell_axis_task over the simulated NC): it makes its axes ready, cycles through a
%% point-to-point move and a cut along a path, and an axis's fault is the operator's
%% error with Retry, after which the cycle goes on. The monitor applies the machine's
%% speed override to the axes while the task runs.
-module(cell_axis_task_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([cycles/1, fault_is_the_operators_error/1, override_while_running/1]).

-define(WAIT, 20000).

all() ->
    [cycles, fault_is_the_operators_error, override_while_running].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    {ok, Path} = cell_hal_path:new([{line, {0, 0}, {100, 0}}, {arc, {100, 20}, 20, 270, 90},
                                    {line, {100, 40}, {0, 40}}]),
    Task = #{id => robot, module => cell_axis_task, zone => <<"robot">>, lane => <<"Test">>,
             args => #{axes => [x, y], channel => xy, path => Path, notify => self()}},
    Hardware = [#{id => A, kind => axis, type => sim,
                  opts => #{limits => {-10.0, 300.0}, home_ms => 10}} || A <- [x, y]]
        ++ [#{id => xy, kind => channel, type => sim, opts => #{axes => [x, y]}}],
    Spec = #{name => <<"axis suite">>, tasks => [Task],
             hal => #{connections => [], groups => [], hardware => Hardware},
             monitor => #{io => #{}, drives => []}},
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe(),
    ok = cell_log:subscribe(),
    Config.

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok = application:unset_env(cell, cell_spec),
    ok.

%% -------------------------------------------------------------------------------------

cycles(_Config) ->
    ok = start(),
    %% Three cycles: each a move to the start and the cut along the path.
    ok = cell_axis_task:await_cycles(robot, 3, ?WAIT),
    {ok, #{state := S, position := P}} = cell_hal_axis:status(y),
    ?assert(lists:member(S, [standstill, discrete_motion, synchronized_motion])),
    ?assert(P >= 0.0 andalso P =< 40.0).

fault_is_the_operators_error(_Config) ->
    ok = start(),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT),
    %% The next move of x faults: the task raises its error, naming the axis.
    ok = cell_hal_axis_sim:fault_next(x),
    receive {axis_task, robot, fault, x, _} -> ok after ?WAIT -> ct:fail(no_fault) end,
    Alarm = cell_axis_task:await_error(?WAIT),
    #{id := Id, solutions := [retry], description := Text} = Alarm,
    ?assertNotEqual(nomatch, binary:match(Text, <<"Axis x stopped">>)),
    ?assertMatch({ok, #{state := error_stop}}, cell_hal_axis:status(x)),
    %% Retry: the axis is reset and the cycle goes on.
    ok = cell_alarms:answer(Id, retry, <<"suite">>),
    ok = cell_axis_task:await_cycles(robot, 2, ?WAIT),
    ?assertMatch({ok, #{error := 0}}, cell_hal_axis:status(x)).

override_while_running(_Config) ->
    ok = start(),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT),
    ok = cell_settings:put(machine, #{speed_override => 30}, <<"suite">>),
    ok = await_override(30),
    ok = cell_axis_task:await_cycles(robot, 2, ?WAIT).

%% -------------------------------------------------------------------------------------

start() ->
    ok = cell_controller:start(),
    ok.

%% The monitor told both axes the new override (its log line comes after).
await_override(Pct) ->
    case [A || A <- [x, y], {ok, #{override := P}} <- [cell_hal_axis:status(A)], P =:= Pct] of
        [x, y] -> ok;
        _ ->
            receive {cell_log, _} -> await_override(Pct)
            after ?WAIT -> ct:fail({override_not_applied, Pct})
            end
    end.
