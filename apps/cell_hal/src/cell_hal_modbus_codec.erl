%% @doc Modbus TCP on the wire: the MBAP header and the PDUs of function codes 1, 2, 3,
%% 4, 5, 6, 15, 16, 22 and 23, both directions, as the Modbus Application Protocol
%% Specification V1.1b3 and the Modbus Messaging on TCP/IP Implementation Guide V1.0b
%% give them. Pure: no sockets, no processes.
%%
%% Registers travel as binaries of big-endian 16-bit words (what {@link
%% cell_hal_type_codec} reads and writes); coils and discrete inputs as lists of
%% booleans. Every decoder takes any binary: a frame that is not what was asked for is
%% `{error, Why}' (which {@link format_error/1} turns into words), never a crash.
%%
%% The protocol's limits, each checked by {@link check_request/1}:
%% <table>
%% <tr><th>function</th><th>quantity</th></tr>
%% <tr><td>1 read coils, 2 read discrete inputs</td><td>1..2000</td></tr>
%% <tr><td>3 read holding registers, 4 read input registers</td><td>1..125</td></tr>
%% <tr><td>15 write multiple coils</td><td>1..1968</td></tr>
%% <tr><td>16 write multiple registers</td><td>1..123</td></tr>
%% <tr><td>23 read/write multiple registers</td><td>read 1..125, write 1..121</td></tr>
%% </table>
%% and the last address of a request is at most 65535. A PDU is at most 253 bytes, so
%% the MBAP length field is 2..254.
-module(cell_hal_modbus_codec).

-export([check_request/1, request_pdu/1, adu/3, frame/1]).
-export([decode_request/1, response_pdu/2, decode_response/2]).
-export([exception_name/1, exception_text/1, format_error/1, describe/1, limit/1]).

-export_type([request/0, reply/0, address/0, unit_id/0, tid/0, error_reason/0,
              exception_code/0]).

-type address() :: 0..65535.
-type unit_id() :: 0..255.
-type tid() :: 0..65535.
-type registers() :: binary().
-type exception_code() :: 1..255.
-type request() ::
        {read_coils, address(), pos_integer()}
      | {read_discrete_inputs, address(), pos_integer()}
      | {read_holding_registers, address(), pos_integer()}
      | {read_input_registers, address(), pos_integer()}
      | {write_single_coil, address(), boolean()}
      | {write_single_register, address(), 0..65535}
      | {write_multiple_coils, address(), [boolean()]}
      | {write_multiple_registers, address(), registers()}
      | {mask_write_register, address(), And :: 0..65535, Or :: 0..65535}
      | {read_write_registers, ReadAddress :: address(), ReadCount :: pos_integer(),
         WriteAddress :: address(), registers()}
      | {user_function, 1..127, binary()}.
%% A write answers `ok' once its echo matched the request; a user-defined function
%% answers its raw data.
-type reply() :: [boolean()] | registers() | ok | binary().
-type error_reason() ::
        {bad_protocol_id, non_neg_integer()}
      | {bad_length_field, non_neg_integer()}
      | {wrong_function, Asked :: byte(), Answered :: byte()}
      | {bad_byte_count, Expected :: non_neg_integer(), Got :: non_neg_integer()}
      | {bad_size, Expected :: non_neg_integer(), Got :: non_neg_integer()}
      | echo_mismatch
      | bad_exception
      | empty_pdu
      | {bad_request, atom()}.

-define(MAX_PDU, 253).
-define(IS_WORD(V), (is_integer(V) andalso V >= 0 andalso V =< 65535)).
-define(FC_READ_COILS, 1).
-define(FC_READ_DISCRETE, 2).
-define(FC_READ_HOLDING, 3).
-define(FC_READ_INPUT, 4).
-define(FC_WRITE_COIL, 5).
-define(FC_WRITE_REGISTER, 6).
-define(FC_WRITE_COILS, 15).
-define(FC_WRITE_REGISTERS, 16).
-define(FC_MASK_WRITE, 22).
-define(FC_READ_WRITE, 23).
-define(KNOWN_FCS, [1, 2, 3, 4, 5, 6, 15, 16, 22, 23]).

