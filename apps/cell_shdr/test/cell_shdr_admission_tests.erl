%% Unit tests of the adapter's admission (pure): both sides of the limit.
-module(cell_shdr_admission_tests).
-include_lib("eunit/include/eunit.hrl").

below_the_limit_test() ->
    ?assertEqual(admit, cell_shdr_admission:admit([], 1)),
    ?assertEqual(admit, cell_shdr_admission:admit([{1, false, a}, {2, true, b}], 3)).

at_the_limit_the_oldest_silent_one_gives_its_place_test() ->
    Clients = [{5, false, e}, {1, true, a}, {3, false, c}, {2, true, b}],
    ?assertEqual({evict, c}, cell_shdr_admission:admit(Clients, 4)),
    ?assertEqual({evict, e}, cell_shdr_admission:admit([{5, false, e}, {1, true, a}], 2)).

at_the_limit_all_alive_test() ->
    ?assertEqual(full, cell_shdr_admission:admit([{1, true, a}], 1)),
    ?assertEqual(full, cell_shdr_admission:admit([{1, true, a}, {2, true, b}], 2)).

limit_lowered_below_the_clients_test() ->
    ?assertEqual(full, cell_shdr_admission:admit([{1, true, a}, {2, true, b}], 1)),
    ?assertEqual({evict, b}, cell_shdr_admission:admit([{1, true, a}, {2, false, b}], 1)).
