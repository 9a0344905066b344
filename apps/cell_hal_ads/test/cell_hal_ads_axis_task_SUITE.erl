%% A device task moving the axes of TwinCAT NC over ADS in a running cell, as seed
%% 000's robot tasks move theirs: cell_axis_task (the cell's tests) over two axes of
%% type `ads' against the fake PLC's NC (peers/fake_plc.py, axes 1 and 2). The task
%% powers and homes its axes, then cycles through point-to-point moves, each started
%% in one step and waited for as a reply; an NC error is the operator's error naming
%% the axis and the NC's code, and Retry resets the axis on the NC and the cycle goes
%% on; the monitor connects the axes with the cell and applies the machine's speed
%% override to them on the NC. With an NC I channel over the two axes (type `ads' of
%% kind `channel'), the task's cycle cuts along a path the NC runs as its program, and
%% an NC error on the path is the operator's error naming the channel and the code.
-module(cell_hal_ads_axis_task_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([cycles_on_the_nc/1, nc_error_is_the_operators_error/1, override_on_the_nc/1,
         cuts_on_the_nc_channel/1, channel_error_is_the_operators_error/1,
         estop_halts_the_nc_channel/1]).

-define(WAIT, 20000).
-define(NET, "127.0.0.1.1.1").

all() ->
    [cycles_on_the_nc, nc_error_is_the_operators_error, override_on_the_nc,
     cuts_on_the_nc_channel, channel_error_is_the_operators_error,
     estop_halts_the_nc_channel].

%% The cases whose cell has the NC I channel `xy' over the two axes.
-define(CHANNEL_CASES, [cuts_on_the_nc_channel, channel_error_is_the_operators_error,
                        estop_halts_the_nc_channel]).
