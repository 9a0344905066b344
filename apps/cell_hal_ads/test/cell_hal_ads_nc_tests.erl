%% The NC axis's ADS mapping (cell_hal_ads_nc) without a process: the requests each
%% command and effect become, the online state decoded, the news a poll brings.
-module(cell_hal_ads_nc_tests).
-include_lib("eunit/include/eunit.hrl").

-define(CTX, #{axis => 3, jerk => 5000, in_position => 0.01}).
-define(PARAMS, #{velocity => 100, acceleration => 1000, deceleration => 2000}).

groups_test() ->
    ?assertEqual(#{parameters => 16#4003, state => 16#4103, functions => 16#4203,
                   cyclic => 16#4303}, cell_hal_ads_nc:groups(3)),
    ?assertEqual(#{parameters => 16#40FF, state => 16#41FF, functions => 16#42FF,
                   cyclic => 16#43FF}, cell_hal_ads_nc:groups(255)).

requests_test_() ->
    R = fun(Op) -> cell_hal_ads_nc:request(Op, ?CTX) end,
    [?_assertEqual({read, 16#4103, 0, 256}, R(online)),
     ?_assertEqual([{write, 16#4203, 1, <<>>}], R(reset)),
     ?_assertEqual([{write, 16#4203, 2, <<>>}], R(stop)),
     ?_assertEqual([{write, 16#4203, 16#10, <<>>}], R(reference)),
     ?_assertEqual([{write, 16#4203, 4, <<1500.0:64/float-little, 5000.0:64/float-little>>}],
                   R({stop, 1500, 5000})),
     ?_assertEqual([{write, 16#4303, 2, <<1, 0>>}, {write, 16#4303, 3, <<1, 0>>},
                    {write, 16#4303, 4, <<1, 0>>}], R({enable, true})),
     ?_assertEqual([{write, 16#4303, 2, <<0, 0>>}, {write, 16#4303, 3, <<0, 0>>},
                    {write, 16#4303, 4, <<0, 0>>}], R({enable, false})),
     %% Override: 1000000 is 100 %, both ends and a fraction.
     ?_assertEqual([{write, 16#4303, 16#21, <<1000000:32/little>>}], R({override, 100})),
     ?_assertEqual([{write, 16#4303, 16#21, <<0:32/little>>}], R({override, 0})),
     ?_assertEqual([{write, 16#4303, 16#21, <<125000:32/little>>}], R({override, 12.5})),
     %% Set actual position (0x1A): absolute (1), reserved, the position.
     ?_assertEqual([{write, 16#4203, 16#1A, <<1:32/little, 0:32, -2.5:64/float-little>>}],
                   R({set_position, -2.5})),
     %% Extended start (0x21): absolute (1), reserved, target, velocity, then the
     %% acceleration, deceleration and jerk, each flagged as given (0).
     ?_assertEqual([{write, 16#4203, 16#21, <<1:32/little, 0:32, 250.0:64/float-little,
                                             100.0:64/float-little,
                                             0:32, 0:32, 1000.0:64/float-little,
                                             0:32, 0:32, 2000.0:64/float-little,
                                             0:32, 0:32, 5000.0:64/float-little>>}],
                   R({start, 250, ?PARAMS})),
     %% No jerk given: the axis's own (flag 1).
     ?_assertMatch([{write, 16#4203, 16#21, <<_:56/binary, 1:32/little, 0:32, _:8/binary>>}],
                   cell_hal_ads_nc:request({start, 250, ?PARAMS}, ?CTX#{jerk => 0}))].

%% What each of the state machine's effects writes to the NC, and the job watched.
effect_writes_test_() ->
    W0 = cell_hal_ads_nc:watch(undefined),
    Move = #{id => 1, kind => move, target => 10.0, params => ?PARAMS},
    Home = #{id => 2, kind => home, target => 5.0},
    Halt = #{id => 3, kind => halt, deceleration => 800},
    E = fun(Effects, W) -> cell_hal_ads_nc:effect_writes(Effects, W, ?CTX) end,
    [?_assertEqual({cell_hal_ads_nc:request({enable, true}, ?CTX), W0}, E([power_on], W0)),
     ?_assertEqual({cell_hal_ads_nc:request({start, 10.0, ?PARAMS}, ?CTX),
                    #{job => Move}}, E([{run, Move}], W0)),
     %% A newer job replaces the one watched; the aborted one writes nothing.
     ?_assertEqual({cell_hal_ads_nc:request({stop, 800, 5000}, ?CTX),
                    #{job => Halt}},
                   E([{aborted, Move}, {run, Halt}], #{job => Move})),
     ?_assertEqual({cell_hal_ads_nc:request(reference, ?CTX),
                    #{job => Home}}, E([{run, Home}], W0)),
     %% Homing done: the actual position set to the one asked.
     ?_assertEqual({cell_hal_ads_nc:request({set_position, 5.0}, ?CTX), W0},
                   E([{done, Home}], #{job => Home})),
     ?_assertEqual({[], W0}, E([{failed, Move, 16#4550}, quick_stop],
                               #{job => Move})),
     ?_assertEqual({cell_hal_ads_nc:request({enable, false}, ?CTX), W0},
                   E([{aborted, Move}, power_off], #{job => Move})),
     ?_assertEqual({cell_hal_ads_nc:request({override, 40}, ?CTX), W0},
                   E([{override, 40}], W0))].

command_writes_test_() ->
    C = fun(Command, State) -> cell_hal_ads_nc:command_writes(Command, State, ?CTX) end,
    [?_assertEqual(cell_hal_ads_nc:request(reset, ?CTX), C(reset, error_stop)),
     ?_assertEqual([], C(reset, standstill)),
     ?_assertEqual(cell_hal_ads_nc:request({enable, false}, ?CTX), C({power, false}, error_stop)),
     ?_assertEqual([], C({power, false}, standstill)),
     ?_assertEqual([], C({move_absolute, 1, ?PARAMS}, standstill))].

decode_test_() ->
    [?_assertMatch({ok, #{error := 0, position := 12.5, velocity := -3.0, override := 50.0,
                          has_job := true, not_moving := false, referenced := true,
                          enabled := true, homing := false, in_error := false}},
                   cell_hal_ads_nc:decode_online(
                     online(#{pos => 12.5, vel => -3.0, override => 500000,
                              bits => [1, 8, 20]}))),
     ?_assertMatch({ok, #{error := 16#4550, in_error := true, has_job := false}},
                   cell_hal_ads_nc:decode_online(online(#{error => 16#4550, bits => [2, 31]}))),
     %% Cut right after the status word: enough; a byte less is not.
     ?_assertMatch({ok, #{not_moving := true}},
                   cell_hal_ads_nc:decode_online(binary:part(online(#{bits => [2]}), 0, 108))),
     ?_assertEqual({error, {short_online_state, 107}},
                   cell_hal_ads_nc:decode_online(binary:part(online(#{}), 0, 107)))].

%% A poll's news: faults once, a job's end only when the NC says so.
news_test_() ->
    Move = #{id => 7, kind => move, target => 100.0, params => ?PARAMS},
    Home = #{id => 8, kind => home, target => 0.0},
    Halt = #{id => 9, kind => halt, deceleration => 100},
    N = fun(Online, W, State) ->
                {ok, O} = cell_hal_ads_nc:decode_online(online(Online)),
                cell_hal_ads_nc:news(O, W, #{state => State, ctx => ?CTX})
        end,
    Watch = fun(Job) -> cell_hal_ads_nc:watch(Job) end,
    Moving = #{pos => 50.0, vel => 10.0, bits => [8, 20]},
    [?_assertMatch({[], #{job := Move}}, N(Moving, Watch(Move), discrete_motion)),
     ?_assertMatch({[{done, 7}], _},
                   N(#{pos => 100.0, bits => [2, 4, 20]}, Watch(Move), discrete_motion)),
     %% Within in_position of the target, and just beyond it.
     ?_assertMatch({[{done, 7}], _},
                   N(#{pos => 99.995, bits => [2, 20]}, Watch(Move), discrete_motion)),
     ?_assertMatch({[], _}, N(#{pos => 99.98, bits => [2, 20]}, Watch(Move), discrete_motion)),
     %% Standing at the target but the NC still has the job: not yet.
     ?_assertMatch({[], _}, N(#{pos => 100.0, bits => [2, 8, 20]}, Watch(Move), discrete_motion)),
     ?_assertMatch({[{fault, 16#4550}], #{job := undefined}},
                   N(#{error => 16#4550, bits => [2, 31]}, Watch(Move), discrete_motion)),
     %% In ErrorStop the fault is old news.
     ?_assertMatch({[], _}, N(#{error => 16#4550, bits => [2, 31]}, Watch(undefined), error_stop)),
     ?_assertMatch({[{fault, 16#4260}], _},
                   N(#{error => 16#4260, bits => [2, 31]}, Watch(undefined), standstill)),
     %% Homing: done once the NC has no job, is not homing and is referenced.
     ?_assertMatch({[], _}, N(#{bits => [2, 8, 11, 20]}, Watch(Home), homing)),
     ?_assertMatch({[], _}, N(#{bits => [2, 20]}, Watch(Home), homing)),
     ?_assertMatch({[{done, 8}], _}, N(#{bits => [1, 2, 20]}, Watch(Home), homing)),
     ?_assertMatch({[], _}, N(#{vel => 5.0, bits => [8, 20]}, Watch(Halt), discrete_motion)),
     ?_assertMatch({[{done, 9}], _}, N(#{pos => 3.0, bits => [2, 20]}, Watch(Halt),
                                       discrete_motion)),
     ?_assertMatch({[], _}, N(#{bits => [2, 20]}, Watch(undefined), standstill))].

%% The axis's state rebuilt from the NC's after a (re)connection.
resync_test_() ->
    New = cell_hal_axis_fsm:new(#{limits => none}),
    R = fun(Online, Override) ->
                {ok, O} = cell_hal_ads_nc:decode_online(online(Online)),
                A = cell_hal_ads_nc:resync(O, New, Override),
                {cell_hal_axis_fsm:state(A), cell_hal_axis_fsm:powered(A),
                 cell_hal_axis_fsm:homed(A), cell_hal_axis_fsm:error_code(A),
                 cell_hal_axis_fsm:override(A)}
        end,
    [?_assertEqual({disabled, false, false, 0, 100}, R(#{bits => [2]}, 100)),
     ?_assertEqual({standstill, true, false, 0, 100}, R(#{bits => [0, 2, 20]}, 100)),
     ?_assertEqual({standstill, true, true, 0, 30}, R(#{bits => [0, 1, 2, 20]}, 30)),
     ?_assertEqual({error_stop, true, true, 16#4550, 100},
                   R(#{error => 16#4550, bits => [1, 2, 20, 31]}, 100))].

%% An online structure of TwinCAT 3's layout (256 bytes).
online(M) ->
    Pos = maps:get(pos, M, 0.0),
    Vel = maps:get(vel, M, 0.0),
    Bits = lists:foldl(fun(B, Acc) -> Acc bor (1 bsl B) end, 0, maps:get(bits, M, [])),
    Head = <<(maps:get(error, M, 0)):32/signed-little, 0:32,
             Pos:64/float-little, Pos:64/float-little, Pos:64/float-little,
             Pos:64/float-little, Vel:64/float-little, Vel:64/float-little,
             (maps:get(override, M, 1000000)):32/little, 0:32,
             0:5/unit:64, Bits:32/little, 0:32, 0:32, 0:32>>,
    <<Head/binary, 0:((256 - byte_size(Head)) * 8)>>.
