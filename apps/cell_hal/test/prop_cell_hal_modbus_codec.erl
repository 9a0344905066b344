%% PropEr properties of the Modbus TCP codec: every valid request and reply survives
%% the wire both ways, quantities just past a limit are refused, and any byte string
%% (random garbage, truncated or corrupted frames) gets an answer, never a crash.
-module(prop_cell_hal_modbus_codec).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(C, cell_hal_modbus_codec).

properties_test_() ->
    [{timeout, 120, ?_assert(run(P, N))}
     || {P, N} <- [{prop_request_roundtrip(), 2000},
                   {prop_reply_roundtrip(), 2000},
                   {prop_exception_roundtrip(), 500},
                   {prop_over_limit_refused(), 1000},
                   {prop_frame_roundtrip(), 1000},
                   {prop_stream_split_anywhere(), 500},
                   {prop_garbage_frames(), 3000},
                   {prop_garbage_replies(), 3000},
                   {prop_corrupted_replies(), 2000},
                   {prop_garbage_requests(), 2000}]].

run(Prop, N) ->
    proper:quickcheck(Prop, [{to_file, user}, {numtests, N}]).

%%--------------------------------------------------------------------
%% Generators
%%--------------------------------------------------------------------

%% A start address and a quantity within `Max' that stay inside the address space;
%% quantities at the limit and at 1 come up often.
span(Max) ->
    ?LET(N, frequency([{1, 1}, {1, Max}, {6, integer(1, Max)}]),
         ?LET(A, frequency([{1, 0}, {1, 65536 - N}, {6, integer(0, 65536 - N)}]), {A, N})).

words(N) -> binary(2 * N).

request() ->
    oneof([?LET({A, N}, span(2000), {read_coils, A, N}),
           ?LET({A, N}, span(2000), {read_discrete_inputs, A, N}),
           ?LET({A, N}, span(125), {read_holding_registers, A, N}),
           ?LET({A, N}, span(125), {read_input_registers, A, N}),
           {write_single_coil, integer(0, 65535), boolean()},
           {write_single_register, integer(0, 65535), integer(0, 65535)},
           ?LET({A, N}, span(1968), {write_multiple_coils, A, vector(N, boolean())}),
           ?LET({A, N}, span(123), ?LET(R, words(N), {write_multiple_registers, A, R})),
           {mask_write_register, integer(0, 65535), integer(0, 65535), integer(0, 65535)},
           ?LET({{RA, RN}, {WA, WN}}, {span(125), span(121)},
                ?LET(R, words(WN), {read_write_registers, RA, RN, WA, R})),
           ?LET(Fc, user_fc(), {user_function, Fc, binary()})]).

user_fc() ->
    ?SUCHTHAT(Fc, integer(1, 127), not lists:member(Fc, [1, 2, 3, 4, 5, 6, 15, 16, 22, 23])).

%% A request with a reply a server could give to it.
request_reply() ->
    ?LET(Req, request(), {Req, reply(Req)}).

reply({read_coils, _, N}) -> vector(N, boolean());
reply({read_discrete_inputs, _, N}) -> vector(N, boolean());
reply({read_holding_registers, _, N}) -> words(N);
reply({read_input_registers, _, N}) -> words(N);
reply({read_write_registers, _, N, _, _}) -> words(N);
reply({user_function, _, _}) -> binary();
reply(_) -> ok.

%%--------------------------------------------------------------------
%% Properties
%%--------------------------------------------------------------------

prop_request_roundtrip() ->
    ?FORALL(Req, request(),
            begin
                ok = ?C:check_request(Req),
                Pdu = ?C:request_pdu(Req),
                byte_size(Pdu) =< 253 andalso {ok, Req} =:= ?C:decode_request(Pdu)
            end).

prop_reply_roundtrip() ->
    ?FORALL({Req, Reply}, request_reply(),
            begin
                Pdu = ?C:response_pdu(Req, Reply),
                ?WHENFAIL(io:format("~p~n~p~n", [Pdu, ?C:decode_response(Req, Pdu)]),
                          byte_size(Pdu) =< 253 andalso
                          {ok, Reply} =:= ?C:decode_response(Req, Pdu))
            end).

prop_exception_roundtrip() ->
    ?FORALL({Req, Code}, {request(), integer(1, 255)},
            {exception, Code} =:= ?C:decode_response(Req, ?C:response_pdu(Req, {exception, Code}))).

%% One past each quantity limit (and zero) is refused, client and server side.
prop_over_limit_refused() ->
    ?FORALL({Kind, A, Extra}, {oneof([read_coils, read_discrete_inputs,
                                      read_holding_registers, read_input_registers,
                                      write_multiple_coils, write_multiple_registers]),
                               integer(0, 1000), integer(1, 40)},
            begin
                Limit = case Kind of
                            read_coils -> 2000;
                            read_discrete_inputs -> 2000;
                            read_holding_registers -> 125;
                            read_input_registers -> 125;
                            write_multiple_coils -> 1968;
                            write_multiple_registers -> 123
                        end,
                Over = over(Kind, A, Limit + Extra),
                At = over(Kind, A, Limit),
                Zero = over(Kind, A, 0),
                ok =:= ?C:check_request(At) andalso
                    {error, {bad_request, quantity}} =:= ?C:check_request(Over) andalso
                    {error, {bad_request, quantity}} =:= ?C:check_request(Zero) andalso
                    server_refuses(Kind, A, Limit + Extra)
            end).

over(write_multiple_coils, A, N) -> {write_multiple_coils, A, lists:duplicate(N, false)};
over(write_multiple_registers, A, N) -> {write_multiple_registers, A, <<0:(16 * N)>>};
over(Kind, A, N) -> {Kind, A, N}.

%% A server parsing a request PDU that asks for too much refuses it.
server_refuses(Kind, A, N) when Kind =:= write_multiple_coils;
                                Kind =:= write_multiple_registers ->
    %% Too many to fit the frame at all past 246 bytes of data; the header says so.
    Fc = case Kind of write_multiple_coils -> 15; _ -> 16 end,
    Count = case Kind of write_multiple_coils -> (N + 7) div 8; _ -> 2 * N end,
    Pdu = <<Fc, A:16, N:16, (Count band 255), 0:((Count band 255) * 8)>>,
    element(1, ?C:decode_request(Pdu)) =:= error;
server_refuses(Kind, A, N) ->
    Fc = case Kind of read_coils -> 1; read_discrete_inputs -> 2;
             read_holding_registers -> 3; read_input_registers -> 4 end,
    element(1, ?C:decode_request(<<Fc, A:16, N:16>>)) =:= error.

prop_frame_roundtrip() ->
    ?FORALL({Tid, Unit, Pdu, Rest},
            {integer(0, 65535), integer(0, 255),
             ?LET(N, integer(1, 253), binary(N)), binary()},
            {ok, Tid, Unit, Pdu, Rest} =:= ?C:frame(<<(?C:adu(Tid, Unit, Pdu))/binary, Rest/binary>>)).

%% Frames arriving in pieces cut anywhere come out whole and in order.
prop_stream_split_anywhere() ->
    ?FORALL({Frames, Cuts},
            {non_empty(list({integer(0, 65535), integer(0, 255),
                             ?LET(N, integer(1, 253), binary(N))})),
             list(integer(1, 64))},
            begin
                Stream = iolist_to_binary([?C:adu(T, U, P) || {T, U, P} <- Frames]),
                Frames =:= reassemble(chunks(Stream, Cuts), <<>>, [])
            end).

chunks(<<>>, _) -> [];
chunks(Bin, []) -> [Bin];
chunks(Bin, [C | Cs]) when C >= byte_size(Bin) -> [Bin | chunks(<<>>, Cs)];
chunks(Bin, [C | Cs]) ->
    <<Chunk:C/binary, Rest/binary>> = Bin,
    [Chunk | chunks(Rest, Cs)].

reassemble([], <<>>, Acc) -> lists:reverse(Acc);
reassemble([], _Partial, _) -> incomplete;
reassemble([Chunk | Chunks], Buf, Acc) ->
    {Buf1, Acc1} = drain(<<Buf/binary, Chunk/binary>>, Acc),
    reassemble(Chunks, Buf1, Acc1).

drain(Buf, Acc) ->
    case ?C:frame(Buf) of
        {ok, T, U, P, Rest} -> drain(Rest, [{T, U, P} | Acc]);
        more -> {Buf, Acc}
    end.

%% Any bytes: a frame, more, or an error; a frame is never longer than what came in,
%% and never longer than Modbus TCP allows.
prop_garbage_frames() ->
    ?FORALL(Bin, frequency([{3, binary()}, {1, ?LET({N, B}, {integer(0, 300), binary()},
                                                      <<0:16, 0:16, N:16, B/binary>>)}]),
            case ?C:frame(Bin) of
                {ok, _, _, Pdu, Rest} ->
                    byte_size(Pdu) >= 1 andalso byte_size(Pdu) =< 253 andalso
                        byte_size(Pdu) + 7 + byte_size(Rest) =:= byte_size(Bin);
                more ->
                    byte_size(Bin) < 7 + 253;
                {error, _} ->
                    true
            end).

%% Any PDU against any request: a reply of the right shape, an exception or an error.
prop_garbage_replies() ->
    ?FORALL({Req, Pdu}, {request(), binary()},
            well_formed(Req, ?C:decode_response(Req, Pdu))).

%% A valid reply with one byte changed or cut short is never taken for another reply
%% of the wrong shape.
prop_corrupted_replies() ->
    ?FORALL({{Req, Reply}, Pos, Byte, Cut}, {request_reply(), nat(), byte(), boolean()},
            begin
                Pdu = ?C:response_pdu(Req, Reply),
                P = Pos rem byte_size(Pdu),
                Bad = case Cut of
                          true -> binary:part(Pdu, 0, P);
                          false -> <<(binary:part(Pdu, 0, P))/binary, Byte,
                                     (binary:part(Pdu, P + 1, byte_size(Pdu) - P - 1))/binary>>
                      end,
                well_formed(Req, ?C:decode_response(Req, Bad))
            end).

prop_garbage_requests() ->
    ?FORALL(Pdu, binary(),
            case ?C:decode_request(Pdu) of
                {ok, Req} -> ok =:= ?C:check_request(Req) andalso ?C:request_pdu(Req) =:= Pdu;
                {error, _} -> true
            end).

well_formed(Req, {ok, Reply}) ->
    case Req of
        {read_coils, _, N} -> bits(Reply, N);
        {read_discrete_inputs, _, N} -> bits(Reply, N);
        {read_holding_registers, _, N} -> is_binary(Reply) andalso byte_size(Reply) =:= 2 * N;
        {read_input_registers, _, N} -> is_binary(Reply) andalso byte_size(Reply) =:= 2 * N;
        {read_write_registers, _, N, _, _} -> is_binary(Reply) andalso byte_size(Reply) =:= 2 * N;
        {user_function, _, _} -> is_binary(Reply);
        _ -> Reply =:= ok
    end;
well_formed(_, {exception, Code}) -> is_integer(Code) andalso Code >= 1 andalso Code =< 255;
well_formed(_, {error, Why}) -> is_list(?C:format_error(Why)).

bits(L, N) -> is_list(L) andalso length(L) =:= N andalso lists:all(fun is_boolean/1, L).
