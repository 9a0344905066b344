%% The virtual PLC's register map without sockets: what it answers and what it writes,
%% both sides of every limit.
-module(cell_vplc_image_tests).

-include_lib("eunit/include/eunit.hrl").

f(Unit, Table, A) -> #{unit => Unit, table => Table, address => A, bit => none,
                       word_order => big}.

image() ->
    {ok, I} = cell_vplc_image:new(
                [{{g, run}, bool, f(1, coil, 10)},
                 {{g, seen}, bool, f(1, discrete_input, 10)},
                 {{g, seen2}, bool, f(1, discrete_input, 11)},
                 {{g, target}, lreal, f(1, holding_register, 100)},
                 {{g, cmd}, int32, f(1, holding_register, 104)},
                 {{g, pos}, int32, f(1, input_register, 100)},
                 {{g, name}, {string, 3}, f(1, input_register, 102)},
                 {{h, other}, int16, (f(2, holding_register, 0))#{word_order => little}}]),
    I.

values() ->
    #{{g, seen} => true, {g, target} => 2.5, {g, cmd} => 70000, {g, pos} => -2,
      {g, name} => <<"abc">>}.

ask(Unit, Pdu) -> ask(Unit, Pdu, values()).

ask(Unit, Pdu, Values) ->
    cell_vplc_image:answer(Unit, Pdu, {image(), fun(K) -> maps:get(K, Values, undefined) end}).

new_test_() ->
    [?_assertEqual([1, 2], cell_vplc_image:units(image())),
     ?_assertEqual(1 + 2 + 4 + 2 + 2 + 2 + 1, cell_vplc_image:size(image())),
     %% An lreal over 100..103 and an int16 at 103 share a register.
     ?_assertEqual({error, {overlap, {g, a}, {g, b}}},
                   cell_vplc_image:new([{{g, a}, lreal, f(1, holding_register, 100)},
                                        {{g, b}, int16, f(1, holding_register, 103)}])),
     ?_assertMatch({ok, _}, cell_vplc_image:new([{{g, a}, lreal, f(1, holding_register, 100)},
                                                 {{g, b}, int16, f(1, holding_register, 104)}])),
     %% The same address in two tables or two units is two places.
     ?_assertMatch({ok, _}, cell_vplc_image:new([{{g, a}, bool, f(1, coil, 0)},
                                                 {{g, b}, bool, f(1, discrete_input, 0)},
                                                 {{g, c}, bool, f(2, coil, 0)}]))].

read_test_() ->
    [?_assertEqual({reply, <<2, 1, 2#01>>, []}, ask(1, <<2, 10:16, 2:16>>)),
     %% Unset reads as zero.
     ?_assertEqual({reply, <<1, 1, 0>>, []}, ask(1, <<1, 10:16, 1:16>>)),
     ?_assertEqual({reply, <<3, 12, 2.5:64/float, 70000:32>>, []}, ask(1, <<3, 100:16, 6:16>>)),
     ?_assertEqual({reply, <<4, 8, -2:32, "abc", 0>>, []}, ask(1, <<4, 100:16, 4:16>>)),
     %% Part of a value: its own words.
     ?_assertEqual({reply, <<3, 4, 70000:32>>, []}, ask(1, <<3, 104:16, 2:16>>)),
     ?_assertEqual({reply, <<3, 2, (70000 band 16#FFFF):16>>, []}, ask(1, <<3, 105:16, 1:16>>)),
     %% One past either end of a span.
     ?_assertEqual({reply, <<16#82, 2>>, []}, ask(1, <<2, 9:16, 2:16>>)),
     ?_assertEqual({reply, <<16#82, 2>>, []}, ask(1, <<2, 10:16, 3:16>>)),
     ?_assertEqual({reply, <<16#83, 2>>, []}, ask(1, <<3, 100:16, 7:16>>)),
     %% A table asked at an address another table holds.
     ?_assertEqual({reply, <<16#81, 2>>, []}, ask(1, <<1, 11:16, 1:16>>)),
     ?_assertEqual({reply, <<16#83, 11>>, []}, ask(3, <<3, 100:16, 1:16>>)),
     ?_assertEqual({reply, <<16#83, 3>>, []}, ask(1, <<3, 100:16, 126:16>>)),
     ?_assertEqual({reply, <<16#81, 3>>, []}, ask(1, <<1, 0:16, 0:16>>)),
     ?_assertEqual({reply, <<16#C1, 1>>, []}, ask(1, <<16#41, 0>>)),
     ?_assertEqual(close, ask(1, <<>>))].

write_test_() ->
    [?_assertEqual({reply, <<5, 10:16, 16#FF00:16>>, [{{g, run}, true}]},
                   ask(1, <<5, 10:16, 16#FF00:16>>)),
     ?_assertEqual({reply, <<15, 10:16, 1:16>>, [{{g, run}, false}]},
                   ask(1, <<15, 10:16, 1:16, 1, 0>>)),
     %% Coils and inputs: only coils are written.
     ?_assertEqual({reply, <<16#85, 2>>, []}, ask(1, <<5, 11:16, 16#FF00:16>>)),
     ?_assertEqual({reply, <<16, 100:16, 4:16>>, [{{g, target}, 1.0}]},
                   ask(1, <<16, 100:16, 4:16, 8, 1.0:64/float>>, #{})),
     %% A holding register no point holds.
     ?_assertEqual({reply, <<16#90, 2>>, []}, ask(1, <<16, 99:16, 1:16, 2, 0:16>>)),
     ?_assertEqual({reply, <<16, 100:16, 6:16>>, [{{g, target}, -1.5}, {{g, cmd}, 9}]},
                   ask(1, <<16, 100:16, 6:16, 12, -1.5:64/float, 9:32>>)),
     %% The low word alone: the high word kept.
     ?_assertEqual({reply, <<6, 105:16, 5:16>>, [{{g, cmd}, 65536 + 5}]},
                   ask(1, <<6, 105:16, 5:16>>)),
     ?_assertEqual({reply, <<22, 105:16, 16#FFF0:16, 16#0003:16>>,
                    [{{g, cmd}, 65536 + ((70000 band 16#FFF0) bor 3)}]},
                   ask(1, <<22, 105:16, 16#FFF0:16, 16#0003:16>>)),
     %% The write first, then the read, which sees it.
     ?_assertEqual({reply, <<23, 4, 8:32>>, [{{g, cmd}, 8}]},
                   ask(1, <<23, 104:16, 2:16, 104:16, 2:16, 4, 8:32>>)),
     %% Unit 2's word order does not matter for a single register.
     ?_assertEqual({reply, <<6, 0:16, 65535:16>>, [{{h, other}, -1}]},
                   ask(2, <<6, 0:16, 65535:16>>)),
     ?_assertEqual({reply, <<16#85, 3>>, []}, ask(1, <<5, 10:16, 16#1234:16>>))].

%% Booleans packed into the bits of a holding register (an S7 UDT's BOOLs): read as one
%% word, a write sets each from its bit; a bit taken twice, or a register shared with a
%% value, is refused.
packed_bits_test_() ->
    Bit = fun(A, B) -> (f(1, holding_register, A))#{bit => B} end,
    {ok, I} = cell_vplc_image:new([{{u, hb}, bool, Bit(5, 8)}, {{u, echo}, bool, Bit(5, 9)},
                                   {{u, pass}, bool, Bit(5, 0)},
                                   {{u, status}, int16, f(1, holding_register, 6)}]),
    Values = #{{u, hb} => true, {u, pass} => true, {u, status} => 2},
    Ask = fun(Pdu) -> cell_vplc_image:answer(1, Pdu, {I, fun(K) -> maps:get(K, Values, undefined) end}) end,
    [?_assertEqual({reply, <<3, 4, 16#01, 16#01, 0, 2>>, []}, Ask(<<3, 5:16, 2:16>>)),
     ?_assertEqual({reply, <<6, 5:16, 16#0200:16>>,
                    [{{u, pass}, false}, {{u, hb}, false}, {{u, echo}, true}]},
                   Ask(<<6, 5:16, 16#0200:16>>)),
     ?_assertEqual({error, {overlap, {u, a}, {u, b}}},
                   cell_vplc_image:new([{{u, a}, bool, Bit(5, 1)}, {{u, b}, bool, Bit(5, 1)}])),
     ?_assertEqual({error, {overlap, {u, a}, {u, b}}},
                   cell_vplc_image:new([{{u, a}, int16, f(1, holding_register, 5)},
                                        {{u, b}, bool, Bit(5, 1)}])),
     ?_assertEqual({error, {overlap, {u, a}, {u, b}}},
                   cell_vplc_image:new([{{u, a}, bool, Bit(5, 1)},
                                        {{u, b}, int16, f(1, holding_register, 5)}]))].
