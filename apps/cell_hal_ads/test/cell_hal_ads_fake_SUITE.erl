%% The ADS client against the suite's fake TwinCAT PLC (test/peers/fake_plc.py), which
%% serves what pyads' test server does not: symbols and handles, the symbol table and
%% version, sum commands, and device notifications over the wire.
%%
%% The fake is proven first: Beckhoff's AdsLib (through pyads) reads, writes, sum-reads,
%% sum-writes and receives notifications from it (group `proof'). Only if all of that
%% passed do the client's groups run; otherwise they are skipped, which `make test'
%% counts as failures. Then our frames are compared byte for byte with AdsLib's for the
%% same operations (group `crosscheck').
-module(cell_hal_ads_fake_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, groups/0, init_per_suite/1, end_per_suite/1, init_per_group/2,
         end_per_group/2, init_per_testcase/2, end_per_testcase/2]).
-export([adslib_reads_and_writes/1, adslib_symbol_info/1, adslib_sum_reads/1,
         adslib_sum_writes/1, adslib_notifications/1]).
-export([device_info_and_state/1, every_type_round_trip/1, values_agree_with_adslib/1,
         handles_cached_and_released/1, exit_releases_handles/1,
         group_in_one_sum_command/1, sum_split_at_limit/1, sum_beyond_plc_limit/1,
         raw_sum_commands/1, one_by_one_without_sum_commands/1,
         structure_fields_by_name/1, image_wildcards/1, image_by_address/1,
         missing_symbol_is_clear/1, retyped_symbol_is_clear/1,
         removed_symbol_ends_subscription/1, notifications_keep_plc_stamps/1,
         laser_beam_latch/1, cyclic_notifications/1, unsubscribe_deletes_notification/1,
         trigger_enable_by_handle/1, several_requests_in_flight/1,
         timeout_never_blocks_caller/1, garbage_closes_only_the_connection/1,
         oversized_frame_closes_only_the_connection/1, bad_options/1,
         stop_leaves_plc_tidy/1, requests_without_waiting/1,
         one_connection_without_reconnecting/1, stalled_plc_blocks_nobody/1]).
-export([reads_skip_the_connection/1, read_across_program_change/1,
         caller_killed_mid_read/1, connection_lost_mid_read/1, silent_plc_ends_direct_read/1]).
-export([frames_match_adslib/1]).

-define(NET, "127.0.0.1.1.1").
-define(ADSLIB_NET, "10.11.12.13.1.1").
-define(WAIT, 10000).
-define(FILETIME_UNIX_EPOCH, 116444736000000000).

all() ->
    [{group, proof}, {group, client}, {group, direct}, {group, crosscheck}].

groups() ->
    [{proof, [sequence], [adslib_reads_and_writes, adslib_symbol_info, adslib_sum_reads,
                          adslib_sum_writes, adslib_notifications]},
     {client, [], [device_info_and_state, every_type_round_trip, values_agree_with_adslib,
                   handles_cached_and_released, exit_releases_handles,
                   group_in_one_sum_command, sum_split_at_limit, sum_beyond_plc_limit,
                   raw_sum_commands, one_by_one_without_sum_commands,
                   structure_fields_by_name, image_wildcards, image_by_address,
                   missing_symbol_is_clear, retyped_symbol_is_clear,
                   removed_symbol_ends_subscription, notifications_keep_plc_stamps,
                   laser_beam_latch, cyclic_notifications, unsubscribe_deletes_notification,
                   trigger_enable_by_handle, several_requests_in_flight,
                   timeout_never_blocks_caller, garbage_closes_only_the_connection,
                   oversized_frame_closes_only_the_connection, bad_options,
                   stop_leaves_plc_tidy, requests_without_waiting,
                   one_connection_without_reconnecting, stalled_plc_blocks_nobody]},
     {direct, [], [reads_skip_the_connection, read_across_program_change,
                   caller_killed_mid_read, connection_lost_mid_read,
                   silent_plc_ends_direct_read]},
     {crosscheck, [], [frames_match_adslib]}].

%%--------------------------------------------------------------------
%% Setup
%%--------------------------------------------------------------------

init_per_suite(Config) ->
    Root = filename:join(?config(priv_dir, Config), "root"),
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, Root),
    {ok, Apps} = application:ensure_all_started(cell_base),
    case cell_hal_ads_peer:start("fake_plc.py", []) of
        {ok, Fake, {ready, Port, _}} ->
            Symbols = define_symbols(Fake),
            [{apps, Apps}, {fake, Fake}, {port, Port}, {symbols, Symbols} | Config];
        {error, Reason} ->
            ct:fail("the fake PLC did not start: ~tp", [Reason])
    end.

end_per_suite(Config) ->
    ok = cell_hal_ads_peer:stop(?config(fake, Config)),
    Config.

init_per_group(proof, Config) ->
    [{adslib, adslib(Config)} | Config];
init_per_group(_, Config) ->
    case filelib:is_regular(proven(Config)) of
        true -> Config;
        false -> {skip, "the fake PLC was not proven by Beckhoff's AdsLib"}
    end.

end_per_group(proof, Config) ->
    ok = cell_hal_ads_peer:stop(?config(adslib, Config)),
    Results = ?config(tc_group_result, Config),
    case proplists:get_value(failed, Results, []) ++ proplists:get_value(skipped, Results, []) of
        [] -> ok = file:write_file(proven(Config), <<"proven\n">>);
        Failed -> ct:log("the fake PLC is not proven: ~p", [Failed])
    end;
end_per_group(_, _Config) ->
    ok.

init_per_testcase(_Case, Config) ->
    Config.

end_per_testcase(_Case, Config) ->
    %% Settings some cases change on the shared fake go back to normal.
    Fake = ?config(fake, Config),
    ok = cell_hal_ads_peer:cmd(Fake, "unmute"),
    ok = cell_hal_ads_peer:cmd(Fake, "unstall"),
    ok = cell_hal_ads_peer:cmd(Fake, "limit 100000"),
    ok.

proven(Config) ->
    filename:join(?config(priv_dir, Config), "fake_plc_proven").

%% The PLC's variables: every seed type, a structure with fields, IO image names, the
%% laser-beam signals and a 200-point IO group.
define_symbols(Fake) ->
    Scalars = [{"MAIN.counter", "DINT", 3, <<42:32/little>>},
               {"MAIN.flag", "BOOL", 33, <<0>>},
               {"MAIN.pos", "LREAL", 5, <<10.0:64/float-little>>},
               {"MAIN.speed", "REAL", 4, <<1.5:32/float-little>>},
               {"MAIN.b", "BYTE", 17, <<200>>},
               {"MAIN.sb", "SINT", 16, <<-5:8/signed>>},
               {"MAIN.i", "INT", 2, <<-300:16/little-signed>>},
               {"MAIN.w", "WORD", 18, <<60000:16/little>>},
               {"MAIN.dw", "DWORD", 19, <<4000000000:32/little>>},
               {"MAIN.li", "LINT", 20, <<-5000000000:64/little-signed>>},
               {"MAIN.uli", "ULINT", 21, <<10000000000000000000:64/little>>},
               {"MAIN.d", "DATE", 19, <<1700006400:32/little>>},
               {"MAIN.t", "TIME", 19, <<90000:32/little>>},
               {"MAIN.c", "STRING(1)", 30, <<"A", 0>>},
               {"MAIN.name", "STRING(20)", 30, <<"hello", 0:(16 * 8)>>},
               {"MAIN.retyped", "DINT", 3, <<7:32/little>>},
               {"MAIN.removed", "DINT", 3, <<8:32/little>>},
               {"MAIN.StopLoadingSegmentTriggerEnable", "BOOL", 33, <<0>>},
               {"MAIN.LaserBeam", "BOOL", 33, <<0>>},
               {"MAIN.AxisPos", "LREAL", 5, <<0.0:64/float-little>>},
               {"MAIN.GeneralInputs", "GeneralInputs", 65, <<0, 0>>},
               {".GeneralOutputs", "GeneralOutputs", 65, <<0>>},
               {"Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn", "BOOL", 33, <<1>>},
               {"Term 5 (EL1008).ManipulatorInputs.ZAxisCylinder1IsUp", "BOOL", 33, <<0>>},
               {"Term 9 (EL2008).ManipulatorOutputs.ZAxisCylinder1Up", "BOOL", 33, <<0>>},
               {"Term 6 (EL1008).Spare.In", "BOOL", 33, <<0>>},
               {"Term 7 (EL1008).Spare.In", "BOOL", 33, <<0>>}],
    Fields = [{"MAIN.GeneralInputs.StartButton", "BOOL", 33, <<1>>},
              {"MAIN.GeneralInputs.StopButton", "BOOL", 33, <<0>>},
              {".GeneralOutputs.StartButtonLight", "BOOL", 33, <<0>>}],
    Group = [{point(I), "DINT", 3, <<(I * 3):32/little>>} || I <- lists:seq(0, 199)],
    maps:from_list(
      [{list_to_binary(N), add(Fake, N, T, A, V, "")} || {N, T, A, V} <- Scalars ++ Group] ++
      [{list_to_binary(N), add(Fake, N, T, A, V, " nested")} || {N, T, A, V} <- Fields]).

point(I) ->
    lists:flatten(io_lib:format("GVL.Io.P~3..0b", [I])).

add(Fake, Name, Type, Adst, Value, Extra) ->
    {ok, G, O} = cell_hal_ads_peer:cmd(Fake, ["add ", q(Name), " ", Type, " ",
                                              integer_to_list(Adst), " ",
                                              integer_to_list(byte_size(Value)), " ",
                                              hex(Value), Extra]),
    {G, O, byte_size(Value)}.

hex(Bin) ->
    binary:encode_hex(Bin).

%% A name for the fake's command line: spaces as %20.
q(Name) ->
    string:replace(Name, " ", "%20", all).

adslib(Config) ->
    {ok, Peer, {ready, _AmsPort}} =
        cell_hal_ads_peer:start("pyads_client.py",
                                ["--port", integer_to_list(?config(port, Config)),
                                 "--target", ?NET, "--local", ?ADSLIB_NET]),
    Peer.

client(Config) ->
    client(Config, #{}).

client(Config, Extra) ->
    Opts = maps:merge(#{host => "127.0.0.1", port => ?config(port, Config),
                        target_net_id => ?NET, handle_idle => 0},
                      Extra),
    {ok, C} = cell_hal_ads_client:start(Opts),
    stop_with_test(C),
    ok = cell_hal_ads_client:subscribe_status(C),
    %% the present state comes first, before the call returns
    receive
        {cell_hal_ads, C, up} -> ok;
        {cell_hal_ads, C, {down, _}} -> ok = await_status(C, up)
    after 0 -> ct:fail("no present state from ~p", [C])
    end,
    C.

%% The client goes with the test case's process.
stop_with_test(C) ->
    Test = self(),
    _ = spawn(fun() ->
                      Ref = monitor(process, Test),
                      receive {'DOWN', Ref, process, Test, _} -> ok end,
                      catch cell_hal_ads_client:stop(C)
              end),
    ok.

await_status(C, Status) ->
    case cell_hal_ads_peer:await(fun({cell_hal_ads, P, S}) when P =:= C, S =:= Status -> {true, ok};
                                    ({cell_hal_ads, P, {down, _} = S}) when P =:= C,
                                                                           Status =:= down ->
                                         {true, S};
                                    (_) -> false
                                 end, ?WAIT) of
        {ok, _} -> ok;
        {error, timeout} -> ct:fail("client ~p never became ~p", [C, Status])
    end.

%% A round trip through the client's connection: everything it sent before has reached
%% the PLC.
barrier(C) ->
    {ok, _} = cell_hal_ads_client:read_state(C),
    ok.

stats(Config) ->
    {ok, Stats} = cell_hal_ads_peer:cmd(?config(fake, Config), "stats"),
    Stats.

stat(Config, Key) ->
    maps:get(Key, stats(Config), 0).

clear(Config) ->
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "clear").

set(Config, Name, Bin) ->
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), ["set ", q(Name), " ", hex(Bin)]).

value(Config, Name) ->
    {ok, Bin} = cell_hal_ads_peer:cmd(?config(fake, Config), ["get ", q(Name)]),
    Bin.

%%--------------------------------------------------------------------
%% proof: Beckhoff's AdsLib against the fake
%%--------------------------------------------------------------------

adslib_reads_and_writes(Config) ->
    A = ?config(adslib, Config),
    {ok, <<"Fake PLC">>, {3, 1, 4024}} = cell_hal_ads_peer:cmd(A, "info"),
    {ok, 5, 0} = cell_hal_ads_peer:cmd(A, "state"),
    {ok, 42} = cell_hal_ads_peer:cmd(A, "read MAIN.counter DINT"),
    {ok, 10.0} = cell_hal_ads_peer:cmd(A, "read MAIN.pos LREAL"),
    {ok, <<"hello">>} = cell_hal_ads_peer:cmd(A, "read MAIN.name STRING"),
    {ok, -300} = cell_hal_ads_peer:cmd(A, "read MAIN.i INT"),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.counter DINT 1234567"),
    ?assertEqual(<<1234567:32/little>>, value(Config, "MAIN.counter")),
    {ok, 1234567} = cell_hal_ads_peer:cmd(A, "read MAIN.counter DINT"),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.flag BOOL True"),
    ?assertEqual(<<1>>, value(Config, "MAIN.flag")),
    %% by handle, as the seed's trigger pattern does
    {ok, H} = cell_hal_ads_peer:cmd(A, "handle MAIN.pos"),
    ok = cell_hal_ads_peer:cmd(A, ["write_handle ", integer_to_list(H), " LREAL -2.5"]),
    {ok, -2.5} = cell_hal_ads_peer:cmd(A, ["read_handle ", integer_to_list(H), " LREAL"]),
    ok = cell_hal_ads_peer:cmd(A, ["release ", integer_to_list(H)]),
    %% a released handle is gone
    {error, 16#710} = cell_hal_ads_peer:cmd(A, ["read_handle ", integer_to_list(H), " LREAL"]),
    {error, 16#710} = cell_hal_ads_peer:cmd(A, "read MAIN.nothing DINT"),
    %% back as the other cases expect
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.counter DINT 42"),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.flag BOOL False"),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.pos LREAL 10.0").

adslib_symbol_info(Config) ->
    A = ?config(adslib, Config),
    #{<<"MAIN.pos">> := {G, O, 8}} = ?config(symbols, Config),
    {ok, <<"MAIN.pos">>, <<"LREAL">>, G, O, 8, 5} = cell_hal_ads_peer:cmd(A, "info_by_name MAIN.pos"),
    #{<<"MAIN.GeneralInputs.StartButton">> := {G, O2, 1}} = ?config(symbols, Config),
    {ok, <<"MAIN.GeneralInputs.StartButton">>, <<"BOOL">>, G, O2, 1, 33} =
        cell_hal_ads_peer:cmd(A, "info_by_name main.generalinputs.startbutton").

adslib_sum_reads(Config) ->
    A = ?config(adslib, Config),
    Names = [point(I) || I <- lists:seq(0, 199)],
    {ok, Values} = cell_hal_ads_peer:cmd(A, ["sum_read" | [[" ", N] || N <- Names]]),
    ?assertEqual([I * 3 || I <- lists:seq(0, 199)], Values),
    {ok, [42, false, 10.0, <<"hello">>]} =
        cell_hal_ads_peer:cmd(A, "sum_read MAIN.counter MAIN.flag MAIN.pos MAIN.name"),
    set(Config, "MAIN.counter", <<99:32/little>>),
    {ok, [99, 10.0]} = cell_hal_ads_peer:cmd(A, "sum_read MAIN.counter MAIN.pos"),
    set(Config, "MAIN.counter", <<42:32/little>>).

adslib_sum_writes(Config) ->
    A = ?config(adslib, Config),
    {ok, [<<"no error">>, <<"no error">>]} =
        cell_hal_ads_peer:cmd(A, "sum_write MAIN.counter DINT 77 MAIN.pos LREAL 3.5"),
    ?assertEqual(<<77:32/little>>, value(Config, "MAIN.counter")),
    ?assertEqual(<<3.5:64/float-little>>, value(Config, "MAIN.pos")),
    {ok, [77, 3.5]} = cell_hal_ads_peer:cmd(A, "sum_read MAIN.counter MAIN.pos"),
    set(Config, "MAIN.counter", <<42:32/little>>),
    set(Config, "MAIN.pos", <<10.0:64/float-little>>).

adslib_notifications(Config) ->
    A = ?config(adslib, Config),
    ok = cell_hal_ads_peer:listen(A),
    %% on change: the present value first, then every change
    {ok, NH, UH} = cell_hal_ads_peer:cmd(A, "notify MAIN.AxisPos LREAL on_change 10"),
    {ok, _} = await_adslib(NH, fun(V) -> V =:= 0.0 end),
    set(Config, "MAIN.AxisPos", <<12.5:64/float-little>>),
    {ok, _} = await_adslib(NH, fun(V) -> V =:= 12.5 end),
    %% samples of one PLC cycle share a stamp; several stamps in one frame
    {ok, NH2, UH2} = cell_hal_ads_peer:cmd(A, "notify MAIN.LaserBeam BOOL on_change 10"),
    {ok, _} = await_adslib(NH2, fun(V) -> V =:= false end),
    T1 = 133400000000000000,
    T2 = T1 + 10000,
    ok = cell_hal_ads_peer:cmd(?config(fake, Config),
                               ["burst ", integer_to_list(T1), " MAIN.AxisPos ",
                                hex(<<20.0:64/float-little>>), " MAIN.LaserBeam 01 ; ",
                                integer_to_list(T2), " MAIN.AxisPos ",
                                hex(<<21.0:64/float-little>>)]),
    {ok, {T1, 20.0}} = await_adslib(NH, fun(V) -> V =:= 20.0 end),
    {ok, {T1, true}} = await_adslib(NH2, fun(V) -> V =:= true end),
    {ok, {T2, 21.0}} = await_adslib(NH, fun(V) -> V =:= 21.0 end),
    ok = cell_hal_ads_peer:cmd(A, ["del_notify ", integer_to_list(NH), " ", integer_to_list(UH)]),
    ok = cell_hal_ads_peer:cmd(A, ["del_notify ", integer_to_list(NH2), " ",
                                   integer_to_list(UH2)]),
    %% cyclic: a sample every cycle, stamps moving on
    {ok, NH3, UH3} = cell_hal_ads_peer:cmd(A, "notify MAIN.counter DINT cyclic 20"),
    Stamps = [begin {ok, {T, 42}} = await_adslib(NH3, fun(V) -> V =:= 42 end), T end
              || _ <- lists:seq(1, 3)],
    ?assertEqual(lists:usort(Stamps), Stamps),
    ok = cell_hal_ads_peer:cmd(A, ["del_notify ", integer_to_list(NH3), " ",
                                   integer_to_list(UH3)]),
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>),
    set(Config, "MAIN.LaserBeam", <<0>>).

await_adslib(NH, Pred) ->
    case cell_hal_ads_peer:await_event(
           fun({notification, H, T, V}) when H =:= NH -> 
                   case Pred(V) of
                       true -> {true, {T, V}};
                       false -> false
                   end;
              (_) -> false
           end, ?WAIT) of
        {ok, R} -> {ok, R};
        {error, timeout} -> ct:fail("AdsLib got no notification ~p", [NH])
    end.

%%--------------------------------------------------------------------
%% client
%%--------------------------------------------------------------------

device_info_and_state(Config) ->
    C = client(Config),
    {ok, #{name := <<"Fake PLC">>, version := {3, 1, 4024}}} = cell_hal_ads_client:read_device_info(C),
    {ok, #{ads_state := run, device_state := 0}} = cell_hal_ads_client:read_state(C),
    ok = cell_hal_ads_client:write_control(C, stop, 0),
    {ok, #{ads_state := stop}} = cell_hal_ads_client:read_state(C),
    ok = cell_hal_ads_client:write_control(C, run, 0),
    #{state := up, device := #{name := <<"Fake PLC">>}, symbol_version := V,
      target := <<"127.0.0.1.1.1:851">>} = cell_hal_ads_client:status(C),
    ?assert(is_integer(V)).

%% Every seed type, read as the PLC holds it and written back as the PLC expects.
every_type_round_trip(Config) ->
    C = client(Config),
    Cases = [{"MAIN.counter", int32, 42, -7, <<-7:32/little-signed>>},
             {"MAIN.flag", bool, false, true, <<1>>},
             {"MAIN.pos", lreal, 10.0, -0.125, <<-0.125:64/float-little>>},
             {"MAIN.speed", real, 1.5, 2.25, <<2.25:32/float-little>>},
             {"MAIN.b", byte, 200, 255, <<255>>},
             {"MAIN.sb", sbyte, -5, -128, <<-128:8/signed>>},
             {"MAIN.i", int16, -300, 32767, <<32767:16/little>>},
             {"MAIN.w", uint16, 60000, 65535, <<65535:16/little>>},
             {"MAIN.dw", uint32, 4000000000, 1, <<1:32/little>>},
             {"MAIN.li", int64, -5000000000, -1, <<-1:64/little-signed>>},
             {"MAIN.uli", uint64, 10000000000000000000, 16#FFFFFFFFFFFFFFFF,
              <<16#FFFFFFFFFFFFFFFF:64/little>>},
             {"MAIN.d", date, {2023, 11, 15}, {1970, 1, 2}, <<86400:32/little>>},
             {"MAIN.t", time, 90000, 1500, <<1500:32/little>>},
             {"MAIN.c", char, $A, $z, <<"z", 0>>},
             {"MAIN.name", {string, 20}, <<"hello">>, <<"abc">>, <<"abc", 0:(18 * 8)>>}],
    Vars = [{list_to_binary(N), T} || {N, T, _, _, _} <- Cases],
    {ok, Infos} = cell_hal_ads_client:resolve(C, Vars),
    [{ok, #{size := _}} = I || I <- Infos],
    {ok, Before} = cell_hal_ads_client:read_vars(C, Vars),
    ?assertEqual([{ok, V} || {_, _, V, _, _} <- Cases], Before),
    {ok, Written} = cell_hal_ads_client:write_vars(C, [{V, New} || {V, {_, _, _, New, _}}
                                                                      <- lists:zip(Vars, Cases)]),
    ?assertEqual([ok || _ <- Cases], Written),
    [?assertEqual(Bytes, value(Config, N)) || {N, _, _, _, Bytes} <- Cases],
    {ok, After} = cell_hal_ads_client:read_vars(C, Vars),
    ?assertEqual([{ok, New} || {_, _, _, New, _} <- Cases], After),
    %% a value that does not fit is refused for that variable only, nothing is sent
    {ok, [{error, {bad_value, int16, 40000}}, ok]} =
        cell_hal_ads_client:write_vars(C, [{{<<"MAIN.i">>, int16}, 40000},
                                           {{<<"MAIN.b">>, byte}, 1}]),
    ?assertEqual(<<32767:16/little>>, value(Config, "MAIN.i")),
    %% the PLC's old values back for the other cases
    {ok, _} = cell_hal_ads_client:write_vars(C, [{V, Old} || {V, {_, _, Old, _, _}}
                                                                 <- lists:zip(Vars, Cases)]).

%% What we write AdsLib reads, and the other way round.
values_agree_with_adslib(Config) ->
    A = adslib(Config),
    C = client(Config),
    Var = {<<"MAIN.counter">>, int32},
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Var]),
    {ok, [ok]} = cell_hal_ads_client:write_vars(C, [{Var, -123456}]),
    {ok, -123456} = cell_hal_ads_peer:cmd(A, "read MAIN.counter DINT"),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.counter DINT 654321"),
    {ok, [{ok, 654321}]} = cell_hal_ads_client:read_vars(C, [Var]),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.name STRING 'fromAdsLib'"),
    {ok, <<"fromAdsLib">>} = cell_hal_ads_client:read_by_name(C, <<"MAIN.name">>, {string, 20}),
    ok = cell_hal_ads_client:write_by_name(C, <<"MAIN.name">>, {string, 20}, <<"hello">>),
    {ok, <<"hello">>} = cell_hal_ads_peer:cmd(A, "read MAIN.name STRING"),
    ok = cell_hal_ads_peer:cmd(A, "write MAIN.counter DINT 42"),
    ok = cell_hal_ads_peer:stop(A).

%% One handle per variable and connection, shared by every caller; back to the PLC when
%% the last one releases it.
handles_cached_and_released(Config) ->
    C = client(Config),
    Var = {<<"MAIN.speed">>, real},
    clear(Config),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Var]),
    Other = spawn_user(C, [Var]),
    {ok, [{ok, _}, {ok, _}]} = cell_hal_ads_client:resolve(C, [Var, Var]),
    ?assertEqual(1, stat(Config, acquired)),
    ok = cell_hal_ads_client:release(C, [Var, Var]),
    ok = cell_hal_ads_client:release(C, [Var]),
    ok = barrier(C),
    ?assertEqual(0, stat(Config, released)),        % the other process still uses it
    {ok, [{ok, 1.5}]} = cell_hal_ads_client:read_vars(C, [Var]),
    ok = release_user(Other, [Var]),
    ok = barrier(C),
    ?assertEqual(1, stat(Config, released)),
    ?assertEqual(1, stat(Config, acquired)),
    %% released: not readable until resolved again
    {ok, [{error, {not_resolved, <<"MAIN.speed">>}}]} = cell_hal_ads_client:read_vars(C, [Var]).

%% A process that exits gives its variables back.
exit_releases_handles(Config) ->
    C = client(Config),
    Var = {<<"MAIN.w">>, uint16},
    clear(Config),
    Pid = spawn_user(C, [Var]),
    ?assertEqual(1, stat(Config, acquired)),
    Ref = monitor(process, Pid),
    Pid ! stop,
    receive {'DOWN', Ref, process, Pid, _} -> ok after ?WAIT -> ct:fail(no_exit) end,
    %% The client hears of the exit on its own; the PLC sees the handle come back.
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "wait_stat released 1 10000"),
    #{variables := 0} = cell_hal_ads_client:status(C).

spawn_user(C, Vars) ->
    Parent = self(),
    Pid = spawn(fun() ->
                        {ok, Results} = cell_hal_ads_client:resolve(C, Vars),
                        Parent ! {resolved, self(), Results},
                        user_loop(C)
                end),
    receive {resolved, Pid, Results} -> [{ok, _} = R || R <- Results], Pid
    after ?WAIT -> ct:fail(no_resolve)
    end.

user_loop(C) ->
    receive
        {release, From, Vars} -> From ! {released, cell_hal_ads_client:release(C, Vars)},
                                 user_loop(C);
        stop -> ok
    end.

release_user(Pid, Vars) ->
    Pid ! {release, self(), Vars},
    receive {released, R} -> R after ?WAIT -> ct:fail(no_release) end.

group() ->
    [{list_to_binary(point(I)), int32} || I <- lists:seq(0, 199)].

%% A 200-point IO group: resolved in two round trips (symbol info, handles), read in one.
group_in_one_sum_command(Config) ->
    C = client(Config),
    clear(Config),
    {ok, Infos} = cell_hal_ads_client:resolve(C, group()),
    ?assertEqual(200, length([ok || {ok, _} <- Infos])),
    ?assertEqual(2, stat(Config, sums)),
    ?assertEqual(200, stat(Config, acquired)),
    clear(Config),
    {ok, Values} = cell_hal_ads_client:read_vars(C, group()),
    ?assertEqual([{ok, I * 3} || I <- lists:seq(0, 199)], Values),
    ?assertEqual(#{sums => 1, sub_commands => 200, requests => 1},
                 maps:with([sums, sub_commands, requests], stats(Config))),
    clear(Config),
    {ok, Oks} = cell_hal_ads_client:write_vars(C, [{V, -I} || {I, V} <- lists:zip(lists:seq(0, 199), group())]),
    ?assertEqual([ok || _ <- Oks], Oks),
    ?assertEqual(1, stat(Config, sums)),
    {ok, Neg} = cell_hal_ads_client:read_vars(C, group()),
    ?assertEqual([{ok, -I} || I <- lists:seq(0, 199)], Neg),
    {ok, _} = cell_hal_ads_client:write_vars(C, [{V, I * 3} || {I, V} <- lists:zip(lists:seq(0, 199), group())]).

%% Split only where the limit requires: 50 in one, 51 in two, 200 in four.
sum_split_at_limit(Config) ->
    C = client(Config, #{max_sum => 50}),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "limit 50"),
    {ok, _} = cell_hal_ads_client:resolve(C, group()),
    [begin
         clear(Config),
         {ok, Values} = cell_hal_ads_client:read_vars(C, lists:sublist(group(), N)),
         ?assertEqual([{ok, I * 3} || I <- lists:seq(0, N - 1)], Values),
         ?assertEqual(Expected, maps:with([sums, sub_commands, requests], stats(Config)))
     end || {N, Expected} <- [{50, #{sums => 1, sub_commands => 50, requests => 1}},
                              %% the one left over is a plain read
                              {51, #{sums => 1, sub_commands => 50, requests => 2}},
                              {101, #{sums => 2, sub_commands => 100, requests => 3}},
                              {200, #{sums => 4, sub_commands => 200, requests => 4}}]],
    %% one item is a plain read, not a sum of one
    clear(Config),
    {ok, [{ok, 0}]} = cell_hal_ads_client:read_vars(C, lists:sublist(group(), 1)),
    ?assertEqual(0, stat(Config, sums)).

%% A PLC with a lower limit than configured refuses the sum: each point says so.
sum_beyond_plc_limit(Config) ->
    C = client(Config),
    {ok, _} = cell_hal_ads_client:resolve(C, group()),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "limit 100"),
    {ok, Values} = cell_hal_ads_client:read_vars(C, group()),
    ?assertEqual([{error, {ads_error, 16#705, invalid_size}} || _ <- group()], Values),
    #{state := up} = cell_hal_ads_client:status(C).

%% Sum commands by index group and offset, and what a failed sub-command gives.
raw_sum_commands(Config) ->
    C = client(Config),
    #{<<"MAIN.counter">> := {G, O1, 4}, <<"MAIN.pos">> := {G, O2, 8}} = ?config(symbols, Config),
    {ok, [{ok, <<42:32/little>>}, {ok, <<10.0:64/float-little>>},
          {error, {ads_error, 16#703, invalid_index_offset}}]} =
        cell_hal_ads_client:sum_read(C, [{G, O1, 4}, {G, O2, 8}, {G, 999999, 2}]),
    {ok, [ok, {error, {ads_error, 16#702, invalid_index_group}}]} =
        cell_hal_ads_client:sum_write(C, [{G, O1, <<43:32/little>>}, {16#1234, 0, <<1>>}]),
    ?assertEqual(<<43:32/little>>, value(Config, "MAIN.counter")),
    {ok, [{ok, <<H:32/little>>}, {error, {ads_error, 16#710, symbol_not_found}}]} =
        cell_hal_ads_client:sum_read_write(C, [{16#F003, 0, 4, <<"MAIN.counter", 0>>},
                                               {16#F003, 0, 4, <<"MAIN.none", 0>>}]),
    {ok, <<43:32/little>>} = cell_hal_ads_client:read(C, 16#F005, H, 4),
    ok = cell_hal_ads_client:write(C, 16#F005, H, <<42:32/little>>),
    ok = cell_hal_ads_client:write(C, 16#F006, 0, <<H:32/little>>),
    {error, {ads_error, 16#710, symbol_not_found}} = cell_hal_ads_client:read(C, 16#F005, H, 4),
    {ok, [{ok, _}, {ok, _}]} = cell_hal_ads_client:sum_read(C, [{G, O1, 4}, {G, O2, 8}]),
    {error, {bad_argument, _}} = cell_hal_ads_client:sum_read(C, [{G, -1, 4}]).

%% A PLC without sum commands: every point its own request, still all in flight.
one_by_one_without_sum_commands(Config) ->
    C = client(Config, #{sum_commands => false}),
    clear(Config),
    {ok, _} = cell_hal_ads_client:resolve(C, group()),
    ?assertEqual(0, stat(Config, sums)),
    clear(Config),
    {ok, Values} = cell_hal_ads_client:read_vars(C, group()),
    ?assertEqual([{ok, I * 3} || I <- lists:seq(0, 199)], Values),
    ?assertEqual(#{reads => 200, requests => 200},
                 maps:with([reads, requests, sums], stats(Config))).

%% Seed §4.1.1: instances in a program ("MAIN.GeneralInputs") or global
%% (".GeneralOutputs") with ".Field" names; fields are not in the symbol table but are
%% found by name.
structure_fields_by_name(Config) ->
    C = client(Config),
    Vars = [{<<"MAIN.GeneralInputs.StartButton">>, bool},
            {<<"MAIN.GeneralInputs.StopButton">>, bool},
            {<<".GeneralOutputs.StartButtonLight">>, bool}],
    {ok, [{ok, #{symbol := <<"MAIN.GeneralInputs.StartButton">>, plc_type := <<"BOOL">>}},
          {ok, _}, {ok, _}]} = cell_hal_ads_client:resolve(C, Vars),
    {ok, [{ok, true}, {ok, false}, {ok, false}]} = cell_hal_ads_client:read_vars(C, Vars),
    {ok, [ok]} = cell_hal_ads_client:write_vars(C, [{lists:last(Vars), true}]),
    ?assertEqual(<<1>>, value(Config, ".GeneralOutputs.StartButtonLight")),
    {ok, [ok]} = cell_hal_ads_client:write_vars(C, [{lists:last(Vars), false}]),
    {ok, Table} = cell_hal_ads_client:symbols(C),
    Names = [N || #{name := N} <- Table],
    ?assert(lists:member(<<"MAIN.GeneralInputs">>, Names)),
    ?assertNot(lists:member(<<"MAIN.GeneralInputs.StartButton">>, Names)).

%% Seed §4.1.2: "*Name" matches the one symbol whose name ends so.
image_wildcards(Config) ->
    C = client(Config),
    {ok, [{ok, #{symbol := <<"Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn">>}},
          {ok, #{symbol := <<"Term 9 (EL2008).ManipulatorOutputs.ZAxisCylinder1Up">>}},
          {error, {ambiguous_symbol, <<"*Spare.In">>,
                   [<<"Term 6 (EL1008).Spare.In">>, <<"Term 7 (EL1008).Spare.In">>]}},
          {error, {unknown_symbol, <<"*ManipulatorInputs.Missing">>}}]} =
        cell_hal_ads_client:resolve(C, [{<<"*ManipulatorInputs.FailPaletteIsIn">>, bool},
                                        {<<"*manipulatoroutputs.zaxiscylinder1up">>, bool},
                                        {<<"*Spare.In">>, bool},
                                        {<<"*ManipulatorInputs.Missing">>, bool}]),
    {ok, [{ok, true}]} =
        cell_hal_ads_client:read_vars(C, [{<<"*ManipulatorInputs.FailPaletteIsIn">>, bool}]),
    {error, {bad_variable, {<<"Term*">>, bool}}} =
        cell_hal_ads_client:resolve(C, [{<<"Term*">>, bool}]).

%% An image's points read by index group and offset, no handles.
image_by_address(Config) ->
    C = client(Config, #{access => address}),
    clear(Config),
    Vars = [{<<"*ManipulatorInputs.FailPaletteIsIn">>, bool},
            {<<"*ManipulatorInputs.ZAxisCylinder1IsUp">>, bool}],
    {ok, [{ok, _}, {ok, _}]} = cell_hal_ads_client:resolve(C, Vars),
    ?assertEqual(0, stat(Config, acquired)),
    set(Config, "Term 5 (EL1008).ManipulatorInputs.ZAxisCylinder1IsUp", <<1>>),
    {ok, [{ok, true}, {ok, true}]} = cell_hal_ads_client:read_vars(C, Vars),
    set(Config, "Term 5 (EL1008).ManipulatorInputs.ZAxisCylinder1IsUp", <<0>>).

%% A missing symbol is an error naming it, logged for the operator; the connection and
%% every other variable carry on.
missing_symbol_is_clear(Config) ->
    C = client(Config),
    ok = cell_log:subscribe(),
    {ok, [{ok, _}, {error, {unknown_symbol, <<"MAIN.DoesNotExist">>} = Reason}]} =
        cell_hal_ads_client:resolve(C, [{<<"MAIN.counter">>, int32},
                                        {<<"MAIN.DoesNotExist">>, int32}]),
    ?assertEqual(<<"the PLC has no symbol MAIN.DoesNotExist">>,
                 cell_hal_ads_client:format_error(Reason)),
    {ok, _} = await_log(<<"MAIN.DoesNotExist">>),
    ok = cell_log:unsubscribe(),
    {ok, [{ok, 42}, {error, {not_resolved, <<"MAIN.DoesNotExist">>}}]} =
        cell_hal_ads_client:read_vars(C, [{<<"MAIN.counter">>, int32},
                                          {<<"MAIN.DoesNotExist">>, int32}]),
    {error, {unknown_symbol, <<"MAIN.DoesNotExist">>}} =
        cell_hal_ads_client:read_by_name(C, <<"MAIN.DoesNotExist">>, int32),
    #{state := up} = cell_hal_ads_client:status(C).

%% A symbol whose type changes with a program download: the client notices the new
%% symbol version, resolves again, and names the symbol and both types. Fixed in the
%% PLC, it works again.
retyped_symbol_is_clear(Config) ->
    Fake = ?config(fake, Config),
    C = client(Config),
    Var = {<<"MAIN.retyped">>, int32},
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Var]),
    {ok, [{ok, 7}]} = cell_hal_ads_client:read_vars(C, [Var]),
    ok = cell_log:subscribe(),
    ok = cell_hal_ads_peer:cmd(Fake, "retype MAIN.retyped INT 2 2 0500"),
    ok = await_status(C, symbols_changed),
    Expected = {type_mismatch, <<"MAIN.retyped">>,
                #{expected => <<"DINT">>, plc_type => <<"INT">>, size => 2}},
    {ok, [{error, Expected}]} = cell_hal_ads_client:read_vars(C, [Var]),
    #{failed := [<<"MAIN.retyped">>], state := up} = cell_hal_ads_client:status(C),
    {ok, Line} = await_log(<<"MAIN.retyped">>),
    ct:log("operator sees: ~ts", [Line]),
    ok = cell_log:unsubscribe(),
    ok = cell_hal_ads_peer:cmd(Fake, "retype MAIN.retyped DINT 3 4 07000000"),
    ok = await_status(C, symbols_changed),
    {ok, [{ok, 7}]} = cell_hal_ads_client:read_vars(C, [Var]),
    #{failed := []} = cell_hal_ads_client:status(C).

%% A symbol removed by a download: its subscription is told, reads say it is gone.
removed_symbol_ends_subscription(Config) ->
    Fake = ?config(fake, Config),
    C = client(Config),
    Var = {<<"MAIN.removed">>, int32},
    {ok, [{ok, Ref}]} = cell_hal_ads_client:subscribe(C, [{Var, #{}}]),
    {ok, [{_, 8}]} = await_samples(Ref, 1),
    ok = cell_hal_ads_peer:cmd(Fake, "remove MAIN.removed"),
    {ok, {error, {unknown_symbol, <<"MAIN.removed">>}}} =
        cell_hal_ads_peer:await(fun({cell_hal_ads, R, {error, E}}) when R =:= Ref -> {true, {error, E}};
                                   (_) -> false
                                end, ?WAIT),
    {ok, [{error, {unknown_symbol, <<"MAIN.removed">>}}]} = cell_hal_ads_client:read_vars(C, [Var]),
    {ok, _, _} = cell_hal_ads_peer:cmd(Fake, "add MAIN.removed DINT 3 4 08000000"),
    ok = cell_hal_ads_peer:cmd(Fake, "bump"),
    ok = await_status(C, symbols_changed),
    {ok, [{_, 8}]} = await_samples(Ref, 1).

%% Samples carry the PLC's stamps, exactly: FILETIME x 100 = ns since 1970.
notifications_keep_plc_stamps(Config) ->
    C = client(Config),
    Pos = {<<"MAIN.AxisPos">>, lreal},
    Beam = {<<"MAIN.LaserBeam">>, bool},
    {ok, [{ok, PosRef}, {ok, BeamRef}]} =
        cell_hal_ads_client:subscribe(C, [{Pos, #{mode => on_change, cycle_us => 1000}},
                                          {Beam, #{}}]),
    {ok, [{_, 0.0}]} = await_samples(PosRef, 1),
    {ok, [{_, false}]} = await_samples(BeamRef, 1),
    T1 = 133500000000000001,
    T2 = T1 + 5000,
    burst(Config, [{T1, [{"MAIN.AxisPos", <<1.5:64/float-little>>},
                         {"MAIN.LaserBeam", <<1>>}]},
                   {T2, [{"MAIN.AxisPos", <<2.5:64/float-little>>}]}]),
    {ok, [{N1, 1.5}, {N2, 2.5}]} = await_samples(PosRef, 2),
    {ok, [{N1, true}]} = await_samples(BeamRef, 1),
    ?assertEqual((T1 - ?FILETIME_UNIX_EPOCH) * 100, N1),
    ?assertEqual((T2 - ?FILETIME_UNIX_EPOCH) * 100, N2),
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>),
    set(Config, "MAIN.LaserBeam", <<0>>).

burst(Config, Stamps) ->
    Parts = [[integer_to_list(T), [[" ", N, " ", hex(V)] || {N, V} <- Pairs]]
             || {T, Pairs} <- Stamps],
    ok = cell_hal_ads_peer:cmd(?config(fake, Config),
                               ["burst " | lists:join(" ; ", Parts)]).

%% Seed §2.3.7: the axis drives the tool through the laser beam; the position is
%% latched at the beam's edge from the PLC's time-stamped samples, not from when the
%% samples arrived.
laser_beam_latch(Config) ->
    C = client(Config),
    {ok, [{ok, PosRef}, {ok, BeamRef}]} =
        cell_hal_ads_client:subscribe(C, [{{<<"MAIN.AxisPos">>, lreal}, #{cycle_us => 0}},
                                          {{<<"MAIN.LaserBeam">>, bool}, #{cycle_us => 0}}]),
    {ok, [_]} = await_samples(PosRef, 1),
    {ok, [_]} = await_samples(BeamRef, 1),
    %% One cycle a millisecond, 0.2 mm a cycle; the beam breaks in cycle 37 (at 7.4 mm)
    %% and clears in cycle 80.
    T0 = 133600000000000000,
    Cycle = 10000,
    Stamps = [{T0 + K * Cycle,
               [{"MAIN.AxisPos", <<(K * 0.2):64/float-little>>}] ++
                   [{"MAIN.LaserBeam", <<1>>} || K =:= 37] ++
                   [{"MAIN.LaserBeam", <<0>>} || K =:= 80]}
              || K <- lists:seq(1, 100)],
    burst(Config, Stamps),
    {ok, Positions} = await_samples(PosRef, 100),
    {ok, Beam} = await_samples(BeamRef, 2),
    {ok, #{time := Edge, position := P, exact := true}} =
        cell_hal_ads_latch:position_at_edge(Beam, Positions, #{edge => rising, initial => false}),
    ?assertEqual((T0 + 37 * Cycle - ?FILETIME_UNIX_EPOCH) * 100, Edge),
    ?assertEqual(37 * 0.2, P),
    {ok, #{position := Off}} =
        cell_hal_ads_latch:position_at_edge(Beam, Positions, #{edge => falling}),
    ?assertEqual(80 * 0.2, Off),
    set(Config, "MAIN.AxisPos", <<0.0:64/float-little>>),
    set(Config, "MAIN.LaserBeam", <<0>>).

cyclic_notifications(Config) ->
    C = client(Config),
    {ok, [{ok, Ref}]} =
        cell_hal_ads_client:subscribe(C, [{{<<"MAIN.b">>, byte},
                                           #{mode => cyclic, cycle_us => 20000}}]),
    {ok, Samples} = await_samples(Ref, 4),
    Stamps = [T || {T, 200} <- Samples],
    ?assertEqual(4, length(Stamps)),
    ?assertEqual(lists:usort(Stamps), Stamps).

unsubscribe_deletes_notification(Config) ->
    C = client(Config),
    Before = stat(Config, notes),
    {ok, [{ok, Ref}]} = cell_hal_ads_client:subscribe(C, [{{<<"MAIN.dw">>, uint32}, #{}}]),
    {ok, [_]} = await_samples(Ref, 1),
    ?assertEqual(Before + 1, stat(Config, notes)),
    ok = cell_hal_ads_client:unsubscribe(C, [Ref]),
    ok = barrier(C),
    ?assertEqual(Before, stat(Config, notes)),
    set(Config, "MAIN.dw", <<5:32/little>>),
    ok = barrier(C),
    receive {cell_hal_ads, Ref, _} = M -> ct:fail("sample after unsubscribe: ~p", [M])
    after 0 -> ok
    end,
    set(Config, "MAIN.dw", <<4000000000:32/little>>).

%% Seed §2.3.7's trigger: a PLC variable enabled by handle before an expected edge.
trigger_enable_by_handle(Config) ->
    C = client(Config),
    clear(Config),
    Enable = {<<"MAIN.StopLoadingSegmentTriggerEnable">>, bool},
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Enable]),
    {ok, [ok]} = cell_hal_ads_client:write_vars(C, [{Enable, true}]),
    ?assertEqual(<<1>>, value(Config, "MAIN.StopLoadingSegmentTriggerEnable")),
    {ok, [ok]} = cell_hal_ads_client:write_vars(C, [{Enable, false}]),
    ?assertEqual(<<0>>, value(Config, "MAIN.StopLoadingSegmentTriggerEnable")),
    ok = cell_hal_ads_client:release(C, [Enable]),
    ok = barrier(C),
    ?assertEqual(#{acquired => 1, released => 1}, maps:with([acquired, released], stats(Config))).

%% The fake holds its answers until five requests wait: only a client with several
%% requests in flight gets any answer.
several_requests_in_flight(Config) ->
    C = client(Config),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "hold 5"),
    Self = self(),
    Pids = [spawn_link(fun() -> Self ! {done, self(), cell_hal_ads_client:read_state(C, 5000)} end)
            || _ <- lists:seq(1, 5)],
    [receive {done, P, {ok, #{ads_state := run}}} -> ok after ?WAIT -> ct:fail(no_answer) end
     || P <- Pids].

%% No caller waits past its timeout; a PLC that answers nothing at all is a dead
%% connection (a pulled cable): closed, the client ending with the reason. Logging it
%% and connecting again are the owner's (cell_hal_ads_hal_SUITE).
timeout_never_blocks_caller(Config) ->
    Fake = ?config(fake, Config),
    %% Nothing else may come from the PLC meanwhile, not even its symbol version.
    C = client(Config, #{link_check => infinity, symbol_version => read}),
    Mon = monitor(process, C),
    ok = cell_hal_ads_peer:cmd(Fake, "mute"),
    T0 = erlang:monotonic_time(millisecond),
    {error, timeout} = cell_hal_ads_client:read_state(C, 300),
    Took = erlang:monotonic_time(millisecond) - T0,
    ct:log("a 300 ms call returned after ~b ms", [Took]),
    ?assert(Took >= 300),
    ?assert(Took < 2000),
    {down, no_answer} = receive_down(C),
    ?assertEqual({shutdown, no_answer}, await_exit(Mon, C)),
    ok = cell_hal_ads_peer:cmd(Fake, "unmute"),
    %% the PLC itself is fine: a new connection is served
    C2 = client(Config),
    {ok, _} = cell_hal_ads_client:read_state(C2).

%% The reason a client ended with, by the monitor set before it could end.
await_exit(Mon, C) ->
    receive {'DOWN', Mon, process, C, Why} -> Why
    after ?WAIT -> ct:fail("client ~p still running", [C])
    end.

receive_down(C) ->
    {ok, Down} = cell_hal_ads_peer:await(fun({cell_hal_ads, P, {down, _} = D}) when P =:= C ->
                                                 {true, D};
                                            (_) -> false
                                         end, ?WAIT),
    Down.

%% A frame that cannot be read closes that connection only: the client ends with a
%% reason that reads as words (its owner logs it and connects again, the HAL group
%% coming back up: cell_hal_ads_hal_SUITE), the caller is told, and nothing else
%% goes: the PLC serves a new client, its subscriptions included.
garbage_closes_only_the_connection(Config) ->
    C = client(Config),
    {ok, [{ok, Ref}]} = cell_hal_ads_client:subscribe(C, [{{<<"MAIN.sb">>, sbyte}, #{}}]),
    {ok, [_]} = await_samples(Ref, 1),
    Mon = monitor(process, C),
    %% AMS/TCP length 4: shorter than an AMS header
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "garbage 000004000000deadbeef"),
    {down, {bad_frame, shorter_than_ams_header}} = receive_down(C),
    {shutdown, Why} = await_exit(Mon, C),
    ?assertEqual({bad_frame, shorter_than_ams_header}, Why),
    ?assertEqual(<<"the PLC sent a malformed frame (shorter than ams header)">>,
                 cell_hal_ads_client:format_error(Why)),
    C2 = client(Config),
    {ok, [{ok, Ref2}]} = cell_hal_ads_client:subscribe(C2, [{{<<"MAIN.sb">>, sbyte}, #{}}]),
    {ok, [{_, -5}]} = await_samples(Ref2, 1).

oversized_frame_closes_only_the_connection(Config) ->
    C = client(Config, #{max_frame => 65536}),
    Mon = monitor(process, C),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "garbage 0000ffffff7f"),
    {down, {frame_too_long, 16#7FFFFFFF}} = receive_down(C),
    ?assertEqual({shutdown, {frame_too_long, 16#7FFFFFFF}}, await_exit(Mon, C)),
    C2 = client(Config, #{max_frame => 65536}),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C2, [{<<"MAIN.counter">>, int32}]),
    {ok, [{ok, 42}]} = cell_hal_ads_client:read_vars(C2, [{<<"MAIN.counter">>, int32}]).

bad_options(_Config) ->
    Good = #{host => "127.0.0.1", target_net_id => ?NET},
    [?assertEqual({error, {bad_option, K}}, cell_hal_ads_client:start_link(maps:merge(Good, Bad)))
     || {K, Bad} <- [{target_net_id, #{target_net_id => "1.2.3.4.5"}},
                     {target_net_id, #{target_net_id => "1.2.3.4.5.256"}},
                     {port, #{port => 0}},
                     {target_port, #{target_port => 70000}},
                     {source_net_id, #{source_net_id => "x"}},
                     %% a client does not connect again by itself: its owner does
                     {backoff, #{backoff => {50, 1000}}},
                     {reconnect, #{reconnect => true}},
                     {reconnect, #{reconnect => false}},
                     {max_sum, #{max_sum => 0}},
                     {sum_commands, #{sum_commands => yes}},
                     {access, #{access => symbol}},
                     {symbol_version, #{symbol_version => always}},
                     {link_check, #{link_check => 0}},
                     {max_frame, #{max_frame => 10}},
                     {reconnect, #{reconnect => sometimes}},
                     {log_variables, #{log_variables => 1}},
                     {colour, #{colour => blue}}]],
    {error, {bad_option, host}} = cell_hal_ads_client:start_link(#{target_net_id => ?NET}),
    {error, {bad_option, target_net_id}} = cell_hal_ads_client:start_link(#{host => "h"}),
    {error, {bad_option, opts}} = cell_hal_ads_client:start_link([]).

%% On stop the client deletes its notifications and gives its handles back.
stop_leaves_plc_tidy(Config) ->
    Fake = ?config(fake, Config),
    ok = cell_hal_ads_peer:cmd(Fake, "wait_clients 0 10000"),
    C = client(Config),
    {ok, _} = cell_hal_ads_client:resolve(C, lists:sublist(group(), 10)),
    {ok, [{ok, _}]} = cell_hal_ads_client:subscribe(C, [{{<<"MAIN.t">>, time}, #{}}]),
    #{handles := 11, notes := 2} = stats(Config),    % with the symbol version's
    clear(Config),
    ok = cell_hal_ads_client:stop(C),
    ok = cell_hal_ads_peer:cmd(Fake, "wait_clients 0 10000"),
    %% given back by the client before it closed, not cleaned up by the PLC
    ?assertEqual(#{notes_deleted => 2, released => 11},
                 maps:with([notes_deleted, released], stats(Config))).

%% A caller that must not wait (the HAL's worker) starts calls and recognizes their
%% answers among its other messages; each carries the caller's label.
requests_without_waiting(Config) ->
    C = client(Config),
    Counter = {<<"MAIN.counter">>, int32},
    Flag = {<<"MAIN.flag">>, bool},
    Ids0 = gen_statem:reqids_new(),
    {ok, Ids1} = cell_hal_ads_client:send_request(C, {resolve, [Counter, Flag]}, ?WAIT,
                                                  resolved, Ids0),
    {{ok, [{ok, #{symbol := <<"MAIN.counter">>}}, {ok, _}]}, resolved, Ids2} = response(Ids1),
    {ok, Ids3} = cell_hal_ads_client:send_request(C, {write_vars, [{Flag, true}]}, ?WAIT,
                                                  {write, 1}, Ids2),
    {ok, Ids4} = cell_hal_ads_client:send_request(C, {read_vars, [Counter, Flag]}, ?WAIT,
                                                  {read, 2}, Ids3),
    %% answered in the order asked: the write reached the PLC before the read
    {{ok, [ok]}, {write, 1}, Ids5} = response(Ids4),
    {{ok, [{ok, 42}, {ok, true}]}, {read, 2}, Ids6} = response(Ids5),
    no_request = cell_hal_ads_client:check_response(anything, Ids6),
    {ok, Ids7} = cell_hal_ads_client:send_request(C, {subscribe, [{Flag, #{}}]}, ?WAIT, sub, Ids6),
    {{ok, [{ok, Ref}]}, sub, Ids8} = response(Ids7),
    {ok, [{_, true}]} = await_samples(Ref, 1),
    {ok, Ids9} = cell_hal_ads_client:send_request(C, {unsubscribe, [Ref]}, ?WAIT, unsub, Ids8),
    {ok, unsub, Ids10} = response(Ids9),
    {ok, Ids11} = cell_hal_ads_client:send_request(C, {release, [Counter, Flag]}, ?WAIT, rel,
                                                   Ids10),
    {ok, rel, Ids12} = response(Ids11),
    %% a time already past is answered, not dropped
    {ok, Ids13} = cell_hal_ads_client:send_request(C, read_state, 0, late, Ids12),
    {{error, timeout}, late, Ids14} = response(Ids13),
    %% bad arguments never leave the caller
    {error, {bad_variable, {<<"MAIN.x">>, float}}} =
        cell_hal_ads_client:send_request(C, {resolve, [{<<"MAIN.x">>, float}]}, ?WAIT, x, Ids14),
    {error, {bad_argument, {read, -1, 0, 4}}} =
        cell_hal_ads_client:send_request(C, {read, -1, 0, 4}, ?WAIT, x, Ids14),
    {ok, Ids15} = cell_hal_ads_client:send_request(C, {write_vars, [{Flag, false}]}, ?WAIT,
                                                   {write, 3}, Ids14),
    {{ok, [{error, {not_resolved, <<"MAIN.flag">>}}]}, {write, 3}, _} = response(Ids15),
    ?assertEqual(<<1>>, value(Config, "MAIN.flag")),
    set(Config, "MAIN.flag", <<0>>).

response(Ids) ->
    receive
        Msg ->
            case cell_hal_ads_client:check_response(Msg, Ids) of
                no_reply -> self() ! Msg, ct:fail("not an answer: ~p", [Msg]);
                no_request -> ct:fail(no_request);
                Answer -> Answer
            end
    after ?WAIT -> ct:fail(no_answer)
    end.

%% A client is one connection, no more. A lost connection or one that cannot be made
%% ends the client with the reason; it logs nothing of its own (its owner does).
one_connection_without_reconnecting(Config) ->
    Fake = ?config(fake, Config),
    ok = cell_log:subscribe(),
    C = client(Config, #{name => <<"hal/one">>}),
    Ref = monitor(process, C),
    ok = cell_hal_ads_peer:cmd(Fake, "drop"),
    receive {'DOWN', Ref, process, C, Why} -> ?assertEqual({shutdown, closed}, Why)
    after ?WAIT -> ct:fail(client_still_running)
    end,
    {ok, Probe} = gen_tcp:listen(0, [{ip, {127, 0, 0, 1}}]),
    {ok, Port} = inet:port(Probe),
    ok = gen_tcp:close(Probe),
    %% Linked, exits trapped: the reason arrives even if the client has ended before a
    %% monitor could be set.
    Trap = process_flag(trap_exit, true),
    {ok, C2} = cell_hal_ads_client:start_link(#{host => {127, 0, 0, 1}, port => Port,
                                               target_net_id => ?NET,
                                               name => <<"hal/one">>}),
    receive {'EXIT', C2, Why2} ->
            ?assertEqual({shutdown, {connect, econnrefused}}, Why2)
    after ?WAIT -> ct:fail(client_still_running)
    end,
    process_flag(trap_exit, Trap),
    %% the lines of the one source: connected, never "lost" or "retrying"
    Lines = log_lines(<<"hal/one">>),
    ct:log("~p", [Lines]),
    ?assertMatch([_], [T || T <- Lines, binary:match(T, <<"connected to">>) =/= nomatch]),
    ?assertEqual([], [T || T <- Lines, binary:match(T, [<<"lost">>, <<"retrying">>]) =/= nomatch]),
    ok = cell_log:unsubscribe().

%% The log lines of a source in the mailbox: a client logs from its own process, so
%% its lines arrive before the monitor says it exited.
log_lines(Source) ->
    collect_lines(Source, []).

collect_lines(Source, Acc) ->
    receive
        {cell_log, #{source := Source, text := T}} -> collect_lines(Source, [T | Acc]);
        {cell_log, _} -> collect_lines(Source, Acc)
    after 0 -> lists:reverse(Acc)
    end.

%% A PLC that hangs with its network stack alive takes nothing more: the socket's
%% queue fills. A reader is not held past its timeout, and the client, which cannot
%% hand over its writes, gives the connection up after its request timeout instead of
%% waiting for the PLC for ever: it ends with the reason.
stalled_plc_blocks_nobody(Config) ->
    Fake = ?config(fake, Config),
    C = client(Config, #{request_timeout => 500, link_check => infinity,
                         symbol_version => read}),
    Counter = {<<"MAIN.counter">>, int32},
    Name = {<<"MAIN.name">>, {string, 20}},
    {ok, [{ok, _}, {ok, _}]} = cell_hal_ads_client:resolve(C, [Counter, Name]),
    #{<<"MAIN.name">> := {G, O, _}} = ?config(symbols, Config),
    Mon = monitor(process, C),
    ok = cell_hal_ads_peer:cmd(Fake, "stall"),
    Big = binary:copy(<<0>>, 4 bsl 20),
    _ = lists:foldl(fun(I, Ids) ->
                            {ok, Ids1} = cell_hal_ads_client:send_request(
                                           C, {write, G, O, Big}, ?WAIT, I, Ids),
                            Ids1
                    end, gen_statem:reqids_new(), lists:seq(1, 4)),
    T0 = erlang:monotonic_time(millisecond),
    {error, timeout} = cell_hal_ads_client:read_vars(C, [Counter], 300),
    Took = erlang:monotonic_time(millisecond) - T0,
    ct:log("a 300 ms read returned after ~b ms", [Took]),
    ?assert(Took < 1000),
    {down, Why} = receive_down(C),
    ct:log("given up: ~ts", [cell_hal_ads_client:format_error(Why)]),
    ?assertEqual({socket, timeout}, Why),
    ?assertEqual({shutdown, {socket, timeout}}, await_exit(Mon, C)),
    ok = cell_hal_ads_peer:cmd(Fake, "unstall"),
    C2 = client(Config),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C2, [Counter]),
    {ok, [{ok, 42}]} = cell_hal_ads_client:read_vars(C2, [Counter]).

%%--------------------------------------------------------------------
%% direct: reads that skip the client's process (cell_hal_ads_direct)
%%--------------------------------------------------------------------

%% A read of resolved variables in one request is written by the caller itself, with
%% an even invoke id: the client's process gets no call, only the answer from the PLC.
%% What needs more than one request, or is not resolved, goes through the process.
reads_skip_the_connection(Config) ->
    C = client(Config),
    Counter = {<<"MAIN.counter">>, int32},
    Group = lists:sublist(group(), 50),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Counter]),
    {ok, Resolved} = cell_hal_ads_client:resolve(C, Group),
    50 = length([ok || {ok, _} <- Resolved]),
    clear(Config),
    {Calls, {ok, [{ok, 42}]}} = calls_to(C, fun() -> cell_hal_ads_client:read_vars(C, [Counter]) end),
    ?assertEqual([], Calls),
    {[], {ok, Values}} = calls_to(C, fun() -> cell_hal_ads_client:read_vars(C, Group) end),
    ?assertEqual([{ok, I * 3} || I <- lists:seq(0, 49)], Values),
    {ok, Frames} = cell_hal_ads_peer:cmd(?config(fake, Config), "frames"),
    [Single, Sum] = [F || F <- Frames, lists:member(cmd_name(F), [read, read_write])],
    ?assertEqual({read, 0}, {cmd_name(Single), invoke(Single) band 1}),
    ?assertEqual({read_write, 0}, {cmd_name(Sum), invoke(Sum) band 1}),
    %% the same group split in two sum commands: through the process
    C2 = client(Config, #{max_sum => 30}),
    {ok, _} = cell_hal_ads_client:resolve(C2, Group),
    {[_], {ok, Values}} = calls_to(C2, fun() -> cell_hal_ads_client:read_vars(C2, Group) end),
    {[_], {ok, [{error, {not_resolved, <<"MAIN.flag">>}}]}} =
        calls_to(C, fun() -> cell_hal_ads_client:read_vars(C, [{<<"MAIN.flag">>, bool}]) end),
    #{in_flight := 0} = cell_hal_ads_client:status(C).

%% The calls a client's process received while Fun ran, and Fun's result.
calls_to(C, Fun) ->
    1 = erlang:trace(C, true, ['receive']),
    Result = Fun(),
    1 = erlang:trace(C, false, ['receive']),
    Ref = erlang:trace_delivered(C),
    receive {trace_delivered, C, Ref} -> ok after ?WAIT -> ct:fail(trace_not_delivered) end,
    {traced_calls(C, []), Result}.

traced_calls(C, Acc) ->
    receive
        {trace, C, 'receive', {'$gen_call', _, Call}} -> traced_calls(C, [Call | Acc]);
        {trace, C, 'receive', _} -> traced_calls(C, Acc)
    after 0 -> lists:reverse(Acc)
    end.

cmd_name(<<_:22/binary, Cmd:16/little, _/binary>>) -> cell_hal_ads_codec:command_name(Cmd).

invoke(<<_:34/binary, Invoke:32/little, _/binary>>) -> Invoke.

%% A program change while a direct read is in flight: the client gives its handles
%% back, so the answer, which came through the old handle, is not used; the read is
%% made again through the client's process once the variable is resolved again.
read_across_program_change(Config) ->
    Fake = ?config(fake, Config),
    %% the answer comes with the first request the program change makes
    {C, Reader} = held_read(Config, #{}),
    ok = cell_hal_ads_peer:cmd(Fake, "bump"),
    ?assertEqual({ok, [{ok, 42}]}, read_result(Reader)),
    ok = await_status(C, symbols_changed),
    {ok, Frames} = cell_hal_ads_peer:cmd(Fake, "frames"),
    Reads = [{invoke(F) band 1, H} || F <- Frames, {ok, H} <- [read_by_handle(F)]],
    ct:log("reads of the counter (invoke id parity, handle): ~p", [Reads]),
    [{0, Old}, {1, New}] = Reads,
    ?assertNotEqual(Old, New).

read_by_handle(<<_:22/binary, 2:16/little, _:14/binary, 16#F005:32/little, H:32/little,
                 _/binary>>) ->
    {ok, H};
read_by_handle(_) ->
    error.

%% A client with a direct read of the counter in flight, whose answer the PLC holds
%% until the next request comes.
held_read(Config, Opts) ->
    Fake = ?config(fake, Config),
    C = client(Config, Opts),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [counter()]),
    clear(Config),
    ok = cell_hal_ads_peer:cmd(Fake, "hold 2"),
    Reader = reader(C, [counter()]),
    ok = cell_hal_ads_peer:cmd(Fake, "wait_stat requests 1 10000"),
    {C, Reader}.

counter() ->
    {<<"MAIN.counter">>, int32}.

%% A caller in a process of its own.
reader(C, Vars) ->
    Test = self(),
    spawn(fun() -> Test ! {read, self(), cell_hal_ads_client:read_vars(C, Vars, ?WAIT)} end).

read_result(Reader) ->
    receive {read, Reader, Result} -> Result after ?WAIT -> ct:fail(reader_stuck) end.

%% A caller that exits mid-read keeps its slot until its answer comes or the link
%% check finds it gone; then the slot is given back and what waited for it is sent.
%% Here the PLC answers nothing until a second request comes, which the only slot,
%% held by the caller gone, keeps back: the link check frees it.
caller_killed_mid_read(Config) ->
    {C, Reader} = held_read(Config, #{max_in_flight => 1, link_check => 200}),
    Counter = counter(),
    Ref = monitor(process, Reader),
    exit(Reader, kill),
    receive {'DOWN', Ref, process, Reader, killed} -> ok end,
    %% its slot is still taken (its answer may come): this read waits for it
    #{in_flight := 1} = cell_hal_ads_client:status(C),
    {[_], {ok, [{ok, 42}]}} =
        calls_to(C, fun() -> cell_hal_ads_client:read_vars(C, [Counter]) end),
    #{state := up} = cell_hal_ads_client:status(C),
    {[], {ok, [{ok, 42}]}} =
        calls_to(C, fun() -> cell_hal_ads_client:read_vars(C, [Counter]) end).

%% The connection is lost with a direct read in flight: the read is answered
%% `disconnected', the client ends with the reason; the next connection's reads skip
%% its process again.
connection_lost_mid_read(Config) ->
    %% the read's answer is held until the next connection's requests come
    {C, Reader} = held_read(Config, #{}),
    Mon = monitor(process, C),
    ok = cell_hal_ads_peer:cmd(?config(fake, Config), "drop"),
    ?assertEqual({error, disconnected}, read_result(Reader)),
    {down, closed} = receive_down(C),
    ?assertEqual({shutdown, closed}, await_exit(Mon, C)),
    C2 = client(Config),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C2, [counter()]),
    {[], {ok, [{ok, 42}]}} =
        calls_to(C2, fun() -> cell_hal_ads_client:read_vars(C2, [counter()]) end).

%% A PLC that answers nothing: the direct read returns at its timeout, and the client,
%% told that nothing at all came since the read was sent, gives the connection up: it
%% ends with the reason.
silent_plc_ends_direct_read(Config) ->
    Fake = ?config(fake, Config),
    C = client(Config, #{link_check => infinity, symbol_version => read}),
    Counter = {<<"MAIN.counter">>, int32},
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [Counter]),
    Mon = monitor(process, C),
    ok = cell_hal_ads_peer:cmd(Fake, "mute"),
    T0 = erlang:monotonic_time(millisecond),
    {error, timeout} = cell_hal_ads_client:read_vars(C, [Counter], 300),
    Took = erlang:monotonic_time(millisecond) - T0,
    ct:log("a 300 ms direct read returned after ~b ms", [Took]),
    ?assert(Took >= 300 andalso Took < 2000),
    {down, no_answer} = receive_down(C),
    ?assertEqual({shutdown, no_answer}, await_exit(Mon, C)),
    ok = cell_hal_ads_peer:cmd(Fake, "unmute"),
    C2 = client(Config),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C2, [Counter]),
    {[], {ok, [{ok, 42}]}} =
        calls_to(C2, fun() -> cell_hal_ads_client:read_vars(C2, [Counter]) end).

%%--------------------------------------------------------------------
%% crosscheck: our frames beside AdsLib's, byte for byte
%%--------------------------------------------------------------------

frames_match_adslib(Config) ->
    A = adslib(Config),
    ok = cell_hal_ads_peer:listen(A),
    {ok, {ready, AmsPort}} = cell_hal_ads_peer:ready(A),
    C = client(Config, #{source_net_id => ?ADSLIB_NET, source_port => AmsPort,
                         link_check => infinity, symbol_version => ignore}),
    Syms = ?config(symbols, Config),
    #{<<"MAIN.counter">> := {G, OC, 4}, <<"MAIN.flag">> := {G, OF, 1},
      <<"MAIN.pos">> := {G, OP, 8}} = Syms,
    Same = fun(Theirs, Ours) ->
                   AF = frames_of(Config, Theirs),
                   OF2 = frames_of(Config, Ours),
                   ct:log("AdsLib: ~p~nours:   ~p", [AF, OF2]),
                   ?assertEqual([normal(F) || F <- AF], [normal(F) || F <- OF2])
           end,
    Same(fun() -> {ok, _, _} = cell_hal_ads_peer:cmd(A, "info") end,
         fun() -> {ok, _} = cell_hal_ads_client:read_device_info(C) end),
    Same(fun() -> {ok, 5, 0} = cell_hal_ads_peer:cmd(A, "state") end,
         fun() -> {ok, _} = cell_hal_ads_client:read_state(C) end),
    Same(fun() -> ok = cell_hal_ads_peer:cmd(A, "write_control 5 0") end,
         fun() -> ok = cell_hal_ads_client:write_control(C, run, 0, <<0:16>>, 5000) end),
    Same(fun() -> {ok, _} = cell_hal_ads_peer:cmd(A, "handle MAIN.counter") end,
         fun() -> {ok, _} = cell_hal_ads_client:read_write(C, 16#F003, 0, 4, <<"MAIN.counter", 0>>) end),
    {ok, H} = cell_hal_ads_peer:cmd(A, "handle MAIN.pos"),
    HS = integer_to_list(H),
    Same(fun() -> {ok, 10.0} = cell_hal_ads_peer:cmd(A, ["read_handle ", HS, " LREAL"]) end,
         fun() -> {ok, _} = cell_hal_ads_client:read(C, 16#F005, H, 8) end),
    Same(fun() -> ok = cell_hal_ads_peer:cmd(A, ["write_handle ", HS, " LREAL 10.0"]) end,
         fun() -> ok = cell_hal_ads_client:write(C, 16#F005, H, <<10.0:64/float-little>>) end),
    Same(fun() -> ok = cell_hal_ads_peer:cmd(A, ["release ", HS]) end,
         fun() -> {error, _} = cell_hal_ads_client:write(C, 16#F006, 0, <<H:32/little>>) end),
    %% a sum read of three symbols: AdsLib asks for each symbol's info first (the
    %% same request three times over), then reads by index group and offset
    Theirs = frames_of(Config, fun() ->
                                       {ok, [42, false, 10.0]} =
                                           cell_hal_ads_peer:cmd(A, "sum_read MAIN.counter "
                                                                 "MAIN.flag MAIN.pos")
                               end),
    [Info1, _, _, SumRead] = Theirs,
    <<_:38/binary, 16#F009:32/little, 0:32, InfoLen:32/little, _/binary>> = Info1,
    Ours = frames_of(Config, fun() ->
                                     [{ok, _} = cell_hal_ads_client:read_write(C, 16#F009, 0, InfoLen,
                                                                               <<N/binary, 0>>)
                                      || N <- [<<"MAIN.counter">>, <<"MAIN.flag">>, <<"MAIN.pos">>]],
                                     {ok, [{ok, _}, {ok, _}, {ok, _}]} =
                                         cell_hal_ads_client:sum_read(C, [{G, OC, 4}, {G, OF, 1},
                                                                          {G, OP, 8}])
                             end),
    ?assertEqual([normal(F) || F <- Theirs], [normal(F) || F <- Ours]),
    ?assertEqual(normal(SumRead), normal(lists:last(Ours))),
    %% a sum write (symbol infos are cached by AdsLib by now)
    Same(fun() -> {ok, _} = cell_hal_ads_peer:cmd(A, "sum_write MAIN.counter DINT 42 MAIN.pos LREAL 10.0") end,
         fun() -> {ok, [ok, ok]} = cell_hal_ads_client:sum_write(C, [{G, OC, <<42:32/little>>},
                                                                      {G, OP, <<10.0:64/float-little>>}]) end),
    %% notifications: add and delete, the handles being each side's own
    TheirNotes =
        frames_of(Config,
                  fun() ->
                          {ok, NH, UH} = cell_hal_ads_peer:cmd(A, "notify MAIN.counter DINT on_change 10"),
                          {ok, _} = await_adslib(NH, fun(_) -> true end),
                          ok = cell_hal_ads_peer:cmd(A, ["del_notify ", integer_to_list(NH), " ",
                                                         integer_to_list(UH)])
                  end),
    OurNotes =
        frames_of(Config,
                  fun() ->
                          {ok, [{ok, Ref}]} =
                              cell_hal_ads_client:subscribe(C, [{{<<"MAIN.counter">>, int32},
                                                                 #{cycle_us => 10000}}]),
                          {ok, _} = await_samples(Ref, 1),
                          ok = cell_hal_ads_client:unsubscribe(C, [Ref]),
                          ok = barrier(C)
                  end),
    [TheirAdd, TheirDel] = [F || F <- TheirNotes, lists:member(command(F), [6, 7])],
    [OurAdd, OurDel] = [F || F <- OurNotes, lists:member(command(F), [6, 7])],
    ?assertEqual(without_handle(TheirAdd, 42), without_handle(OurAdd, 42)),
    ?assertEqual(without_handle(TheirDel, 38), without_handle(OurDel, 38)),
    ok = cell_hal_ads_peer:stop(A).

frames_of(Config, Fun) ->
    clear(Config),
    Fun(),
    {ok, Frames} = cell_hal_ads_peer:cmd(?config(fake, Config), "frames"),
    clear(Config),
    Frames.

%% A frame with its invoke id zeroed: everything else must be the same.
normal(<<Head:34/binary, _Invoke:32, Data/binary>>) ->
    <<Head/binary, 0:32, Data/binary>>.

command(<<_:22/binary, Cmd:16/little, _/binary>>) -> Cmd.

%% The 4-byte handle at `At' zeroed too (each client's handles are its own).
without_handle(Frame, At) ->
    <<Head:At/binary, _:32, Tail/binary>> = normal(Frame),
    <<Head/binary, 0:32, Tail/binary>>.

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

%% N samples of a subscription, possibly over several messages, in order.
await_samples(Ref, N) ->
    await_samples(Ref, N, [], erlang:monotonic_time(millisecond) + ?WAIT).

await_samples(_Ref, N, Acc, _) when length(Acc) >= N ->
    {ok, Acc};
await_samples(Ref, N, Acc, Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {cell_hal_ads, Ref, {samples, Samples}} -> await_samples(Ref, N, Acc ++ Samples, Deadline)
    after Left ->
            ct:fail("only ~p of ~p samples: ~p", [length(Acc), N, Acc])
    end.

await_log(Text) ->
    cell_hal_ads_peer:await(fun({cell_log, #{text := T}}) ->
                                    case binary:match(T, Text) of
                                        nomatch -> false;
                                        _ -> {true, T}
                                    end;
                               (_) -> false
                            end, ?WAIT).