-define(PROGRAM, "C:\\TwinCAT\\Mc\\Nci\\robot.nc").

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    {Fake, Port} = start_fake(),
    Channel = lists:member(Case, ?CHANNEL_CASES),
    Conn = #{host => "127.0.0.1", port => Port, target_net_id => ?NET, reconnect_ms => 100,
             max_reconnect_ms => 400},
    Args = case Channel of
               true -> #{axes => [x, y], channel => xy, path => cut(Case), notify => self()};
               false -> #{axes => [x, y], far => 150.0, notify => self()}
           end,
    Task = #{id => robot, module => cell_axis_task, zone => <<"robot">>, lane => <<"Test">>,
             args => Args},
    Hardware = [#{id => Id, kind => axis, type => ads,
                  opts => Conn#{axis => N, limits => {-100.0, 1000.0}}}
                || {Id, N} <- [{x, 1}, {y, 2}]]
        ++ [#{id => xy, kind => channel, type => ads,
              opts => Conn#{channel => 1, axes => [1, 2], program => ?PROGRAM}} || Channel],
    Spec = #{name => <<"ads axis suite">>, tasks => [Task],
             hal => #{connections => [], groups => [], hardware => Hardware},
             monitor => #{io => #{}, drives => []}},
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    %% The NC reached before Start (a task finding its axis not connected asks the
    %% operator, as it should: not this suite's subject).
    %% The monitor adds the hardware as its first event: answered after it.
    _ = sys:get_state(cell_monitor),
    ok = await_up([x, y] ++ [xy || Channel]),
    ok = cell_events:subscribe(),
    ok = cell_log:subscribe(),
    [{fake, Fake} | Config].

end_per_testcase(_Case, Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok = application:unset_env(cell, cell_spec),
    _ = cell_hal_ads_peer:stop(?config(fake, Config)),
    ok.

start_fake() ->
    case cell_hal_ads_peer:start("fake_plc.py", ["--port", "0"]) of
        {ok, Fake, {ready, Bound, _}} ->
            ok = cell_hal_ads_peer:cmd(Fake, "nc_axis 1 -100 1000 50"),
            ok = cell_hal_ads_peer:cmd(Fake, "nc_axis 2 -100 1000 50"),
            ok = cell_hal_ads_peer:cmd(Fake, "nc_channel 1 1 2"),
            {Fake, Bound};
        {error, Reason} ->
            ct:fail("the fake PLC did not start: ~tp", [Reason])
    end.

%% -------------------------------------------------------------------------------------

%% Three cycles on the NC; the axes were powered and homed there by the task.
cycles_on_the_nc(Config) ->
    ok = cell_controller:start(),
    ok = cell_axis_task:await_cycles(robot, 3, ?WAIT),
    [?assertMatch(#{enabled := true, referenced := true}, nc(Config, N)) || N <- [1, 2]],
    {ok, #{position := P}} = cell_hal_axis:status(x),
    ?assert(P >= 0.0 andalso P =< 150.0).

%% A following error on the NC fails the move: the task's error names the axis and the
%% code; Retry resets the axis on the NC, and the cycle goes on.
nc_error_is_the_operators_error(Config) ->
    ok = cell_controller:start(),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_fail 1 0x4550"),
    receive {axis_task, robot, fault, x, 16#4550} -> ok
    after ?WAIT -> ct:fail({no_fault, cell_hal_axis:status(x)})
    end,
    #{id := Id, solutions := [retry], description := Text} =
        cell_axis_task:await_error(?WAIT),
    ?assertNotEqual(nomatch, binary:match(Text, <<"Axis x stopped: NC error 16#4550">>)),
    ?assertMatch(#{error := 16#4550}, nc(Config, 1)),
    ok = cell_alarms:answer(Id, retry, <<"suite">>),
    ok = cell_axis_task:await_cycles(robot, 2, ?WAIT),
    ?assertMatch(#{error := 0}, nc(Config, 1)).

%% The machine's speed override, changed while the task runs, is the NC's.
override_on_the_nc(Config) ->
    ok = cell_controller:start(),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT),
    ok = cell_settings:put(machine, #{speed_override => 40}, <<"suite">>),
    ok = await_override(Config, 400000),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT).

%% Three cycles with the NC's channel: each a point-to-point move to the start and the
%% cut along the path, which the NC ran as its program (three runs at least, no
%% error): the path's arc among its blocks.
cuts_on_the_nc_channel(Config) ->
    ok = cell_controller:start(),
    ok = cell_axis_task:await_cycles(robot, 3, ?WAIT),
    ?assertMatch(#{runs := Runs, error := 0, loaded := <<?PROGRAM>>} when Runs >= 3,
                 nc_channel(Config)),
    {ok, Program} = cell_hal_ads_peer:cmd(?config(fake, Config), "file_get " ++ ?PROGRAM),
    ?assertNotEqual(nomatch, binary:match(Program, <<" G03 X60.0000 Y40.0000 I0.0000 "
                                                     "J20.0000 F60000.0000\n">>)),
    %% The machine's speed override, changed while it cuts, is the path's override.
    ok = cell_settings:put(machine, #{speed_override => 40}, <<"suite">>),
    ok = await_override(Config, 400000, [1, 2, channel]),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT).

%% A fault of the NC's channel halfway along the path: the task's error names the
%% channel and the NC's code; Retry and the next cut runs (the channel reset first).
channel_error_is_the_operators_error(Config) ->
    ok = cell_controller:start(),
    ok = cell_axis_task:await_cycles(robot, 1, ?WAIT),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_channel_fail 1 0x4650"),
    receive {axis_task, robot, fault, xy, 16#4650} -> ok
    after ?WAIT -> ct:fail({no_fault, cell_hal_channel:status(xy)})
    end,
    #{id := Id, solutions := [retry], description := Text} =
        cell_axis_task:await_error(?WAIT),
    ?assertNotEqual(nomatch, binary:match(Text, <<"Axis xy stopped: NC error 16#4650">>)),
    ?assertMatch(#{error := 16#4650}, nc_channel(Config)),
    ok = cell_alarms:answer(Id, retry, <<"suite">>),
    ok = cell_axis_task:await_cycles(robot, 2, ?WAIT),
    ?assertMatch(#{error := 0}, nc_channel(Config)).

%% The emergency stop while the NC runs the cut: once it is raised (every task has
%% secured its outputs) the NC's channel is stopped and reset, and its axes stand.
estop_halts_the_nc_channel(Config) ->
    {ok, _} = cell_hal_hw:watch(xy),
    ok = cell_controller:start(),
    ok = await_following(),
    ?assertMatch(#{state := 5}, nc_channel(Config)),
    ok = cell_controller:estop(true),
    ?assertMatch(#{state := 1, error := 0}, nc_channel(Config)),
    [?assertMatch(#{velocity := 0.0}, nc(Config, N)) || N <- [1, 2]].

%% -------------------------------------------------------------------------------------

%% The cut: a line and a half circle back, from (0, 0) to (0, 40); for the emergency
%% stop, a long one (back and forth over 900 mm, four seconds at the task's speed).
cut(estop_halts_the_nc_channel) ->
    {ok, Path} = cell_hal_path:new([{line, {0, 0}, {900, 0}}, {line, {900, 0}, {0, 0}},
                                    {line, {0, 0}, {900, 0}}, {line, {900, 0}, {0, 0}}]),
    Path;
cut(_) ->
    {ok, Path} = cell_hal_path:new([{line, {0, 0}, {60, 0}},
                                    {arc, {60, 20}, 20, -90, 90},
                                    {line, {60, 40}, {0, 40}}]),
    Path.

%% The channel following a path (told of each change of the channel object).
await_following() ->
    receive
        {cell_hal_hw_changed, xy} ->
            case cell_hal_channel:status(xy) of
                {ok, #{state := following}} -> ok;
                _ -> await_following()
            end
    after ?WAIT ->
        ct:fail({not_following, cell_hal_channel:status(xy)})
    end.

%% Each axis object (the monitor adds them as the cell starts) up on the NC.
await_up([]) ->
    ok;
await_up([Id | Rest]) ->
    case cell_hal_hw:subscribe(Id) of
        {ok, up} ->
            await_up(Rest);
        Status ->
            receive {cell_hal_hw, Id, up} -> await_up(Rest)
            after ?WAIT -> ct:fail({axis_not_up, Id, Status})
            end
    end.

%% The monitor's override reached both axes on the NC (its log line comes after), and
%% the channel's path override where the cell has the channel.
await_override(Config, Nc) ->
    await_override(Config, Nc, [1, 2]).

await_override(Config, Nc, Want) ->
    Axes = [N || N <- [1, 2], #{override := O} <- [nc(Config, N)], O =:= Nc],
    Channel = case nc_channel(Config) of
                  #{override := Nc} -> [channel];
                  _ -> []
              end,
    case lists:sort(Want) =:= lists:sort(Axes ++ Channel) of
        true -> ok;
        _ ->
            receive {cell_log, _} -> await_override(Config, Nc, Want)
            after ?WAIT -> ct:fail({override_not_on_the_nc, Nc})
            end
    end.

%% The fake NC's own view of its channel 1.
nc_channel(Config) ->
    {ok, Channel} = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_channel_get 1"),
    Channel.

%% The fake NC's own view of axis N.
nc(Config, N) ->
    {ok, Axis} = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_get " ++ integer_to_list(N)),
    Axis.
