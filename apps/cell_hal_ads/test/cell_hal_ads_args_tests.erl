%% Unit tests of the calls' argument checks, made in the caller.
-module(cell_hal_ads_args_tests).
-include_lib("eunit/include/eunit.hrl").

-define(A, cell_hal_ads_args).

checks_test_() ->
    V = {<<"MAIN.a">>, int32},
    [?_assert(?A:request({read, 1, 2, 3})),
     ?_assertNot(?A:request({read, -1, 2, 3})),
     ?_assertNot(?A:request({write, 1, 2, [bad]})),
     ?_assert(?A:request({write_control, run, 0, <<>>})),
     ?_assertEqual(ok, ?A:vars([V])),
     ?_assertEqual({error, {bad_variable, {<<"MAIN.a">>, float}}},
                   ?A:vars([V, {<<"MAIN.a">>, float}])),
     ?_assertEqual({error, {bad_argument, x}}, ?A:vars(x)),
     %% reads only look at the shape: an odd type is the connection's to answer
     ?_assertEqual(ok, ?A:shapes([{<<"MAIN.a">>, float}])),
     ?_assertEqual({error, {bad_variable, {a, int32}}}, ?A:shapes([{a, int32}])),
     ?_assertEqual(ok, ?A:pairs([{V, 1}])),
     ?_assertEqual({error, {bad_argument, [a]}}, ?A:pairs([a])),
     ?_assertEqual({error, {bad_variable, <<"MAIN.a">>}}, ?A:pairs([V])),
     ?_assertEqual({error, {bad_argument, [x]}}, ?A:refs([x])),
     ?_assertEqual(ok, ?A:refs([make_ref()])),
     ?_assertEqual({ok, [{V, #{mode => cyclic, cycle => 1000, max_delay => 0}}]},
                   ?A:subs([{V, #{mode => cyclic, cycle_us => 100}}])),
     ?_assertEqual({error, {bad_sub_opts, #{mode => x}}}, ?A:subs([{V, #{mode => x}}])),
     ?_assertEqual({error, {bad_argument, [V]}}, ?A:subs([V])),
     ?_assert(?A:items(read_writes, [{1, 2, 3, <<>>}])),
     ?_assertNot(?A:items(writes, [{1, 2, 3, <<>>}]))].
