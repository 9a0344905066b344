%% @doc The wire formats of Beckhoff ADS over AMS/TCP, as pure functions: no sockets,
%% no processes, so every frame can be tested byte for byte.
%%
%% A frame on the TCP stream is a 6-byte AMS/TCP header (2 reserved bytes, then the
%% length of what follows, little-endian) and a 32-byte AMS header (target and source
%% AMS address, command id, state flags, data length, error code, invoke id), then the
%% command's data. Everything on the wire is little-endian.
%%
%% <ul>
%% <li>Framing: {@link encode_frame/4} builds a request frame; {@link next_frame/2}
%%     cuts one frame off a receive buffer; {@link decode_ams/1} reads its AMS header.</li>
%% <li>Commands: {@link encode_request/1} gives the command id and data of a request
%%     (ReadDeviceInfo, Read, Write, ReadState, WriteControl, AddDeviceNotification,
%%     DeleteDeviceNotification, ReadWrite); {@link decode_response/2} reads its answer.</li>
%% <li>Sum commands (index groups 0xF080, 0xF081, 0xF082): many reads or writes in one
%%     ReadWrite; the builders and the answer parsers are here.</li>
%% <li>The device notification stream (command 8): time stamps (FILETIME, 100 ns since
%%     1601) with their samples.</li>
%% <li>Symbol entries (0xF009 answers) and the uploaded symbol table (0xF00C info,
%%     0xF00B table).</li>
%% <li>ADS result codes and ADS states: names and texts for people.</li>
%% </ul>
%%
%% Malformed input never raises: every decoder answers `{error, Reason}' with a reason
%% that says what was wrong. Names are atoms from fixed tables here, never made from
%% network data.
-module(cell_hal_ads_codec).

-include("cell_hal_ads.hrl").

-export([encode_frame/4, addresses/2, encode_frame/3, next_frame/2, decode_ams/1,
         decode_answer/1]).
-export([encode_request/1, request_command/1, decode_response/2, command_id/1,
         command_name/1]).
-export([decode_notification/1]).
-export([sum_read/1, sum_write/1, sum_read_write/1,
         decode_sum_read/2, decode_sum_write/2, decode_sum_read_write/2]).
-export([decode_symbol/1, decode_symbol_table/1, decode_upload_info/1]).
-export([filetime_to_ns/1, ns_to_filetime/1]).
-export([parse_net_id/1, format_net_id/1]).
-export([error_name/1, error_text/1, ads_error/1, ads_state_name/1, ads_state_code/1,
         is_ads_state/1]).

-export_type([net_id/0, ams_port/0, ams_addr/0, command/0, request/0, response/0,
              header/0, trans_mode/0, ads_state/0, symbol/0, ads_error/0,
              decode_error/0, stamp/0]).

-type net_id() :: {byte(), byte(), byte(), byte(), byte(), byte()}.
-type ams_port() :: 0..65535.
-type ams_addr() :: {net_id(), ams_port()}.
-type u32() :: 0..16#FFFFFFFF.

-type command() :: read_device_info | read | write | read_state | write_control
                 | add_notification | delete_notification | device_notification
                 | read_write.

-type trans_mode() :: cyclic | on_change.

%% An ADS state by name, or its number when this module does not know it.
-type ads_state() :: invalid | idle | reset | init | start | run | stop | save_config
                   | load_config | power_failure | power_good | error | shutdown
                   | suspend | resume | config | reconfig | stopping | incompatible
                   | exception | 0..65535.

%% A request as the client thinks of it. Lengths are byte counts; delays and cycle
%% times of notifications are in the protocol's unit, 100 ns.
-type request() :: read_device_info
                 | read_state
                 | {read, Group :: u32(), Offset :: u32(), Length :: u32()}
                 | {write, Group :: u32(), Offset :: u32(), iodata()}
                 | {read_write, Group :: u32(), Offset :: u32(), ReadLength :: u32(),
                    iodata()}
                 | {write_control, ads_state(), DeviceState :: 0..65535, iodata()}
                 | {add_notification, Group :: u32(), Offset :: u32(), Length :: u32(),
                    trans_mode(), MaxDelay :: u32(), CycleTime :: u32()}
                 | {delete_notification, Handle :: u32()}.

%% What a successful answer carries, by command.
-type response() :: #{name := binary(), version := {byte(), byte(), 0..65535}}  %% device info
                  | binary()                                                  %% read, read_write
                  | {ads_state(), DeviceState :: 0..65535}                    %% read_state
                  | u32()                                                     %% add_notification
                  | ok.                                                       %% the others

-type header() :: #{target := ams_addr(), source := ams_addr(),
                    command := command() | {unknown, 0..65535},
                    flags := 0..65535, error := u32(), invoke := u32()}.

-type symbol() :: #{name := binary(), type := binary(), comment := binary(),
                    group := u32(), offset := u32(), size := u32(),
                    data_type := u32(), flags := u32()}.

%% An ADS result code with its name (`unknown' for a code not in the table).
-type ads_error() :: {ads_error, u32(), atom()}.

