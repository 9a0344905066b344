%% Hardware objects (seed 000 §4.2): the factory driven by settings, and the simulated
%% camera, code reader and laser marker behind their kinds' interfaces.
-module(cell_hal_hw_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, end_per_testcase/2]).
-export([factory_from_settings/1, factory_refuses_bad_settings/1, cell_specific_types/1,
         camera_grabs/1, code_reader_reads/1, laser_marker_marks/1, connectivity/1,
         wrong_kind_or_absent/1, remove_stops_the_object/1, watchers_hear_of_changes/1]).

-define(WAIT, 5000).

all() ->
    [factory_from_settings, factory_refuses_bad_settings, cell_specific_types, camera_grabs,
     code_reader_reads, laser_marker_marks, connectivity, wrong_kind_or_absent,
     remove_stops_the_object, watchers_hear_of_changes].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

end_per_testcase(_Case, _Config) ->
    [ok = cell_hal_hw:remove(Id) || {Id, _, _} <- cell_hal_hw:list()],
    ok.

settings() ->
    #{camera => #{type => sim, opts => #{width => 16, height => 8, exposure_ms => 30}},
      code_reader => #{type => sim, opts => #{decode_ms => 20, read_window_ms => 100}},
      laser_marker => #{type => sim, opts => #{setup_ms => 20, ms_per_char => 2}}}.

