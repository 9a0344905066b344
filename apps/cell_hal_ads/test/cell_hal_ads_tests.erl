%% Unit tests of the ADS driver's pure parts: options, fields, plans, words.
-module(cell_hal_ads_tests).
-include_lib("eunit/include/eunit.hrl").

-define(D, cell_hal_ads).

base() ->
    #{host => "10.0.0.5", target_net_id => "10.0.0.5.1.1"}.

options_test_() ->
    {ok, Opts} = ?D:check_opts(base()),
    [?_assertMatch(#{timeout_ms := 1000, target_port := 851, port := 48898,
                     access := handle, sum_commands := true, max_sum := 500}, Opts),
     %% what the driver sets on the client itself is not an option
     ?_assertNot(maps:is_key(reconnect, Opts)),
     ?_assertMatch({ok, #{timeout_ms := 250, access := address, target_port := 27905}},
                   ?D:check_opts((base())#{timeout_ms => 250, access => address,
                                           target_port => 27905}))] ++
    [?_assertEqual({error, {bad_option, K}}, ?D:check_opts(maps:merge(base(), #{K => V})))
     || {K, V} <- [{timeout_ms, 0}, {timeout_ms, fast}, {name, plc1}, {reconnect, true},
                   {log_variables, false}, {request_timeout, 10}, {backoff, {1, 2}},
                   {connect_timeout, 10}, {max_sum, 0}, {colour, red}]] ++
    [?_assertEqual({error, {bad_option, target_net_id}},
                   ?D:check_opts(maps:remove(target_net_id, base()))),
     ?_assertEqual({error, {bad_option, host}}, ?D:check_opts(maps:remove(host, base())))].

point(Name, Dir, Field) ->
    #{name => Name, dir => Dir, type => bool, address => <<"A1">>, caption => <<"C">>,
      field => Field}.

fields_test_() ->
    {ok, Opts} = ?D:check_opts(base()),
    Check = fun(GroupOpts, P) -> ?D:check_point(Opts, g, GroupOpts, P) end,
    Structs = #{input_struct => <<"MAIN.GeneralInputs">>, output_struct => <<".GeneralOutputs">>},
    [?_assertEqual({ok, #{symbol => <<"MAIN.GeneralInputs.StartButton">>, notify => false}},
                   Check(Structs, point(start, in, <<".StartButton">>))),
     ?_assertEqual({ok, #{symbol => <<".GeneralOutputs.StartButtonLight">>, notify => false}},
                   Check(Structs, point(light, out, <<".StartButtonLight">>))),
     ?_assertEqual({ok, #{symbol => <<"*ManipulatorInputs.FailPaletteIsIn">>, notify => false}},
                   Check(#{}, point(palette, in, <<"*ManipulatorInputs.FailPaletteIsIn">>))),
     %% notified inputs: all, or by name; never outputs
     ?_assertEqual({ok, #{symbol => <<"MAIN.GeneralInputs.Beam">>, notify => #{}}},
                   Check(Structs#{notify => all}, point(beam, in, <<".Beam">>))),
     ?_assertEqual({ok, #{symbol => <<".GeneralOutputs.X">>, notify => false}},
                   Check(Structs#{notify => all}, point(x, out, <<".X">>))),
     ?_assertEqual({ok, #{symbol => <<"MAIN.GeneralInputs.Beam">>,
                          notify => #{mode => cyclic, cycle_us => 1000}}},
                   Check(Structs#{notify => [beam], notify_opts => #{mode => cyclic,
                                                                      cycle_us => 1000}},
                         point(beam, in, <<".Beam">>))),
     ?_assertEqual({ok, #{symbol => <<"MAIN.GeneralInputs.Other">>, notify => false}},
                   Check(Structs#{notify => [beam]}, point(other, in, <<".Other">>))),
     ?_assertEqual({error, {notify, output}},
                   Check(Structs#{notify => [x]}, point(x, out, <<".X">>))),
     ?_assertEqual({error, notify}, Check(Structs#{notify => yes}, point(x, in, <<".X">>))),
     ?_assertEqual({error, notify_opts},
                   Check(Structs#{notify_opts => #{cycle_us => -1}}, point(x, in, <<".X">>))),
     ?_assertEqual({error, notify_opts},
                   Check(Structs#{notify_opts => #{colour => red}}, point(x, in, <<".X">>))),
     ?_assertEqual({error, notify_opts},
                   Check(Structs#{notify_opts => []}, point(x, in, <<".X">>))),
     %% the forms of seed 000 §4.1.1 and §4.1.2 only
     ?_assertEqual({error, input_struct}, Check(#{}, point(x, in, <<".X">>))),
     ?_assertEqual({error, bad_field}, Check(Structs, point(x, in, <<"X">>))),
     ?_assertEqual({error, bad_field}, Check(Structs, point(x, in, {coil, 1}))),
     ?_assertEqual({error, bad_field}, Check(Structs, point(x, in, <<".A", 0, "B">>))),
     ?_assertEqual({error, bad_field}, Check(Structs, point(x, in, <<"*A*B">>)))].

%% A plan counts the sum commands one read sends and the points notifications feed.
plan_test_() ->
    State = fun(Extra) -> {ok, O} = ?D:check_opts(maps:merge(base(), Extra)),
                          ?D:init(plc, O)
            end,
    Points = fun(N, Notify) ->
                     [#{key => {g, list_to_atom("p" ++ integer_to_list(I))}, dir => in,
                        type => int32,
                        field => #{symbol => list_to_binary("GVL.P" ++ integer_to_list(I)),
                                   notify => Notify}}
                      || I <- lists:seq(1, N)]
             end,
    Info = fun(Ps, S) -> element(2, ?D:plan(Ps, S)) end,
    Out = #{key => {g, out}, dir => out, type => bool,
            field => #{symbol => <<"GVL.P1">>, notify => false}},
    [?_assertEqual(#{requests => 0, pushed => 0}, Info([], State(#{}))),
     ?_assertEqual(#{requests => 1, pushed => 0}, Info(Points(1, false), State(#{}))),
     ?_assertEqual(#{requests => 1, pushed => 0}, Info(Points(200, false), State(#{}))),
     ?_assertEqual(#{requests => 1, pushed => 0}, Info(Points(500, false), State(#{}))),
     ?_assertEqual(#{requests => 2, pushed => 0}, Info(Points(501, false), State(#{}))),
     ?_assertEqual(#{requests => 4, pushed => 0},
                   Info(Points(200, false), State(#{max_sum => 50}))),
     ?_assertEqual(#{requests => 200, pushed => 0},
                   Info(Points(200, false), State(#{sum_commands => false}))),
     ?_assertEqual(#{requests => 0, pushed => 3}, Info(Points(3, #{}), State(#{}))),
     %% outputs among the points are read in the same sum command
     ?_assertEqual(#{requests => 1, pushed => 0}, Info([Out | Points(1, false)], State(#{}))),
     %% an output is read, never notified, whatever its field says
     ?_assertEqual(#{requests => 1, pushed => 0},
                   Info([Out#{field := #{symbol => <<"GVL.P1">>, notify => #{}}}], State(#{})))].

endpoint_test() ->
    {ok, O} = ?D:check_opts(base()),
    ?assertEqual("10.0.0.5:48898, AMS 10.0.0.5.1.1:851",
                 lists:flatten(io_lib:format("~s", [?D:endpoint(?D:init(plc, O))]))).

words_test_() ->
    W = fun(R) -> lists:flatten(io_lib:format("~ts", [?D:format_reason(R)])) end,
    [?_assertEqual("no answer within 3000 ms", W({no_answer, 3000})),
     ?_assertEqual("the PLC has no symbol MAIN.x", W({unknown_symbol, <<"MAIN.x">>})),
     ?_assertEqual("the PLC closed the connection", W(closed)),
     ?_assertEqual("cannot connect: connection refused", W({connect, econnrefused})),
     ?_assertEqual("outputs cannot be fed by notifications", W({notify, output}))].
