%% The interpolation channel of TwinCAT NC I over ADS (cell_hal_ads_channel) through
%% the channel's API (cell_hal_channel), against the fake PLC's NC (fake_plc.py): a
%% path becomes a DIN 66025 program written on the target, loaded and run by the
%% channel, and the path's end, its progress and the NC's errors come back as on the
%% simulated channel; a halt stops and resets the channel; what cannot run is refused;
%% a lost connection ends the job and the channel comes back with the NC.
%%
%% Each case has a fake PLC of its own with NC axes 1 and 2 (limits -10 to 1000,
%% homing in 50 ms) and channel 1 over them, the axis objects `x' and `y' (to power
%% and home them) and the channel object `xy'.
-module(cell_hal_ads_channel_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([follows_a_path/1, progress_along_the_path/1, nc_error_fails_the_path/1,
         halt_aborts_the_path/1, refused/1, connection_lost_and_back/1,
         bad_options/1]).

-define(WAIT, 15000).
-define(NET, "127.0.0.1.1.1").
-define(PROGRAM, "C:\\TwinCAT\\Mc\\Nci\\xy.nc").
-define(FAST, #{velocity => 2000, acceleration => 20000, deceleration => 20000}).
-define(SLOW, #{velocity => 100, acceleration => 1000, deceleration => 1000}).

all() ->
    [follows_a_path, progress_along_the_path, nc_error_fails_the_path,
     halt_aborts_the_path, refused, connection_lost_and_back, bad_options].

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
    try
        [ok = cell_hal_hw:add(#{id => Id, kind => axis, type => ads,
                                opts => (client(Port))#{axis => A,
                                                        limits => {-10.0, 1000.0}}})
         || {Id, A} <- [{x, 1}, {y, 2}]],
        ok = cell_hal_hw:add(#{id => xy, kind => channel, type => ads, opts => opts(Port)}),
        [ok = await_status(Id, up) || Id <- [x, y, xy]]
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
            ok = cell_hal_ads_peer:cmd(Fake, "nc_axis 1 -10 1000 50"),
            ok = cell_hal_ads_peer:cmd(Fake, "nc_axis 2 -10 1000 50"),
            ok = cell_hal_ads_peer:cmd(Fake, "nc_channel 1 1 2"),
            {Fake, Bound};
        {error, Reason} ->
            ct:fail("the fake PLC did not start: ~tp", [Reason])
    end.

client(Port) ->
    #{host => "127.0.0.1", port => Port, target_net_id => ?NET, reconnect_ms => 100,
      max_reconnect_ms => 400}.

opts(Port) ->
    (client(Port))#{channel => 1, axes => [1, 2], program => ?PROGRAM}.

%% A line along X, a half circle counter-clockwise round (100, 50), a line back along
%% Y = 100: 200 mm of lines and 157 mm of arc.
square_path() ->
    {ok, Path} = cell_hal_path:new([{line, {0, 0}, {100, 0}},
                                    {arc, {100, 50}, 50, -90, 90},
                                    {line, {100, 100}, {0, 100}}]),
    Path.

%% -------------------------------------------------------------------------------------

follows_a_path(Config) ->
    ok = ready(),
    Path = square_path(),
    {ok, Ref} = cell_hal_channel:follow(xy, Path, ?FAST),
    ok = await(Ref, done),
    %% The axes stand at the path's end on the NC, and the channel says it is there.
    ?assertMatch(#{position := 0.0}, nc_axis(Config, 1)),
    ?assertMatch(#{position := 100.0}, nc_axis(Config, 2)),
    Length = cell_hal_path:length(Path),
    {ok, #{state := idle, along := Along, length := Length, position := {X, Y, _}}} =
        cell_hal_channel:status(xy),
    ?assertEqual(Length, Along),
    ?assert(abs(X) < 1.0e-6 andalso abs(Y - 100.0) < 1.0e-6),
    %% The program the NC ran: absolute, in millimetres, the arc counter-clockwise with
    %% its centre from its start, at 2000 mm/s.
    {ok, Program} = cell_hal_ads_peer:cmd(?config(fake, Config),
                                          "file_get " ++ quote(?PROGRAM)),
    Lines = string:split(string:trim(Program), "\n", all),
    ?assertMatch(<<"N10 G17 G71 G90">>, hd(Lines)),
    ?assert(lists:member(<<"G03 X100.0000 Y100.0000 I0.0000 J50.0000 F120000.0000">>,
                         [strip_n(L) || L <- Lines]), Lines),
    ?assertMatch(<<"N", _/binary>>, lists:last(Lines)),
    ?assertEqual(<<"M30">>, strip_n(lists:last(Lines))),
    ?assertMatch(#{runs := 1, error := 0, loaded := <<?PROGRAM>>}, nc_channel(Config)),
    %% A second path from where the first ended.
    {ok, Back} = cell_hal_path:new([{line, {0, 100}, {0, 0}}]),
    ok = done(cell_hal_channel:follow(xy, Back, ?FAST)),
    ?assertMatch(#{position := 0.0}, nc_axis(Config, 2)),
    ?assertMatch(#{runs := 2}, nc_channel(Config)).

%% While the NC runs the path, the channel's status tells how far along it is: later
%% readings further along, never past the end, on the segment where the axes are.
progress_along_the_path(_Config) ->
    ok = ready(),
    Path = square_path(),
    {ok, _} = cell_hal_hw:watch(xy),
    {ok, Ref} = cell_hal_channel:follow(xy, Path, ?SLOW),
    Seen = progress(Ref, []),
    Alongs = [A || #{along := A} <- Seen],
    ?assert(length(lists:usort(Alongs)) >= 3, Seen),
    ?assertEqual(Alongs, lists:sort(Alongs)),
    ?assert(lists:all(fun(A) -> A =< cell_hal_path:length(Path) end, Alongs)),
    %% Readings on the arc (segment 2 of 3) lie on its circle.
    OnArc = [P || #{segment := 2, position := P} <- Seen],
    ?assert(OnArc =/= [], Seen),
    [?assert(abs(math:sqrt((Px - 100) * (Px - 100) + (Py - 50) * (Py - 50)) - 50) < 0.5,
             P) || {Px, Py, _} = P <- OnArc].

progress(Ref, Acc) ->
    receive
        {cell_hal_hw_changed, xy} ->
            {ok, Status} = cell_hal_channel:status(xy),
            case Status of
                #{state := following} -> progress(Ref, [Status | Acc]);
                _ -> progress(Ref, Acc)
            end;
        {Ref, done} ->
            lists:reverse(Acc)
    after ?WAIT ->
        ct:fail({no_end, lists:reverse(Acc)})
    end.

nc_error_fails_the_path(Config) ->
    ok = ready(),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_channel_fail 1 0x4650"),
    {ok, Ref} = cell_hal_channel:follow(xy, square_path(), ?FAST),
    ok = await(Ref, {error, {xy, 16#4650}}),
    {ok, #{state := idle, along := Along, length := Length}} = cell_hal_channel:status(xy),
    ?assert(Along > 0 andalso Along < Length, {Along, Length}),
    %% The next path resets the channel first and runs.
    ok = done(cell_hal_channel:follow(xy, square_path(), ?FAST)),
    ?assertMatch(#{error := 0, runs := 2}, nc_channel(Config)).

halt_aborts_the_path(Config) ->
    ok = ready(),
    {ok, Ref} = cell_hal_channel:follow(xy, square_path(), ?SLOW),
    ?assertMatch(#{state := 5}, nc_channel(Config)),
    {ok, H} = cell_hal_channel:halt(xy, 1000),
    ok = await(Ref, aborted),
    ok = await(H, done),
    ?assertMatch({ok, #{state := idle}}, cell_hal_channel:status(xy)),
    %% The interpreter reset, the axes standing where the stop left them.
    ?assertMatch(#{state := 1}, nc_channel(Config)),
    #{position := X1} = nc_axis(Config, 1),
    ?assertMatch(#{position := X1, velocity := 0.0}, nc_axis(Config, 1)),
    ok = done(cell_hal_channel:follow(xy, square_path(), ?FAST)).

refused(Config) ->
    %% The axes not powered: the NC refuses to start, nothing runs.
    ?assertMatch({error, {nc_refused, _}},
                 cell_hal_channel:follow(xy, square_path(), ?FAST)),
    ?assertMatch({ok, #{state := idle}}, cell_hal_channel:status(xy)),
    ok = ready(),
    ?assertMatch({error, {bad_params, _}},
                 cell_hal_channel:follow(xy, square_path(), #{velocity => 0})),
    {ok, Ref} = cell_hal_channel:follow(xy, square_path(), ?SLOW),
    ?assertEqual({error, busy}, cell_hal_channel:follow(xy, square_path(), ?FAST)),
    ?assertMatch({error, {bad_deceleration, _}}, cell_hal_channel:halt(xy, 0)),
    ok = done(cell_hal_channel:halt(xy, 1000)),
    ok = await(Ref, aborted),
    ?assertMatch({error, {bad_override, _}}, cell_hal_channel:set_override(xy, 120)),
    %% The override is the channel's path override; its axes keep their own.
    ok = cell_hal_channel:set_override(xy, 50),
    ?assertMatch(#{override := 500000}, nc_channel(Config)),
    ?assertMatch(#{override := 1000000}, nc_axis(Config, 1)),
    ?assertMatch(#{override := 1000000}, nc_axis(Config, 2)).

connection_lost_and_back(Config) ->
    ok = ready(),
    Port = ?config(port, Config),
    {ok, Ref} = cell_hal_channel:follow(xy, square_path(), ?SLOW),
    ok = cell_hal_ads_peer:stop(?config(fake, Config)),
    ok = await(Ref, {error, not_connected}),
    ok = await_status(xy, down),
    ?assertEqual({error, not_connected}, cell_hal_channel:follow(xy, square_path(), ?FAST)),
    ?assertEqual({error, not_connected}, cell_hal_channel:halt(xy, 1000)),
    %% The NC back on the same port: the channel connects again by itself.
    {Fake2, Port} = start_fake(Port),
    try
        [ok = await_status(Id, up) || Id <- [xy, x, y]],
        ok = ready(),
        ok = done(cell_hal_channel:follow(xy, square_path(), ?FAST))
    after
        cell_hal_ads_peer:stop(Fake2)
    end.

bad_options(Config) ->
    Opts = opts(?config(port, Config)),
    [?assertEqual({error, {bad_option, K}},
                  cell_hal_hw:add(#{id => bad, kind => channel, type => ads,
                                    opts => maps:remove(K, Opts)}))
     || K <- [channel, axes, program]],
    [?assertEqual({error, {bad_option, K}},
                  cell_hal_hw:add(#{id => bad, kind => channel, type => ads,
                                    opts => Opts#{K => V}}))
     || {K, V} <- [{channel, 0}, {channel, 256}, {axes, [1]}, {axes, [1, 1]},
                   {axes, [1, 2, 3, 4]}, {program, ""}, {program, 42}]].

%% -------------------------------------------------------------------------------------

ready() ->
    [ok = done(cell_hal_axis:power(A, true)) || A <- [x, y]],
    [ok = done(cell_hal_axis:home(A, 0.0)) || A <- [x, y]],
    ok.

done(Result) ->
    cell_hal_ads_nc_await:done(Result).

await(Ref, What) ->
    cell_hal_ads_nc_await:await(Ref, What).

await_status(Id, Want) ->
    cell_hal_ads_nc_await:status(Id, Want).

nc_axis(Config, Id) ->
    {ok, Axis} = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_get " ++ integer_to_list(Id)),
    Axis.

nc_channel(Config) ->
    {ok, Channel} = cell_hal_ads_peer:cmd(?config(fake, Config), "nc_channel_get 1"),
    Channel.

quote(S) ->
    lists:flatten(string:replace(S, " ", "%20", all)).

strip_n(Line) ->
    [_N, Rest] = string:split(Line, " "),
    Rest.
