%% PropEr properties of the ADS wire formats. The expected bytes and values come from
%% encoders and parsers written here, from the ADS specification, not from the codec.
%% Random garbage never makes a decoder raise: it answers `{error, Reason}'.
-module(prop_cell_hal_ads_codec).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(N, 500).

properties_test_() ->
    [{timeout, 120, {atom_to_list(P), ?_assert(proper:quickcheck(?MODULE:P(),
                                                                [{to_file, user}, {numtests, ?N}]))}}
     || P <- [prop_request_frames, prop_stream_in_pieces, prop_responses, prop_sum_read,
              prop_sum_read_write, prop_notifications, prop_symbol_table, prop_garbage,
              prop_garbage_frames, prop_garbage_stream, prop_value_round_trip,
              prop_value_garbage]].

%%--------------------------------------------------------------------
%% Generators
%%--------------------------------------------------------------------

u32() -> integer(0, 16#FFFFFFFF).
u16() -> integer(0, 16#FFFF).
net_id() -> {byte(), byte(), byte(), byte(), byte(), byte()}.
addr() -> {net_id(), u16()}.
data() -> ?LET(B, binary(), B).

request() ->
    oneof([read_device_info,
           read_state,
           {read, u32(), u32(), u32()},
           {write, u32(), u32(), data()},
           {read_write, u32(), u32(), u32(), data()},
           {write_control, oneof([run, stop, config, u16()]), u16(), data()},
           {add_notification, u32(), u32(), u32(), oneof([cyclic, on_change]), u32(), u32()},
           {delete_notification, u32()}]).

%%--------------------------------------------------------------------
%% Requests
%%--------------------------------------------------------------------

%% Every request frame reads back, field by field, as the specification lays it out.
prop_request_frames() ->
    ?FORALL({Target, Source, Invoke, Request}, {addr(), addr(), u32(), request()},
            begin
                Frame = iolist_to_binary(cell_hal_ads_codec:encode_frame(Target, Source, Invoke,
                                                                         Request)),
                {{TNet, TPort}, {SNet, SPort}} = {Target, Source},
                {TNetB, SNetB} = {net_bin(TNet), net_bin(SNet)},
                <<0:16, Len:32/little, TNetB:6/binary, TPort:16/little, SNetB:6/binary,
                  SPort:16/little, Cmd:16/little, 4:16/little, DLen:32/little, 0:32,
                  Invoke:32/little, Data/binary>> = Frame,
                Len =:= 32 + DLen andalso byte_size(Data) =:= DLen andalso
                    model_request(Cmd, Data) =:= normal(Request)
            end).

net_bin(Id) -> list_to_binary(tuple_to_list(Id)).

model_request(1, <<>>) -> read_device_info;
model_request(2, <<G:32/little, O:32/little, L:32/little>>) -> {read, G, O, L};
model_request(3, <<G:32/little, O:32/little, L:32/little, D:L/binary>>) -> {write, G, O, D};
model_request(4, <<>>) -> read_state;
model_request(5, <<S:16/little, Dev:16/little, L:32/little, D:L/binary>>) ->
    {write_control, S, Dev, D};
model_request(6, <<G:32/little, O:32/little, L:32/little, M:32/little, Delay:32/little,
                   Cycle:32/little, 0:128>>) ->
    {add_notification, G, O, L, case M of 3 -> cyclic; 4 -> on_change end, Delay, Cycle};
model_request(7, <<H:32/little>>) -> {delete_notification, H};
model_request(9, <<G:32/little, O:32/little, RL:32/little, WL:32/little, D:WL/binary>>) ->
    {read_write, G, O, RL, D}.

normal({write_control, S, Dev, D}) ->
    {write_control, state_code(S), Dev, iolist_to_binary(D)};
normal(R) -> R.

state_code(run) -> 5;
state_code(stop) -> 6;
state_code(config) -> 15;
state_code(N) -> N.

%% A stream of frames cut anywhere (as TCP may deliver it) gives back every frame.
prop_stream_in_pieces() ->
    ?FORALL({Requests, Cuts}, {non_empty(list(request())), list(integer(1, 64))},
            begin
                Frames = [iolist_to_binary(cell_hal_ads_codec:encode_frame(
                                             {{1, 2, 3, 4, 1, 1}, 851}, {{5, 6, 7, 8, 1, 1}, 30000},
                                             I, R))
                          || {I, R} <- lists:zip(lists:seq(1, length(Requests)), Requests)],
                Bodies = [B || <<_:48, B/binary>> <- Frames],
                Stream = iolist_to_binary(Frames),
                feed(pieces(Stream, Cuts), <<>>, []) =:= Bodies
            end).

pieces(<<>>, _) -> [];
pieces(Bin, []) -> [Bin];
pieces(Bin, [N | _]) when N >= byte_size(Bin) -> [Bin];
pieces(Bin, [N | Ns]) ->
    <<P:N/binary, Rest/binary>> = Bin,
    [P | pieces(Rest, Ns)].

feed([], <<>>, Acc) -> lists:reverse(Acc);
feed([], _, _) -> leftover;
feed([P | Ps], Buffer, Acc) -> drain(Ps, <<Buffer/binary, P/binary>>, Acc).

drain(Ps, Buffer, Acc) ->
    case cell_hal_ads_codec:next_frame(Buffer, 1 bsl 24) of
        more -> feed(Ps, Buffer, Acc);
        {ams, Body, Rest} -> drain(Ps, Rest, [Body | Acc])
    end.

%%--------------------------------------------------------------------
%% Responses
%%--------------------------------------------------------------------

response() ->
    oneof([{read_device_info, {byte(), byte(), u16(), ?LET(N, binary(), binary:part(nonul(N), 0, min(16, byte_size(N))))}},
           {read, data()},
           {read_write, data()},
           {read_state, {integer(0, 19), u16()}},
           {add_notification, u32()},
           {write, ok}, {write_control, ok}, {delete_notification, ok},
           {error_of, oneof([read, write, read_write, add_notification]), integer(1, 16#FFFF)}]).

nonul(Bin) -> << <<(max(1, C))>> || <<C>> <= Bin >>.

%% Each answer the specification allows decodes to what it carries.
prop_responses() ->
    ?FORALL(R, response(),
            case R of
                {read_device_info, {Ma, Mi, B, Name}} ->
                    Pad = 16 - byte_size(Name),
                    {ok, #{name => Name, version => {Ma, Mi, B}}} =:=
                        cell_hal_ads_codec:decode_response(
                          read_device_info, <<0:32, Ma, Mi, B:16/little, Name/binary, 0:(Pad * 8)>>);
                {Cmd, Data} when Cmd =:= read; Cmd =:= read_write ->
                    {ok, Data} =:= cell_hal_ads_codec:decode_response(
                                     Cmd, <<0:32, (byte_size(Data)):32/little, Data/binary>>);
                {read_state, {S, Dev}} ->
                    {ok, {S1, Dev}} = cell_hal_ads_codec:decode_response(
                                        read_state, <<0:32, S:16/little, Dev:16/little>>),
                    is_atom(S1) andalso cell_hal_ads_codec:ads_state_code(S1) =:= S;
                {add_notification, H} ->
                    {ok, H} =:= cell_hal_ads_codec:decode_response(add_notification,
                                                                   <<0:32, H:32/little>>);
                {Cmd, ok} ->
                    {ok, ok} =:= cell_hal_ads_codec:decode_response(Cmd, <<0:32>>);
                {error_of, Cmd, Code} ->
                    {error, {ads_error, Code, cell_hal_ads_codec:error_name(Code)}} =:=
                        cell_hal_ads_codec:decode_response(Cmd, <<Code:32/little, 0:32>>)
            end).

item() -> {integer(0, 40), oneof([0, 0, 0, 16#710, 16#705])}.

%% Sum read answers, with and without the slots of failed items.
prop_sum_read() ->
    ?FORALL({Items, Compact}, {non_empty(list(item())), boolean()},
            begin
                Datas = [{binary:copy(<<(I rem 256)>>, L), E} || {I, {L, E}} <- enum(Items)],
                Codes = << <<E:32/little>> || {_, E} <- Datas >>,
                Body = << <<D/binary>> || {D, E} <- Datas, E =:= 0 orelse not Compact >>,
                Expected = [case E of
                                0 -> {ok, D};
                                _ -> {error, cell_hal_ads_codec:ads_error(E)}
                            end || {D, E} <- Datas],
                Lens = [L || {L, _} <- Items],
                {ok, Expected} =:= cell_hal_ads_codec:decode_sum_read(Lens, <<Codes/binary, Body/binary>>)
            end).

enum(L) -> lists:zip(lists:seq(1, length(L)), L).

prop_sum_read_write() ->
    ?FORALL(Items, list({data(), oneof([0, 16#710])}),
            begin
                Heads = << <<E:32/little, (case E of 0 -> byte_size(D); _ -> 0 end):32/little>>
                           || {D, E} <- Items >>,
                Body = << <<D/binary>> || {D, 0} <- Items >>,
                Expected = [case E of 0 -> {ok, D}; _ -> {error, cell_hal_ads_codec:ads_error(E)} end
                            || {D, E} <- Items],
                {ok, Expected} =:= cell_hal_ads_codec:decode_sum_read_write(
                                     length(Items), <<Heads/binary, Body/binary>>)
            end).

%% Notification streams: every stamp and sample in order.
prop_notifications() ->
    ?FORALL(Stamps, list({integer(0, 16#FFFFFFFFFFFFFFFF), list({u32(), data()})}),
            begin
                Body = <<(length(Stamps)):32/little,
                         (<< <<T:64/little, (length(Ss)):32/little,
                               (<< <<H:32/little, (byte_size(V)):32/little, V/binary>>
                                   || {H, V} <- Ss >>)/binary>> || {T, Ss} <- Stamps >>)/binary>>,
                {ok, Stamps} =:= cell_hal_ads_codec:decode_notification(
                                   <<(byte_size(Body)):32/little, Body/binary>>)
            end).

name() -> ?LET(B, non_empty(binary()), nonul(B)).

symbol() ->
    ?LET({Name, Type, Comment, G, O, Size, DT, Flags},
         {name(), name(), ?LET(C, binary(), nonul(C)), u32(), u32(), u32(), u32(), u32()},
         #{name => Name, type => Type, comment => Comment, group => G, offset => O,
           size => Size, data_type => DT, flags => Flags}).

prop_symbol_table() ->
    ?FORALL(Symbols, list(symbol()),
            begin
                Table = << <<(entry(S))/binary>> || S <- Symbols >>,
                {ok, Symbols} =:= cell_hal_ads_codec:decode_symbol_table(Table)
            end).

entry(#{name := N, type := T, comment := C, group := G, offset := O, size := S,
        data_type := DT, flags := F}) ->
    Strings = <<N/binary, 0, T/binary, 0, C/binary, 0>>,
    <<(30 + byte_size(Strings)):32/little, G:32/little, O:32/little, S:32/little,
      DT:32/little, F:32/little, (byte_size(N)):16/little, (byte_size(T)):16/little,
      (byte_size(C)):16/little, Strings/binary>>.

%%--------------------------------------------------------------------
%% Garbage
%%--------------------------------------------------------------------

%% Any bytes at all: every decoder answers, none raises.
prop_garbage() ->
    ?FORALL(Bin, binary(), decoders_answer(Bin)).

%% Frames whose AMS/TCP header is right but whose content is random.
prop_garbage_frames() ->
    ?FORALL({Cmd, Junk}, {integer(0, 12), binary()},
            begin
                Body = <<0:128, Cmd:16/little, 5:16/little, (byte_size(Junk)):32/little,
                         0:32, 1:32, Junk/binary>>,
                {ams, Body, <<>>} =:= cell_hal_ads_codec:next_frame(
                                        <<0:16, (byte_size(Body)):32/little, Body/binary>>, 1 bsl 20)
                    andalso decoders_answer(Junk)
                    andalso element(1, cell_hal_ads_codec:decode_ams(Body)) =:= ok
            end).

%% Random bytes between good frames: the splitter answers frames, `more' or an error.
prop_garbage_stream() ->
    ?FORALL(Bin, binary(),
            case catch split_all(Bin) of
                ok -> true;
                Other -> Other
            end).

