%% Unit tests of the ADS wire formats, against frames written out byte by byte here.
-module(cell_hal_ads_codec_tests).
-include_lib("eunit/include/eunit.hrl").

-define(T, {{5, 23, 1, 7, 1, 1}, 851}).
-define(S, {{192, 168, 0, 10, 1, 1}, 32905}).

%% A Read of 4 bytes at 0xF005/0x1234, invoke id 7, in full.
read_frame_test() ->
    Frame = iolist_to_binary(cell_hal_ads_codec:encode_frame(?T, ?S, 7, {read, 16#F005, 16#1234, 4})),
    Expected = <<0, 0, 44, 0, 0, 0,                     % AMS/TCP: reserved, length 32 + 12
                 5, 23, 1, 7, 1, 1, 16#53, 16#03,       % target 5.23.1.7.1.1:851
                 192, 168, 0, 10, 1, 1, 16#89, 16#80,   % source ...:32905
                 2, 0, 4, 0,                            % Read, request flags
                 12, 0, 0, 0, 0, 0, 0, 0, 7, 0, 0, 0,   % length 12, error 0, invoke 7
                 16#05, 16#F0, 0, 0, 16#34, 16#12, 0, 0, 4, 0, 0, 0>>,
    ?assertEqual(Expected, Frame).

%% The same frame from addresses built once.
addresses_test() ->
    Addresses = cell_hal_ads_codec:addresses(?T, ?S),
    ?assertEqual(<<5, 23, 1, 7, 1, 1, 16#53, 16#03, 192, 168, 0, 10, 1, 1, 16#89, 16#80>>,
                 Addresses),
    ?assertEqual(iolist_to_binary(cell_hal_ads_codec:encode_frame(?T, ?S, 7, {read, 16#F005, 16#1234, 4})),
                 iolist_to_binary(cell_hal_ads_codec:encode_frame(Addresses, 7, {read, 16#F005, 16#1234, 4}))).

%% The answer to a Read, invoke id 8, ADS error 0, 4 bytes read: in one match.
decode_answer_test_() ->
    Data = <<0:32, 4:32/little, 42:32/little>>,
    %% to the client (192.168.0.10.1.1:32905) from the PLC
    Head = <<192, 168, 0, 10, 1, 1, 16#89, 16#80, 5, 23, 1, 7, 1, 1, 16#53, 16#03,
             2, 0>>,
    Tail = <<12:32/little, 0:32, 8:32/little, Data/binary>>,
    Answer = <<0:16, 44:32/little, Head/binary, 5, 0, Tail/binary>>,
    [?_assertEqual({answer, 32905, read, 0, 8, Data}, cell_hal_ads_codec:decode_answer(Answer)),
     %% a request (no response flag) is not an answer
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(<<0:16, 44:32/little, Head/binary,
                                                              4, 0, Tail/binary>>)),
     %% one byte short, one byte more, two frames: cut and read the long way
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(binary:part(Answer, 0, 49))),
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(<<Answer/binary, 0>>)),
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(<<Answer/binary, Answer/binary>>)),
     %% the AMS/TCP length must say what follows
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(<<0:16, 45:32/little, Head/binary,
                                                              5, 0, Tail/binary>>)),
     %% a router frame
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(<<1, 16#10, 44:32/little, Head/binary,
                                                              5, 0, Tail/binary>>)),
     ?_assertEqual(other, cell_hal_ads_codec:decode_answer(<<>>))].

request_payloads_test_() ->
    [?_assertEqual({1, <<>>}, flat(read_device_info)),
     ?_assertEqual({4, <<>>}, flat(read_state)),
     ?_assertEqual({3, <<1:32/little, 2:32/little, 3:32/little, "abc">>},
                   flat({write, 1, 2, [<<"a">>, "bc"]})),
     ?_assertEqual({9, <<16#F003:32/little, 0:32, 4:32/little, 5:32/little, "MAIN", 0>>},
                   flat({read_write, 16#F003, 0, 4, <<"MAIN", 0>>})),
     ?_assertEqual({5, <<5:16/little, 7:16/little, 2:32/little, 1, 2>>},
                   flat({write_control, run, 7, <<1, 2>>})),
     ?_assertEqual({5, <<6:16/little, 0:16, 0:32>>}, flat({write_control, 6, 0, <<>>})),
     ?_assertEqual({6, <<16#F005:32/little, 9:32/little, 4:32/little, 4:32/little,
                         0:32, 100000:32/little, 0:128>>},
                   flat({add_notification, 16#F005, 9, 4, on_change, 0, 100000})),
     ?_assertEqual({6, <<1:32/little, 2:32/little, 8:32/little, 3:32/little,
                         10:32/little, 20:32/little, 0:128>>},
                   flat({add_notification, 1, 2, 8, cyclic, 10, 20})),
     ?_assertEqual({7, <<16#01020304:32/little>>}, flat({delete_notification, 16#01020304}))].

flat(Request) ->
    {Cmd, Data} = cell_hal_ads_codec:encode_request(Request),
    ?assertEqual(cell_hal_ads_codec:command_id(cell_hal_ads_codec:request_command(Request)), Cmd),
    {Cmd, iolist_to_binary(Data)}.

next_frame_test_() ->
    Body = <<0:(32 * 8), "data">>,
    Frame = <<0:16, 36:32/little, Body/binary>>,
    [?_assertEqual(more, cell_hal_ads_codec:next_frame(<<>>, 1000)),
     ?_assertEqual(more, cell_hal_ads_codec:next_frame(<<0, 0, 36>>, 1000)),
     ?_assertEqual(more, cell_hal_ads_codec:next_frame(binary:part(Frame, 0, 41), 1000)),
     ?_assertEqual({ams, Body, <<>>}, cell_hal_ads_codec:next_frame(Frame, 1000)),
     ?_assertEqual({ams, Body, <<1, 2>>}, cell_hal_ads_codec:next_frame(<<Frame/binary, 1, 2>>, 1000)),
     ?_assertEqual({router, 16#1001, <<1, 2>>, <<>>},
                   cell_hal_ads_codec:next_frame(<<1, 16#10, 2:32/little, 1, 2>>, 1000)),
     ?_assertEqual({error, {bad_frame, shorter_than_ams_header}},
                   cell_hal_ads_codec:next_frame(<<0:16, 4:32/little, 1, 2, 3, 4>>, 1000)),
     %% both sides of the limit
     ?_assertEqual({ams, Body, <<>>}, cell_hal_ads_codec:next_frame(Frame, 36)),
     ?_assertEqual({error, {frame_too_long, 36}}, cell_hal_ads_codec:next_frame(Frame, 35)),
     %% an absurd length is refused before waiting for its bytes
     ?_assertEqual({error, {frame_too_long, 16#FFFFFFFF}},
                   cell_hal_ads_codec:next_frame(<<0:16, 16#FFFFFFFF:32>>, 1000))].

decode_ams_test_() ->
    Header = <<5, 23, 1, 7, 1, 1, 16#53, 16#03, 1, 2, 3, 4, 5, 6, 16#89, 16#80,
               2, 0, 5, 0, 3:32/little, 16#710:32/little, 99:32/little>>,
    [?_assertEqual({ok, #{target => {{5, 23, 1, 7, 1, 1}, 851}, source => {{1, 2, 3, 4, 5, 6}, 32905},
                          command => read, flags => 5, error => 16#710, invoke => 99},
                    <<"abc">>},
                   cell_hal_ads_codec:decode_ams(<<Header/binary, "abc">>)),
     ?_assertEqual({error, {bad_frame, length_mismatch}},
                   cell_hal_ads_codec:decode_ams(<<Header/binary, "ab">>)),
     ?_assertEqual({error, {bad_frame, length_mismatch}},
                   cell_hal_ads_codec:decode_ams(<<Header/binary, "abcd">>)),
     ?_assertEqual({error, {bad_frame, shorter_than_ams_header}},
                   cell_hal_ads_codec:decode_ams(binary:part(Header, 0, 31))),
     ?_assertMatch({ok, #{command := {unknown, 77}}, <<>>},
                   cell_hal_ads_codec:decode_ams(<<0:128, 77:16/little, 0:16, 0:96>>))].

decode_response_test_() ->
    D = fun cell_hal_ads_codec:decode_response/2,
    [?_assertEqual({ok, #{name => <<"Plc30 App">>, version => {3, 1, 4024}}},
                   D(read_device_info, <<0:32, 3, 1, 4024:16/little, "Plc30 App", 0:56>>)),
     ?_assertEqual({ok, #{name => <<"TestServer">>, version => {1, 2, 3}}},
                   D(read_device_info, <<0:32, 1, 2, 3, 0, "TestServer", 0>>)),
     ?_assertEqual({error, {bad_response, wrong_length}},
                   D(read_device_info, <<0:32, 1, 2, 3, 0, 0:(17 * 8)>>)),
     ?_assertEqual({ok, <<1, 2, 3>>}, D(read, <<0:32, 3:32/little, 1, 2, 3>>)),
     ?_assertEqual({ok, <<>>}, D(read_write, <<0:32, 0:32>>)),
     ?_assertEqual({error, {bad_response, wrong_length}}, D(read, <<0:32, 4:32/little, 1, 2, 3>>)),
     ?_assertEqual({error, {bad_response, wrong_length}}, D(read, <<0:32, 2:32/little, 1, 2, 3>>)),
     ?_assertEqual({ok, ok}, D(write, <<0:32>>)),
     ?_assertEqual({ok, ok}, D(write_control, <<0:32>>)),
     ?_assertEqual({ok, ok}, D(delete_notification, <<0:32>>)),
     ?_assertEqual({error, {bad_response, wrong_length}}, D(write, <<0:32, 0>>)),
     ?_assertEqual({ok, {run, 0}}, D(read_state, <<0:32, 5:16/little, 0:16>>)),
     ?_assertEqual({ok, {config, 3}}, D(read_state, <<0:32, 15:16/little, 3:16/little>>)),
     ?_assertEqual({ok, {4711, 0}}, D(read_state, <<0:32, 4711:16/little, 0:16>>)),
     ?_assertEqual({ok, 16#ABCD}, D(add_notification, <<0:32, 16#ABCD:32/little>>)),
     %% a failed command carries only its result
     ?_assertEqual({error, {ads_error, 16#710, symbol_not_found}}, D(read, <<16#710:32/little>>)),
     ?_assertEqual({error, {ads_error, 16#705, invalid_size}},
                   D(read_write, <<16#705:32/little, 0:32>>)),
     ?_assertEqual({error, {ads_error, 16#745, client_timeout}}, D(write, <<16#745:32/little>>)),
     ?_assertEqual({error, {bad_response, wrong_length}}, D(read, <<>>)),
     ?_assertEqual({error, {bad_response, wrong_length}}, D(device_notification, <<0:32>>))].

notification_test_() ->
    Stream = fun(Stamps) ->
                     Body = <<(length(Stamps)):32/little,
                              (<< <<T:64/little, (length(Ss)):32/little,
                                    (<< <<H:32/little, (byte_size(V)):32/little, V/binary>>
                                        || {H, V} <- Ss >>)/binary>> || {T, Ss} <- Stamps >>)/binary>>,
                     <<(byte_size(Body)):32/little, Body/binary>>
             end,
    One = [{133000000000000000, [{7, <<1>>}, {8, <<1.5:64/float-little>>}]}],
    Two = One ++ [{133000000000000100, [{7, <<0>>}]}],
    Full = Stream(Two),
    [?_assertEqual({ok, One}, cell_hal_ads_codec:decode_notification(Stream(One))),
     ?_assertEqual({ok, Two}, cell_hal_ads_codec:decode_notification(Full)),
     ?_assertEqual({ok, []}, cell_hal_ads_codec:decode_notification(Stream([]))),
     ?_assertEqual({ok, [{1, []}]}, cell_hal_ads_codec:decode_notification(Stream([{1, []}]))),
     ?_assertEqual({error, {bad_notification, truncated_sample}},
                   cell_hal_ads_codec:decode_notification(fix_len(binary:part(Full, 0, byte_size(Full) - 1)))),
     ?_assertEqual({error, {bad_notification, trailing_bytes}},
                   cell_hal_ads_codec:decode_notification(fix_len(<<Full/binary, 0>>))),
     ?_assertEqual({error, {bad_notification, too_short}},
                   cell_hal_ads_codec:decode_notification(<<100:32/little, 1:32/little>>)),
     ?_assertEqual({error, {bad_notification, too_short}},
                   cell_hal_ads_codec:decode_notification(<<1, 2>>)),
     %% the stamp count promises more than there is
     ?_assertEqual({error, {bad_notification, truncated_stamp}},
                   cell_hal_ads_codec:decode_notification(<<4:32/little, 3:32/little>>))].

%% The stream's own length field made to match a changed body.
fix_len(<<_:32, Body/binary>>) ->
    <<(byte_size(Body)):32/little, Body/binary>>.

sum_read_test_() ->
    Req = cell_hal_ads_codec:sum_read([{16#F005, 1, 4}, {16#4040, 2, 1}]),
    [?_assertEqual({read_write, 16#F080, 2, 2 * 4 + 4 + 1,
                    <<16#F005:32/little, 1:32/little, 4:32/little,
                      16#4040:32/little, 2:32/little, 1:32/little>>}, flat_rw(Req)),
     %% every slot present
     ?_assertEqual({ok, [{ok, <<1, 2, 3, 4>>}, {ok, <<9>>}]},
                   cell_hal_ads_codec:decode_sum_read([4, 1], <<0:32, 0:32, 1, 2, 3, 4, 9>>)),
     ?_assertEqual({ok, [{error, {ads_error, 16#710, symbol_not_found}}, {ok, <<9>>}]},
                   cell_hal_ads_codec:decode_sum_read([4, 1], <<16#710:32/little, 0:32, 0:32, 9>>)),
     %% a failed item without its slot
     ?_assertEqual({ok, [{error, {ads_error, 16#710, symbol_not_found}}, {ok, <<9>>}]},
                   cell_hal_ads_codec:decode_sum_read([4, 1], <<16#710:32/little, 0:32, 9>>)),
     ?_assertEqual({error, {bad_response, sum_length_mismatch}},
                   cell_hal_ads_codec:decode_sum_read([4, 1], <<0:32, 0:32, 1, 2>>)),
     ?_assertEqual({error, {bad_response, sum_too_short}},
                   cell_hal_ads_codec:decode_sum_read([4, 1], <<0:32>>))].

flat_rw({read_write, G, O, L, Data}) ->
    {read_write, G, O, L, iolist_to_binary(Data)}.

sum_write_test_() ->
    Req = cell_hal_ads_codec:sum_write([{16#F005, 1, <<7:32/little>>}, {16#F006, 0, <<1, 0, 0, 0>>}]),
    [?_assertEqual({read_write, 16#F081, 2, 8,
                    <<16#F005:32/little, 1:32/little, 4:32/little,
                      16#F006:32/little, 0:32, 4:32/little, 7:32/little, 1, 0, 0, 0>>},
                   flat_rw(Req)),
     ?_assertEqual({ok, [ok, {error, {ads_error, 16#704, invalid_access}}]},
                   cell_hal_ads_codec:decode_sum_write(2, <<0:32, 16#704:32/little>>)),
     ?_assertEqual({error, {bad_response, sum_length_mismatch}},
                   cell_hal_ads_codec:decode_sum_write(2, <<0:32>>))].

sum_read_write_test_() ->
    Req = cell_hal_ads_codec:sum_read_write([{16#F003, 0, 4, <<"A", 0>>}, {16#F003, 0, 4, <<"BC", 0>>}]),
    [?_assertEqual({read_write, 16#F082, 2, 16 + 8,
                    <<16#F003:32/little, 0:32, 4:32/little, 2:32/little,
                      16#F003:32/little, 0:32, 4:32/little, 3:32/little, "A", 0, "BC", 0>>},
                   flat_rw(Req)),
     ?_assertEqual({ok, [{ok, <<1:32/little>>}, {error, {ads_error, 16#710, symbol_not_found}}]},
                   cell_hal_ads_codec:decode_sum_read_write(
                     2, <<0:32, 4:32/little, 16#710:32/little, 0:32, 1:32/little>>)),
     ?_assertEqual({error, {bad_response, sum_length_mismatch}},
                   cell_hal_ads_codec:decode_sum_read_write(1, <<0:32, 4:32/little, 1:16>>)),
     ?_assertEqual({error, {bad_response, sum_too_short}},
                   cell_hal_ads_codec:decode_sum_read_write(2, <<0:32, 4:32/little>>))].

entry(Name, Type, Comment, Sep, Trailer) ->
    Strings = <<Name/binary, Sep, Type/binary, Sep, Comment/binary, Trailer/binary>>,
    <<(30 + byte_size(Strings)):32/little, 16#4040:32/little, 1000:32/little, 4:32/little,
      3:32/little, 8:32/little, (byte_size(Name)):16/little, (byte_size(Type)):16/little,
      (byte_size(Comment)):16/little, Strings/binary>>.

symbol_test_() ->
    Sym = #{name => <<"MAIN.counter">>, type => <<"DINT">>, comment => <<"counts">>,
            group => 16#4040, offset => 1000, size => 4, data_type => 3, flags => 8},
    NulSep = entry(<<"MAIN.counter">>, <<"DINT">>, <<"counts">>, 0, <<0>>),
    %% as pyads' test server writes them: spaces between, no last NUL
    SpaceSep = entry(<<"MAIN.counter">>, <<"DINT">>, <<"counts">>, $\s, <<>>),
    %% TwinCAT 3 appends more after the comment (type GUID, attributes)
    Extra = entry(<<"MAIN.counter">>, <<"DINT">>, <<"counts">>, 0, <<0, 1:128>>),
    [?_assertEqual({ok, Sym}, cell_hal_ads_codec:decode_symbol(NulSep)),
     ?_assertEqual({ok, Sym}, cell_hal_ads_codec:decode_symbol(SpaceSep)),
     ?_assertEqual({ok, Sym}, cell_hal_ads_codec:decode_symbol(Extra)),
     ?_assertEqual({ok, [Sym, Sym#{name => <<"X">>}]},
                   cell_hal_ads_codec:decode_symbol_table(
                     <<NulSep/binary, (entry(<<"X">>, <<"DINT">>, <<"counts">>, 0, <<0>>))/binary>>)),
     ?_assertEqual({ok, []}, cell_hal_ads_codec:decode_symbol_table(<<>>)),
     ?_assertEqual({error, {bad_symbol, truncated_entry}},
                   cell_hal_ads_codec:decode_symbol_table(<<NulSep/binary, 1, 2>>)),
     ?_assertEqual({error, {bad_symbol, entry_too_short}},
                   cell_hal_ads_codec:decode_symbol(<<29:32/little, 0:(25 * 8)>>)),
     ?_assertEqual({error, {bad_symbol, truncated_entry}},
                   cell_hal_ads_codec:decode_symbol(binary:part(NulSep, 0, 40))),
     %% name length beyond the entry
     ?_assertEqual({error, {bad_symbol, strings_exceed_entry}},
                   cell_hal_ads_codec:decode_symbol(<<32:32/little, 0:(20 * 8), 9:16/little,
                                                      0:16, 0:16, 0, 0>>)),
     ?_assertEqual({ok, #{symbols => 2, size => 300}},
                   cell_hal_ads_codec:decode_upload_info(<<2:32/little, 300:32/little>>)),
     ?_assertEqual({ok, #{symbols => 2, size => 300}},
                   cell_hal_ads_codec:decode_upload_info(<<2:32/little, 300:32/little, 0:128>>)),
     ?_assertEqual({error, {bad_response, upload_info_too_short}},
                   cell_hal_ads_codec:decode_upload_info(<<2:32/little>>))].

filetime_test_() ->
    %% 2020-01-01T00:00:00Z
    Ft = 132223104000000000,
    Ns = 1577836800 * 1000000000,
    [?_assertEqual(Ns, cell_hal_ads_codec:filetime_to_ns(Ft)),
     ?_assertEqual(Ft, cell_hal_ads_codec:ns_to_filetime(Ns)),
     ?_assertEqual(Ns + 100, cell_hal_ads_codec:filetime_to_ns(Ft + 1)),
     ?_assertEqual(Ft, cell_hal_ads_codec:ns_to_filetime(Ns + 99)),
     ?_assertEqual(116444736000000000 - 1, cell_hal_ads_codec:ns_to_filetime(-1)),
     ?_assertEqual(0, cell_hal_ads_codec:filetime_to_ns(116444736000000000))].

net_id_test_() ->
    P = fun cell_hal_ads_codec:parse_net_id/1,
    [?_assertEqual({ok, {5, 23, 1, 7, 1, 1}}, P(<<"5.23.1.7.1.1">>)),
     ?_assertEqual({ok, {5, 23, 1, 7, 1, 1}}, P("5.23.1.7.1.1")),
     ?_assertEqual({ok, {255, 0, 0, 0, 0, 255}}, P("255.0.0.0.0.255")),
     ?_assertEqual(error, P("256.0.0.0.0.1")),
     ?_assertEqual(error, P("1.2.3.4.5")),
     ?_assertEqual(error, P("1.2.3.4.5.6.7")),
     ?_assertEqual(error, P("1.2.3.4.5.x")),
     ?_assertEqual(error, P("1.2.3.4.5.")),
     ?_assertEqual(error, P("1.2.3.4.5.-1")),
     ?_assertEqual(error, P("1.2.3.4.5.0001")),
     ?_assertEqual(error, P([1000])),
     ?_assertEqual(error, P(42)),
     ?_assertEqual({ok, {1, 2, 3, 4, 5, 6}}, P({1, 2, 3, 4, 5, 6})),
     ?_assertEqual(error, P({1, 2, 3, 4, 5, 256})),
     ?_assertEqual(<<"5.23.1.7.1.1">>, cell_hal_ads_codec:format_net_id({5, 23, 1, 7, 1, 1}))].

errors_test_() ->
    N = fun cell_hal_ads_codec:error_name/1,
    [?_assertEqual(invalid_index_group, N(16#702)),
     ?_assertEqual(invalid_size, N(16#705)),
     ?_assertEqual(symbol_not_found, N(16#710)),
     ?_assertEqual(client_timeout, N(16#745)),
     ?_assertEqual(target_machine_not_found, N(7)),
     ?_assertEqual(unknown, N(16#12345)),
     ?_assertEqual(<<"symbol not found">>, cell_hal_ads_codec:error_text(16#710)),
     ?_assertEqual(<<"unknown ADS error 0x12345">>, cell_hal_ads_codec:error_text(16#12345)),
     ?_assertEqual({ads_error, 16#711, symbol_version_invalid}, cell_hal_ads_codec:ads_error(16#711)),
     ?_assertEqual(run, cell_hal_ads_codec:ads_state_name(5)),
     ?_assertEqual(1000, cell_hal_ads_codec:ads_state_name(1000)),
     ?_assertEqual(15, cell_hal_ads_codec:ads_state_code(config)),
     ?_assertEqual(99, cell_hal_ads_codec:ads_state_code(99))].

is_ads_state_test_() ->
    [?_assert(cell_hal_ads_codec:is_ads_state(run)),
     ?_assert(cell_hal_ads_codec:is_ads_state(0)),
     ?_assert(cell_hal_ads_codec:is_ads_state(65535)),
     ?_assertNot(cell_hal_ads_codec:is_ads_state(65536)),
     ?_assertNot(cell_hal_ads_codec:is_ads_state(-1)),
     ?_assertNot(cell_hal_ads_codec:is_ads_state(sleeping))].
