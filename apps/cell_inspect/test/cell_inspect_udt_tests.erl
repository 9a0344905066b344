%% The S7 UDT of seed 004 byte for byte: the seed's offset table, the whole block built
%% by hand at those offsets, Modbus registers, and the layout's rules for other string
%% lengths as properties.
-module(cell_inspect_udt_tests).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(U, cell_inspect_udt).

%% The seed's table, copied as it stands: name, offset, declared length.
seed_table() ->
    [{heartbeat, {0, 0}}, {trigger_inspection_echo, {0, 1}}, {clear_results_echo, {0, 2}},
     {cancel_inspection_echo, {0, 3}}, {log_override_echo, {0, 4}},
     {inspection_pass, {0, 5}}, {inspection_fail, {0, 6}}, {send_message_echo, {0, 7}},
     {inspection_status, {2, none}}, {error_code, {4, none}},
     {inspection_point_id_echo, {6, none}}, {part_serial_echo, {24, none}},
     {employee_override_echo, {74, none}}, {inspection_string, {124, none}},
     {message_id_echo, {296, none}}, {message_status, {298, none}},
     {message_result, {300, none}},
     {trigger_inspection, {174, 0}}, {clear_results, {174, 1}},
     {cancel_inspection, {174, 2}}, {log_override, {174, 3}}, {send_message, {174, 4}},
     {inspection_point_id, {176, none}}, {part_serial, {194, none}},
     {override_employee_id, {244, none}}, {message_id, {294, none}}].

default() -> ?U:layout(?U:default_lengths()).

seed_offsets_test_() ->
    L = default(),
    [?_assertEqual({T, Off}, {T, ?U:offset(T, L)}) || {T, Off} <- seed_table()] ++
    [?_assertEqual(26, length(L))].

