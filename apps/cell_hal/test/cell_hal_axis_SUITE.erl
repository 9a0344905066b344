%% The axis as a hardware object (cell_hal_axis) over the simulated NC
%% (cell_hal_axis_sim): a task's view of it. Commands are accepted or refused at once
%% and each job's end comes as a message; a newer command aborts the running one; a
%% fault fails it and leaves the axis in ErrorStop until reset; stop holds the axis
%% while its Execute is held; the override is a time base (0 holds the axis where it
%% is); software limits and an unhomed axis refuse moves.
-module(cell_hal_axis_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([power_home_move/1, refused_commands/1, newer_move_aborts/1, halt_mid_move/1,
         stop_holds_until_released/1, fault_fails_the_move/1, override_is_a_time_base/1,
         power_off_aborts/1, publishes_its_position/1, publishes_into_outputs/1, time_scale_speeds_the_machine/1,
         bad_options/1]).

-define(WAIT, 10000).
-define(FAST, #{velocity => 2000, acceleration => 20000, deceleration => 20000}).
%% 100 mm/s with a second to reach it: a move of 500 mm takes 6 s.
-define(SLOW, #{velocity => 100, acceleration => 100, deceleration => 100}).

all() ->
    [power_home_move, refused_commands, newer_move_aborts, halt_mid_move,
     stop_holds_until_released, fault_fails_the_move, override_is_a_time_base,
     power_off_aborts, publishes_its_position, publishes_into_outputs, time_scale_speeds_the_machine, bad_options].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_testcase(_Case, Config) ->
    ok = cell_hal_hw:add(#{id => x, kind => axis, type => sim,
                           opts => #{limits => {-100.0, 1000.0}, home_ms => 20}}),
    Config.

end_per_testcase(_Case, _Config) ->
    [ok = cell_hal_hw:remove(Id) || {Id, _, _} <- cell_hal_hw:list()],
    ok.

%% -------------------------------------------------------------------------------------

power_home_move(_Config) ->
    ?assertMatch({ok, #{state := disabled, homed := false, position := 0.0}},
                 cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:power(x, true)),
    ?assertMatch({ok, #{state := standstill, powered := true}}, cell_hal_axis:status(x)),
    {ok, H} = cell_hal_axis:home(x, 10.0),
    ?assertMatch({ok, #{state := homing}}, cell_hal_axis:status(x)),
    ok = await(H, done),
    ?assertMatch({ok, #{state := standstill, homed := true, position := 10.0}},
                 cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:move_absolute(x, 250.0, ?FAST)),
    ?assertMatch({ok, #{state := standstill, position := 250.0, velocity := 0.0}},
                 cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:move_relative(x, -50.0, ?FAST)),
    ?assertMatch({ok, #{position := 200.0}}, cell_hal_axis:status(x)).

refused_commands(_Config) ->
    %% Disabled: no motion.
    ?assertEqual({error, disabled}, cell_hal_axis:move_relative(x, 1.0, ?FAST)),
    ?assertEqual({error, disabled}, cell_hal_axis:home(x, 0.0)),
    ok = done(cell_hal_axis:power(x, true)),
    %% Not homed: no absolute move; a relative one is fine.
    ?assertEqual({error, not_homed}, cell_hal_axis:move_absolute(x, 5.0, ?FAST)),
    ok = home(),
    %% Beyond the software limits, and bad parameters: the axis unchanged.
    ?assertMatch({error, {beyond_limits, 2000.0, _}},
                 cell_hal_axis:move_absolute(x, 2000.0, ?FAST)),
    ?assertMatch({error, {beyond_limits, _, _}}, cell_hal_axis:move_relative(x, -500.0, ?FAST)),
    ?assertMatch({error, {bad_params, _}},
                 cell_hal_axis:move_absolute(x, 5.0, ?FAST#{velocity => 0})),
    ?assertMatch({error, {bad_override, 120}}, cell_hal_axis:set_override(x, 120)),
    ?assertMatch({ok, #{state := standstill, position := 0.0}}, cell_hal_axis:status(x)),
    %% Homing only from standstill.
    {ok, M} = cell_hal_axis:move_absolute(x, 500.0, ?SLOW),
    ?assertEqual({error, {busy, discrete_motion}}, cell_hal_axis:home(x, 0.0)),
    ok = done(cell_hal_axis:halt(x, 10000)),
    ok = await(M, aborted).

newer_move_aborts(_Config) ->
    ok = ready(),
    {ok, M1} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ok = moving(),
    %% Replaced while moving forward: the new move turns the axis round.
    {ok, M2} = cell_hal_axis:move_absolute(x, 0.0, ?FAST),
    ok = await(M1, aborted),
    ok = await(M2, done),
    ?assertMatch({ok, #{state := standstill, position := 0.0}}, cell_hal_axis:status(x)).

halt_mid_move(_Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ok = moving(),
    {ok, H} = cell_hal_axis:halt(x, 1000),
    ok = await(M, aborted),
    ok = await(H, done),
    {ok, #{state := standstill, position := P}} = cell_hal_axis:status(x),
    ?assert(P >= 0.0 andalso P < 900.0),
    %% After a halt a move may follow.
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?FAST)).

stop_holds_until_released(_Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ok = moving(),
    {ok, S} = cell_hal_axis:stop(x, true, 1000),
    ok = await(M, aborted),
    ok = await(S, done),
    %% Stopped, and held there while Execute is held: moves are refused.
    ?assertMatch({ok, #{state := stopping, velocity := 0.0}}, cell_hal_axis:status(x)),
    ?assertEqual({error, stopping}, cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    ok = done(cell_hal_axis:stop(x, false, 1000)),
    ?assertMatch({ok, #{state := standstill}}, cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?FAST)).

fault_fails_the_move(_Config) ->
    ok = ready(),
    ok = cell_hal_axis_sim:fault_next(x),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?FAST),
    %% A following error, as TwinCAT NC reports it.
    ok = await(M, {error, 16#4550}),
    ?assertMatch({ok, #{state := error_stop, error := 16#4550}}, cell_hal_axis:status(x)),
    ?assertEqual({error, {error_stop, 16#4550}}, cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    ok = done(cell_hal_axis:reset(x)),
    ?assertMatch({ok, #{state := standstill, error := 0, homed := true}},
                 cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    %% A fault while standing: ErrorStop all the same, reset to standstill.
    ok = cell_hal_axis_sim:fault(x, 16#4260),
    ?assertMatch({ok, #{state := error_stop, error := 16#4260}}, cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:reset(x)).

override_is_a_time_base(_Config) ->
    ok = ready(),
    ok = cell_hal_axis:set_override(x, 0),
    %% At 0 % the axis holds its place: the move stands at its start however long.
    {ok, M} = cell_hal_axis:move_absolute(x, 100.0, ?FAST),
    {ok, #{state := discrete_motion, position := P0, velocity := V0}} = cell_hal_axis:status(x),
    ?assertEqual({0.0, 0.0}, {P0, V0}),
    receive {M, Early} -> ct:fail({ended_at_override_0, Early}) after 200 -> ok end,
    ?assertMatch({ok, #{position := 0.0}}, cell_hal_axis:status(x)),
    %% Raised, the move goes on and ends.
    ok = cell_hal_axis:set_override(x, 100),
    ok = await(M, done),
    ?assertMatch({ok, #{position := 100.0, override := 100}}, cell_hal_axis:status(x)),
    %% At 50 % a move takes at least twice its time (a lower bound: a busy machine
    %% only makes it later). ?SLOW over 100 mm: 2 s at 100 %.
    ok = cell_hal_axis:set_override(x, 50),
    T0 = erlang:monotonic_time(millisecond),
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?SLOW)),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 4000).

power_off_aborts(_Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ok = moving(),
    ok = done(cell_hal_axis:power(x, false)),
    ok = await(M, aborted),
    {ok, #{state := disabled, position := P, velocity := 0.0}} = cell_hal_axis:status(x),
    ?assertMatch({ok, #{position := P}}, cell_hal_axis:status(x)).

%% Published into a simulated PLC's inputs, the position is a HAL point like any other:
%% it follows the move and ends at the target.
publishes_its_position(_Config) ->
    ok = cell_hal:add_connection(#{id => nc, driver => cell_hal_sim, opts => #{poll_ms => 10}}),
    ok = cell_hal:add_group(#{id => axes_io, module => cell_hal_test_axis_io, connection => nc}),
    try
        ok = cell_hal_hw:add(#{id => px, kind => axis, type => sim,
                               opts => #{home_ms => 1, position => 5.0,
                                         publish => #{group => axes_io, position => x_pos,
                                                      velocity => x_vel, period_ms => 10}}}),
        %% At rest where it starts.
        ok = await_point(x_pos, {eq, 5.0}),
        ok = done(cell_hal_axis:power(px, true)),
        ok = done(cell_hal_axis:home(px, 0.0)),
        ok = await_point(x_pos, {eq, 0.0}),
        %% Moving: the published position passes 100 on its way to 300, the velocity
        %% is seen above zero; at rest at the target, velocity zero.
        {ok, M} = cell_hal_axis:move_absolute(px, 300.0, ?SLOW#{velocity => 200}),
        ok = await_point(x_pos, {gt, 100.0}),
        ok = await_point(x_vel, {gt, 0.0}),
        ok = await(M, done),
        ok = await_point(x_pos, {eq, 300.0}),
        ok = await_point(x_vel, {eq, 0.0})
    after
        _ = cell_hal_hw:remove(px),
        ok = cell_hal:remove_group(axes_io),
        ok = cell_hal:remove_connection(nc)
    end.

%% Published into an output, the position is written through the HAL as the tasks'
%% outputs are: the PLC sees it follow the move and come to rest at its target.
publishes_into_outputs(_Config) ->
    ok = cell_hal:add_connection(#{id => nc, driver => cell_hal_sim, opts => #{poll_ms => 10}}),
    ok = cell_hal:add_group(#{id => axes_io, module => cell_hal_test_axis_io, connection => nc}),
    Self = self(),
    ok = cell_hal_sim:on_change({axes_io, x_told}, fun(V) -> Self ! {told, V}, [] end),
    try
        ok = cell_hal_hw:add(#{id => px, kind => axis, type => sim,
                               opts => #{home_ms => 1,
                                         publish => #{group => axes_io, position => x_told,
                                                      period_ms => 10}}}),
        ok = done(cell_hal_axis:power(px, true)),
        ok = done(cell_hal_axis:home(px, 0.0)),
        {ok, M} = cell_hal_axis:move_absolute(px, 300.0, ?SLOW#{velocity => 200}),
        ok = await(M, done),
        Told = told(300.0, []),
        ?assert(lists:any(fun(V) -> V > 0.0 andalso V < 300.0 end, Told), Told)
    after
        _ = cell_hal_hw:remove(px),
        ok = cell_hal:remove_group(axes_io),
        ok = cell_hal:remove_connection(nc)
    end.

%% What the PLC was told, oldest first, up to `Last'.
told(Last, Acc) ->
    receive
        {told, Last} -> lists:reverse([Last | Acc]);
        {told, V} -> told(Last, [V | Acc])
    after ?WAIT -> ct:fail({not_told, Last, lists:reverse(Acc)})
    end.

await_point(P, Cond) ->
    {ok, Ref} = cell_hal:watch(axes_io, P, Cond),
    receive {cell_hal_watch, Ref, _} -> ok after ?WAIT -> ct:fail({point, P, Cond}) end.

%% A simulated machine ten times faster than real time (a test's physics): homing and a
%% move take a tenth of their time, and the axis reads the machine's own velocity.
%% ?SLOW over 100 mm takes 2 s of the machine's time: between 0.2 s (a lower bound, as a
%% busy machine only makes it later) and the 2 s it would take in real time.
time_scale_speeds_the_machine(_Config) ->
    ok = cell_hal_hw:add(#{id => fast, kind => axis, type => sim,
                           opts => #{home_ms => 3000, time_scale => 0.1}}),
    try
        ok = done(cell_hal_axis:power(fast, true)),
        T0 = erlang:monotonic_time(millisecond),
        ok = done(cell_hal_axis:home(fast, 0.0)),
        T1 = erlang:monotonic_time(millisecond),
        ?assert(T1 - T0 >= 300 andalso T1 - T0 < 3000, T1 - T0),
        {ok, M} = cell_hal_axis:move_absolute(fast, 100.0, ?SLOW),
        {ok, #{velocity := V}} = cell_hal_axis:status(fast),
        ?assert(V >= 0.0 andalso V =< 100.0, V),
        ok = await(M, done),
        T2 = erlang:monotonic_time(millisecond),
        ?assert(T2 - T1 >= 200 andalso T2 - T1 < 2000, T2 - T1),
        ?assertMatch({ok, #{position := 100.0, velocity := 0.0}}, cell_hal_axis:status(fast))
    after
        ok = cell_hal_hw:remove(fast)
    end.

bad_options(_Config) ->
    Add = fun(Opts) -> cell_hal_hw:add(#{id => y, kind => axis, type => sim, opts => Opts}) end,
    ?assertEqual({error, {bad_option, limits}}, Add(#{limits => {5, 1}})),
    ?assertEqual({error, {bad_option, fault_rate}}, Add(#{fault_rate => 2})),
    ?assertEqual({error, {bad_option, speed}}, Add(#{speed => 1})),
    ?assertEqual({error, {bad_option, time_scale}}, Add(#{time_scale => 0})),
    ?assertEqual({error, {bad_option, publish}}, Add(#{publish => #{group => g}})),
    ?assertEqual({error, not_present}, cell_hal_axis:status(y)).

%% -------------------------------------------------------------------------------------

ready() ->
    ok = done(cell_hal_axis:power(x, true)),
    home().

home() ->
    done(cell_hal_axis:home(x, 0.0)).

%% The command accepted and its job done.
done({ok, Ref}) ->
    await(Ref, done);
done(Other) ->
    ct:fail({refused, Other}).

await(Ref, What) ->
    receive {Ref, Got} -> ?assertEqual(What, Got), ok
    after ?WAIT -> ct:fail({no_end, What})
    end.

%% The axis is on its way (asked right after a slow move starts: it moves at once).
moving() ->
    {ok, #{state := discrete_motion}} = cell_hal_axis:status(x),
    ok.