factory_from_settings(_Config) ->
    ok = cell_hal_hw:from_settings((settings())#{laser_marker := #{type => none}}),
    ?assertEqual([{camera, camera, cell_hal_camera_sim},
                  {code_reader, code_reader, cell_hal_code_reader_sim}], cell_hal_hw:list()),
    ?assert(cell_hal_hw:present(camera)),
    %% `none' is the seed's null: the machine has no such hardware.
    ?assertNot(cell_hal_hw:present(laser_marker)),
    ?assertEqual({error, not_present}, cell_hal_laser_marker:mark(laser_marker, #{text => <<"X">>}, 1000)),
    %% An object whose id is not its kind names it.
    ok = cell_hal_hw:from_settings(#{top_camera => #{kind => camera, type => sim}}),
    ?assertMatch({ok, #{width := 320, height := 240}}, cell_hal_camera:grab(top_camera, ?WAIT)).

factory_refuses_bad_settings(_Config) ->
    ?assertEqual({error, {camera, {bad_option, type}}},
                 cell_hal_hw:from_settings(#{camera => #{type => ueye}})),
    ?assertEqual({error, {camera, {bad_option, width}}},
                 cell_hal_hw:from_settings(#{camera => #{type => sim, opts => #{width => 0}}})),
    ?assertEqual({error, {camera, {bad_option, exposure}}},
                 cell_hal_hw:from_settings(#{camera => #{type => sim, opts => #{exposure => 1}}})),
    ?assertEqual({error, {printer, {bad_option, kind}}},
                 cell_hal_hw:from_settings(#{printer => #{type => sim}})),
    ?assertEqual({error, {camera, {bad_option, spec}}}, cell_hal_hw:from_settings(#{camera => sim})),
    ?assertEqual({error, {bad_option, type}}, cell_hal_hw:add(#{id => c, kind => camera})),
    ?assertEqual({error, {bad_option, id}}, cell_hal_hw:add(#{id => "c", kind => camera, type => sim})),
    ?assertEqual({error, {bad_option, opts}},
                 cell_hal_hw:add(#{id => c, kind => camera, type => sim, opts => []})),
    ok = cell_hal_hw:add(#{id => c, kind => camera, type => sim}),
    ?assertEqual({error, {already_exists, c}}, cell_hal_hw:add(#{id => c, kind => camera, type => sim})).

%% A cell registers its own implementations by type.
cell_specific_types(_Config) ->
    ok = application:set_env(cell_hal, hardware_types, #{{code_reader, acme} => cell_hal_code_reader_sim}),
    try
        ok = cell_hal_hw:from_settings(#{code_reader => #{type => acme}}),
        ?assertEqual([{code_reader, code_reader, cell_hal_code_reader_sim}], cell_hal_hw:list())
    after
        application:unset_env(cell_hal, hardware_types)
    end.

camera_grabs(_Config) ->
    ok = cell_hal_hw:from_settings(settings()),
    T0 = erlang:monotonic_time(millisecond),
    {ok, #{width := 16, height := 8, format := mono8, data := D1, seq := 0}} =
        cell_hal_camera:grab(camera, ?WAIT),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 30),
    ?assertEqual(16 * 8, byte_size(D1)),
    {ok, #{data := D2, seq := 1}} = cell_hal_camera:grab(camera, ?WAIT),
    ?assertNotEqual(D1, D2),
    %% What the simulation shows it, the camera sees.
    Scene = binary:copy(<<200>>, 16 * 8),
    ok = cell_hal_camera_sim:show(camera, Scene),
    {ok, #{data := Scene}} = cell_hal_camera:grab(camera, ?WAIT),
    ?assertEqual({error, bad_scene}, cell_hal_camera_sim:show(camera, <<1, 2, 3>>)),
    %% Grabs asked at once are served in turn, one exposure each.
    Self = self(),
    T1 = erlang:monotonic_time(millisecond),
    [spawn_link(fun() -> Self ! {grabbed, cell_hal_camera:grab(camera, ?WAIT)} end)
     || _ <- [1, 2, 3]],
    Seqs = [receive {grabbed, {ok, #{seq := Seq}}} -> Seq after ?WAIT -> ct:fail(no_image) end
            || _ <- [1, 2, 3]],
    ?assertEqual([3, 4, 5], lists:sort(Seqs)),
    ?assert(erlang:monotonic_time(millisecond) - T1 >= 3 * 30),
    %% The caller's deadline holds; the device finishes that grab before the next.
    ?assertEqual({error, timeout}, cell_hal_camera:grab(camera, #{exposure_ms => 500}, 50)),
    ok = cell_hal_camera_sim:fail_next(camera, trigger_lost),
    ?assertEqual({error, trigger_lost}, cell_hal_camera:grab(camera, ?WAIT)),
    {ok, #{seq := 7}} = cell_hal_camera:grab(camera, ?WAIT).

code_reader_reads(_Config) ->
    ok = cell_hal_hw:from_settings(settings()),
    T0 = erlang:monotonic_time(millisecond),
    ?assertEqual({error, no_read}, cell_hal_code_reader:read(code_reader, ?WAIT)),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 100),
    ok = cell_hal_code_reader_sim:present(code_reader, <<"PCB-000123">>),
    ?assertEqual({ok, <<"PCB-000123">>}, cell_hal_code_reader:read(code_reader, ?WAIT)),
    Ref = cell_hal_code_reader:read_async(code_reader),
    receive {Ref, R} -> ?assertEqual({ok, <<"PCB-000123">>}, R) after ?WAIT -> ct:fail(no_answer) end,
    ok = cell_hal_code_reader_sim:fail_next(code_reader, dirty_lens),
    ?assertEqual({error, dirty_lens}, cell_hal_code_reader:read(code_reader, ?WAIT)),
    ?assertEqual({ok, <<"PCB-000123">>}, cell_hal_code_reader:read(code_reader, ?WAIT)),
    ok = cell_hal_code_reader_sim:present(code_reader, none),
    ?assertEqual({error, no_read}, cell_hal_code_reader:read(code_reader, ?WAIT)).

laser_marker_marks(_Config) ->
    ok = cell_hal_hw:from_settings(settings()),
    T0 = erlang:monotonic_time(millisecond),
    ok = cell_hal_laser_marker:mark(laser_marker, #{text => <<"SN0001">>}, ?WAIT),
    ?assert(erlang:monotonic_time(millisecond) - T0 >= 20 + 2 * 6),
    ok = cell_hal_laser_marker:mark(laser_marker, #{text => <<"SN0002">>, layout => <<"L1">>}, ?WAIT),
    ?assertEqual([#{text => <<"SN0001">>}, #{text => <<"SN0002">>, layout => <<"L1">>}],
                 cell_hal_laser_marker_sim:marks(laser_marker)),
    ?assertEqual({error, {bad_job, text}}, cell_hal_laser_marker:mark(laser_marker, #{text => <<>>}, ?WAIT)),
    ?assertEqual({error, {bad_job, text}}, cell_hal_laser_marker:mark(laser_marker, #{}, ?WAIT)),
    ?assertEqual({error, {bad_job, power}},
                 cell_hal_laser_marker:mark(laser_marker, #{text => <<"A">>, power => 9}, ?WAIT)),
    ok = cell_hal_laser_marker_sim:fail_next(laser_marker, interlock_open),
    ?assertEqual({error, interlock_open},
                 cell_hal_laser_marker:mark(laser_marker, #{text => <<"SN0003">>}, ?WAIT)),
    ?assertEqual(2, length(cell_hal_laser_marker_sim:marks(laser_marker))).

connectivity(_Config) ->
    ok = cell_hal_hw:from_settings(settings()),
    ?assertEqual({ok, up}, cell_hal_hw:subscribe(camera)),
    ok = cell_hal_camera_sim:set_link(camera, down),
    receive {cell_hal_hw, camera, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    ?assertEqual(down, cell_hal_hw:status(camera)),
    ?assertEqual({error, not_connected}, cell_hal_camera:grab(camera, ?WAIT)),
    ok = cell_hal_camera_sim:set_link(camera, up),
    receive {cell_hal_hw, camera, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    {ok, _} = cell_hal_camera:grab(camera, ?WAIT),
    %% A grab waiting behind one in progress fails when the camera goes away.
    ?assertEqual({error, timeout}, cell_hal_camera:grab(camera, #{exposure_ms => 300}, 1)),
    Self = self(),
    spawn_link(fun() -> Self ! {queued, cell_hal_camera:grab(camera, ?WAIT)} end),
    ok = cell_hal_camera_sim:set_link(camera, down),
    receive {queued, R} -> ?assertEqual({error, not_connected}, R) after ?WAIT -> ct:fail(stuck) end,
    receive {cell_hal_hw, camera, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    ok = cell_hal_camera_sim:set_link(camera, up),
    receive {cell_hal_hw, camera, up} -> ok after ?WAIT -> ct:fail(no_up) end,
    ok = cell_hal_hw:unsubscribe(camera),
    ok = cell_hal_camera_sim:set_link(camera, down),
    ?assertEqual(down, cell_hal_hw:status(camera)),
    receive {cell_hal_hw, camera, _} = M -> ct:fail({after_unsubscribe, M}) after 0 -> ok end.

wrong_kind_or_absent(_Config) ->
    ok = cell_hal_hw:from_settings(settings()),
    ?assertEqual({error, not_present}, cell_hal_camera:grab(code_reader, ?WAIT)),
    ?assertEqual({error, not_present}, cell_hal_code_reader:read(camera, ?WAIT)),
    ?assertEqual({error, not_present}, cell_hal_code_reader:read(nothing, ?WAIT)),
    %% Asked without waiting: answered as a message all the same.
    Ref = cell_hal_code_reader:read_async(nothing),
    receive {Ref, R} -> ?assertEqual({error, not_present}, R) after ?WAIT -> ct:fail(no_answer) end,
    Ref2 = cell_hal_code_reader:read_async(camera),
    receive {Ref2, R2} -> ?assertEqual({error, not_present}, R2) after ?WAIT -> ct:fail(no_answer) end,
    ?assertEqual({error, not_present}, cell_hal_hw:status(nothing)),
    ?assertEqual({error, not_present}, cell_hal_hw:subscribe(nothing)).

remove_stops_the_object(_Config) ->
    ok = cell_hal_hw:from_settings(settings()),
    {ok, up} = cell_hal_hw:subscribe(code_reader),
    ok = cell_hal_hw:remove(code_reader),
    receive {cell_hal_hw, code_reader, down} -> ok after ?WAIT -> ct:fail(no_down) end,
    ?assertNot(cell_hal_hw:present(code_reader)),
    ?assertEqual({error, not_present}, cell_hal_hw:remove(code_reader)).

%% A watcher hears that an axis may have changed: a command it took, the end of its
%% job; never a question of its status (the watcher's own reads would echo forever).
watchers_hear_of_changes(_Config) ->
    ok = cell_hal_hw:from_settings(#{x => #{kind => axis, type => sim}}),
    {ok, Pid} = cell_hal_hw:watch(x),
    ?assert(is_pid(Pid)),
    ?assertEqual({error, not_present}, cell_hal_hw:watch(nothing_here)),
    {ok, _} = cell_hal_axis:status(x),
    {ok, P} = cell_hal_axis:power(x, true),
    receive {cell_hal_hw_changed, x} -> ok after ?WAIT -> ct:fail(no_change_told) end,
    receive {P, done} -> ok after ?WAIT -> ct:fail(not_powered) end,
    flush_changes(),
    {ok, _} = cell_hal_axis:status(x),
    %% The status read is not a change: the next message is the one the override makes.
    ok = cell_hal_axis:set_override(x, 50),
    {ok, #{override := 50}} = cell_hal_axis:status(x),
    {messages, Msgs} = process_info(self(), messages),
    ?assertEqual([{cell_hal_hw_changed, x}], Msgs),
    flush_changes().

flush_changes() ->
    receive {cell_hal_hw_changed, _} -> flush_changes()
    after 0 -> ok
    end.