split_all(Bin) ->
    case cell_hal_ads_codec:next_frame(Bin, 4096) of
        more -> ok;
        {error, {frame_too_long, _}} -> ok;
        {error, {bad_frame, _}} -> ok;
        {ams, Body, Rest} -> _ = shape(cell_hal_ads_codec:decode_ams(Body)), split_all(Rest);
        {router, _, _, Rest} -> split_all(Rest)
    end.

decoders_answer(Bin) ->
    Commands = [read_device_info, read, write, read_state, write_control, add_notification,
                delete_notification, read_write, device_notification],
    Results = [cell_hal_ads_codec:decode_response(C, Bin) || C <- Commands] ++
        [cell_hal_ads_codec:decode_ams(Bin),
         cell_hal_ads_codec:decode_notification(Bin),
         cell_hal_ads_codec:decode_symbol(Bin),
         cell_hal_ads_codec:decode_symbol_table(Bin),
         cell_hal_ads_codec:decode_upload_info(Bin),
         cell_hal_ads_codec:decode_sum_read([1, 2, 3], Bin),
         cell_hal_ads_codec:decode_sum_write(3, Bin),
         cell_hal_ads_codec:decode_sum_read_write(3, Bin)],
    lists:all(fun(R) -> shape(R) end, Results).

shape({ok, _}) -> true;
shape({ok, _, _}) -> true;
shape({error, {Kind, _}}) when is_atom(Kind) -> true;
shape({error, {ads_error, _, _}}) -> true;
shape(_) -> false.

