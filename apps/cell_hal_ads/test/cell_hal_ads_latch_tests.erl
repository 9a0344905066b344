%% Unit tests of the laser-beam latch (seed 000 §2.3.7).
-module(cell_hal_ads_latch_tests).
-include_lib("eunit/include/eunit.hrl").

-define(L(S, P, O), cell_hal_ads_latch:position_at_edge(S, P, O)).

beam() -> [{10, false}, {20, false}, {30, true}, {40, true}, {50, false}].
axis() -> [{10, 1.0}, {20, 2.0}, {25, 2.5}, {30, 3.0}, {35, 3.5}, {50, 5.0}].

exact_stamp_test() ->
    ?assertEqual({ok, #{time => 30, position => 3.0, exact => true}}, ?L(beam(), axis(), #{})).

falling_edge_test() ->
    ?assertEqual({ok, #{time => 50, position => 5.0, exact => true}},
                 ?L(beam(), axis(), #{edge => falling})).

hold_test() ->
    %% no position sample at 30: the last one before it held
    Axis = [{10, 1.0}, {25, 2.5}, {35, 3.5}],
    ?assertEqual({ok, #{time => 30, position => 2.5, exact => false}}, ?L(beam(), Axis, #{})).

interpolate_test() ->
    Axis = [{10, 1.0}, {25, 2.5}, {35, 3.5}],
    {ok, #{time := 30, position := P, exact := false}} =
        ?L(beam(), Axis, #{method => interpolate}),
    ?assert(abs(P - 3.0) < 1.0e-9).

interpolate_needs_a_later_sample_test() ->
    ?assertEqual({error, {no_position, 30}},
                 ?L(beam(), [{10, 1.0}, {25, 2.5}], #{method => interpolate})).

no_position_before_edge_test() ->
    ?assertEqual({error, {no_position, 30}}, ?L(beam(), [{31, 3.1}], #{})).

no_edge_test_() ->
    [?_assertEqual({error, no_edge}, ?L([{1, false}, {2, false}], axis(), #{})),
     ?_assertEqual({error, no_edge}, ?L([], axis(), #{})),
     %% the first sample only sets the level ...
     ?_assertEqual({error, no_edge}, ?L([{30, true}, {40, true}], axis(), #{})),
     %% ... unless the level before it is known
     ?_assertEqual({ok, #{time => 30, position => 3.0, exact => true}},
                   ?L([{30, true}], axis(), #{initial => false}))].

from_test() ->
    Beam = [{10, false}, {20, true}, {25, false}, {30, true}],
    ?assertMatch({ok, #{time := 20}}, ?L(Beam, axis(), #{})),
    ?assertMatch({ok, #{time := 30}}, ?L(Beam, axis(), #{from => 21})),
    ?assertMatch({ok, #{time := 20}}, ?L(Beam, axis(), #{from => 20})).

any_order_test() ->
    %% samples from several messages, not sorted
    ?assertEqual(?L(beam(), axis(), #{}),
                 ?L(lists:reverse(beam()), lists:reverse(axis()), #{})).

first_edge_test_() ->
    [?_assertEqual({ok, 30}, cell_hal_ads_latch:first_edge(beam(), #{})),
     ?_assertEqual(none, cell_hal_ads_latch:first_edge([{1, true}], #{})),
     ?_assertEqual({ok, 1}, cell_hal_ads_latch:first_edge([{1, false}], #{edge => falling,
                                                                       initial => true}))].
