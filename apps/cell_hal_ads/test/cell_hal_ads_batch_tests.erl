%% Unit tests of batching: sum commands split only where the limit requires.
-module(cell_hal_ads_batch_tests).
-include_lib("eunit/include/eunit.hrl").

chunks_test_() ->
    C = fun cell_hal_ads_batch:chunks/2,
    [?_assertEqual([], C([], 3)),
     ?_assertEqual([[1]], C([1], 3)),
     ?_assertEqual([[1, 2, 3]], C([1, 2, 3], 3)),
     ?_assertEqual([[1, 2, 3], [4]], C([1, 2, 3, 4], 3)),
     ?_assertEqual([[1, 2, 3], [4, 5, 6], [7]], C(lists:seq(1, 7), 3)),
     ?_assertEqual([[1], [2]], C([1, 2], 1))].

items(N) -> [{16#F005, I, 4} || I <- lists:seq(1, N)].

reads_test_() ->
    Sum = #{sum => true, max_sum => 3},
    Plain = #{sum => false, max_sum => 3},
    Kinds = fun(Requests) -> [element(1, R) || R <- Requests] end,
    [?_assertMatch({[], _}, cell_hal_ads_batch:reads([], Sum)),
     %% one item is a plain read
     ?_assertMatch({[{read, 16#F005, 1, 4}], _}, cell_hal_ads_batch:reads(items(1), Sum)),
     ?_assertMatch({[{read_write, 16#F080, 3, 24, _}], _}, cell_hal_ads_batch:reads(items(3), Sum)),
     ?_assertMatch({[{read_write, 16#F080, 3, _, _}, {read, 16#F005, 4, 4}], _},
                   cell_hal_ads_batch:reads(items(4), Sum)),
     ?_assertMatch({[{read_write, 16#F080, 3, _, _}, {read_write, 16#F080, 2, _, _}], _},
                   cell_hal_ads_batch:reads(items(5), Sum)),
     ?_assertEqual([read, read, read, read], Kinds(element(1, cell_hal_ads_batch:reads(items(4), Plain))))].

assemble_test() ->
    {_, Assemble} = cell_hal_ads_batch:reads(items(4), #{sum => true, max_sum => 3}),
    SumAnswer = {ok, <<0:32, 16#710:32/little, 0:32, 1:32/little, 0:32, 3:32/little>>},
    ?assertEqual([{ok, <<1:32/little>>}, {error, {ads_error, 16#710, symbol_not_found}},
                  {ok, <<3:32/little>>}, {ok, <<4:32/little>>}],
                 Assemble([SumAnswer, {ok, <<4:32/little>>}])),
    %% a whole sum failing fails each of its items, not the others
    ?assertEqual([{error, timeout}, {error, timeout}, {error, timeout}, {ok, <<4:32/little>>}],
                 Assemble([{error, timeout}, {ok, <<4:32/little>>}])),
    %% a malformed sum answer too
    ?assertEqual([{error, {bad_response, sum_too_short}} || _ <- [1, 2, 3]] ++ [{error, timeout}],
                 Assemble([{ok, <<>>}, {error, timeout}])).

writes_test() ->
    Items = [{16#F005, I, <<I>>} || I <- lists:seq(1, 3)],
    {Requests, Assemble} = cell_hal_ads_batch:writes(Items, #{sum => true, max_sum => 2}),
    ?assertMatch([{read_write, 16#F081, 2, 8, _}, {write, 16#F005, 3, <<3>>}], Requests),
    ?assertEqual([ok, {error, {ads_error, 16#704, invalid_access}}, ok],
                 Assemble([{ok, <<0:32, 16#704:32/little>>}, {ok, ok}])),
    {Plain, Assemble2} = cell_hal_ads_batch:writes(Items, #{sum => false, max_sum => 2}),
    ?assertEqual(3, length(Plain)),
    ?assertEqual([ok, {error, x}, ok], Assemble2([{ok, ok}, {error, x}, {ok, ok}])).

read_writes_test() ->
    Items = [{16#F003, 0, 4, <<"A", 0>>}, {16#F003, 0, 4, <<"B", 0>>}],
    {[Request], Assemble} = cell_hal_ads_batch:read_writes(Items, #{sum => true, max_sum => 500}),
    ?assertMatch({read_write, 16#F082, 2, 24, _}, Request),
    ?assertEqual([{ok, <<7:32/little>>}, {ok, <<8:32/little>>}],
                 Assemble([{ok, <<0:32, 4:32/little, 0:32, 4:32/little, 7:32/little, 8:32/little>>}])),
    ?assertMatch({read_write, 16#F080, 4, _, _}, sum_of_check(4)).

sum_of_check(N) ->
    {[R], _} = cell_hal_ads_batch:reads(items(N), #{sum => true, max_sum => N}),
    R.
