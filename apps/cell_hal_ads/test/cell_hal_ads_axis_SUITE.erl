%% The axis of TwinCAT NC over ADS (cell_hal_ads_axis) through the axis's API
%% (cell_hal_axis), against the fake PLC's NC (test/peers/fake_plc.py, AMS port 500):
%% power, home and moves run on the NC and end when its state says so; a newer
%% command, halt or stop aborts what runs; an NC error fails the move and reset
%% clears it on the NC; the override is the NC's; a lost connection makes the object
%% down and refuses commands until the NC is back; a watcher hears of the axis only
%% when what it shows changed, not at each poll.
%%
%% Each case has a fake PLC of its own with NC axis 1 (limits -100 to 1000, homing
%% in 50 ms), and the object `x' connected to it.
-module(cell_hal_ads_axis_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([power_home_move/1, halt_aborts_move/1, stop_holds_until_released/1,
         newer_move_aborts/1, nc_error_fails_move/1, override_is_the_ncs/1,
         power_off_aborts/1, connection_lost_and_back/1, refused_commands/1,
         bad_options/1, watchers_hear_only_changes/1]).

-define(WAIT, 15000).
-define(NET, "127.0.0.1.1.1").
-define(FAST, #{velocity => 2000, acceleration => 20000, deceleration => 20000}).
%% 100 mm/s reached in a second: a move of 900 mm takes 10 s.
-define(SLOW, #{velocity => 100, acceleration => 100, deceleration => 100}).

all() ->
    [power_home_move, halt_aborts_move, stop_holds_until_released, newer_move_aborts,
     nc_error_fails_move, override_is_the_ncs, power_off_aborts, connection_lost_and_back,
     refused_commands, bad_options, watchers_hear_only_changes].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_testcase(_Case, Config) ->
    {Fake, Port} = start_fake(0),
    Config1 = [{fake, Fake}, {port, Port} | Config],
    ok = cell_hal_hw:add(#{id => x, kind => axis, type => ads, opts => opts(Port)}),
    try
        ok = await_status(x, up)
    catch
        C:R:St ->
            %% end_per_testcase is not run after a failed init.
            end_per_testcase(init, Config1),
            erlang:raise(C, R, St)
    end,
    Config1.

end_per_testcase(_Case, Config) ->
    [ok = cell_hal_hw:remove(Id) || {Id, _, _} <- cell_hal_hw:list()],
    _ = [cell_hal_ads_peer:stop(F) || F <- [?config(fake, Config)], is_pid(F)],
    ok.

start_fake(Port) ->
    case cell_hal_ads_peer:start("fake_plc.py", ["--port", integer_to_list(Port)]) of
        {ok, Fake, {ready, Bound, _}} ->
            ok = cell_hal_ads_peer:cmd(Fake, "nc_axis 1 -100 1000 50"),
            {Fake, Bound};
        {error, Reason} ->
            ct:fail("the fake PLC did not start: ~tp", [Reason])
    end.

opts(Port) ->
    #{host => "127.0.0.1", port => Port, target_net_id => ?NET, axis => 1,
      limits => {-100.0, 1000.0}, reconnect_ms => 100, max_reconnect_ms => 400}.

%% -------------------------------------------------------------------------------------

power_home_move(Config) ->
    ?assertMatch({ok, #{state := disabled, homed := false, powered := false}},
                 cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:power(x, true)),
    ?assertMatch(#{enabled := true}, nc(Config)),
    {ok, H} = cell_hal_axis:home(x, 10.0),
    ?assertMatch({ok, #{state := homing}}, cell_hal_axis:status(x)),
    ok = await(H, done),
    ?assertMatch({ok, #{state := standstill, homed := true, position := 10.0}},
                 cell_hal_axis:status(x)),
    ?assertMatch(#{referenced := true, position := 10.0}, nc(Config)),
    ok = done(cell_hal_axis:move_absolute(x, 250.0, ?FAST)),
    %% Read back: the object's status and the NC's own.
    ?assertMatch({ok, #{state := standstill, position := 250.0, velocity := 0.0}},
                 cell_hal_axis:status(x)),
    ?assertMatch(#{position := 250.0, job := none}, nc(Config)),
    ok = done(cell_hal_axis:move_relative(x, -50.0, ?FAST)),
    ?assertMatch({ok, #{position := 200.0}}, cell_hal_axis:status(x)),
    %% A move to where the axis stands is done too.
    ok = done(cell_hal_axis:move_absolute(x, 200.0, ?FAST)),
    ?assertMatch({ok, #{state := standstill, position := 200.0}}, cell_hal_axis:status(x)).

halt_aborts_move(Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ?assertMatch(#{job := move}, nc(Config)),
    {ok, H} = cell_hal_axis:halt(x, 1000),
    ok = await(M, aborted),
    ok = await(H, done),
    {ok, #{state := standstill, position := P}} = cell_hal_axis:status(x),
    ?assert(P >= 0.0 andalso P < 900.0),
    ?assertMatch(#{job := none, velocity := 0.0}, nc(Config)),
    %% After a halt a move may follow.
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?FAST)).

stop_holds_until_released(_Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    {ok, S} = cell_hal_axis:stop(x, true, 1000),
    ok = await(M, aborted),
    ok = await(S, done),
    ?assertMatch({ok, #{state := stopping, velocity := 0.0}}, cell_hal_axis:status(x)),
    ?assertEqual({error, stopping}, cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    ok = done(cell_hal_axis:stop(x, false, 1000)),
    ?assertMatch({ok, #{state := standstill}}, cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?FAST)).

newer_move_aborts(Config) ->
    ok = ready(),
    {ok, M1} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    {ok, M2} = cell_hal_axis:move_absolute(x, -50.0, ?FAST),
    ok = await(M1, aborted),
    ok = await(M2, done),
    ?assertMatch({ok, #{state := standstill, position := -50.0}}, cell_hal_axis:status(x)),
    ?assertMatch(#{position := -50.0}, nc(Config)).

nc_error_fails_move(Config) ->
    ok = ready(),
    %% A following error halfway, as TwinCAT NC reports it.
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_fail 1 0x4550"),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?FAST),
    ok = await(M, {error, 16#4550}),
    ?assertMatch({ok, #{state := error_stop, error := 16#4550}}, cell_hal_axis:status(x)),
    {ok, #{position := Stopped}} = cell_hal_axis:status(x),
    ?assert(Stopped > 0.0 andalso Stopped < 900.0),
    ?assertEqual({error, {error_stop, 16#4550}}, cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    %% Reset clears it on the NC too.
    ok = done(cell_hal_axis:reset(x)),
    ?assertMatch(#{error := 0}, nc(Config)),
    ?assertMatch({ok, #{state := standstill, error := 0, homed := true}},
                 cell_hal_axis:status(x)),
    ok = done(cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    ?assertMatch({ok, #{position := 0.0}}, cell_hal_axis:status(x)).

override_is_the_ncs(Config) ->
    ok = ready(),
    ok = cell_hal_axis:set_override(x, 50),
    ?assertMatch(#{override := 500000}, nc(Config)),
    ?assertMatch({ok, #{override := 50}}, cell_hal_axis:status(x)),
    ?assertMatch({error, {bad_override, 120}}, cell_hal_axis:set_override(x, 120)),
    %% At 50 % the NC runs ?SLOW's 100 mm at 50 mm/s: 2.5 s rather than 2 s (a lower
    %% bound: a busy machine only makes it later).
    T0 = erlang:monotonic_time(millisecond),
    ok = done(cell_hal_axis:move_absolute(x, 100.0, ?SLOW)),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 2400),
    %% At 0 % the NC holds the axis: the move does not end however long.
    ok = cell_hal_axis:set_override(x, 0),
    ?assertMatch(#{override := 0}, nc(Config)),
    {ok, M} = cell_hal_axis:move_absolute(x, 0.0, ?FAST),
    receive {M, Early} -> ct:fail({ended_at_override_0, Early}) after 300 -> ok end,
    ?assertMatch(#{position := 100.0, job := move}, nc(Config)),
    ok = cell_hal_axis:set_override(x, 100),
    ok = await(M, done),
    ?assertMatch({ok, #{position := 0.0, override := 100}}, cell_hal_axis:status(x)).

power_off_aborts(Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ok = done(cell_hal_axis:power(x, false)),
    ok = await(M, aborted),
    ?assertMatch({ok, #{state := disabled, powered := false}}, cell_hal_axis:status(x)),
    ?assertMatch(#{enabled := false, job := none}, nc(Config)).

%% The fake killed while a move runs: the object is down, the move ends with
%% not_connected, commands are refused; with an NC on the same address again the
%% object comes back with the NC's state (a fresh axis: disabled).
connection_lost_and_back(Config) ->
    ok = ready(),
    {ok, M} = cell_hal_axis:move_absolute(x, 900.0, ?SLOW),
    ok = cell_hal_ads_peer:stop(?config(fake, Config)),
    ok = await_status(x, down),
    ok = await(M, {error, not_connected}),
    ?assertEqual({error, not_connected}, cell_hal_axis:move_absolute(x, 0.0, ?FAST)),
    ?assertEqual({error, not_connected}, cell_hal_axis:power(x, true)),
    ?assertEqual({error, not_connected}, cell_hal_axis:status(x)),
    {Fake, _} = start_fake(?config(port, Config)),
    try
        ok = await_status(x, up),
        ?assertMatch({ok, #{state := disabled, homed := false}}, cell_hal_axis:status(x)),
        ok = ready(),
        ok = done(cell_hal_axis:move_absolute(x, 20.0, ?FAST)),
        ?assertMatch({ok, #{position := 20.0}}, cell_hal_axis:status(x))
    after
        cell_hal_ads_peer:stop(Fake)
    end.

refused_commands(_Config) ->
    ?assertEqual({error, disabled}, cell_hal_axis:move_relative(x, 1.0, ?FAST)),
    ok = done(cell_hal_axis:power(x, true)),
    ?assertEqual({error, not_homed}, cell_hal_axis:move_absolute(x, 5.0, ?FAST)),
    ok = home(),
    ?assertMatch({error, {beyond_limits, 2000.0, _}},
                 cell_hal_axis:move_absolute(x, 2000.0, ?FAST)),
    ?assertMatch({error, {bad_params, _}},
                 cell_hal_axis:move_absolute(x, 5.0, ?FAST#{velocity => 0})),
    %% Coupled motion is the simulated NC's only.
    ?assertEqual({error, {unsupported, follow}},
                 cell_hal_axis:follow(x, #{range => {0.0, 1.0}})),
    ?assertMatch({ok, #{state := standstill, position := 0.0}}, cell_hal_axis:status(x)).

bad_options(Config) ->
    Port = ?config(port, Config),
    Add = fun(Opts) -> cell_hal_hw:add(#{id => y, kind => axis, type => ads, opts => Opts}) end,
    ?assertEqual({error, {bad_option, axis}}, Add(maps:remove(axis, opts(Port)))),
    ?assertEqual({error, {bad_option, axis}}, Add((opts(Port))#{axis => 0})),
    ?assertEqual({error, {bad_option, host}}, Add(maps:remove(host, opts(Port)))),
    ?assertEqual({error, {bad_option, target_net_id}},
                 Add((opts(Port))#{target_net_id => "1.2.3"})),
    ?assertEqual({error, {bad_option, poll_ms}}, Add((opts(Port))#{poll_ms => 0})),
    ?assertEqual({error, {bad_option, speed}}, Add((opts(Port))#{speed => 1})),
    ?assertEqual({error, not_present}, cell_hal_axis:status(y)).

%% A watcher of an axis at rest hears nothing of the polls that read it as it was
%% (counted on the fake NC: the object is polled, and says nothing); it hears of the
%% axis pushed to another position, which its status then shows.
watchers_hear_only_changes(Config) ->
    Fake = ?config(fake, Config),
    {ok, _} = cell_hal_hw:watch(x),
    %% What the object may have said before its first poll after the watch is past.
    ok = polls(Fake, 1),
    _ = flush_changes(),
    %% Three polls more: the two before the last surely answered and handled (one poll
    %% at a time, the next sent after the answer).
    ok = polls(Fake, 3),
    ?assertEqual(0, flush_changes()),
    ok = cell_hal_ads_peer:cmd(Fake, "nc_pos 1 42.5"),
    receive {cell_hal_hw_changed, x} -> ok
    after ?WAIT -> ct:fail(no_change_told)
    end,
    ?assertMatch({ok, #{state := disabled, position := 42.5}}, cell_hal_axis:status(x)).

%% -------------------------------------------------------------------------------------

%% Returns once the fake NC has been asked for an axis's state N times more.
polls(Fake, N) ->
    {ok, #{nc_reads := Now}} = cell_hal_ads_peer:cmd(Fake, "stats"),
    Line = io_lib:format("wait_stat nc_reads ~b ~b", [Now + N, ?WAIT]),
    cell_hal_ads_peer:cmd(Fake, Line).

%% How many change messages of the axis came.
flush_changes() ->
    receive {cell_hal_hw_changed, x} -> 1 + flush_changes()
    after 0 -> 0
    end.

ready() ->
    ok = done(cell_hal_axis:power(x, true)),
    home().

home() ->
    done(cell_hal_axis:home(x, 0.0)).

done(Result) ->
    cell_hal_ads_nc_await:done(Result).

await(Ref, What) ->
    cell_hal_ads_nc_await:await(Ref, What).

await_status(Id, Want) ->
    cell_hal_ads_nc_await:status(Id, Want).

%% The axis as the fake's NC has it.
nc(Config) ->
    {ok, Axis} = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_get 1"),
    Axis.