%%====================================================================
%% Requests (client side)
%%====================================================================

%% @doc The protocol's limit on a quantity: `read_bits' 2000, `read_registers' 125,
%% `write_bits' 1968, `write_registers' 123, `read_write_registers' 121 (written).
-spec limit(read_bits | read_registers | write_bits | write_registers
            | read_write_registers) -> pos_integer().
limit(read_bits) -> 2000;
limit(read_registers) -> 125;
limit(write_bits) -> 1968;
limit(write_registers) -> 123;
limit(read_write_registers) -> 121.

%% @doc Whether a request is within the protocol's limits.
-spec check_request(term()) -> ok | {error, {bad_request, atom()}}.
check_request({read_coils, A, N}) -> range(A, N, limit(read_bits));
check_request({read_discrete_inputs, A, N}) -> range(A, N, limit(read_bits));
check_request({read_holding_registers, A, N}) -> range(A, N, limit(read_registers));
check_request({read_input_registers, A, N}) -> range(A, N, limit(read_registers));
check_request({write_single_coil, A, V}) when is_boolean(V) -> range(A, 1, 1);
check_request({write_single_register, A, V}) when ?IS_WORD(V) -> range(A, 1, 1);
check_request({write_multiple_coils, A, Bits}) when is_list(Bits) ->
    case lists:all(fun is_boolean/1, Bits) of
        true -> range(A, length(Bits), limit(write_bits));
        false -> {error, {bad_request, value}}
    end;
check_request({write_multiple_registers, A, Regs}) when is_binary(Regs) ->
    registers_range(A, Regs, limit(write_registers));
check_request({mask_write_register, A, And, Or}) when ?IS_WORD(And), ?IS_WORD(Or) ->
    range(A, 1, 1);
check_request({read_write_registers, RA, RN, WA, Regs}) when is_binary(Regs) ->
    case range(RA, RN, limit(read_registers)) of
        ok -> registers_range(WA, Regs, limit(read_write_registers));
        Error -> Error
    end;
check_request({user_function, Fc, Data}) when is_integer(Fc), Fc >= 1, Fc =< 127,
                                              is_binary(Data) ->
    case lists:member(Fc, ?KNOWN_FCS) of
        true -> {error, {bad_request, function}};
        false when byte_size(Data) < ?MAX_PDU -> ok;
        false -> {error, {bad_request, size}}
    end;
check_request(_) ->
    {error, {bad_request, request}}.

registers_range(A, Regs, Max) when byte_size(Regs) rem 2 =:= 0 ->
    range(A, byte_size(Regs) div 2, Max);
registers_range(_, _, _) ->
    {error, {bad_request, value}}.

range(A, _, _) when not ?IS_WORD(A) -> {error, {bad_request, address}};
range(_, N, Max) when not is_integer(N); N < 1; N > Max -> {error, {bad_request, quantity}};
range(A, N, _) when A + N > 65536 -> {error, {bad_request, address}};
range(_, _, _) -> ok.

%% @doc The PDU of a request (checked with {@link check_request/1} first).
-spec request_pdu(request()) -> binary().
request_pdu({read_coils, A, N}) -> <<?FC_READ_COILS, A:16, N:16>>;
request_pdu({read_discrete_inputs, A, N}) -> <<?FC_READ_DISCRETE, A:16, N:16>>;
request_pdu({read_holding_registers, A, N}) -> <<?FC_READ_HOLDING, A:16, N:16>>;
request_pdu({read_input_registers, A, N}) -> <<?FC_READ_INPUT, A:16, N:16>>;
request_pdu({write_single_coil, A, true}) -> <<?FC_WRITE_COIL, A:16, 16#FF00:16>>;
request_pdu({write_single_coil, A, false}) -> <<?FC_WRITE_COIL, A:16, 0:16>>;
request_pdu({write_single_register, A, V}) -> <<?FC_WRITE_REGISTER, A:16, V:16>>;
request_pdu({write_multiple_coils, A, Bits}) ->
    Packed = pack_bits(Bits),
    <<?FC_WRITE_COILS, A:16, (length(Bits)):16, (byte_size(Packed)), Packed/binary>>;
request_pdu({write_multiple_registers, A, Regs}) ->
    <<?FC_WRITE_REGISTERS, A:16, (byte_size(Regs) div 2):16, (byte_size(Regs)),
      Regs/binary>>;
request_pdu({mask_write_register, A, And, Or}) -> <<?FC_MASK_WRITE, A:16, And:16, Or:16>>;
request_pdu({read_write_registers, RA, RN, WA, Regs}) ->
    <<?FC_READ_WRITE, RA:16, RN:16, WA:16, (byte_size(Regs) div 2):16,
      (byte_size(Regs)), Regs/binary>>;
request_pdu({user_function, Fc, Data}) -> <<Fc, Data/binary>>.

%% @doc A whole Modbus TCP frame: the MBAP header and the PDU.
-spec adu(tid(), unit_id(), binary()) -> binary().
adu(Tid, Unit, Pdu) ->
    <<Tid:16, 0:16, (byte_size(Pdu) + 1):16, Unit, Pdu/binary>>.

%% @doc Takes one frame off the front of a received byte stream. `more' means the
%% frame is not complete yet; an error means the stream cannot be Modbus TCP (a
%% protocol id other than 0, a length field outside 2..254) and the connection should
%% be closed: nothing after it can be trusted.
-spec frame(binary()) -> {ok, tid(), unit_id(), Pdu :: binary(), Rest :: binary()}
                         | more | {error, error_reason()}.
