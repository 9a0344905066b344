%% The interpolation channel as a hardware object (cell_hal_channel) over two simulated
%% NC axes (cell_hal_channel_sim, cell_hal_axis_sim): it follows a path of lines and
%% arcs from where the axes stand, tells its progress, ends with the axes at the path's
%% end; an axis that faults fails the path and the other is halted; an axis not ready,
%% or a path beyond the limits, is refused; a halt aborts the path.
-module(cell_hal_channel_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([follows_lines_and_arcs/1, progress_while_following/1, axis_fault_fails_the_path/1,
         refused/1, halt_aborts/1, bad_options/1]).

-define(WAIT, 15000).
-define(FAST, #{velocity => 5000, acceleration => 50000, deceleration => 50000}).
%% 50 mm/s along the path: 250 mm take more than 5 s.
-define(SLOW, #{velocity => 50, acceleration => 500, deceleration => 500}).
-define(EPS, 1.0e-6).

all() ->
    [follows_lines_and_arcs, progress_while_following, axis_fault_fails_the_path, refused,
     halt_aborts, bad_options].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_testcase(_Case, Config) ->
    [ok = cell_hal_hw:add(#{id => A, kind => axis, type => sim,
                            opts => #{limits => {-10.0, 500.0}, home_ms => 10}})
     || A <- [x, y]],
    ok = cell_hal_hw:add(#{id => xy, kind => channel, type => sim, opts => #{axes => [x, y]}}),
    Config.

end_per_testcase(_Case, _Config) ->
    [ok = cell_hal_hw:remove(Id) || {Id, _, _} <- cell_hal_hw:list()],
    ok.

%% -------------------------------------------------------------------------------------

%% A line, a quarter arc and a line, started away from where the axes stand: the
%% channel goes to the start, follows it, and both axes end at its end.
follows_lines_and_arcs(_Config) ->
    ok = ready([x, y]),
    Path = path([{line, {10, 10}, {100, 10}},
                 %% About (100, 60), radius 50, from -90° to 0°: to (150, 60).
                 {arc, {100, 60}, 50, 270, 0},
                 {line, {150, 60}, {150, 200}}]),
    ok = done(cell_hal_channel:follow(xy, Path, ?FAST)),
    ?assert(near(150.0, position(x)) andalso near(200.0, position(y))),
    {ok, #{state := idle, along := Along, length := Length, segment := 4, segments := 4}} =
        cell_hal_channel:status(xy),
    %% The connecting line from (0, 0) to the start came first.
    ?assert(near(Length, Along)),
    ?assert(near(Length, math:sqrt(200) + 90 + 25 * math:pi() + 140)),
    ?assertMatch({ok, #{state := standstill}}, cell_hal_axis:status(x)).

progress_while_following(_Config) ->
    ok = ready([x, y]),
    Path = path([{line, {0, 0}, {100, 0}}, {line, {100, 0}, {100, 150}}]),
    {ok, Ref} = cell_hal_channel:follow(xy, Path, ?SLOW),
    {ok, #{state := following, along := A1, length := 250.0, segments := 2,
           position := {X1, Y1, _}}} = cell_hal_channel:status(xy),
    %% Where the channel says it is, on the path, is where the axes are (read just after:
    %% they move at most 50 mm/s meanwhile).
    ?assert(A1 >= 0.0 andalso A1 < 250.0),
    ?assert(abs(position(x) - X1) < 5.0 andalso abs(position(y) - Y1) < 5.0),
    ?assertMatch({ok, #{state := synchronized_motion}}, cell_hal_axis:status(y)),
    ok = await(Ref, done),
    ?assert(near(100.0, position(x)) andalso near(150.0, position(y))).

axis_fault_fails_the_path(_Config) ->
    ok = ready([x, y]),
    ok = cell_hal_axis_sim:fault_next(y),
    Path = path([{line, {0, 0}, {400, 0}}, {line, {400, 0}, {400, 400}}]),
    {ok, Ref} = cell_hal_channel:follow(xy, Path, ?FAST),
    ok = await(Ref, {error, {y, 16#4550}}),
    ?assertMatch({ok, #{state := error_stop, error := 16#4550}}, cell_hal_axis:status(y)),
    %% The other axis is halted: it comes to a stop, off the path's end.
    {ok, #{state := S}} = cell_hal_axis:status(x),
    ?assert(lists:member(S, [discrete_motion, standstill])),
    ?assertMatch({ok, #{state := idle}}, cell_hal_channel:status(xy)).

refused(_Config) ->
    %% y not homed: refused naming it; x, which had accepted, halted again.
    ok = done(cell_hal_axis:power(x, true)),
    ok = done(cell_hal_axis:home(x, 0.0)),
    ok = done(cell_hal_axis:power(y, true)),
    Path = path([{line, {0, 0}, {100, 0}}]),
    ?assertEqual({error, {y, not_homed}}, cell_hal_channel:follow(xy, Path, ?FAST)),
    ok = done(cell_hal_axis:home(y, 0.0)),
    %% Beyond x's limits (500).
    ?assertMatch({error, {x, {beyond_limits, _, _}}},
                 cell_hal_channel:follow(xy, path([{line, {0, 0}, {600, 0}}]), ?FAST)),
    ?assertMatch({error, {bad_params, _}},
                 cell_hal_channel:follow(xy, Path, ?FAST#{velocity => 0})),
    %% One path at a time.
    {ok, Ref} = cell_hal_channel:follow(xy, path([{line, {0, 0}, {300, 0}}]), ?SLOW),
    ?assertEqual({error, busy}, cell_hal_channel:follow(xy, Path, ?FAST)),
    {ok, H} = cell_hal_channel:halt(xy, 5000),
    ok = await(Ref, aborted),
    ok = await(H, done).

halt_aborts(_Config) ->
    ok = ready([x, y]),
    {ok, Ref} = cell_hal_channel:follow(xy, path([{line, {0, 0}, {300, 300}}]), ?SLOW),
    {ok, H} = cell_hal_channel:halt(xy, 5000),
    ok = await(Ref, aborted),
    ok = await(H, done),
    {ok, #{state := idle, along := Along, length := Length}} = cell_hal_channel:status(xy),
    ?assert(Along < Length),
    ?assertMatch({ok, #{state := standstill}}, cell_hal_axis:status(x)),
    %% Halted, the channel follows the next path from where the axes stopped.
    ok = done(cell_hal_channel:follow(xy, path([{line, {0, 0}, {20, 0}}]), ?FAST)),
    ?assert(near(20.0, position(x)) andalso near(0.0, position(y))).

bad_options(_Config) ->
    Add = fun(Opts) -> cell_hal_hw:add(#{id => c, kind => channel, type => sim, opts => Opts}) end,
    ?assertEqual({error, {bad_option, axes}}, Add(#{axes => [x]})),
    ?assertEqual({error, {bad_option, axes}}, Add(#{axes => [x, x]})),
    ?assertEqual({error, {bad_option, axes}}, Add(#{})).

%% -------------------------------------------------------------------------------------

ready(Axes) ->
    [begin
         ok = done(cell_hal_axis:power(A, true)),
         ok = done(cell_hal_axis:home(A, 0.0))
     end || A <- Axes],
    ok.

path(Segments) ->
    {ok, Path} = cell_hal_path:new(Segments),
    Path.

position(Axis) ->
    {ok, #{position := P}} = cell_hal_axis:status(Axis),
    P.

near(A, B) ->
    abs(A - B) < ?EPS.

done({ok, Ref}) ->
    await(Ref, done);
done(Other) ->
    ct:fail({refused, Other}).

await(Ref, What) ->
    receive {Ref, Got} -> ?assertEqual(What, Got), ok
    after ?WAIT -> ct:fail({no_end, What})
    end.
