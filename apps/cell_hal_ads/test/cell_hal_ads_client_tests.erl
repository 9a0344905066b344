%% Unit tests of the client's option checks and its texts for people.
-module(cell_hal_ads_client_tests).
-include_lib("eunit/include/eunit.hrl").

-define(C, cell_hal_ads_client).

defaults_test() ->
    {ok, Opts} = ?C:check_opts(#{host => <<"plc1">>, target_net_id => <<"5.23.1.7.1.1">>}),
    ?assertMatch(#{host := "plc1", port := 48898, target_net_id := {5, 23, 1, 7, 1, 1},
                   target_port := 851, source_net_id := auto, max_sum := 500,
                   sum_commands := true, access := handle, symbol_version := watch}, Opts).

accepted_test_() ->
    Base = #{host => {192, 168, 0, 5}, target_net_id => {5, 23, 1, 7, 1, 1}},
    [?_assertMatch({ok, _}, ?C:check_opts(maps:merge(Base, O)))
     || O <- [#{}, #{source_net_id => "10.0.0.2.1.1", source_port => 30000},
              #{name => plc1}, #{name => <<"hal/plc1">>},
              #{link_check => infinity}, #{handle_idle => 0}, #{access => address},
              #{symbol_version => ignore}, #{max_in_flight => 1}, #{max_frame => 1024}]].

refused_test_() ->
    Base = #{host => "plc1", target_net_id => "5.23.1.7.1.1"},
    [?_assertEqual({error, {bad_option, K}}, ?C:check_opts(maps:merge(Base, #{K => V})))
     || {K, V} <- [{host, ""}, {host, {1, 2, 3}}, {host, 42}, {host, [300]},
                   {port, 65536}, {source_port, 0}, {request_timeout, 0},
                   {connect_timeout, -1}, {max_in_flight, 0}, {handle_idle, -1},
                   {max_frame, 1023}, {name, ""}, {name, <<>>}, {unknown, 1}]] ++
    [?_assertEqual({error, {bad_option, opts}}, ?C:check_opts(nil))].

%% Every reason the client gives reads as words.
format_error_test_() ->
    Reasons = [timeout, disconnected, no_answer, closed, starting, {connect, econnrefused},
               {connect, nxdomain}, {socket, etimedout}, {ads_error, 16#710, symbol_not_found},
               {ads_error, 16#12345, unknown}, {unknown_symbol, <<"MAIN.x">>},
               {ambiguous_symbol, <<"*In">>, [<<"A.In">>, <<"B.In">>]},
               {type_mismatch, <<"MAIN.x">>, #{expected => <<"DINT">>, plc_type => <<"INT">>, size => 2}},
               {bad_name, <<"a*">>}, {bad_variable, x}, {bad_value, int16, 70000},
               {bad_size, int32, 3}, {not_resolved, <<"MAIN.x">>},
               {symbol_table, timeout}, {symbol_error, <<"MAIN.x">>, {bad_response, wrong_length}},
               {bad_frame, length_mismatch}, {bad_notification, too_short}, {bad_symbol, truncated_entry},
               {frame_too_long, 99999999}, {unexpected_answer, read, write}, symbols_changed,
               {bad_sub_opts, #{mode => x}}, {bad_argument, [1]}, {restore, timeout}, something_else],
    [?_assert(is_binary(?C:format_error(R)) andalso byte_size(?C:format_error(R)) > 0) || R <- Reasons] ++
    [?_assertEqual(<<"symbol MAIN.x is INT (2 bytes) in the PLC, but the configuration expects DINT">>,
                   ?C:format_error(lists:nth(13, Reasons))),
     ?_assertEqual(<<"symbol not found (ADS error 0x710)">>,
                   ?C:format_error({ads_error, 16#710, symbol_not_found})),
     ?_assertEqual(<<"cannot connect: connection refused">>,
                   ?C:format_error({connect, econnrefused})),
     ?_assertEqual(<<"the PLC sent a malformed frame (shorter than ams header)">>,
                   ?C:format_error({bad_frame, shorter_than_ams_header}))].

%% The HAL's driver sets this itself; a host may too.
host_options_test_() ->
    Base = #{host => "plc1", target_net_id => "5.23.1.7.1.1"},
    [?_assertMatch({ok, #{log_variables := true}}, ?C:check_opts(Base)),
     ?_assertMatch({ok, #{log_variables := false}},
                   ?C:check_opts(Base#{log_variables => false})),
     ?_assertEqual({error, {bad_option, log_variables}},
                   ?C:check_opts(Base#{log_variables => no}))].

%% A client is one connection: connecting again, and its back-off, are its owner's.
%% Options for a reconnecting client are refused, whatever their value, rather than
%% taken and not acted on.
no_reconnect_options_test_() ->
    Base = #{host => "plc1", target_net_id => "5.23.1.7.1.1"},
    {ok, Full} = ?C:check_opts(Base),
    [?_assertNot(maps:is_key(reconnect, Full)),
     ?_assertNot(maps:is_key(backoff, Full))] ++
    [?_assertEqual({error, {bad_option, K}}, ?C:check_opts(Base#{K => V}))
     || {K, V} <- [{reconnect, true}, {reconnect, false}, {reconnect, no},
                   {backoff, {10, 10}}, {backoff, {500, 30000}}]].

%% Calls without waiting are checked in the caller too.
send_request_arguments_test_() ->
    Nobody = list_to_pid("<0.9999.0>"),
    Ids = gen_statem:reqids_new(),
    [?_assertEqual({error, {bad_variable, {<<"a*b">>, int32}}},
                   ?C:send_request(Nobody, {resolve, [{<<"a*b">>, int32}]}, 100, l, Ids)),
     ?_assertEqual({error, {bad_argument, [x]}},
                   ?C:send_request(Nobody, {write_vars, [x]}, 100, l, Ids)),
     ?_assertEqual({error, {bad_argument, {launch, rockets}}},
                   ?C:send_request(Nobody, {launch, rockets}, 100, l, Ids)),
     ?_assertEqual({error, {bad_argument, [x]}},
                   ?C:send_request(Nobody, {unsubscribe, [x]}, 100, l, Ids))].

%% Arguments are checked in the caller, before any message.
arguments_test_() ->
    Nobody = list_to_pid("<0.9999.0>"),
    [?_assertEqual({error, {bad_variable, {"MAIN.x", int32}}},
                   ?C:read_vars(Nobody, [{"MAIN.x", int32}])),
     ?_assertEqual({error, {bad_variable, {<<"a*b">>, int32}}},
                   ?C:resolve(Nobody, [{<<"a*b">>, int32}])),
     ?_assertEqual({error, {bad_variable, {<<"x">>, word}}}, ?C:resolve(Nobody, [{<<"x">>, word}])),
     ?_assertEqual({error, {bad_argument, x}}, ?C:read_vars(Nobody, x)),
     ?_assertEqual({error, {bad_argument, [x]}}, ?C:write_vars(Nobody, [x])),
     ?_assertEqual({error, {bad_sub_opts, #{mode => sometimes}}},
                   ?C:subscribe(Nobody, [{{<<"x">>, bool}, #{mode => sometimes}}])),
     ?_assertEqual({error, {bad_sub_opts, #{cycle_us => -1}}},
                   ?C:subscribe(Nobody, [{{<<"x">>, bool}, #{cycle_us => -1}}])),
     ?_assertEqual({error, {bad_argument, [x]}}, ?C:unsubscribe(Nobody, [x])),
     ?_assertEqual({error, {bad_variable, 1}}, ?C:release(Nobody, [1]))].

raw_arguments_test_() ->
    Nobody = list_to_pid("<0.9999.0>"),
    [?_assertEqual({error, {bad_argument, {read, -1, 0, 4}}}, ?C:read(Nobody, -1, 0, 4)),
     ?_assertEqual({error, {bad_argument, {read, 0, 0, 16#100000000}}},
                   ?C:read(Nobody, 0, 0, 16#100000000)),
     ?_assertEqual({error, {bad_argument, {write, 1, 2, [x]}}}, ?C:write(Nobody, 1, 2, [x])),
     ?_assertEqual({error, {bad_argument, {read_write, 1, 2, 4, y}}},
                   ?C:read_write(Nobody, 1, 2, 4, y)),
     ?_assertEqual({error, {bad_argument, {write_control, sleeping, 0, <<>>}}},
                   ?C:write_control(Nobody, sleeping, 0, <<>>, 100)),
     ?_assertEqual({error, {bad_argument, {write_control, run, 70000, <<>>}}},
                   ?C:write_control(Nobody, run, 70000, <<>>, 100))].