%% MessageResult, a STRING[48] at 300, ends at 349: 350 bytes. The seed's "348 bytes
%% (depending on string length)" is the same block with a STRING[46] there.
size_test_() ->
    [?_assertEqual(350, ?U:size(default())),
     ?_assertEqual(348, ?U:size(?U:layout((?U:default_lengths())#{result => 46})))].

values() ->
    #{heartbeat => true, trigger_inspection_echo => false, clear_results_echo => true,
      cancel_inspection_echo => false, log_override_echo => true, inspection_pass => true,
      inspection_fail => false, send_message_echo => true,
      inspection_status => 2, error_code => -3,
      inspection_point_id_echo => <<"STATION-01">>, part_serial_echo => <<"SN 4711">>,
      employee_override_echo => <<"E42">>, inspection_string => <<"OCR:AB12">>,
      message_id_echo => 513, message_status => 5, message_result => <<"yes">>,
      trigger_inspection => true, clear_results => false, cancel_inspection => true,
      log_override => false, send_message => true,
      inspection_point_id => <<"STATION-01">>,
      part_serial => <<"0123456789012345678901234567890123456789012345678">>,
      override_employee_id => <<>>, message_id => -1}.

%% The whole UDT, built by hand from the seed's offsets only.
by_hand() ->
    Patches =
        [{2, <<0, 2>>}, {4, <<16#FF, 16#FD>>},
         {6, <<16, 10, "STATION-01">>}, {24, <<48, 7, "SN 4711">>}, {74, <<48, 3, "E42">>},
         {124, <<48, 8, "OCR:AB12">>},
         {174, <<2#00010101>>},
         {176, <<16, 10, "STATION-01">>},
         {194, <<48, 48, "012345678901234567890123456789012345678901234567">>},
         {244, <<48, 0>>},
         {294, <<16#FF, 16#FF>>}, {296, <<16#02, 16#01>>}, {298, <<0, 5>>},
         {300, <<48, 3, "yes">>}],
    lists:foldl(fun({At, Bytes}, Bin) ->
                        <<Pre:At/binary, _:(byte_size(Bytes))/binary, Post/binary>> = Bin,
                        <<Pre/binary, Bytes/binary, Post/binary>>
                end, <<0:350/unit:8>>, Patches).

whole_udt_test_() ->
    %% Byte 0: Heartbeat .0, ClearResults_ECHO .2, LogOveride_ECHO .4,
    %% Inspection_PASS .5, SendMessage_ECHO .7 -> 1 + 4 + 16 + 32 + 128 = 181.
    %% Byte 174: TriggerInspection .0, CancelInspection .2, SendMessage .4 -> 21.
    <<_, Rest/binary>> = by_hand(),
    Expected = <<181, Rest/binary>>,
    Bin = ?U:encode(default(), values()),
    Decoded = ?U:decode(default(), Bin),
    [?_assertEqual(350, byte_size(Bin)),
     ?_assertEqual(Expected, Bin),
     %% The PartSerial of 49 characters is cut to its 48.
     ?_assertEqual(maps:put(part_serial,
                            <<"012345678901234567890123456789012345678901234567">>, values()),
                   Decoded)].

s7_strings_test_() ->
    [?_assertEqual(<<4, 2, "AB", 0, 0>>, ?U:string_bytes(4, <<"AB">>)),
     ?_assertEqual(<<2, 2, "AB">>, ?U:string_bytes(2, <<"ABC">>)),
     ?_assertEqual(<<3, 0, 0, 0, 0>>, ?U:string_bytes(3, <<>>)),
     %% The actual length says what counts; bytes after it are not the value.
     ?_assertEqual(<<"AB">>, ?U:string_value(4, <<4, 2, "ABXY">>)),
     %% A PLC's own maximum, or the declared one, bounds a wrong actual length.
     ?_assertEqual(<<"ABC">>, ?U:string_value(4, <<3, 9, "ABCD">>)),
     ?_assertEqual(<<"ABCD">>, ?U:string_value(4, <<9, 9, "ABCDEF">>)),
     ?_assertEqual(<<>>, ?U:string_value(4, <<>>)),
     ?_assertEqual(16#1005, ?U:header(16, 5)),
     ?_assertEqual(16#1010, ?U:header(16, 99))].

%% Byte B is register B div 2; the even byte is the high half of its register.
registers_test_() ->
    [?_assertEqual(0, ?U:register(0)), ?_assertEqual(0, ?U:register(1)),
     ?_assertEqual(87, ?U:register(174)), ?_assertEqual(150, ?U:register(300)),
     ?_assertEqual(8, ?U:register_bit(0, 0)), ?_assertEqual(15, ?U:register_bit(0, 7)),
     ?_assertEqual(12, ?U:register_bit(174, 4)), ?_assertEqual(3, ?U:register_bit(175, 3))].

addresses_test_() ->
    L = default(),
    A = fun(T) -> ?U:address(hd([E || #{tag := X} = E <- L, X =:= T])) end,
    [?_assertEqual(<<"DBX174.4">>, A(send_message)), ?_assertEqual(<<"DBW2">>, A(inspection_status)),
     ?_assertEqual(<<"DBB300">>, A(message_result))].

lengths_test_() ->
    [?_assertMatch({ok, #{serial := 20, point_id := 16}}, ?U:check_lengths(#{serial => 20})),
     ?_assertEqual({error, {bad_option, serial}}, ?U:check_lengths(#{serial => 0})),
     ?_assertEqual({error, {bad_option, serial}}, ?U:check_lengths(#{serial => 255})),
     ?_assertMatch({ok, _}, ?U:check_lengths(#{result => 254})),
     ?_assertEqual({error, {bad_option, colour}}, ?U:check_lengths(#{colour => 1})),
     ?_assertEqual({error, {bad_option, lengths}}, ?U:check_lengths([]))].

%%--------------------------------------------------------------------
%% Properties: any lengths, any values
%%--------------------------------------------------------------------

properties_test_() ->
    [{timeout, 120, ?_assert(proper:quickcheck(prop_layout_rules(), [{to_file, user},
                                                                    {numtests, 300}]))},
     {timeout, 120, ?_assert(proper:quickcheck(prop_round_trip(), [{to_file, user},
                                                                  {numtests, 300}]))}].

lengths() ->
    ?LET({P, S, E, T, R}, {range(1, 254), range(1, 254), range(1, 254), range(1, 254),
                           range(1, 254)},
         #{point_id => P, serial => S, employee => E, string => T, result => R}).

%% Elements never overlap, words and strings start at even bytes, the tags keep the
%% seed's order, and the UDT ends at an even byte just after its last element.
prop_layout_rules() ->
    ?FORALL(L, lengths(),
            begin
                Layout = ?U:layout(L),
                Bits = lists:append([span(E) || E <- Layout]),
                Aligned = lists:all(fun(#{kind := bool}) -> true;
                                       (#{byte := B}) -> B rem 2 =:= 0
                                    end, Layout),
                Last = lists:max([B || {B, _} <- Bits]),
                Size = ?U:size(Layout),
                length(Bits) =:= length(lists:usort(Bits)) andalso Aligned
                    andalso [T || #{tag := T} <- Layout] =:= cell_inspect_tags:all()
                    andalso Size rem 2 =:= 0 andalso Size - Last =< 2
            end).

span(#{kind := bool, byte := B, bit := Bit}) -> [{B, Bit}];
span(#{kind := int, byte := B}) -> [{X, all} || X <- [B, B + 1]];
span(#{kind := {string, N}, byte := B}) -> [{X, all} || X <- lists:seq(B, B + N + 1)].

value(#{kind := bool}) -> boolean();
value(#{kind := int}) -> range(-32768, 32767);
value(#{kind := {string, N}}) ->
    ?LET(Len, range(0, N), ?LET(Bytes, vector(Len, range(1, 255)), list_to_binary(Bytes))).

prop_round_trip() ->
    ?FORALL(L, lengths(),
            begin
                Layout = ?U:layout(L),
                ?FORALL(Values, fixed_map(maps:from_list([{T, value(E)}
                                                         || #{tag := T} = E <- Layout])),
                        begin
                            Bin = ?U:encode(Layout, Values),
                            byte_size(Bin) =:= ?U:size(Layout)
                                andalso ?U:decode(Layout, Bin) =:= Values
                        end)
            end).

fixed_map(M) ->
    ?LET(Pairs, [{K, V} || {K, V} <- maps:to_list(M)], maps:from_list(Pairs)).