%%--------------------------------------------------------------------
%% Values
%%--------------------------------------------------------------------

typed_value() ->
    oneof([{bool, boolean()},
           {byte, integer(0, 255)},
           {sbyte, integer(-128, 127)},
           {char, byte()},
           {int16, integer(-32768, 32767)},
           {uint16, integer(0, 65535)},
           {int32, integer(-16#80000000, 16#7FFFFFFF)},
           {uint32, u32()},
           {int64, integer(-16#8000000000000000, 16#7FFFFFFFFFFFFFFF)},
           {uint64, integer(0, 16#FFFFFFFFFFFFFFFF)},
           %% a float a REAL holds exactly
           {real, ?LET(F, float(-1.0e30, 1.0e30), begin <<R:32/float>> = <<F:32/float>>, R end)},
           {lreal, float()},
           {lreal, oneof([nan, infinity, neg_infinity])},
           {real, oneof([nan, infinity, neg_infinity])},
           ?LET(N, integer(1, 100), {{string, N}, ?LET(B, binary(), binary:part(nonul(B), 0, min(N, byte_size(B))))}),
           {date, ?LET(D, integer(0, 49710), calendar:gregorian_days_to_date(719528 + D))},
           {time, u32()},
           {decimal, binary(16)},
           ?LET(N, integer(1, 40), {{bytes, N}, binary(N)})]).

prop_value_round_trip() ->
    ?FORALL({Type, Value}, typed_value(),
            begin
                {ok, Bin} = cell_hal_ads_types:encode(Type, Value),
                byte_size(Bin) =:= cell_hal_ads_types:plc_size(Type) andalso
                    {ok, Value} =:= cell_hal_ads_types:decode(Type, Bin)
            end).

prop_value_garbage() ->
    ?FORALL({{Type, _}, Bin}, {typed_value(), binary()},
            case cell_hal_ads_types:decode(Type, Bin) of
                {ok, _} -> true;
                {error, {bad_size, Type, N}} -> N =:= byte_size(Bin)
            end).