frame(<<_:16, Proto:16, _/binary>>) when Proto =/= 0 ->
    {error, {bad_protocol_id, Proto}};
frame(<<_:32, Len:16, _/binary>>) when Len < 2; Len > ?MAX_PDU + 1 ->
    {error, {bad_length_field, Len}};
frame(<<Tid:16, 0:16, Len:16, Unit, Rest/binary>>) when byte_size(Rest) >= Len - 1 ->
    <<Pdu:(Len - 1)/binary, Tail/binary>> = Rest,
    {ok, Tid, Unit, Pdu, Tail};
frame(_) ->
    more.

%% @doc The reply to a request from the PDU that answered it: `{exception, Code}' when
%% the device refused it, `{error, Why}' when the PDU does not answer this request.
-spec decode_response(request(), binary()) ->
          {ok, reply()} | {exception, exception_code()} | {error, error_reason()}.
decode_response(_, <<>>) ->
    {error, empty_pdu};
decode_response(Req, <<EFc, Rest/binary>>) when EFc >= 16#80 ->
    Fc = function_code(Req),
    case {EFc - 16#80, Rest} of
        {Fc, <<Code>>} when Code > 0 -> {exception, Code};
        {Fc, _} -> {error, bad_exception};
        {Other, _} -> {error, {wrong_function, Fc, Other}}
    end;
decode_response(Req, <<Fc, Rest/binary>> = Pdu) ->
    case function_code(Req) of
        Fc -> decode_reply(Req, Rest, Pdu);
        Asked -> {error, {wrong_function, Asked, Fc}}
    end.

decode_reply({Read, _, N}, Rest, _) when Read =:= read_coils;
                                         Read =:= read_discrete_inputs ->
    case counted(Rest, (N + 7) div 8) of
        {ok, Data} -> {ok, unpack_bits(Data, N)};
        Error -> Error
    end;
decode_reply({Read, _, N}, Rest, _) when Read =:= read_holding_registers;
                                         Read =:= read_input_registers ->
    counted(Rest, 2 * N);
decode_reply({read_write_registers, _, N, _, _}, Rest, _) ->
    counted(Rest, 2 * N);
decode_reply({Echo, _, _} = Req, _, Pdu) when Echo =:= write_single_coil;
                                              Echo =:= write_single_register ->
    echo(request_pdu(Req), Pdu);
decode_reply({mask_write_register, _, _, _} = Req, _, Pdu) ->
    echo(request_pdu(Req), Pdu);
decode_reply({write_multiple_coils, A, Bits}, _, Pdu) ->
    echo(<<?FC_WRITE_COILS, A:16, (length(Bits)):16>>, Pdu);
decode_reply({write_multiple_registers, A, Regs}, _, Pdu) ->
    echo(<<?FC_WRITE_REGISTERS, A:16, (byte_size(Regs) div 2):16>>, Pdu);
decode_reply({user_function, _, _}, Rest, _) ->
    {ok, Rest}.

%% A byte count followed by exactly that many bytes, and the count the request implies.
counted(<<Count, Data/binary>>, Count) when byte_size(Data) =:= Count -> {ok, Data};
counted(<<Count, Data/binary>>, Count) -> {error, {bad_size, Count + 1, byte_size(Data) + 1}};
counted(<<Count, _/binary>>, Expected) -> {error, {bad_byte_count, Expected, Count}};
counted(<<>>, Expected) -> {error, {bad_size, Expected + 1, 0}}.

echo(Pdu, Pdu) -> {ok, ok};
echo(Expected, Got) when byte_size(Expected) =/= byte_size(Got) ->
    {error, {bad_size, byte_size(Expected) - 1, byte_size(Got) - 1}};
echo(_, _) -> {error, echo_mismatch}.

function_code({read_coils, _, _}) -> ?FC_READ_COILS;
function_code({read_discrete_inputs, _, _}) -> ?FC_READ_DISCRETE;
function_code({read_holding_registers, _, _}) -> ?FC_READ_HOLDING;
function_code({read_input_registers, _, _}) -> ?FC_READ_INPUT;
function_code({write_single_coil, _, _}) -> ?FC_WRITE_COIL;
function_code({write_single_register, _, _}) -> ?FC_WRITE_REGISTER;
function_code({write_multiple_coils, _, _}) -> ?FC_WRITE_COILS;
function_code({write_multiple_registers, _, _}) -> ?FC_WRITE_REGISTERS;
function_code({mask_write_register, _, _, _}) -> ?FC_MASK_WRITE;
function_code({read_write_registers, _, _, _, _}) -> ?FC_READ_WRITE;
function_code({user_function, Fc, _}) -> Fc.

%%====================================================================
%% Requests and responses (server side: test peers and properties)
%%====================================================================

%% @doc The request a PDU asks for, checked against the protocol's limits.
-spec decode_request(binary()) -> {ok, request()} | {error, error_reason()}.
decode_request(Pdu) ->
    case parse_request(Pdu) of
        {ok, Req} ->
            case check_request(Req) of
                ok -> {ok, Req};
                Error -> Error
            end;
        Error ->
            Error
    end.

parse_request(<<Fc, A:16, N:16>>) when Fc >= 1, Fc =< 4 ->
    {ok, {element(Fc, {read_coils, read_discrete_inputs, read_holding_registers,
                        read_input_registers}), A, N}};
parse_request(<<?FC_WRITE_COIL, A:16, 16#FF00:16>>) -> {ok, {write_single_coil, A, true}};
parse_request(<<?FC_WRITE_COIL, A:16, 0:16>>) -> {ok, {write_single_coil, A, false}};
parse_request(<<?FC_WRITE_COIL, _:32>>) -> {error, {bad_request, value}};
parse_request(<<?FC_WRITE_REGISTER, A:16, V:16>>) -> {ok, {write_single_register, A, V}};
parse_request(<<?FC_WRITE_COILS, A:16, N:16, Count, Packed/binary>>) ->
    case byte_size(Packed) =:= Count andalso Count =:= (N + 7) div 8 of
        true -> {ok, {write_multiple_coils, A, unpack_bits(Packed, N)}};
        false -> {error, {bad_byte_count, (N + 7) div 8, Count}}
    end;
parse_request(<<?FC_WRITE_REGISTERS, A:16, N:16, Count, Regs/binary>>) ->
    case byte_size(Regs) =:= Count andalso Count =:= 2 * N of
        true -> {ok, {write_multiple_registers, A, Regs}};
        false -> {error, {bad_byte_count, 2 * N, Count}}
    end;
parse_request(<<?FC_MASK_WRITE, A:16, And:16, Or:16>>) ->
    {ok, {mask_write_register, A, And, Or}};
parse_request(<<?FC_READ_WRITE, RA:16, RN:16, WA:16, WN:16, Count, Regs/binary>>) ->
    case byte_size(Regs) =:= Count andalso Count =:= 2 * WN of
        true -> {ok, {read_write_registers, RA, RN, WA, Regs}};
        false -> {error, {bad_byte_count, 2 * WN, Count}}
    end;
parse_request(<<Fc, Data/binary>>) when Fc >= 1, Fc =< 127 ->
    case lists:member(Fc, ?KNOWN_FCS) of
        true -> {error, {bad_request, size}};
        false -> {ok, {user_function, Fc, Data}}
    end;
parse_request(<<>>) ->
    {error, empty_pdu};
parse_request(<<_, _/binary>>) ->
    {error, {bad_request, function}}.

%% @doc The PDU a server answers a request with: its reply, or an exception.
-spec response_pdu(request(), reply() | {exception, exception_code()}) -> binary().
response_pdu(Req, {exception, Code}) ->
    <<(function_code(Req) + 16#80), Code>>;
response_pdu({Read, _, _} = Req, Bits) when Read =:= read_coils;
                                            Read =:= read_discrete_inputs ->
    Packed = pack_bits(Bits),
    <<(function_code(Req)), (byte_size(Packed)), Packed/binary>>;
response_pdu(Req, Regs) when element(1, Req) =:= read_holding_registers;
                             element(1, Req) =:= read_input_registers;
                             element(1, Req) =:= read_write_registers ->
    <<(function_code(Req)), (byte_size(Regs)), Regs/binary>>;
response_pdu({write_multiple_coils, A, Bits}, ok) ->
    <<?FC_WRITE_COILS, A:16, (length(Bits)):16>>;
response_pdu({write_multiple_registers, A, Regs}, ok) ->
    <<?FC_WRITE_REGISTERS, A:16, (byte_size(Regs) div 2):16>>;
response_pdu({user_function, Fc, _}, Data) ->
    <<Fc, Data/binary>>;
response_pdu(Req, ok) ->
    request_pdu(Req).

%%====================================================================
%% Words for operators
%%====================================================================

%% @doc The name of an exception code (Modbus specification §7).
-spec exception_name(exception_code()) -> atom().
exception_name(1) -> illegal_function;
exception_name(2) -> illegal_data_address;
exception_name(3) -> illegal_data_value;
exception_name(4) -> server_device_failure;
exception_name(5) -> acknowledge;
exception_name(6) -> server_device_busy;
exception_name(7) -> negative_acknowledge;
exception_name(8) -> memory_parity_error;
exception_name(10) -> gateway_path_unavailable;
exception_name(11) -> gateway_target_failed_to_respond;
exception_name(_) -> unknown_exception.

%% @doc An exception in an operator's words: what the PLC said, then the
%% specification's name and code for whoever reads the PLC's manual,
%% "the PLC refuses this address (illegal data address, Modbus exception 2)".
-spec exception_text(exception_code()) -> iolist().
exception_text(Code) ->
    Name = string:replace(atom_to_list(exception_name(Code)), "_", " ", all),
    [exception_words(Code), " (", Name, ", Modbus exception ", integer_to_list(Code), ")"].

exception_words(1) -> "the PLC does not offer this function";
exception_words(2) -> "the PLC refuses this address";
exception_words(3) -> "the PLC refuses this quantity or value";
exception_words(4) -> "the PLC failed while handling the request";
exception_words(5) -> "the PLC took the request but has not finished it";
exception_words(6) -> "the PLC is busy with a long command";
exception_words(7) -> "the PLC cannot carry out this request";
exception_words(8) -> "the PLC found a parity error in its memory";
exception_words(10) -> "the gateway has no path to the device behind it";
exception_words(11) -> "the device behind the gateway did not answer";
exception_words(_) -> "the PLC refused the request with a code the specification does not name".

%% @doc What went wrong with a frame, in words.
-spec format_error(error_reason()) -> iolist().
format_error({bad_protocol_id, P}) ->
    io_lib:format("a frame with protocol id ~b arrived, not Modbus (0)", [P]);
format_error({bad_length_field, L}) ->
    io_lib:format("a frame announced ~b bytes, outside Modbus TCP's 2..254", [L]);
format_error({wrong_function, Asked, Got}) ->
    io_lib:format("the device answered function ~b to a request of function ~b",
                  [Got, Asked]);
format_error({bad_byte_count, Expected, Got}) ->
    io_lib:format("a reply counted ~b data bytes where ~b were asked for", [Got, Expected]);
format_error({bad_size, Expected, Got}) ->
    io_lib:format("a reply carried ~b bytes where ~b were expected", [Got, Expected]);
format_error(echo_mismatch) ->
    "the device confirmed a write that differs from the one sent";
format_error(bad_exception) ->
    "a malformed exception reply arrived";
format_error(empty_pdu) ->
    "an empty reply arrived";
format_error({bad_request, What}) ->
    io_lib:format("the request is outside Modbus limits (~s)", [What]).

%% @doc A request in words, for logs: "read holding registers 100..109".
-spec describe(request()) -> iolist().
describe({read_coils, A, N}) -> span("read coils", A, N);
describe({read_discrete_inputs, A, N}) -> span("read discrete inputs", A, N);
describe({read_holding_registers, A, N}) -> span("read holding registers", A, N);
describe({read_input_registers, A, N}) -> span("read input registers", A, N);
describe({write_single_coil, A, _}) -> span("write coil", A, 1);
describe({write_single_register, A, _}) -> span("write holding register", A, 1);
describe({write_multiple_coils, A, Bits}) -> span("write coils", A, length(Bits));
describe({write_multiple_registers, A, R}) ->
    span("write holding registers", A, byte_size(R) div 2);
describe({mask_write_register, A, _, _}) -> span("write bits of holding register", A, 1);
describe({read_write_registers, RA, RN, WA, R}) ->
    [span("read holding registers", RA, RN), " and ",
     span("write", WA, byte_size(R) div 2)];
describe({user_function, Fc, _}) -> io_lib:format("function ~b", [Fc]).

span(What, A, 1) -> io_lib:format("~s ~b", [What, A]);
span(What, A, N) -> io_lib:format("~s ~b..~b", [What, A, A + N - 1]).

%%====================================================================
%% Bits: the first coil in the least significant bit of the first byte
%%====================================================================

pack_bits(Bits) -> pack_bits(Bits, <<>>).

pack_bits([], Acc) -> Acc;
pack_bits(Bits, Acc) ->
    {Byte, Rest} = take_byte(Bits, 0, 0),
    pack_bits(Rest, <<Acc/binary, Byte>>).

take_byte([], _, Byte) -> {Byte, []};
take_byte(Rest, 8, Byte) -> {Byte, Rest};
take_byte([B | Rest], I, Byte) ->
    take_byte(Rest, I + 1, case B of true -> Byte bor (1 bsl I); false -> Byte end).

unpack_bits(Data, N) ->
    lists:sublist([B =:= 1 || <<B7:1, B6:1, B5:1, B4:1, B3:1, B2:1, B1:1, B0:1>> <= Data,
                              B <- [B0, B1, B2, B3, B4, B5, B6, B7]], N).
