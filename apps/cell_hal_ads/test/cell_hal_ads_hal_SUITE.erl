%% The HAL over its ADS driver (cell_hal_ads): IO groups read, written, watched and
%% sampled through `cell_hal' exactly as device tasks use them, against peers written
%% by others: the fake TwinCAT PLC of the ADS tests (test/peers/fake_plc.py, proven
%% against Beckhoff's AdsLib by cell_hal_ads_fake_SUITE) and PyPI pyads' own test
%% server. Everything on 127.0.0.1, on ports the OS picks.
-module(cell_hal_ads_hal_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, groups/0, init_per_suite/1, end_per_suite/1, init_per_group/2,
         end_per_group/2, init_per_testcase/2, end_per_testcase/2]).
-export([every_type_through_a_group/1, structure_and_image_groups/1,
         one_sum_command_per_poll/1, outputs_written_in_order/1,
         notifications_feed_inputs/1, notified_group_added_while_up/1,
         pulse_in_one_notification/1, laser_beam_latch/1, trigger_enable/1,
         missing_symbol_in_a_group/1, symbol_version_change_retries/1,
         retyped_symbol/1, raw_requests/1, bad_configuration/1,
         garbage_closes_only_the_connection/1, group_added_again/1]).
-export([plc_restart/1, connection_refused_then_up/1]).
-export([pyads_group/1]).

-define(NET, "127.0.0.1.1.1").
-define(WAIT, 10000).
-define(FILETIME_UNIX_EPOCH, 116444736000000000).
-define(POINTS, 200).

all() ->
    [{group, fake}, {group, restart}, {group, pyads}].

groups() ->
    [{fake, [], [every_type_through_a_group, structure_and_image_groups,
                 one_sum_command_per_poll, outputs_written_in_order,
                 notifications_feed_inputs, notified_group_added_while_up,
                 pulse_in_one_notification, laser_beam_latch, trigger_enable,
                 missing_symbol_in_a_group, symbol_version_change_retries,
                 retyped_symbol, raw_requests, bad_configuration,
                 garbage_closes_only_the_connection, group_added_again]},
     {restart, [], [plc_restart, connection_refused_then_up]},
     {pyads, [], [pyads_group]}].

%%--------------------------------------------------------------------
%% Setup
%%--------------------------------------------------------------------

init_per_suite(Config) ->
    Root = filename:join(?config(priv_dir, Config), "root"),
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, Root),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_group(fake, Config) ->
    {ok, Fake, {ready, Port, _}} = cell_hal_ads_peer:start("fake_plc.py", []),
    ok = define_symbols(Fake),
    [{fake, Fake}, {port, Port} | Config];
init_per_group(pyads, Config) ->
    {ok, Server, {ready, Port, _}} = cell_hal_ads_peer:start("pyads_server.py", []),
    [{ok, _, _} = cell_hal_ads_peer:cmd(Server, ["add ", N, " ", integer_to_list(A), " ", T,
                                                 " ", binary:encode_hex(V)])
     || {N, A, T, V} <- [{"MAIN.counter", 3, "DINT", <<42:32/little>>},
                         {"MAIN.flag", 33, "BOOL", <<0>>},
                         {"MAIN.speed", 5, "LREAL", <<10.0:64/float-little>>},
                         {"MAIN.text", 30, "STRING(10)", <<"abc", 0:(8 * 8)>>},
                         {"MAIN.setpoint", 18, "UINT", <<7:16/little>>}]],
    [{fake, Server}, {port, Port} | Config];
init_per_group(_, Config) ->
    Config.

end_per_group(Group, Config) when Group =:= fake; Group =:= pyads ->
    ok = cell_hal_ads_peer:stop(?config(fake, Config));
end_per_group(_, _) ->
    ok.

init_per_testcase(_, Config) ->
    Config.

end_per_testcase(_, Config) ->
    [ok = cell_hal:remove_group(G) || G <- cell_hal:groups()],
    [ok = cell_hal:remove_connection(C) || C <- cell_hal:connections()],
    flush(),
    case ?config(fake, Config) of
        undefined -> ok;
        Fake -> _ = cell_hal_ads_peer:cmd(Fake, "unmute"), ok
    end.

%% The PLC's variables: a structure of every type for inputs (in a program) and one for
%% outputs (global), a 200-point group, the laser-beam signals, IO image names.
define_symbols(Fake) ->
    Types = cell_hal_ads_test_io:types(),
    Structs = [{"MAIN.Inputs", "ST_Inputs", 65, <<0:128>>, ""},
               {".Outputs", "ST_Outputs", 65, <<0:128>>, ""}],
    Fields = lists:append(
               [[{"MAIN.Inputs." ++ cell_hal_ads_test_io:field(T), Decl, Adst,
                  plc_bytes(T, Decl, A), " nested"},
                 {".Outputs." ++ cell_hal_ads_test_io:field(T), Decl, Adst,
                  plc_bytes(T, Decl, B), " nested"}]
                || {T, Decl, Adst, A, B} <- Types]),
    Group = [{lists:flatten(io_lib:format("GVL.Io.P~3..0b", [I])), "DINT", 3,
              <<(I * 3):32/little>>, ""} || I <- lists:seq(0, ?POINTS - 1)],
    Others = [{"MAIN.LaserBeam", "BOOL", 33, <<0>>, ""},
              {"MAIN.AxisPos", "LREAL", 5, <<0.0:64/float-little>>, ""},
              {"MAIN.StopLoadingSegmentTriggerEnable", "BOOL", 33, <<0>>, ""},
              {"MAIN.retyped", "DINT", 3, <<7:32/little>>, ""},
              {"MAIN.counter", "DINT", 3, <<42:32/little>>, ""},
              {"Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn", "BOOL", 33, <<1>>, ""},
              {"Term 9 (EL2008).ManipulatorOutputs.ZAxisCylinder1Up", "BOOL", 33, <<0>>, ""},
              {"Term 6 (EL1008).Spare.In", "BOOL", 33, <<0>>, ""},
              {"Term 7 (EL1008).Spare.In", "BOOL", 33, <<0>>, ""}],
    [add(Fake, N, T, A, V, Extra) || {N, T, A, V, Extra} <- Structs ++ Fields ++ Group ++ Others],
    ok.

add(Fake, Name, Type, Adst, Value, Extra) ->
    {ok, _, _} = cell_hal_ads_peer:cmd(Fake, ["add ", q(Name), " ", Type, " ",
                                              integer_to_list(Adst), " ",
                                              integer_to_list(byte_size(Value)), " ",
                                              binary:encode_hex(Value), Extra]),
    ok.

%% A value as the PLC holds it in a symbol of that declaration (a STRING(1) keeps its
%% terminator).
plc_bytes(T, Decl, V) ->
    Size = case Decl of
               "STRING(1)" -> 2;
               _ -> cell_hal_ads_types:plc_size(T)
           end,
    {ok, Bin} = cell_hal_ads_types:encode(T, V, Size),
    Bin.

q(Name) ->
    string:replace(Name, " ", "%20", all).

fake(Config) -> ?config(fake, Config).

set(Config, Name, Bin) ->
    ok = cell_hal_ads_peer:cmd(fake(Config), ["set ", q(Name), " ", binary:encode_hex(Bin)]).

value(Config, Name) ->
    {ok, Bin} = cell_hal_ads_peer:cmd(fake(Config), ["get ", q(Name)]),
    Bin.

stats(Config) ->
    {ok, Stats} = cell_hal_ads_peer:cmd(fake(Config), "stats"),
    Stats.

clear(Config) ->
    ok = cell_hal_ads_peer:cmd(fake(Config), "clear").

%%--------------------------------------------------------------------
%% HAL helpers
%%--------------------------------------------------------------------

connect(Config) ->
    connect(Config, plc, #{}).

connect(Config, Id, Extra) ->
    Opts = maps:merge(#{host => "127.0.0.1", port => ?config(port, Config),
                        target_net_id => ?NET, poll_ms => 20, reconnect_ms => 50,
                        max_reconnect_ms => 400, timeout_ms => 2000}, Extra),
    ok = cell_hal:add_connection(#{id => Id, driver => cell_hal_ads, opts => Opts}),
    {ok, _} = cell_hal:subscribe_connection(Id),
    ok.

group(Id, Opts) ->
    group(Id, plc, Opts).

group(Id, Conn, Opts) ->
    ok = cell_hal:add_group(#{id => Id, module => cell_hal_ads_test_io, connection => Conn,
                              opts => Opts}).

types_group(Id) ->
    group(Id, #{kind => types, input_struct => <<"MAIN.Inputs">>,
                output_struct => <<".Outputs">>}).

await_status(Status) ->
    await_status(plc, Status).

await_status(Conn, Status) ->
    case cell_hal:status(Conn) of
        Status -> ok;
        _ -> receive {cell_hal_conn, Conn, Status} -> ok
             after ?WAIT -> ct:fail({not_reached, Conn, Status, cell_hal:info(Conn)})
             end
    end.

%% Waits for a point to hold a value (a watch: no polling).
await_value(G, Point, V) ->
    {ok, Ref} = cell_hal:watch(G, Point, {eq, V}),
    receive {cell_hal_watch, Ref, Got} -> Got
    after ?WAIT -> ct:fail({never, G, Point, V, cell_hal:read(G, Point)})
    end.

%% Waits for a condition on the HAL's tables, woken by every change of the point and
%% every log line (a point becoming unusable is logged, not published): no polling.
%% The log lines stay in the mailbox.
await(G, Point, Pred) ->
    ok = cell_log:subscribe(),
    ok = cell_hal:subscribe(G, Point),
    Deadline = erlang:monotonic_time(millisecond) + ?WAIT,
    {Result, Lines} = await_loop(G, Point, Pred, Deadline, []),
    ok = cell_hal:unsubscribe(G, Point),
    [self() ! L || L <- lists:reverse(Lines)],
    Result.

await_loop(G, Point, Pred, Deadline, Lines) ->
    Now = cell_hal:read(G, Point),
    case Pred(Now) of
        true ->
            {Now, Lines};
        false ->
            Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
            receive
                {cell_hal, {G, Point}, _} -> await_loop(G, Point, Pred, Deadline, Lines);
                {cell_log, _} = L -> await_loop(G, Point, Pred, Deadline, [L | Lines])
            after Left ->
                    ct:fail({never, G, Point, Now})
            end
    end.

%% The connection is up and every point of these groups has been read once (a group
%% added while the connection was up joins at the next poll).
up(Groups) ->
    ok = await_status(up),
    [_ = await(G, P, fun(R) -> R =/= {error, not_yet_read} andalso R =/= {error, disconnected} end)
     || G <- Groups, {ok, Points} <- [cell_hal:points(G)], #{name := P} <- Points],
    ok.

flush() ->
    receive _ -> flush() after 0 -> ok end.

%% A log line of the connection's source holding `Text'.
await_log(Text) ->
    case cell_hal_ads_peer:await(fun({cell_log, #{source := <<"hal/", _/binary>>, text := T}}) ->
                                         case binary:match(T, Text) of
                                             nomatch -> false;
                                             _ -> {true, T}
                                         end;
                                    (_) -> false
                                 end, ?WAIT) of
        {ok, Line} -> Line;
        {error, timeout} -> ct:fail({no_log_line, Text})
    end.

filetime_ns(FileTime) ->
    (FileTime - ?FILETIME_UNIX_EPOCH) * 100.

filetime_now() ->
    ?FILETIME_UNIX_EPOCH + os:system_time(nanosecond) div 100.

burst(Config, Stamps) ->
    Parts = [[integer_to_list(T), [[" ", N, " ", binary:encode_hex(V)] || {N, V} <- Pairs]]
             || {T, Pairs} <- Stamps],
    ok = cell_hal_ads_peer:cmd(fake(Config), ["burst " | lists:join(" ; ", Parts)]).

%%--------------------------------------------------------------------
%% fake: the HAL over the fake PLC
%%--------------------------------------------------------------------

%% Seed 000 §4.1: every point type through one group, inputs in a program's structure
%% ("MAIN.Inputs"), outputs in a global one (".Outputs"). Outputs show what the PLC
%% holds after connecting; then inputs follow the PLC and outputs reach it, byte for
%% byte as TwinCAT lays them out.
every_type_through_a_group(Config) ->
    Types = cell_hal_ads_test_io:types(),
    [begin
         set(Config, "MAIN.Inputs." ++ cell_hal_ads_test_io:field(T), plc_bytes(T, Decl, A)),
         set(Config, ".Outputs." ++ cell_hal_ads_test_io:field(T), plc_bytes(T, Decl, B))
     end || {T, Decl, _, A, B} <- Types],
    ok = connect(Config),
    ok = types_group(io),
    ok = up([io]),
    [begin
         ?assertEqual({ok, A}, cell_hal:read(io, in_name(T))),
         ?assertEqual({ok, B}, cell_hal:read(io, out_name(T)))
     end || {T, _, _, A, B} <- Types],
    [begin
         set(Config, "MAIN.Inputs." ++ cell_hal_ads_test_io:field(T), plc_bytes(T, Decl, B)),
         ?assertEqual(B, await_value(io, in_name(T), B)),
         ok = cell_hal:write_sync(io, out_name(T), A, ?WAIT),
         ?assertEqual(plc_bytes(T, Decl, A),
                      value(Config, ".Outputs." ++ cell_hal_ads_test_io:field(T))),
         ?assertEqual({ok, A}, cell_hal:read(io, out_name(T)))
     end || {T, Decl, _, A, B} <- Types],
    %% a REAL holds what a task writes, rounded as the HAL rounds it
    ok = cell_hal:write_sync(io, real_out, 0.1, ?WAIT),
    {ok, R} = cell_hal:read(io, real_out),
    ?assertEqual(<<R:32/float-little>>, value(Config, ".Outputs.Real")),
    %% NaN and the infinities, named as the HAL names them
    ok = cell_hal:write_sync(io, lreal_out, neg_infinity, ?WAIT),
    ?assertEqual(<<16#FFF0000000000000:64/little>>, value(Config, ".Outputs.Lreal")),
    set(Config, "MAIN.Inputs.Real", <<16#7FC00000:32/little>>),
    %% (NaN equals nothing, so no watch can wait for it)
    {ok, nan} = await(io, real_in, fun(V) -> V =:= {ok, nan} end),
    {ok, #{faults := []}} = cell_hal:info(plc).

in_name(T) -> name(T, "_in").
out_name(T) -> name(T, "_out").

name({string, N}, Suffix) -> list_to_atom("string" ++ integer_to_list(N) ++ Suffix);
name(T, Suffix) -> list_to_atom(atom_to_list(T) ++ Suffix).

%% Seed 000 §4.1.1 and §4.1.2 side by side: a structure based group and an image based
%% one ("*Name" wildcards, reached by index group and offset, no handles).
structure_and_image_groups(Config) ->
    ok = connect(Config, io_image, #{access => address}),
    ok = group(manipulator, io_image,
               #{kind => list,
                 points => [{palette_in, in, bool, <<"*ManipulatorInputs.FailPaletteIsIn">>},
                            {z1_up, out, bool, <<"*manipulatoroutputs.zaxiscylinder1up">>},
                            {spare, in, bool, <<"*Spare.In">>}]}),
    clear(Config),
    ok = await_status(io_image, up),
    [_ = await(manipulator, P, fun(R) -> R =/= {error, not_yet_read} end)
     || P <- [palette_in, z1_up, spare]],
    ?assertEqual({ok, true}, cell_hal:read(manipulator, palette_in)),
    ?assertEqual({ok, false}, cell_hal:read(manipulator, z1_up)),
    ok = cell_hal:write_sync(manipulator, z1_up, true, ?WAIT),
    ?assertEqual(<<1>>, value(Config, "Term 9 (EL2008).ManipulatorOutputs.ZAxisCylinder1Up")),
    ?assertEqual(0, maps:get(acquired, stats(Config), 0)),
    %% a wildcard that matches two image points names both
    {error, {unavailable, Spare}} = cell_hal:read(manipulator, spare),
    ct:log("~ts", [Spare]),
    ?assertNotEqual(nomatch, binary:match(Spare, <<"Term 6 (EL1008).Spare.In">>)),
    ?assertNotEqual(nomatch, binary:match(Spare, <<"Term 7 (EL1008).Spare.In">>)),
    %% the structure based group on a connection by handle, beside it
    ok = connect(Config),
    ok = group(general, #{kind => list, input_struct => <<"MAIN.Inputs">>,
                          output_struct => <<".Outputs">>,
                          points => [{start_button, in, bool, <<".Bool">>},
                                     {start_light, out, bool, <<".Bool">>}]}),
    ok = up([general]),
    set(Config, "MAIN.Inputs.Bool", <<1>>),
    true = await_value(general, start_button, true),
    ok = cell_hal:write_sync(general, start_light, true, ?WAIT),
    ?assertEqual(<<1>>, value(Config, ".Outputs.Bool")),
    ?assert(maps:get(acquired, stats(Config), 0) >= 2),
    ok = cell_hal:write_sync(manipulator, z1_up, false, ?WAIT).

%% A 200-point group is read in one sum command a poll: the PLC counts one request
%% and one sum of 200 sub-commands for every poll.
one_sum_command_per_poll(Config) ->
    ok = connect(Config),
    ok = group(big, #{kind => points, count => ?POINTS, input_struct => <<"GVL.Io">>}),
    ok = up([big]),
    ?assertEqual({ok, 21}, cell_hal:read(big, p007)),
    ?assertEqual({ok, 199 * 3}, cell_hal:read(big, p199)),
    clear(Config),
    ok = cell_hal_ads_peer:cmd(fake(Config), "wait_stat sums 10 10000"),
    #{requests := Requests, sums := Sums, sub_commands := Sub} = stats(Config),
    ct:log("~b requests, ~b sums, ~b sub-commands", [Requests, Sums, Sub]),
    ?assertEqual(Requests, Sums),
    ?assertEqual(?POINTS * Sums, Sub),
    %% and every poll reads them all
    set(Config, "GVL.Io.P123", <<-5:32/little-signed>>),
    -5 = await_value(big, p123, -5),
    set(Config, "GVL.Io.P123", <<(123 * 3):32/little>>).

%% Writes reach the PLC in the order they were made, even when many are in flight.
outputs_written_in_order(Config) ->
    ok = connect(Config),
    ok = types_group(io),
    ok = up([io]),
    ok = cell_hal_ads_peer:cmd(fake(Config), "record on"),
    clear(Config),
    [ok = cell_hal:write(io, int32_out, I) || I <- lists:seq(1, 100)],
    ok = cell_hal:write_sync(io, int32_out, 101, ?WAIT),
    {ok, Frames} = cell_hal_ads_peer:cmd(fake(Config), "frames"),
    Written = [V || <<_:22/binary, 3:16/little, _:14/binary, 16#F005:32/little, _:32,
                      4:32/little, V:32/little-signed>> <- Frames],
    ?assertEqual(lists:seq(1, 101), Written),
    ?assertEqual(<<101:32/little>>, value(Config, ".Outputs.Int32")).

%% Inputs fed by device notifications: no polling for them, their changes arrive
%% with the PLC's time stamps, kept for tasks.
notifications_feed_inputs(Config) ->
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>),
    ok = connect(Config),
    ok = group(axis, #{kind => list, input_struct => <<"MAIN">>, notify => all,
                       notify_opts => #{mode => on_change, cycle_us => 1000},
                       points => [{pos, in, lreal, <<".AxisPos">>}]}),
    ok = up([axis]),
    {ok, 0.0} = cell_hal:read(axis, pos),
    %% nothing is polled: the PLC sees no reads at all while values change
    clear(Config),
    set(Config, "MAIN.AxisPos", <<12.5:64/float-little>>),
    12.5 = await_value(axis, pos, 12.5),
    ?assertEqual(0, maps:get(requests, stats(Config), 0)),
    %% the PLC's stamps, exactly
    T1 = filetime_now() + 10000000,
    T2 = T1 + 5000,
    burst(Config, [{T1, [{"MAIN.AxisPos", <<1.5:64/float-little>>}]},
                   {T2, [{"MAIN.AxisPos", <<2.5:64/float-little>>}]}]),
    2.5 = await_value(axis, pos, 2.5),
    Since = filetime_ns(T1) - 1,
    {ok, [{_, 12.5}, {N1, 1.5}, {N2, 2.5}]} = cell_hal:samples(axis, pos, Since),
    ?assertEqual(filetime_ns(T1), N1),
    ?assertEqual(filetime_ns(T2), N2),
    {ok, [{N2, 2.5}]} = cell_hal:samples(axis, pos, N2 + 1),
    {error, unknown_point} = cell_hal:samples(axis, missing_point, 0),
    %% a polled point keeps no samples
    ok = group(polled, #{kind => list, input_struct => <<"MAIN">>,
                         points => [{counter, in, int32, <<".counter">>}]}),
    42 = await_value(polled, counter, 42),
    {error, not_sampled} = cell_hal:samples(polled, counter, 0),
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>).

%% A group that notifications alone feed, added once the connection is up, with
%% polls a minute apart: it is read at once, which sets its notifications up.
notified_group_added_while_up(Config) ->
    set(Config, "MAIN.LaserBeam", <<1>>),
    ok = connect(Config, plc, #{poll_ms => 60000}),
    ok = await_status(up),
    ok = group(beam, #{kind => list, input_struct => <<"MAIN">>, notify => all,
                       points => [{beam, in, bool, <<".LaserBeam">>}]}),
    true = await_value(beam, beam, true),
    set(Config, "MAIN.LaserBeam", <<0>>),
    false = await_value(beam, beam, false).

%% A bit that rises and falls within one notification (two samples a PLC cycle apart)
%% is published as both changes, in order, and fires a watch for the rise.
pulse_in_one_notification(Config) ->
    set(Config, "MAIN.LaserBeam", <<0>>),
    ok = connect(Config),
    ok = group(beam, #{kind => list, input_struct => <<"MAIN">>, notify => all,
                       notify_opts => #{cycle_us => 0},
                       points => [{beam, in, bool, <<".LaserBeam">>}]}),
    ok = up([beam]),
    ok = cell_hal:subscribe(beam, beam),
    {ok, Rise} = cell_hal:watch(beam, beam, {eq, true}),
    T = filetime_now(),
    burst(Config, [{T, [{"MAIN.LaserBeam", <<1>>}]}, {T + 10000, [{"MAIN.LaserBeam", <<0>>}]}]),
    [receive {cell_hal, {beam, beam}, Got} -> ?assertEqual(V, Got)
     after ?WAIT -> ct:fail({not_published, V})
     end || V <- [true, false]],
    receive {cell_hal_watch, Rise, true} -> ok after ?WAIT -> ct:fail(rise_not_seen) end,
    {ok, false} = cell_hal:read(beam, beam),
    {ok, [_, {_, true}, {_, false}]} = cell_hal:samples(beam, beam, filetime_ns(T) - 1).

