-module(cell_web_json_tests).
-include_lib("eunit/include/eunit.hrl").

%% A unit's info as `cell_unit:info/1' gives it, in a fault inside a nested sequence.
unit_info() ->
    #{kind => unit, unit_state => fault_reaction, halt => false,
      fault => <<"cylinder clamp did not arrive within 2000 ms">>,
      step => {2, clamp_seq, close},
      sequence => #{sequences => [#{module => main_seq, step => clamp, mode => many},
                                  #{module => clamp_seq, step => close, mode => one}],
                    waiting => [{timer, settle}], halt => false, held => false,
                    actuators => #{}}}.

unit_test_() ->
    U = cell_web_json:unit(unit_info()),
    [?_assertEqual(<<"fault_reaction">>, maps:get(<<"state">>, U)),
     ?_assertEqual(#{<<"sequence">> => <<"clamp_seq">>, <<"step">> => <<"close">>},
                   maps:get(<<"step">>, U)),
     ?_assertEqual([#{<<"sequence">> => <<"main_seq">>, <<"step">> => <<"clamp">>},
                    #{<<"sequence">> => <<"clamp_seq">>, <<"step">> => <<"close">>}],
                   maps:get(<<"sequences">>, U)),
     ?_assertEqual(<<"cylinder clamp did not arrive within 2000 ms">>, maps:get(<<"fault">>, U)),
     ?_assertEqual(false, maps:get(<<"halt">>, U)),
     ?_assertEqual(1, length(maps:get(<<"waiting_for">>, U))),
     %% It goes out as JSON.
     ?_assert(is_binary(cell_web_json:encode(U)))].

not_a_unit_test_() ->
    [?_assertEqual(null, cell_web_json:unit(#{state => off, request => stop})),
     ?_assertEqual(null, cell_web_json:unit(undefined))].

between_steps_test() ->
    Info = (unit_info())#{step => undefined, fault => undefined, unit_state => idle,
                          sequence => #{sequences => [], waiting => [], halt => false,
                                        held => false, actuators => #{}}},
    ?assertMatch(#{<<"step">> := null, <<"fault">> := null, <<"sequences">> := [],
                   <<"state">> := <<"idle">>}, cell_web_json:unit(Info)).
