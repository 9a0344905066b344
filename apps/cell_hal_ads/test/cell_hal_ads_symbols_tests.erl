%% Unit tests of symbol names, wildcards and type checks.
-module(cell_hal_ads_symbols_tests).
-include_lib("eunit/include/eunit.hrl").

sym(Name, Type, DataType, Size) ->
    #{name => Name, type => Type, data_type => DataType, size => Size, comment => <<>>,
      group => 16#4040, offset => 0, flags => 0}.

table() ->
    cell_hal_ads_symbols:new(
      [sym(<<"MAIN.GeneralInputs">>, <<"GeneralInputs">>, 65, 2),
       sym(<<"Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn">>, <<"BIT">>, 33, 0),
       sym(<<"Term 6 (EL1008).Spare.In">>, <<"BIT">>, 33, 0),
       sym(<<"Term 7 (EL1008).Spare.In">>, <<"BIT">>, 33, 0),
       sym(<<"main.generalinputs">>, <<"Other">>, 65, 9),        % same name: first kept
       sym(<<>>, <<"BIT">>, 33, 0)]).                             % nameless: left out

lookup_test_() ->
    T = table(),
    L = fun(N) -> cell_hal_ads_symbols:lookup(N, T) end,
    [?_assertEqual(4, cell_hal_ads_symbols:count(T)),
     ?_assertMatch({ok, #{name := <<"MAIN.GeneralInputs">>, size := 2}}, L(<<"MAIN.GeneralInputs">>)),
     ?_assertMatch({ok, #{name := <<"MAIN.GeneralInputs">>}}, L(<<"main.GENERALinputs">>)),
     ?_assertEqual({error, {unknown_symbol, <<"MAIN.Nope">>}}, L(<<"MAIN.Nope">>)),
     ?_assertMatch({ok, #{name := <<"Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn">>}},
                   L(<<"*ManipulatorInputs.FailPaletteIsIn">>)),
     ?_assertMatch({ok, #{name := <<"Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn">>}},
                   L(<<"*FailPaletteIsIn">>)),
     %% "*" matches anything before, even nothing
     ?_assertMatch({ok, _}, L(<<"*Term 5 (EL1008).ManipulatorInputs.FailPaletteIsIn">>)),
     ?_assertEqual({error, {ambiguous_symbol, <<"*Spare.In">>,
                            [<<"Term 6 (EL1008).Spare.In">>, <<"Term 7 (EL1008).Spare.In">>]}},
                   L(<<"*Spare.In">>)),
     ?_assertEqual({error, {unknown_symbol, <<"*Spare.Out">>}}, L(<<"*Spare.Out">>)),
     ?_assertEqual({error, {unknown_symbol, <<"*X.Term 5 (EL1008).Spare.In">>}},
                   L(<<"*X.Term 5 (EL1008).Spare.In">>))].

ambiguity_names_at_most_five_test() ->
    T = cell_hal_ads_symbols:new([sym(<<"T", (integer_to_binary(I))/binary, ".In">>, <<"BIT">>, 33, 0)
                                  || I <- lists:seq(1, 9)]),
    {error, {ambiguous_symbol, _, Names}} = cell_hal_ads_symbols:lookup(<<"*.In">>, T),
    ?assertEqual(5, length(Names)).

check_name_test_() ->
    Ok = [<<"MAIN.x">>, <<".GeneralInputs.StartButton">>, <<"*In">>, <<"a">>],
    Bad = [<<>>, <<"*">>, <<"**x">>, <<"a*">>, <<"a*b">>, <<"a", 0, "b">>, "MAIN.x", 42,
           binary:copy(<<"a">>, 65536)],
    [?_assertEqual(ok, cell_hal_ads_symbols:check_name(N)) || N <- Ok] ++
    [?_assertEqual({error, {bad_name, N}}, cell_hal_ads_symbols:check_name(N)) || N <- Bad].

check_type_test_() ->
    [?_assertEqual(ok, cell_hal_ads_symbols:check_type(<<"x">>, int16, sym(<<"x">>, <<"INT">>, 2, 2))),
     ?_assertEqual({error, {type_mismatch, <<"x">>, #{expected => <<"DINT">>, plc_type => <<"INT">>,
                                                      size => 2}}},
                   cell_hal_ads_symbols:check_type(<<"x">>, int32, sym(<<"x">>, <<"INT">>, 2, 2)))].

read_size_test_() ->
    [?_assertEqual(1, cell_hal_ads_symbols:read_size(sym(<<"b">>, <<"BIT">>, 33, 0))),
     ?_assertEqual(81, cell_hal_ads_symbols:read_size(sym(<<"s">>, <<"STRING">>, 30, 81)))].

%% ASCII letters fold; other bytes are left as they are.
key_test() ->
    ?assertEqual(<<"MAIN.", 16#C3, 16#A4, "BC_1">>,
                 cell_hal_ads_symbols:key(<<"main.", 16#C3, 16#A4, "bc_1">>)).