%% Seed 000 §2.3.7, end to end through the HAL: an axis drives the tool through the
%% laser beam; the task asks the HAL for both signals' samples since the move began
%% and latches the position at the beam's edge, as the PLC saw it, whatever the lag.
laser_beam_latch(Config) ->
    set(Config, "MAIN.LaserBeam", <<0>>),
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>),
    ok = connect(Config),
    ok = group(tool_setter, #{kind => list, input_struct => <<"MAIN">>,
                              notify => [beam, pos], notify_opts => #{cycle_us => 0},
                              points => [{beam, in, bool, <<".LaserBeam">>},
                                         {pos, in, lreal, <<".AxisPos">>}]}),
    ok = up([tool_setter]),
    ok = cell_hal:subscribe(tool_setter, beam),
    %% One PLC cycle a millisecond, 0.2 mm a cycle; the beam breaks in cycle 37 and
    %% clears in cycle 80.
    T0 = filetime_now() + 10000000,
    Cycle = 10000,
    Since = filetime_ns(T0),
    burst(Config, [{T0 + K * Cycle,
                    [{"MAIN.AxisPos", <<(K * 0.2):64/float-little>>}] ++
                        [{"MAIN.LaserBeam", <<1>>} || K =:= 37] ++
                        [{"MAIN.LaserBeam", <<0>>} || K =:= 80]}
                   || K <- lists:seq(1, 100)]),
    _ = await_value(tool_setter, pos, 100 * 0.2),
    %% each signal's samples come in a message of their own: the beam's too
    [receive {cell_hal, {tool_setter, beam}, V} -> ok
     after ?WAIT -> ct:fail({beam_never, V})
     end || V <- [true, false]],
    {ok, Beam} = cell_hal:samples(tool_setter, beam, Since),
    {ok, Pos} = cell_hal:samples(tool_setter, pos, Since),
    ?assertEqual(101, length(Pos)),
    {ok, #{time := Edge, position := P, exact := true}} =
        cell_hal_ads_latch:position_at_edge(Beam, Pos, #{edge => rising, from => Since}),
    ?assertEqual(filetime_ns(T0 + 37 * Cycle), Edge),
    ?assertEqual(37 * 0.2, P),
    {ok, #{position := Off}} =
        cell_hal_ads_latch:position_at_edge(Beam, Pos, #{edge => falling, from => Edge}),
    ?assertEqual(80 * 0.2, Off),
    %% the connection going down forgets them: no latch across a gap (a muted PLC
    %% keeps it down until the test has looked)
    BeforeGap = os:system_time(nanosecond),
    ok = cell_hal_ads_peer:cmd(fake(Config), "mute"),
    ok = cell_hal_ads_peer:cmd(fake(Config), "drop"),
    ok = await_status(down),
    {error, disconnected} = cell_hal:samples(tool_setter, pos, Since),
    ok = cell_hal_ads_peer:cmd(fake(Config), "unmute"),
    ok = await_status(up),
    _ = await(tool_setter, pos, fun(R) -> element(1, R) =:= ok end),
    {error, {not_kept, Oldest}} = cell_hal:samples(tool_setter, pos, BeforeGap),
    ?assert(Oldest > BeforeGap).

%% Seed 000 §2.3.7's trigger: a PLC variable enabled just before an expected edge is
%% an output point written by handle, one ADS Write.
trigger_enable(Config) ->
    ok = connect(Config),
    ok = group(segment, #{kind => list, output_struct => <<"MAIN">>,
                          points => [{trigger_enable, out, bool,
                                      <<".StopLoadingSegmentTriggerEnable">>}]}),
    ok = up([segment]),
    ok = cell_hal_ads_peer:cmd(fake(Config), "record on"),
    clear(Config),
    T0 = erlang:monotonic_time(microsecond),
    ok = cell_hal:write_sync(segment, trigger_enable, true, ?WAIT),
    ct:log("enabled in ~b us", [erlang:monotonic_time(microsecond) - T0]),
    ?assertEqual(<<1>>, value(Config, "MAIN.StopLoadingSegmentTriggerEnable")),
    {ok, Frames} = cell_hal_ads_peer:cmd(fake(Config), "frames"),
    [_] = [F || <<_:22/binary, 3:16/little, _:14/binary, 16#F005:32/little, _/binary>> = F
                    <- Frames],
    ok = cell_hal:write_sync(segment, trigger_enable, false, ?WAIT),
    ?assertEqual(<<0>>, value(Config, "MAIN.StopLoadingSegmentTriggerEnable")).

%% A symbol the PLC lacks makes its point unusable, said in words, and nothing else:
%% the connection is up and the rest of the group is read as before.
missing_symbol_in_a_group(Config) ->
    ok = cell_log:subscribe(),
    set(Config, "MAIN.counter", <<42:32/little>>),
    ok = connect(Config),
    ok = group(mixed, #{kind => list, input_struct => <<"MAIN">>, output_struct => <<"MAIN">>,
                        points => [{counter, in, int32, <<".counter">>},
                                   {nothing, in, int32, <<".DoesNotExist">>},
                                   {nowhere, out, bool, <<".NoSuchOutput">>}]}),
    ok = up([mixed]),
    ?assertEqual({ok, 42}, cell_hal:read(mixed, counter)),
    {error, {unavailable, Why}} = cell_hal:read(mixed, nothing),
    ?assertEqual(<<"the PLC has no symbol MAIN.DoesNotExist">>, Why),
    {error, {unavailable, _}} = cell_hal:read(mixed, nowhere),
    {error, {unavailable, _}} = cell_hal:write(mixed, nowhere, true),
    {ok, #{status := up, faults := Faults}} = cell_hal:info(plc),
    ?assertEqual([{mixed, nothing}, {mixed, nowhere}], [P || #{point := P} <- Faults]),
    Line = await_log(<<"MAIN.DoesNotExist">>),
    ct:log("operator sees: ~ts", [Line]),
    ?assertNotEqual(nomatch, binary:match(Line, <<"mixed.nothing">>)),
    %% polls go on for the rest
    set(Config, "MAIN.counter", <<43:32/little>>),
    43 = await_value(mixed, counter, 43),
    set(Config, "MAIN.counter", <<42:32/little>>),
    ok = cell_log:unsubscribe().

%% After a program change (a new symbol version) what was missing is asked for again:
%% an input comes back with its value, an output with what the PLC holds.
symbol_version_change_retries(Config) ->
    Fake = fake(Config),
    ok = connect(Config),
    ok = group(later, #{kind => list, input_struct => <<"MAIN">>, output_struct => <<"MAIN">>,
                        points => [{counter, in, int32, <<".counter">>},
                                   {later_in, in, int32, <<".LaterIn">>},
                                   {later_out, out, int16, <<".LaterOut">>}]}),
    ok = up([later]),
    {error, {unavailable, _}} = cell_hal:read(later, later_in),
    {error, {unavailable, _}} = cell_hal:read(later, later_out),
    ok = cell_log:subscribe(),
    ok = add(Fake, "MAIN.LaterIn", "DINT", 3, <<1234:32/little>>, ""),
    ok = add(Fake, "MAIN.LaterOut", "INT", 2, <<-9:16/little-signed>>, ""),
    ok = cell_hal_ads_peer:cmd(Fake, "bump"),
    {ok, 1234} = await(later, later_in, fun(R) -> R =:= {ok, 1234} end),
    {ok, -9} = await(later, later_out, fun(R) -> R =:= {ok, -9} end),
    _ = await_log(<<"can be used again">>),
    ok = cell_log:unsubscribe(),
    ok = cell_hal:write_sync(later, later_out, 300, ?WAIT),
    ?assertEqual(<<300:16/little>>, value(Config, "MAIN.LaterOut")),
    {ok, #{faults := []}} = cell_hal:info(plc),
    ?assertEqual(up, cell_hal:status(plc)),
    ok = cell_hal_ads_peer:cmd(Fake, "remove MAIN.LaterIn"),
    {error, {unavailable, Gone}} =
        await(later, later_in, fun(R) -> element(1, R) =:= error end),
    ct:log("~ts", [Gone]),
    {ok, 42} = cell_hal:read(later, counter),
    ok = cell_hal_ads_peer:cmd(Fake, "remove MAIN.LaterOut").

%% A symbol whose type changed with a download: the point says which types differ,
%% the rest works on; changed back, the point is read again.
retyped_symbol(Config) ->
    Fake = fake(Config),
    ok = connect(Config),
    ok = group(typed, #{kind => list, input_struct => <<"MAIN">>,
                        points => [{retyped, in, int32, <<".retyped">>},
                                   {counter, in, int32, <<".counter">>}]}),
    ok = up([typed]),
    {ok, 7} = cell_hal:read(typed, retyped),
    ok = cell_hal_ads_peer:cmd(Fake, "retype MAIN.retyped INT 2 2 0500"),
    {error, {unavailable, Why}} = await(typed, retyped, fun(R) -> element(1, R) =:= error end),
    ?assertEqual(<<"symbol MAIN.retyped is INT (2 bytes) in the PLC, but the configuration "
                   "expects DINT">>, Why),
    ?assertEqual(up, cell_hal:status(plc)),
    set(Config, "MAIN.counter", <<44:32/little>>),
    44 = await_value(typed, counter, 44),
    ok = cell_hal_ads_peer:cmd(Fake, "retype MAIN.retyped DINT 3 4 07000000"),
    {ok, 7} = await(typed, retyped, fun(R) -> R =:= {ok, 7} end),
    set(Config, "MAIN.counter", <<42:32/little>>).

%% Diagnostics: raw ADS requests through the HAL.
raw_requests(Config) ->
    ok = connect(Config),
    ok = group(io, #{kind => list, input_struct => <<"MAIN">>,
                     points => [{counter, in, int32, <<".counter">>}]}),
    ok = up([io]),
    {ok, #{ads_state := run}} = cell_hal:request(plc, read_state, 1000),
    {ok, #{name := <<"Fake PLC">>}} = cell_hal:request(plc, read_device_info, 1000),
    {ok, Symbols} = cell_hal:request(plc, symbols, 5000),
    #{group := G, offset := O} = hd([S || #{name := <<"MAIN.counter">>} = S <- Symbols]),
    {ok, <<42:32/little>>} = cell_hal:request(plc, {read, G, O, 4}, 1000),
    {ok, ok} = cell_hal:request(plc, {write, G, O, <<42:32/little>>}, 1000),
    {error, {bad_request, {launch, rockets}}} = cell_hal:request(plc, {launch, rockets}, 1000).

%% Faults in the configuration are refused at the door, naming the point.
bad_configuration(Config) ->
    Base = #{host => "127.0.0.1", port => ?config(port, Config), target_net_id => ?NET},
    Add = fun(Opts) -> cell_hal:add_connection(#{id => bad, driver => cell_hal_ads,
                                                 opts => Opts}) end,
    {error, {bad_option, target_net_id}} = Add(maps:remove(target_net_id, Base)),
    {error, {bad_option, host}} = Add(maps:remove(host, Base)),
    {error, {bad_option, timeout_ms}} = Add(Base#{timeout_ms => 0}),
    {error, {bad_option, reconnect}} = Add(Base#{reconnect => true}),
    {error, {bad_option, access}} = Add(Base#{access => symbol}),
    {error, {bad_option, colour}} = Add(Base#{colour => red}),
    ok = connect(Config),
    Point = [{x, out, bool, <<".X">>}],
    {error, {bad_point, x, {field, {notify, output}}}} =
        cell_hal:add_group(#{id => g, module => cell_hal_ads_test_io, connection => plc,
                             opts => #{kind => list, output_struct => <<"MAIN">>,
                                       notify => [x], points => Point}}),
    {error, {bad_point, x, {field, notify_opts}}} =
        cell_hal:add_group(#{id => g, module => cell_hal_ads_test_io, connection => plc,
                             opts => #{kind => list, output_struct => <<"MAIN">>,
                                       notify_opts => #{mode => sometimes}, points => Point}}),
    {error, {bad_point, x, {field, output_struct}}} =
        cell_hal:add_group(#{id => g, module => cell_hal_ads_test_io, connection => plc,
                             opts => #{kind => list, points => Point}}),
    {error, {bad_point, y, {field, bad_field}}} =
        cell_hal:add_group(#{id => g, module => cell_hal_ads_test_io, connection => plc,
                             opts => #{kind => list, points => [{y, in, bool, {coil, 1}}]}}),
    [] = cell_hal:groups().

%% A frame that cannot be read closes that connection only, with the reason in words;
%% the HAL connects again and nothing else stopped.
garbage_closes_only_the_connection(Config) ->
    ok = connect(Config),
    ok = group(io, #{kind => list, input_struct => <<"MAIN">>,
                     points => [{counter, in, int32, <<".counter">>}]}),
    ok = up([io]),
    Worker = worker(plc),
    ok = cell_log:subscribe(),
    %% an AMS/TCP length of 4: shorter than an AMS header
    ok = cell_hal_ads_peer:cmd(fake(Config), "garbage 000004000000deadbeef"),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    Line = await_log(<<"lost">>),
    ct:log("operator sees: ~ts", [Line]),
    ?assertNotEqual(nomatch, binary:match(Line, <<"malformed frame">>)),
    ok = await_status(up),
    {ok, 42} = cell_hal:read(io, counter),
    ?assertEqual(Worker, worker(plc)),
    %% a frame longer than allowed: the same, the worker connecting again
    flush(),
    ok = cell_hal_ads_peer:cmd(fake(Config), "garbage 0000ffffff7f"),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    Line2 = await_log(<<"lost">>),
    ct:log("operator sees: ~ts", [Line2]),
    ?assertNotEqual(nomatch, binary:match(Line2, <<"more than allowed">>)),
    ok = await_status(up),
    {ok, 42} = cell_hal:read(io, counter),
    ?assertEqual(Worker, worker(plc)),
    ok = cell_log:unsubscribe().

%% A group removed and added again under its name, its point now on another symbol:
%% the point shows the new symbol only, never the old one's notifications.
group_added_again(Config) ->
    set(Config, "MAIN.AxisPos", <<1.0:64/float-little>>),
    set(Config, "MAIN.counter", <<42:32/little>>),
    ok = connect(Config),
    ok = group(g, #{kind => list, input_struct => <<"MAIN">>, notify => all,
                    points => [{x, in, lreal, <<".AxisPos">>}]}),
    ok = up([g]),
    {ok, 1.0} = cell_hal:read(g, x),
    ok = cell_hal:remove_group(g),
    ok = group(g, #{kind => list, input_struct => <<"MAIN">>,
                    points => [{x, in, int32, <<".counter">>}]}),
    ok = up([g]),
    {ok, 42} = cell_hal:read(g, x),
    ok = cell_hal:subscribe(g, x),
    %% the old symbol changes first, then the new one: once the new value is seen, the
    %% old one's notification (sent before it on the same stream) was handled
    set(Config, "MAIN.AxisPos", <<12.5:64/float-little>>),
    set(Config, "MAIN.counter", <<43:32/little>>),
    receive {cell_hal, {g, x}, V} -> ?assertEqual(43, V) after ?WAIT -> ct:fail(no_change) end,
    {ok, 43} = cell_hal:read(g, x),
    set(Config, "MAIN.counter", <<42:32/little>>),
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>).

%% The worker of a connection (the connection's id is its child id).
worker(Conn) ->
    [Pid] = [P || {Id, P, _, _} <- supervisor:which_children(cell_hal_conn_sup), Id =:= Conn],
    Pid.

%%--------------------------------------------------------------------
%% restart: the PLC goes away and comes back
%%--------------------------------------------------------------------

%% A restarted PLC knows no handles or notifications: the HAL goes down at once (no
%% input reads as fresh meanwhile), comes up again only after a complete first read
%% with new handles and notifications, and shows the new PLC's values.
plc_restart(Config) ->
    Start = fun(Args, Values) ->
                    {ok, F, {ready, P, _}} = cell_hal_ads_peer:start("fake_plc.py", Args),
                    [ok = add(F, N, T, A, V, "") || {N, T, A, V} <- Values],
                    {F, P}
            end,
    Before = [{"MAIN.counter", "DINT", 3, <<42:32/little>>},
              {"MAIN.AxisPos", "LREAL", 5, <<1.0:64/float-little>>},
              {"MAIN.light", "BOOL", 33, <<1>>}],
    {Fake1, Port} = Start(["--handle-base", "5000"], Before),
    ok = connect([{port, Port} | Config]),
    ok = group(line, #{kind => list, input_struct => <<"MAIN">>, output_struct => <<"MAIN">>,
                       notify => [pos],
                       points => [{counter, in, int32, <<".counter">>},
                                  {pos, in, lreal, <<".AxisPos">>},
                                  {light, out, bool, <<".light">>}]}),
    ok = up([line]),
    {ok, 42} = cell_hal:read(line, counter),
    {ok, 1.0} = cell_hal:read(line, pos),
    {ok, true} = cell_hal:read(line, light),
    ok = cell_hal_ads_peer:stop(Fake1),
    receive {cell_hal_conn, plc, down} -> ok after ?WAIT -> ct:fail(not_down) end,
    {error, disconnected} = cell_hal:read(line, counter),
    {error, disconnected} = cell_hal:read(line, pos),
    {error, disconnected} = cell_hal:write(line, light, false),
    {error, disconnected} = cell_hal:samples(line, pos, 0),
    After = [{"MAIN.counter", "DINT", 3, <<7:32/little>>},
             {"MAIN.AxisPos", "LREAL", 5, <<2.0:64/float-little>>},
             {"MAIN.light", "BOOL", 33, <<0>>}],
    %% it answers once its program is loaded
    {Fake2, Port} = Start(["--port", integer_to_list(Port), "--handle-base", "9000",
                           "--muted"], After),
    ok = cell_hal_ads_peer:cmd(Fake2, "unmute"),
    receive {cell_hal_conn, plc, up} -> ok after ?WAIT -> ct:fail(not_up) end,
    %% fresh at once: the values of the new PLC, the output as it holds it
    {ok, 7} = cell_hal:read(line, counter),
    {ok, 2.0} = cell_hal:read(line, pos),
    {ok, false} = cell_hal:read(line, light),
    {ok, #{acquired := Acquired, notes := Notes}} = cell_hal_ads_peer:cmd(Fake2, "stats"),
    ?assert(Acquired >= 2),
    ?assert(Notes >= 2),     %% ours and the symbol version's
    %% notifications back: a change arrives without polling
    ok = cell_hal_ads_peer:cmd(Fake2, "set MAIN.AxisPos " ++
                                   binary_to_list(binary:encode_hex(<<3.5:64/float-little>>))),
    3.5 = await_value(line, pos, 3.5),
    ok = cell_hal:write_sync(line, light, true, ?WAIT),
    {ok, <<1>>} = cell_hal_ads_peer:cmd(Fake2, "get MAIN.light"),
    ok = cell_hal:remove_group(line),
    ok = cell_hal:remove_connection(plc),
    ok = cell_hal_ads_peer:stop(Fake2).

%% Nothing listens yet: the connection is down with the reason, its inputs read
%% `disconnected', and the worker keeps trying with its back-off; once the PLC listens
%% the back-off reaches it, and the group is read.
connection_refused_then_up(Config) ->
    {ok, Probe} = gen_tcp:listen(0, [{ip, {127, 0, 0, 1}}]),
    {ok, Port} = inet:port(Probe),
    ok = gen_tcp:close(Probe),
    ok = cell_log:subscribe(),
    ok = connect([{port, Port} | Config]),
    ok = group(line, #{kind => list, input_struct => <<"MAIN">>,
                       points => [{counter, in, int32, <<".counter">>}]}),
    Line = await_log(<<"connection refused">>),
    ct:log("operator sees: ~ts", [Line]),
    ?assertEqual(down, cell_hal:status(plc)),
    {error, disconnected} = cell_hal:read(line, counter),
    %% it answers once its program is loaded
    {ok, Fake, {ready, Port, _}} = cell_hal_ads_peer:start(
                                     "fake_plc.py", ["--port", integer_to_list(Port), "--muted"]),
    ok = add(Fake, "MAIN.counter", "DINT", 3, <<42:32/little>>, ""),
    ok = cell_hal_ads_peer:cmd(Fake, "unmute"),
    ok = up([line]),
    {ok, 42} = cell_hal:read(line, counter),
    ok = cell_log:unsubscribe(),
    ok = cell_hal:remove_group(line),
    ok = cell_hal:remove_connection(plc),
    ok = cell_hal_ads_peer:stop(Fake).

%%--------------------------------------------------------------------
%% pyads: the HAL over pyads' own test server
%%--------------------------------------------------------------------

%% The test server knows no sum commands on handles and takes one request at a time:
%% the group is read point by point, still through the HAL.
pyads_group(Config) ->
    ok = connect(Config, plc, #{max_in_flight => 1, sum_commands => false}),
    ok = group(io, #{kind => list, input_struct => <<"MAIN">>, output_struct => <<"MAIN">>,
                     points => [{counter, in, int32, <<".counter">>},
                                {speed, in, lreal, <<".speed">>},
                                {text, in, {string, 10}, <<".text">>},
                                {flag, out, bool, <<".flag">>},
                                {setpoint, out, uint16, <<".setpoint">>}]}),
    ok = up([io]),
    {ok, 42} = cell_hal:read(io, counter),
    {ok, 10.0} = cell_hal:read(io, speed),
    {ok, <<"abc">>} = cell_hal:read(io, text),
    {ok, false} = cell_hal:read(io, flag),
    {ok, 7} = cell_hal:read(io, setpoint),
    ok = cell_hal:write_sync(io, flag, true, ?WAIT),
    ok = cell_hal:write_sync(io, setpoint, 65535, ?WAIT),
    ?assertEqual(<<1>>, value(Config, "MAIN.flag")),
    ?assertEqual(<<65535:16/little>>, value(Config, "MAIN.setpoint")),
    {ok, #{faults := []}} = cell_hal:info(plc),
    ok = cell_hal:write_sync(io, flag, false, ?WAIT).
