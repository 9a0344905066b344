%% Unit tests of the requests of a connection in jobs: queued, sent under odd invoke
%% ids, answered in one piece, timed out, abandoned.
-module(cell_hal_ads_jobs_tests).
-include_lib("eunit/include/eunit.hrl").

-define(J, cell_hal_ads_jobs).

cont() ->
    fun(Answers, Data) -> {Answers, Data} end.

answered_in_one_piece_test() ->
    T0 = ?J:add([read_state, read_device_info], from, 100, cont(), 0, ?J:new()),
    ?assert(?J:waiting(T0)),
    {I1, read_state, T1} = ?J:next(T0),
    {I2, read_device_info, T2} = ?J:next(T1),
    ?assertNot(?J:waiting(T2)),
    %% odd ids: the even ones are the direct reads'
    ?assertEqual({3, 5}, {I1, I2}),
    ?assertEqual(2, ?J:in_flight(T2)),
    %% answered out of order: the job is done with its last answer, answers in order
    {ok, Id, 2, T3} = ?J:answered(I2, read_device_info, T2),
    {pending, T4} = ?J:deliver(Id, 2, {ok, info}, T3),
    ?assertEqual({unexpected, read_state}, ?J:answered(I1, read, T4)),
    ?assertEqual(unknown, ?J:answered(99, read, T4)),
    {ok, Id, 1, T5} = ?J:answered(I1, read_state, T4),
    {done, Cont, Answers, T6} = ?J:deliver(Id, 1, {ok, {run, 0}}, T5),
    ?assertEqual({[{ok, {run, 0}}, {ok, info}], data}, Cont(Answers, data)),
    ?assertEqual(0, ?J:in_flight(T6)),
    ?assertEqual(infinity, ?J:earliest(T6)).

deadlines_test() ->
    T0 = ?J:add([read_state], a, 200, cont(), 5, ?J:new()),
    {set, T1} = ?J:arm(200, T0),
    T2 = ?J:add([read_state, read_state], b, 100, cont(), 7, T1),
    %% armed for the earliest deadline; a later one leaves it
    {set, T3} = ?J:arm(100, T2),
    keep = ?J:arm(150, T3),
    {3, _, T4} = ?J:next(T3),
    {5, _, T5} = ?J:next(T4),
    {ok, B, 1, T6} = ?J:answered(5, read_state, T5),
    {pending, T7} = ?J:deliver(B, 1, {ok, {run, 0}}, T6),
    ?assertEqual([], ?J:due(99, T7)),
    ?assertEqual([B], ?J:due(100, T7)),
    ?assertEqual([B, 1], ?J:due(200, T7)),
    %% a timeout for the answer missing (its request, still queued, is dropped);
    %% packets came since it started
    {Cont, Answers, 0, false, T8} = ?J:time_out(B, 8, T7),
    ?assertEqual({[{ok, {run, 0}}, {error, timeout}], x}, Cont(Answers, x)),
    ?assertNot(?J:waiting(T8)),
    ?assertEqual(none, ?J:time_out(B, 8, T8)),
    ?assertEqual(200, ?J:earliest(T8)),
    %% nothing received since the job started: the connection is dead; its slot freed
    {_, [{error, timeout}], 1, true, T9} = ?J:time_out(1, 5, T8),
    ?assertEqual(0, ?J:in_flight(T9)),
    ?assertEqual(unknown, ?J:answered(3, read_state, T9)).

abandon_test() ->
    T0 = ?J:add([read_state], undefined, infinity, cont(), 0,
                ?J:add([read_state], from, infinity, cont(), 0, ?J:new())),
    {_, _, T1} = ?J:next(T0),
    {[from], T2} = ?J:abandon(T1),
    ?assertEqual(0, ?J:in_flight(T2)),
    ?assertNot(?J:waiting(T2)),
    %% the ids go on after a reconnect
    {5, _, _} = ?J:next(?J:add([read_state], from, infinity, cont(), 0, T2)).
