%% Unit tests of the Modbus TCP codec: the worked examples of the Modbus Application
%% Protocol Specification V1.1b3, both sides of every limit, and malformed frames.
-module(cell_hal_modbus_codec_tests).
-include_lib("eunit/include/eunit.hrl").

-import(cell_hal_modbus_codec, [check_request/1, request_pdu/1, adu/3, frame/1,
                                decode_request/1, response_pdu/2, decode_response/2]).

h(Hex) -> binary:decode_hex(list_to_binary([C || C <- Hex, C =/= $\s])).

bits(Str) -> [C =:= $1 || C <- Str].

%% The specification's examples, request and response, byte for byte.
spec_examples_test_() ->
    Examples =
        [%% 6.1: coils 20..38 (address 19, 19 coils)
         {{read_coils, 19, 19}, "01 0013 0013", "01 03 CD 6B 05",
          bits("1011001111010110101")},
         %% 6.2: discrete inputs 197..218
         {{read_discrete_inputs, 196, 22}, "02 00C4 0016", "02 03 AC DB 35",
          bits("0011010111011011101011")},
         %% 6.3: holding registers 108..110
         {{read_holding_registers, 107, 3}, "03 006B 0003", "03 06 022B 0000 0064",
          h("022B 0000 0064")},
         %% 6.4: input register 9
         {{read_input_registers, 8, 1}, "04 0008 0001", "04 02 000A", h("000A")},
         %% 6.5: coil 173 on
         {{write_single_coil, 172, true}, "05 00AC FF00", "05 00AC FF00", ok},
         %% 6.6: register 2 := 3
         {{write_single_register, 1, 3}, "06 0001 0003", "06 0001 0003", ok},
         %% 6.11: coils 20..29
         {{write_multiple_coils, 19, bits("1011001110")}, "0F 0013 000A 02 CD 01",
          "0F 0013 000A", ok},
         %% 6.12: registers 2..3
         {{write_multiple_registers, 1, h("000A 0102")}, "10 0001 0002 04 000A 0102",
          "10 0001 0002", ok},
         %% 6.16: mask write register 5
         {{mask_write_register, 4, 16#F2, 16#25}, "16 0004 00F2 0025", "16 0004 00F2 0025",
          ok},
         %% 6.17: read 4..9, write 15..17
         {{read_write_registers, 3, 6, 14, h("00FF 00FF 00FF")},
          "17 0003 0006 000E 0003 06 00FF 00FF 00FF",
          "17 0C 00FE 0ACD 0001 0003 000D 00FF", h("00FE 0ACD 0001 0003 000D 00FF")}],
    lists:append(
      [[?_assertEqual(ok, check_request(Req)),
        ?_assertEqual(h(ReqHex), request_pdu(Req)),
        ?_assertEqual({ok, Req}, decode_request(h(ReqHex))),
        ?_assertEqual(h(RespHex), response_pdu(Req, Reply)),
        ?_assertEqual({ok, Reply}, decode_response(Req, h(RespHex)))]
       || {Req, ReqHex, RespHex, Reply} <- Examples]).

%% 7: an exception reply is the function code with its top bit set and one code.
exceptions_test_() ->
    Req = {read_holding_registers, 0, 1},
    [?_assertEqual({exception, 2}, decode_response(Req, h("83 02"))),
     ?_assertEqual({exception, 11}, decode_response(Req, h("83 0B"))),
     ?_assertEqual(h("83 01"), response_pdu(Req, {exception, 1})),
     ?_assertEqual({error, bad_exception}, decode_response(Req, h("83"))),
     ?_assertEqual({error, bad_exception}, decode_response(Req, h("83 02 00"))),
     ?_assertEqual({error, bad_exception}, decode_response(Req, h("83 00"))),
     ?_assertEqual({error, {wrong_function, 3, 4}}, decode_response(Req, h("84 02"))),
     ?_assertEqual(illegal_function, cell_hal_modbus_codec:exception_name(1)),
     ?_assertEqual(illegal_data_address, cell_hal_modbus_codec:exception_name(2)),
     ?_assertEqual(gateway_target_failed_to_respond,
                   cell_hal_modbus_codec:exception_name(11)),
     ?_assertEqual(unknown_exception, cell_hal_modbus_codec:exception_name(99))].

%% Every exception a PLC sends reads as words an operator understands, with the
%% specification's name and code for the PLC's manual.
exception_words_test_() ->
    T = fun(Code) -> lists:flatten(cell_hal_modbus_codec:exception_text(Code)) end,
    Words = [{1, "the PLC does not offer this function (illegal function"},
             {2, "the PLC refuses this address (illegal data address"},
             {3, "the PLC refuses this quantity or value (illegal data value"},
             {4, "the PLC failed while handling the request (server device failure"},
             {5, "the PLC took the request but has not finished it (acknowledge"},
             {6, "the PLC is busy with a long command (server device busy"},
             {10, "the gateway has no path to the device behind it (gateway path unavailable"},
             {11, "the device behind the gateway did not answer (gateway target failed to "
                  "respond"},
             {99, "the PLC refused the request with a code the specification does not name "
                  "(unknown exception"}],
    [[?_assertEqual(Text ++ ", Modbus exception " ++ integer_to_list(C) ++ ")", T(C))
      || {C, Text} <- Words],
     %% Decoded from the wire, then put in words: no code is left without them.
     [?_assertMatch({exception, C}, decode_response({read_coils, 0, 1}, <<16#81, C>>))
      || C <- [1, 2, 3, 4, 5, 6, 10, 11]],
     [?_assertNotEqual(nomatch, string:find(T(C), "Modbus exception"))
      || C <- lists:seq(1, 255)]].

mismatched_replies_test_() ->
    Read = {read_holding_registers, 0, 2},
    [?_assertEqual({error, {wrong_function, 3, 4}}, decode_response(Read, h("04 04 0000 0000"))),
     ?_assertEqual({error, {bad_byte_count, 4, 2}}, decode_response(Read, h("03 02 0000"))),
     ?_assertEqual({error, {bad_size, 5, 4}}, decode_response(Read, h("03 04 0000 00"))),
     ?_assertEqual({error, {bad_size, 5, 6}}, decode_response(Read, h("03 04 0000 0000 00"))),
     ?_assertEqual({error, {bad_size, 5, 0}}, decode_response(Read, h("03"))),
     ?_assertEqual({error, empty_pdu}, decode_response(Read, <<>>)),
     ?_assertEqual({error, echo_mismatch},
                   decode_response({write_single_register, 1, 3}, h("06 0001 0004"))),
     ?_assertEqual({error, echo_mismatch},
                   decode_response({write_single_coil, 1, true}, h("05 0001 0000"))),
     ?_assertEqual({error, {bad_size, 4, 5}},
                   decode_response({write_multiple_registers, 1, h("0001")},
                                   h("10 0001 0001 00"))),
     ?_assertEqual({error, echo_mismatch},
                   decode_response({write_multiple_coils, 1, [true]}, h("0F 0001 0002"))),
     ?_assertEqual({error, {bad_byte_count, 1, 2}},
                   decode_response({read_coils, 0, 8}, h("01 02 FF FF")))].

user_function_test_() ->
    Req = {user_function, 65, <<1, 2>>},
    [?_assertEqual(ok, check_request(Req)),
     ?_assertEqual(<<65, 1, 2>>, request_pdu(Req)),
     ?_assertEqual({ok, Req}, decode_request(<<65, 1, 2>>)),
     ?_assertEqual({ok, <<9>>}, decode_response(Req, <<65, 9>>)),
     ?_assertEqual({exception, 1}, decode_response(Req, <<(65 + 128), 1>>)),
     ?_assertMatch({error, _}, check_request({user_function, 3, <<>>})),
     ?_assertMatch({error, _}, check_request({user_function, 128, <<>>})),
     ?_assertMatch({error, _}, check_request({user_function, 0, <<>>})),
     ?_assertEqual(ok, check_request({user_function, 100, <<0:(252 * 8)>>})),
     ?_assertMatch({error, _}, check_request({user_function, 100, <<0:(253 * 8)>>}))].

%% Both sides of every limit.
limits_test_() ->
    Regs = fun(N) -> <<0:(16 * N)>> end,
    Bits = fun(N) -> lists:duplicate(N, true) end,
    Ok = fun(R) -> ?_assertEqual(ok, check_request(R)) end,
    Bad = fun(R) -> ?_assertMatch({error, {bad_request, _}}, check_request(R)) end,
    [Ok({read_coils, 0, 2000}), Bad({read_coils, 0, 2001}), Bad({read_coils, 0, 0}),
     Ok({read_discrete_inputs, 0, 2000}), Bad({read_discrete_inputs, 0, 2001}),
     Ok({read_holding_registers, 0, 125}), Bad({read_holding_registers, 0, 126}),
     Bad({read_holding_registers, 0, 0}),
     Ok({read_input_registers, 0, 125}), Bad({read_input_registers, 0, 126}),
     Ok({write_multiple_coils, 0, Bits(1968)}), Bad({write_multiple_coils, 0, Bits(1969)}),
     Bad({write_multiple_coils, 0, []}), Bad({write_multiple_coils, 0, [true, 1]}),
     Ok({write_multiple_registers, 0, Regs(123)}),
     Bad({write_multiple_registers, 0, Regs(124)}),
     Bad({write_multiple_registers, 0, <<>>}), Bad({write_multiple_registers, 0, <<0>>}),
     Ok({read_write_registers, 0, 125, 0, Regs(121)}),
     Bad({read_write_registers, 0, 126, 0, Regs(1)}),
     Bad({read_write_registers, 0, 1, 0, Regs(122)}),
     Ok({read_holding_registers, 65535, 1}), Bad({read_holding_registers, 65535, 2}),
     Ok({read_holding_registers, 65411, 125}), Bad({read_holding_registers, 65412, 125}),
     Ok({read_coils, 63536, 2000}), Bad({read_coils, 63537, 2000}),
     Bad({read_coils, -1, 1}), Bad({read_coils, 65536, 1}),
     Ok({write_single_register, 65535, 65535}), Bad({write_single_register, 0, 65536}),
     Bad({write_single_register, 0, -1}), Bad({write_single_coil, 0, 1}),
     Ok({mask_write_register, 0, 65535, 0}), Bad({mask_write_register, 0, 65536, 0}),
     Bad({read_coils, 0}), Bad(hello)].

%% A request PDU a server refuses to parse (the server side of the limits).
server_side_limits_test_() ->
    [?_assertMatch({error, _}, decode_request(h("03 0000 007E"))),
     ?_assertMatch({ok, _}, decode_request(h("03 0000 007D"))),
     ?_assertMatch({error, _}, decode_request(h("01 0000 07D1"))),
     ?_assertMatch({error, _}, decode_request(h("0F 0000 0009 01 FF"))),
     ?_assertMatch({error, _}, decode_request(h("10 0000 0002 02 0000"))),
     ?_assertMatch({error, _}, decode_request(h("05 0000 1234"))),
     ?_assertMatch({error, _}, decode_request(h("03 0000"))),
     ?_assertMatch({error, _}, decode_request(<<>>)),
     ?_assertMatch({error, _}, decode_request(<<200>>))].

frame_test_() ->
    Pdu = h("03 0000 0001"),
    Adu = adu(16#1234, 7, Pdu),
    [?_assertEqual(h("1234 0000 0006 07 03 0000 0001"), Adu),
     ?_assertEqual({ok, 16#1234, 7, Pdu, <<>>}, frame(Adu)),
     ?_assertEqual({ok, 16#1234, 7, Pdu, <<"xy">>}, frame(<<Adu/binary, "xy">>)),
     [?_assertEqual(more, frame(binary:part(Adu, 0, N))) || N <- lists:seq(0, 11)],
     ?_assertEqual({error, {bad_protocol_id, 1}}, frame(h("0000 0001 0006"))),
     ?_assertEqual({error, {bad_protocol_id, 1}}, frame(h("0000 0001"))),
     ?_assertEqual({error, {bad_length_field, 1}}, frame(h("0000 0000 0001 07"))),
     ?_assertEqual({error, {bad_length_field, 0}}, frame(h("0000 0000 0000"))),
     ?_assertEqual({error, {bad_length_field, 255}}, frame(h("0000 0000 00FF"))),
     ?_assertEqual({error, {bad_length_field, 65535}}, frame(h("0000 0000 FFFF"))),
     ?_assertMatch({ok, 0, 1, <<3>>, <<>>}, frame(h("0000 0000 0002 01 03"))),
     ?_assertMatch({ok, 0, 1, <<_:253/binary>>, <<>>},
                   frame(<<0:32, 254:16, 1, 0:(253 * 8)>>))].

errors_read_as_words_test_() ->
    [?_assert(is_list(cell_hal_modbus_codec:format_error(E)))
     || E <- [{bad_protocol_id, 1}, {bad_length_field, 300}, {wrong_function, 3, 4},
              {bad_byte_count, 4, 2}, {bad_size, 5, 4}, echo_mismatch, bad_exception,
              empty_pdu, {bad_request, quantity}]].

describe_test() ->
    ?assertEqual("read holding registers 100..109",
                 lists:flatten(cell_hal_modbus_codec:describe({read_holding_registers, 100, 10}))),
    ?assertEqual("write coil 5",
                 lists:flatten(cell_hal_modbus_codec:describe({write_single_coil, 5, true}))).
