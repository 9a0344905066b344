%% The ADS client against PyPI pyads' own test server (AdsTestServer with its
%% AdvancedHandler), a peer written by others, for the basic commands: device info,
%% state, write control, symbol info and handles by name, reads and writes by handle
%% and by index group, sum reads and writes by index group, adding and deleting
%% notifications.
%%
%% The test server reads one request per recv(), so the client keeps one request in
%% flight (`max_in_flight => 1'); it knows no sum commands on handles (variables go
%% one by one: `sum_commands => false'), sends no notifications over the wire, and
%% drops the connection on an unknown symbol (the client notices that the server
%% stopped answering, and connects again): what it lacks is tested against the fake
%% PLC (cell_hal_ads_fake_SUITE).
-module(cell_hal_ads_pyads_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([device_info_state_and_control/1, variables_by_handle/1, type_mismatch_is_clear/1,
         index_group_access/1, sum_commands_by_index_group/1, handles_released/1,
         notifications_added_and_deleted/1, by_name/1, concurrent_reads_one_at_a_time/1]).

-define(NET, "127.0.0.1.1.1").
-define(WAIT, 10000).

all() ->
    [device_info_state_and_control, variables_by_handle, type_mismatch_is_clear,
     index_group_access, sum_commands_by_index_group, handles_released,
     notifications_added_and_deleted, by_name, concurrent_reads_one_at_a_time].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, _} = application:ensure_all_started(cell_base),
    case cell_hal_ads_peer:start("pyads_server.py", []) of
        {ok, Server, {ready, Port, _}} ->
            Vars = [{"MAIN.counter", 3, "DINT", <<42:32/little>>},
                    {"MAIN.flag", 33, "BOOL", <<0>>},
                    {"MAIN.speed", 5, "LREAL", <<10.0:64/float-little>>},
                    {"MAIN.word", 18, "UINT", <<16#1234:16/little>>},
                    {"MAIN.text", 30, "STRING(10)", <<"abc", 0:(8 * 8)>>}],
            Addrs = [begin
                         {ok, G, O} = cell_hal_ads_peer:cmd(
                                        Server, ["add ", N, " ", integer_to_list(A), " ", T,
                                                 " ", binary:encode_hex(V)]),
                         {list_to_binary(N), {G, O}}
                     end || {N, A, T, V} <- Vars],
            [{server, Server}, {port, Port}, {addrs, maps:from_list(Addrs)} | Config];
        {error, Reason} ->
            ct:fail("pyads' test server did not start: ~tp", [Reason])
    end.

end_per_suite(Config) ->
    ok = cell_hal_ads_peer:stop(?config(server, Config)),
    Config.

client(Config) ->
    client(Config, #{}).

client(Config, Extra) ->
    Opts = maps:merge(#{host => "127.0.0.1", port => ?config(port, Config),
                        target_net_id => ?NET, max_in_flight => 1, sum_commands => false,
                        handle_idle => 0}, Extra),
    {ok, C} = cell_hal_ads_client:start(Opts),
    Test = self(),
    _ = spawn(fun() ->
                      Ref = monitor(process, Test),
                      receive {'DOWN', Ref, process, Test, _} -> ok end,
                      catch cell_hal_ads_client:stop(C)
              end),
    ok = cell_hal_ads_client:subscribe_status(C),
    {ok, up} = cell_hal_ads_peer:await(fun({cell_hal_ads, P, up}) when P =:= C -> {true, up};
                                          (_) -> false
                                       end, ?WAIT),
    C.

value(Config, Name) ->
    {ok, Bin} = cell_hal_ads_peer:cmd(?config(server, Config), ["get ", Name]),
    Bin.

history(Config) ->
    {ok, H} = cell_hal_ads_peer:cmd(?config(server, Config), "history"),
    H.

device_info_state_and_control(Config) ->
    C = client(Config),
    {ok, #{name := <<"TestServer">>, version := {1, 2, 3}}} =
        cell_hal_ads_client:read_device_info(C),
    {ok, #{ads_state := run, device_state := 0}} = cell_hal_ads_client:read_state(C),
    ok = cell_hal_ads_client:write_control(C, run, 0),
    #{state := up, device := #{name := <<"TestServer">>}, symbol_version := 1} =
        cell_hal_ads_client:status(C).

variables_by_handle(Config) ->
    C = client(Config),
    Vars = [{<<"MAIN.counter">>, int32}, {<<"MAIN.flag">>, bool}, {<<"MAIN.speed">>, lreal},
            {<<"MAIN.word">>, uint16}, {<<"MAIN.text">>, {string, 10}}],
    {ok, Infos} = cell_hal_ads_client:resolve(C, Vars),
    [{ok, #{symbol := <<"MAIN.counter">>, plc_type := <<"DINT">>, size := 4}},
     {ok, #{plc_type := <<"BOOL">>, size := 1}}, {ok, #{size := 8}}, {ok, #{size := 2}},
     {ok, #{plc_type := <<"STRING(10)">>, size := 11}}] = Infos,
    {ok, [{ok, 42}, {ok, false}, {ok, 10.0}, {ok, 16#1234}, {ok, <<"abc">>}]} =
        cell_hal_ads_client:read_vars(C, Vars),
    {ok, [ok, ok, ok, ok, ok]} =
        cell_hal_ads_client:write_vars(C, lists:zip(Vars, [-1, true, 0.5, 7, <<"xyz12">>])),
    ?assertEqual(<<-1:32/little-signed>>, value(Config, "MAIN.counter")),
    ?assertEqual(<<1>>, value(Config, "MAIN.flag")),
    ?assertEqual(<<0.5:64/float-little>>, value(Config, "MAIN.speed")),
    ?assertEqual(<<7:16/little>>, value(Config, "MAIN.word")),
    ?assertEqual(<<"xyz12", 0:(6 * 8)>>, value(Config, "MAIN.text")),
    {ok, [{ok, -1}, {ok, true}, {ok, 0.5}, {ok, 7}, {ok, <<"xyz12">>}]} =
        cell_hal_ads_client:read_vars(C, Vars),
    {ok, _} = cell_hal_ads_client:write_vars(C, lists:zip(Vars, [42, false, 10.0, 16#1234,
                                                                <<"abc">>])).

type_mismatch_is_clear(Config) ->
    C = client(Config),
    {ok, [{error, {type_mismatch, <<"MAIN.counter">>,
                   #{expected := <<"INT">>, plc_type := <<"DINT">>, size := 4}} = E}]} =
        cell_hal_ads_client:resolve(C, [{<<"MAIN.counter">>, int16}]),
    Text = cell_hal_ads_client:format_error(E),
    ct:log("~ts", [Text]),
    ?assertNotEqual(nomatch, binary:match(Text, <<"MAIN.counter">>)),
    #{state := up} = cell_hal_ads_client:status(C).

index_group_access(Config) ->
    C = client(Config),
    #{<<"MAIN.counter">> := {G, O}} = ?config(addrs, Config),
    {ok, <<42:32/little>>} = cell_hal_ads_client:read(C, G, O, 4),
    ok = cell_hal_ads_client:write(C, G, O, <<43:32/little>>),
    ?assertEqual(<<43:32/little>>, value(Config, "MAIN.counter")),
    ok = cell_hal_ads_client:write(C, G, O, <<42:32/little>>).

%% The test server sums by index group and offset (not by handle).
sum_commands_by_index_group(Config) ->
    C = client(Config, #{sum_commands => true}),
    #{<<"MAIN.counter">> := {G, O1}, <<"MAIN.word">> := {G, O2}} = ?config(addrs, Config),
    {ok, [{ok, <<42:32/little>>}, {ok, <<16#1234:16/little>>}]} =
        cell_hal_ads_client:sum_read(C, [{G, O1, 4}, {G, O2, 2}]),
    {ok, [ok, ok]} = cell_hal_ads_client:sum_write(C, [{G, O1, <<5:32/little>>},
                                                       {G, O2, <<6:16/little>>}]),
    ?assertEqual(<<5:32/little>>, value(Config, "MAIN.counter")),
    ?assertEqual(<<6:16/little>>, value(Config, "MAIN.word")),
    {ok, [ok, ok]} = cell_hal_ads_client:sum_write(C, [{G, O1, <<42:32/little>>},
                                                       {G, O2, <<16#1234:16/little>>}]).

%% A released handle goes back to the server (a Write to 0xF006).
handles_released(Config) ->
    C = client(Config),
    Before = length([x || {3, 16#F006} <- history(Config)]),
    {ok, [{ok, _}]} = cell_hal_ads_client:resolve(C, [{<<"MAIN.flag">>, bool}]),
    ok = cell_hal_ads_client:release(C, [{<<"MAIN.flag">>, bool}]),
    {ok, _} = cell_hal_ads_client:read_state(C),
    ?assertEqual(Before + 1, length([x || {3, 16#F006} <- history(Config)])).

%% The server takes and deletes notifications (it sends none over the wire); it finds
%% them by index group and offset only, not by handle.
notifications_added_and_deleted(Config) ->
    C = client(Config, #{access => address}),
    {ok, [{ok, Ref}]} = cell_hal_ads_client:subscribe(C, [{{<<"MAIN.word">>, uint16},
                                                            #{mode => cyclic, cycle_us => 100000}}]),
    ok = cell_hal_ads_client:unsubscribe(C, [Ref]),
    {ok, _} = cell_hal_ads_client:read_state(C),
    Commands = [Cmd || {Cmd, _} <- history(Config)],
    ?assert(lists:member(6, Commands)),
    ?assert(lists:member(7, Commands)),
    #{subscriptions := 0} = cell_hal_ads_client:status(C).

by_name(Config) ->
    C = client(Config),
    %% (TwinCAT's names are case-insensitive, the test server's are not)
    {ok, 16#1234} = cell_hal_ads_client:read_by_name(C, <<"MAIN.word">>, uint16),
    ok = cell_hal_ads_client:write_by_name(C, <<"MAIN.word">>, uint16, 99),
    ?assertEqual(<<99:16/little>>, value(Config, "MAIN.word")),
    ok = cell_hal_ads_client:write_by_name(C, <<"MAIN.word">>, uint16, 16#1234).

%% Callers that read at the same time skip the client's process, yet `max_in_flight'
%% holds for them too: the test server, which reads one request per recv() and loses
%% a second one sent with it, answers every read.
concurrent_reads_one_at_a_time(Config) ->
    C = client(Config),
    Counter = {<<"MAIN.counter">>, int32},
    Word = {<<"MAIN.word">>, uint16},
    {ok, [{ok, _}, {ok, _}]} = cell_hal_ads_client:resolve(C, [Counter, Word]),
    Test = self(),
    Readers = [spawn_link(fun() ->
                                  Results = [cell_hal_ads_client:read_vars(C, [Var], ?WAIT)
                                             || _ <- lists:seq(1, 100)],
                                  Test ! {done, self(), lists:usort(Results)}
                          end) || Var <- lists:append(lists:duplicate(4, [Counter, Word]))],
    Results = [receive {done, R, Rs} -> Rs after 4 * ?WAIT -> ct:fail(reader_stuck) end
               || R <- Readers],
    ?assertEqual(lists:append(lists:duplicate(4, [[{ok, [{ok, 42}]}], [{ok, [{ok, 16#1234}]}]])),
                 Results),
    #{in_flight := 0, state := up} = cell_hal_ads_client:status(C).