-type decode_error() :: {bad_frame, atom()} | {bad_response, atom()}
                      | {bad_notification, atom()} | {bad_symbol, atom()}.

%% One time stamp of a notification frame: FILETIME and the samples taken then, by
%% notification handle.
-type stamp() :: {FileTime :: non_neg_integer(), [{Handle :: u32(), binary()}]}.

%% 100 ns ticks between 1601-01-01 (FILETIME) and 1970-01-01 (Unix).
-define(FILETIME_UNIX_EPOCH, 116444736000000000).
-define(AMS_HEADER_SIZE, 32).
-define(FLAGS_REQUEST, 16#0004).
-define(FLAG_RESPONSE, 16#0001).

%%====================================================================
%% Framing
%%====================================================================

%% @doc One request frame (AMS/TCP header, AMS header, data) from `Source' to `Target'.
-spec encode_frame(Target :: ams_addr(), Source :: ams_addr(), Invoke :: u32(),
                   request()) -> iodata().
encode_frame(Target, Source, Invoke, Request) ->
    encode_frame(addresses(Target, Source), Invoke, Request).

%% @doc The target and source AMS addresses as every request frame between them
%% carries them: 16 bytes, built once for many frames.
-spec addresses(Target :: ams_addr(), Source :: ams_addr()) -> binary().
addresses({TNet, TPort}, {SNet, SPort}) ->
    <<(net_id_bin(TNet))/binary, TPort:16/little, (net_id_bin(SNet))/binary, SPort:16/little>>.

%% @doc As {@link encode_frame/4}, with the addresses built by {@link addresses/2}.
-spec encode_frame(Addresses :: <<_:128>>, Invoke :: u32(), request()) -> iodata().
encode_frame(<<_:16/binary>> = Addresses, Invoke, Request) ->
    {Cmd, Data} = encode_request(Request),
    Len = iolist_size(Data),
    [<<0:16, (?AMS_HEADER_SIZE + Len):32/little, Addresses/binary,
       Cmd:16/little, ?FLAGS_REQUEST:16/little, Len:32/little, 0:32, Invoke:32/little>>,
     Data].

%% @doc Cuts the first frame off a receive buffer. `{ams, Body, Rest}' is an AMS
%% frame (header and data); `{router, Code, Body, Rest}' is an AMS/TCP frame of
%% another kind (the router's own messages), which a client skips; `more' asks for
%% more bytes. A length beyond `MaxFrame' is an error: the stream cannot be trusted.
-spec next_frame(binary(), pos_integer()) ->
          {ams, binary(), binary()} | {router, 0..65535, binary(), binary()} | more
        | {error, {frame_too_long, non_neg_integer()} | {bad_frame, atom()}}.
next_frame(<<_:16, Len:32/little, _/binary>>, MaxFrame) when Len > MaxFrame ->
    {error, {frame_too_long, Len}};
next_frame(<<0:16, Len:32/little, Body:Len/binary, Rest/binary>>, _) ->
    case Len >= ?AMS_HEADER_SIZE of
        true -> {ams, Body, Rest};
        false -> {error, {bad_frame, shorter_than_ams_header}}
    end;
next_frame(<<Code:16/little, Len:32/little, Body:Len/binary, Rest/binary>>, _) ->
    {router, Code, Body, Rest};
next_frame(_, _) ->
    more.

%% @doc The AMS header of a frame body and the command's data. The header's data
%% length must match what follows it.
-spec decode_ams(binary()) -> {ok, header(), binary()} | {error, decode_error()}.
decode_ams(<<TNet:6/binary, TPort:16/little, SNet:6/binary, SPort:16/little,
             Cmd:16/little, Flags:16/little, Len:32/little, Err:32/little,
             Invoke:32/little, Data/binary>>) ->
    case byte_size(Data) of
        Len ->
            {ok, #{target => {net_id(TNet), TPort}, source => {net_id(SNet), SPort},
                   command => command_name(Cmd), flags => Flags, error => Err,
                   invoke => Invoke},
             Data};
        _ ->
            {error, {bad_frame, length_mismatch}}
    end;
decode_ams(_) ->
    {error, {bad_frame, shorter_than_ams_header}}.

%% @doc What a client receives most: exactly one frame that answers a request, read
%% in one match (the AMS port it is for, command, ADS error, invoke id and data).
%% Anything else, several frames, part of one or not an answer, is `other': cut it
%% with {@link next_frame/2} and read it with {@link decode_ams/1}.
-spec decode_answer(binary()) ->
          {answer, ams_port(), command() | {unknown, 0..65535}, u32(), u32(), binary()}
        | other.
decode_answer(<<0:16, Len:32/little, _:6/binary, Port:16/little, _:8/binary, Cmd:16/little,
                Flags:16/little, DataLen:32/little, Error:32/little, Invoke:32/little,
                Data:DataLen/binary>>)
  when Len =:= ?AMS_HEADER_SIZE + DataLen, Flags band ?FLAG_RESPONSE =:= ?FLAG_RESPONSE ->
    {answer, Port, command_name(Cmd), Error, Invoke, Data};
decode_answer(_) ->
    other.

%%====================================================================
%% Commands
%%====================================================================

%% @doc The command id and data of a request.
-spec encode_request(request()) -> {1..9, iodata()}.
encode_request(read_device_info) ->
    {1, <<>>};
encode_request({read, G, O, Len}) ->
    {2, <<G:32/little, O:32/little, Len:32/little>>};
encode_request({write, G, O, Data}) ->
    {3, [<<G:32/little, O:32/little, (iolist_size(Data)):32/little>>, Data]};
encode_request(read_state) ->
    {4, <<>>};
encode_request({write_control, State, DevState, Data}) ->
    {5, [<<(ads_state_code(State)):16/little, DevState:16/little,
           (iolist_size(Data)):32/little>>, Data]};
encode_request({add_notification, G, O, Len, Mode, MaxDelay, Cycle}) ->
    {6, <<G:32/little, O:32/little, Len:32/little, (trans_mode_code(Mode)):32/little,
          MaxDelay:32/little, Cycle:32/little, 0:128>>};
encode_request({delete_notification, Handle}) ->
    {7, <<Handle:32/little>>};
encode_request({read_write, G, O, ReadLen, Data}) ->
    {9, [<<G:32/little, O:32/little, ReadLen:32/little, (iolist_size(Data)):32/little>>,
         Data]}.

%% @doc The command a request is sent as.
-spec request_command(request()) -> command().
request_command(read_device_info) -> read_device_info;
request_command(read_state) -> read_state;
request_command({read, _, _, _}) -> read;
request_command({write, _, _, _}) -> write;
request_command({read_write, _, _, _, _}) -> read_write;
request_command({write_control, _, _, _}) -> write_control;
request_command({add_notification, _, _, _, _, _, _}) -> add_notification;
request_command({delete_notification, _}) -> delete_notification.

%% @doc Reads the data of an answer to a `Command' request. An ADS result other than
%% 0 is `{error, {ads_error, Code, Name}}'; a data part that is too short or too long
%% is `{error, {bad_response, What}}'.
-spec decode_response(command(), binary()) ->
          {ok, response()} | {error, ads_error() | decode_error()}.
decode_response(_, <<Result:32/little, _/binary>>) when Result =/= 0 ->
    {error, ads_error(Result)};
decode_response(read_device_info, <<0:32, Major, Minor, Build:16/little, Name/binary>>)
  when byte_size(Name) =< 16 ->
    {ok, #{name => cstring(Name), version => {Major, Minor, Build}}};
decode_response(Cmd, <<0:32, Len:32/little, Data:Len/binary>>)
  when Cmd =:= read; Cmd =:= read_write ->
    {ok, Data};
decode_response(read_state, <<0:32, State:16/little, DevState:16/little>>) ->
    {ok, {ads_state_name(State), DevState}};
decode_response(add_notification, <<0:32, Handle:32/little>>) ->
    {ok, Handle};
decode_response(Cmd, <<0:32>>)
  when Cmd =:= write; Cmd =:= write_control; Cmd =:= delete_notification ->
    {ok, ok};
decode_response(_, _) ->
    {error, {bad_response, wrong_length}}.

%% @doc The command id of a command name.
-spec command_id(command()) -> 1..9.
command_id(read_device_info) -> 1;
command_id(read) -> 2;
command_id(write) -> 3;
command_id(read_state) -> 4;
command_id(write_control) -> 5;
command_id(add_notification) -> 6;
command_id(delete_notification) -> 7;
command_id(device_notification) -> 8;
command_id(read_write) -> 9.

%% @doc The name of a command id (`{unknown, Id}' for ids ADS does not define).
-spec command_name(0..65535) -> command() | {unknown, 0..65535}.
command_name(1) -> read_device_info;
command_name(2) -> read;
command_name(3) -> write;
command_name(4) -> read_state;
command_name(5) -> write_control;
command_name(6) -> add_notification;
command_name(7) -> delete_notification;
command_name(8) -> device_notification;
command_name(9) -> read_write;
command_name(N) -> {unknown, N}.

trans_mode_code(cyclic) -> 3;
trans_mode_code(on_change) -> 4.

%%====================================================================
%% Device notifications
%%====================================================================

%% @doc The stamps of a device notification (command 8) in the order sent, each with
%% its samples: `[{FileTime, [{NotificationHandle, Data}]}]'.
-spec decode_notification(binary()) -> {ok, [stamp()]} | {error, decode_error()}.
decode_notification(<<Len:32/little, Body/binary>>) when Len =< byte_size(Body) ->
    case Body of
        <<Count:32/little, Stamps/binary>> when Len >= 4 ->
            stamps(Count, binary:part(Stamps, 0, Len - 4), []);
        _ ->
            {error, {bad_notification, too_short}}
    end;
decode_notification(_) ->
    {error, {bad_notification, too_short}}.

stamps(0, <<>>, Acc) ->
    {ok, lists:reverse(Acc)};
stamps(0, _, _) ->
    {error, {bad_notification, trailing_bytes}};
stamps(N, <<Time:64/little, Count:32/little, Rest/binary>>, Acc) ->
    case samples(Count, Rest, []) of
        {ok, Samples, Rest1} -> stamps(N - 1, Rest1, [{Time, Samples} | Acc]);
        Error -> Error
    end;
stamps(_, _, _) ->
    {error, {bad_notification, truncated_stamp}}.

samples(0, Rest, Acc) ->
    {ok, lists:reverse(Acc), Rest};
samples(N, <<Handle:32/little, Size:32/little, Data:Size/binary, Rest/binary>>, Acc) ->
    samples(N - 1, Rest, [{Handle, Data} | Acc]);
samples(_, _, _) ->
    {error, {bad_notification, truncated_sample}}.

%%====================================================================
%% Sum commands
%%====================================================================

%% @doc One ReadWrite reading every `{Group, Offset, Length}' (index group 0xF080).
-spec sum_read([{u32(), u32(), u32()}, ...]) -> request().
sum_read(Items) ->
    N = length(Items),
    ReadLen = lists:foldl(fun({_, _, L}, Acc) -> Acc + L end, 4 * N, Items),
    {read_write, ?IG_SUMUP_READ, N, ReadLen,
     [<<G:32/little, O:32/little, L:32/little>> || {G, O, L} <- Items]}.

%% @doc One ReadWrite writing every `{Group, Offset, Data}' (index group 0xF081).
-spec sum_write([{u32(), u32(), iodata()}, ...]) -> request().
sum_write(Items) ->
    N = length(Items),
    {read_write, ?IG_SUMUP_WRITE, N, 4 * N,
     [[<<G:32/little, O:32/little, (iolist_size(D)):32/little>> || {G, O, D} <- Items],
      [D || {_, _, D} <- Items]]}.

%% @doc One ReadWrite doing a ReadWrite for every `{Group, Offset, ReadLength, Data}'
%% (index group 0xF082).
-spec sum_read_write([{u32(), u32(), u32(), iodata()}, ...]) -> request().
sum_read_write(Items) ->
    N = length(Items),
    ReadLen = lists:foldl(fun({_, _, L, _}, Acc) -> Acc + L end, 8 * N, Items),
    {read_write, ?IG_SUMUP_READWRITE, N, ReadLen,
     [[<<G:32/little, O:32/little, L:32/little, (iolist_size(D)):32/little>>
       || {G, O, L, D} <- Items],
      [D || {_, _, _, D} <- Items]]}.

%% @doc The answer to a {@link sum_read/1} of items of these lengths: one result per
%% item. The data of a failed item may or may not have its slot in the answer;
%% both layouts are read.
-spec decode_sum_read([u32()], binary()) ->
          {ok, [{ok, binary()} | {error, ads_error()}]} | {error, decode_error()}.
decode_sum_read(Lens, Bin) ->
    N = length(Lens),
    case Bin of
        <<Codes:(4 * N)/binary, Data/binary>> ->
            Results = [C || <<C:32/little>> <= Codes],
            Size = byte_size(Data),
            case lists:sum(Lens) of
                Size ->
                    {ok, slots(Lens, Results, Data, full)};
                _ ->
                    case lists:sum([L || {L, 0} <- lists:zip(Lens, Results)]) of
                        Size -> {ok, slots(Lens, Results, Data, compact)};
                        _ -> {error, {bad_response, sum_length_mismatch}}
                    end
            end;
        _ ->
            {error, {bad_response, sum_too_short}}
    end.

slots([], [], <<>>, _) ->
    [];
slots([Len | Lens], [0 | Rs], Data, Layout) ->
    <<Slot:Len/binary, Rest/binary>> = Data,
    [{ok, Slot} | slots(Lens, Rs, Rest, Layout)];
slots([Len | Lens], [R | Rs], Data, full) ->
    <<_:Len/binary, Rest/binary>> = Data,
    [{error, ads_error(R)} | slots(Lens, Rs, Rest, full)];
slots([_ | Lens], [R | Rs], Data, compact) ->
    [{error, ads_error(R)} | slots(Lens, Rs, Data, compact)].

%% @doc The answer to a {@link sum_write/1} of `N' items.
-spec decode_sum_write(non_neg_integer(), binary()) ->
          {ok, [ok | {error, ads_error()}]} | {error, decode_error()}.
decode_sum_write(N, Bin) when byte_size(Bin) =:= 4 * N ->
    {ok, [case C of 0 -> ok; _ -> {error, ads_error(C)} end || <<C:32/little>> <= Bin]};
decode_sum_write(_, _) ->
    {error, {bad_response, sum_length_mismatch}}.

%% @doc The answer to a {@link sum_read_write/1} of `N' items: each item's result and
%% returned data.
-spec decode_sum_read_write(non_neg_integer(), binary()) ->
          {ok, [{ok, binary()} | {error, ads_error()}]} | {error, decode_error()}.
decode_sum_read_write(N, Bin) ->
    case Bin of
        <<Heads:(8 * N)/binary, Data/binary>> ->
            Pairs = [{C, L} || <<C:32/little, L:32/little>> <= Heads],
            case lists:sum([L || {_, L} <- Pairs]) =:= byte_size(Data) of
                true -> {ok, rw_slots(Pairs, Data)};
                false -> {error, {bad_response, sum_length_mismatch}}
            end;
        _ ->
            {error, {bad_response, sum_too_short}}
    end.

rw_slots([], <<>>) ->
    [];
rw_slots([{C, L} | Pairs], Data) ->
    <<Slot:L/binary, Rest/binary>> = Data,
    [case C of 0 -> {ok, Slot}; _ -> {error, ads_error(C)} end | rw_slots(Pairs, Rest)].

%%====================================================================
%% Symbols
%%====================================================================

%% @doc One symbol entry, as a ReadWrite of 0xF009 (symbol info by name) answers it.
%% Separators after the name and the type name are skipped whatever they hold.
-spec decode_symbol(binary()) -> {ok, symbol()} | {error, decode_error()}.
decode_symbol(Bin) ->
    case symbol_entry(Bin) of
        {ok, Symbol, _Rest} -> {ok, Symbol};
        Error -> Error
    end.

%% @doc The uploaded symbol table (a Read of 0xF00B): every entry in order.
-spec decode_symbol_table(binary()) -> {ok, [symbol()]} | {error, decode_error()}.
decode_symbol_table(Bin) ->
    symbol_table(Bin, []).

symbol_table(<<>>, Acc) ->
    {ok, lists:reverse(Acc)};
symbol_table(Bin, Acc) ->
    case symbol_entry(Bin) of
        {ok, Symbol, Rest} -> symbol_table(Rest, [Symbol | Acc]);
        Error -> Error
    end.

symbol_entry(<<EntryLen:32/little, _/binary>> = Bin)
  when EntryLen >= 30, EntryLen =< byte_size(Bin) ->
    <<Entry:EntryLen/binary, Rest/binary>> = Bin,
    <<_:32, G:32/little, O:32/little, Size:32/little, Type:32/little, Flags:32/little,
      NameLen:16/little, TypeLen:16/little, CommentLen:16/little, Strings/binary>> = Entry,
    case Strings of
        <<Name:NameLen/binary, _, TypeName:TypeLen/binary, _, Tail/binary>> ->
            Comment = binary:part(Tail, 0, min(CommentLen, byte_size(Tail))),
            {ok, #{name => Name, type => TypeName, comment => Comment, group => G,
                   offset => O, size => Size, data_type => Type, flags => Flags},
             Rest};
        _ ->
            {error, {bad_symbol, strings_exceed_entry}}
    end;
symbol_entry(<<EntryLen:32/little, _/binary>>) when EntryLen < 30 ->
    {error, {bad_symbol, entry_too_short}};
symbol_entry(_) ->
    {error, {bad_symbol, truncated_entry}}.

%% @doc The answer to a Read of 0xF00C: how many symbols the table holds and its size
%% in bytes.
-spec decode_upload_info(binary()) ->
          {ok, #{symbols := u32(), size := u32()}} | {error, decode_error()}.
decode_upload_info(<<Count:32/little, Size:32/little, _/binary>>) ->
    {ok, #{symbols => Count, size => Size}};
decode_upload_info(_) ->
    {error, {bad_response, upload_info_too_short}}.

%%====================================================================
%% Time stamps
%%====================================================================

%% @doc A FILETIME (100 ns ticks since 1601-01-01 UTC) as nanoseconds since the Unix
%% epoch, exactly (the unit of `erlang:system_time(nanosecond)').
-spec filetime_to_ns(non_neg_integer()) -> integer().
filetime_to_ns(FileTime) ->
    (FileTime - ?FILETIME_UNIX_EPOCH) * 100.

%% @doc Nanoseconds since the Unix epoch as a FILETIME (rounded down to 100 ns).
-spec ns_to_filetime(integer()) -> integer().
ns_to_filetime(Ns) ->
    ?FILETIME_UNIX_EPOCH + floor_div(Ns, 100).

floor_div(A, B) when A >= 0 -> A div B;
floor_div(A, B) -> -((-A + B - 1) div B).

%%====================================================================
%% AMS Net IDs
%%====================================================================

%% @doc An AMS Net ID from its text ("5.23.1.7.1.1") or its tuple.
-spec parse_net_id(binary() | string() | net_id()) -> {ok, net_id()} | error.
parse_net_id({_, _, _, _, _, _} = Id) ->
    case lists:all(fun(B) -> is_integer(B) andalso B >= 0 andalso B =< 255 end,
                   tuple_to_list(Id)) of
        true -> {ok, Id};
        false -> error
    end;
parse_net_id(Text) when is_list(Text) ->
    try list_to_binary(Text) of
        Bin -> parse_net_id(Bin)
    catch
        error:badarg -> error
    end;
parse_net_id(Text) when is_binary(Text) ->
    Parts = binary:split(Text, <<".">>, [global]),
    case length(Parts) =:= 6 andalso [byte(P) || P <- Parts] of
        false -> error;
        Bytes ->
            case lists:member(error, Bytes) of
                true -> error;
                false -> {ok, list_to_tuple(Bytes)}
            end
    end;
parse_net_id(_) ->
    error.

byte(Part) when byte_size(Part) >= 1, byte_size(Part) =< 3 ->
    case [C || <<C>> <= Part, C < $0 orelse C > $9] of
        [] ->
            case binary_to_integer(Part) of
                B when B =< 255 -> B;
                _ -> error
            end;
        _ ->
            error
    end;
byte(_) ->
    error.

%% @doc An AMS Net ID as text.
-spec format_net_id(net_id()) -> binary().
format_net_id({A, B, C, D, E, F}) ->
    iolist_to_binary(lists:join(".", [integer_to_list(X) || X <- [A, B, C, D, E, F]])).

net_id_bin({A, B, C, D, E, F}) -> <<A, B, C, D, E, F>>.

net_id(<<A, B, C, D, E, F>>) -> {A, B, C, D, E, F}.

cstring(Bin) ->
    case binary:match(Bin, <<0>>) of
        {Pos, _} -> binary:part(Bin, 0, Pos);
        nomatch -> Bin
    end.

%%====================================================================
%% Result codes and states
%%====================================================================

%% @doc An ADS result code as the error term the client returns.
-spec ads_error(u32()) -> ads_error().
ads_error(Code) ->
    {ads_error, Code, error_name(Code)}.

%% @doc The name of an ADS result code (`unknown' when not in the table).
-spec error_name(u32()) -> atom().
error_name(Code) ->
    case lists:keyfind(Code, 1, errors()) of
        {_, Name, _} -> Name;
        false -> unknown
    end.

%% @doc What an ADS result code means, in words for the people running the machine.
-spec error_text(u32()) -> binary().
error_text(Code) ->
    case lists:keyfind(Code, 1, errors()) of
        {_, _, Text} -> Text;
        false -> iolist_to_binary(io_lib:format("unknown ADS error 0x~.16B", [Code]))
    end.

errors() ->
    [{16#000, no_error, <<"no error">>},
     {16#001, internal_error, <<"internal error in the AMS router">>},
     {16#002, no_realtime, <<"no real-time system">>},
     {16#003, allocation_locked, <<"locked memory could not be allocated">>},
     {16#004, mailbox_full, <<"the AMS router's mailbox is full; the message was not sent">>},
     {16#005, wrong_receive_message, <<"wrong receive message">>},
     {16#006, target_port_not_found,
      <<"target AMS port not found: the ADS server (PLC runtime) is not running">>},
     {16#007, target_machine_not_found,
      <<"target machine not found: the AMS router has no route to it">>},
     {16#008, unknown_command_id, <<"unknown ADS command">>},
     {16#009, invalid_task_id, <<"invalid task id">>},
     {16#00A, no_io, <<"no IO">>},
     {16#00B, unknown_ams_command, <<"unknown AMS command">>},
     {16#00C, win32_error, <<"Win32 error on the target">>},
     {16#00D, port_not_connected, <<"AMS port not connected">>},
     {16#00E, invalid_ams_length, <<"invalid AMS length">>},
     {16#00F, invalid_ams_net_id, <<"invalid AMS Net ID">>},
     {16#010, low_installation_level, <<"installation level too low (license)">>},
     {16#011, no_debug, <<"no debugging available">>},
     {16#012, port_disabled, <<"AMS port disabled">>},
     {16#013, port_already_connected, <<"AMS port already connected">>},
     {16#014, ams_sync_win32_error, <<"AMS sync Win32 error">>},
     {16#015, ams_sync_timeout, <<"AMS sync timeout">>},
     {16#016, ams_sync_ams_error, <<"AMS sync AMS error">>},
     {16#017, ams_sync_no_index_map, <<"no index map for AMS sync">>},
     {16#018, invalid_ams_port, <<"invalid AMS port">>},
     {16#019, no_memory, <<"no memory on the target">>},
     {16#01A, tcp_send_error, <<"TCP send error on the target">>},
     {16#01B, host_unreachable, <<"host unreachable">>},
     {16#01C, invalid_ams_fragment, <<"invalid AMS fragment">>},
     {16#01D, tls_send_error, <<"TLS send error: secure ADS connection failed">>},
     {16#01E, secure_access_denied, <<"secure ADS access denied">>},
     {16#500, router_no_locked_memory, <<"router: no locked memory">>},
     {16#501, router_resize_memory, <<"router: memory could not be resized">>},
     {16#502, router_mailbox_full, <<"router: mailbox full">>},
     {16#503, router_debug_mailbox_full, <<"router: debug mailbox full">>},
     {16#504, router_unknown_port_type, <<"router: unknown port type">>},
     {16#505, router_not_initialized, <<"router: not initialised">>},
     {16#506, router_port_in_use, <<"router: port already in use">>},
     {16#507, router_not_registered, <<"router: port not registered">>},
     {16#508, router_no_more_queues, <<"router: no more queues">>},
     {16#509, router_invalid_port, <<"router: invalid port">>},
     {16#50A, router_not_activated, <<"router: not activated">>},
     {16#50B, router_fragment_box_full, <<"router: fragment mailbox full">>},
     {16#50C, router_fragment_timeout, <<"router: fragment timeout">>},
     {16#50D, router_to_be_removed, <<"router: port is being removed">>},
     {16#700, device_error, <<"general device error">>},
     {16#701, service_not_supported, <<"service not supported by the ADS server">>},
     {16#702, invalid_index_group, <<"invalid index group">>},
     {16#703, invalid_index_offset, <<"invalid index offset">>},
     {16#704, invalid_access, <<"reading or writing not permitted">>},
     {16#705, invalid_size, <<"parameter size not correct">>},
     {16#706, invalid_data, <<"invalid data values">>},
     {16#707, not_ready, <<"device not ready">>},
     {16#708, busy, <<"device busy">>},
     {16#709, invalid_context, <<"invalid operating system context">>},
     {16#70A, out_of_memory, <<"device out of memory">>},
     {16#70B, invalid_parameter, <<"invalid parameter values">>},
     {16#70C, not_found, <<"not found">>},
     {16#70D, syntax_error, <<"syntax error in command or file">>},
     {16#70E, incompatible, <<"objects do not match">>},
     {16#70F, already_exists, <<"object already exists">>},
     {16#710, symbol_not_found, <<"symbol not found">>},
     {16#711, symbol_version_invalid,
      <<"symbol version invalid: the PLC program changed; handles must be renewed">>},
     {16#712, invalid_state, <<"ADS server in an invalid state">>},
     {16#713, trans_mode_not_supported, <<"notification transmission mode not supported">>},
     {16#714, notification_handle_invalid, <<"notification handle invalid">>},
     {16#715, notification_client_unknown, <<"notification client not registered">>},
     {16#716, no_more_notification_handles, <<"no more notification handles">>},
     {16#717, invalid_watch_size, <<"notification size too large">>},
     {16#718, not_initialized, <<"device not initialised">>},
     {16#719, device_timeout, <<"device timeout">>},
     {16#71A, no_interface, <<"interface query failed">>},
     {16#71B, invalid_interface, <<"wrong interface requested">>},
     {16#71C, invalid_class_id, <<"invalid class id">>},
     {16#71D, invalid_object_id, <<"invalid object id">>},
     {16#71E, request_pending, <<"request pending">>},
     {16#71F, request_aborted, <<"request aborted">>},
     {16#720, signal_warning, <<"signal warning">>},
     {16#721, invalid_array_index, <<"invalid array index">>},
     {16#722, symbol_not_active,
      <<"symbol not active: the PLC program changed; handles must be renewed">>},
     {16#723, access_denied, <<"access denied">>},
     {16#724, license_not_found, <<"missing license">>},
     {16#725, license_expired, <<"license expired">>},
     {16#726, license_exceeded, <<"license exceeded">>},
     {16#727, license_invalid, <<"invalid license">>},
     {16#728, license_system_id, <<"license for another system">>},
     {16#729, license_no_time_limit, <<"license without time limit not allowed">>},
     {16#72A, license_future_issue, <<"license issued in the future">>},
     {16#72B, license_time_too_long, <<"license period too long">>},
     {16#72C, exception_at_startup, <<"exception during system start">>},
     {16#72D, license_duplicated, <<"license file read twice">>},
     {16#72E, signature_invalid, <<"invalid signature">>},
     {16#72F, certificate_invalid, <<"invalid certificate">>},
     {16#740, client_error, <<"client error">>},
     {16#741, client_invalid_parameter, <<"invalid parameter at the client">>},
     {16#742, client_polling_list_empty, <<"polling list empty">>},
     {16#743, client_var_connection_in_use, <<"variable connection already in use">>},
     {16#744, client_invoke_id_in_use, <<"invoke id in use">>},
     {16#745, client_timeout, <<"timeout: the target did not answer in time">>},
     {16#746, client_win32_error, <<"Win32 error at the client">>},
     {16#747, client_invalid_timeout, <<"invalid client timeout value">>},
     {16#748, client_port_not_open, <<"ADS port not opened">>},
     {16#749, client_no_ams_address, <<"no AMS address">>},
     {16#750, client_sync_internal, <<"internal error in ADS sync">>},
     {16#751, client_hash_overflow, <<"hash table overflow">>},
     {16#752, client_hash_key_not_found, <<"key not found in hash table">>},
     {16#753, client_no_more_symbols, <<"no more symbols in cache">>},
     {16#754, client_invalid_response, <<"invalid response received">>},
     {16#755, client_sync_port_locked, <<"sync port locked">>}].

%% @doc The name of an ADS state number (the number itself when unknown).
-spec ads_state_name(0..65535) -> ads_state().
ads_state_name(N) ->
    case lists:keyfind(N, 1, states()) of
        {_, Name} -> Name;
        false -> N
    end.

%% @doc The number of an ADS state.
-spec ads_state_code(ads_state()) -> 0..65535.
ads_state_code(N) when is_integer(N) ->
    N;
ads_state_code(Name) ->
    {N, _} = lists:keyfind(Name, 2, states()),
    N.

%% @doc Whether a term names an ADS state (or is a state number).
-spec is_ads_state(term()) -> boolean().
is_ads_state(N) when is_integer(N) -> N >= 0 andalso N =< 16#FFFF;
is_ads_state(Name) -> lists:keymember(Name, 2, states()).

states() ->
    [{0, invalid}, {1, idle}, {2, reset}, {3, init}, {4, start}, {5, run}, {6, stop},
     {7, save_config}, {8, load_config}, {9, power_failure}, {10, power_good},
     {11, error}, {12, shutdown}, {13, suspend}, {14, resume}, {15, config},
     {16, reconfig}, {17, stopping}, {18, incompatible}, {19, exception}].
