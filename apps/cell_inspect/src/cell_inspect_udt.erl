%% @doc The block as a Siemens S7 UDT (seed 004), byte for byte. Pure.
%%
%% The UDT lays out the tags of {@link cell_inspect_tags} in the seed's order, with the
%% placement rules of a standard (not optimised) S7 data block:
%% <ul>
%% <li>BOOLs are packed eight to a byte, `.0' the least significant bit; a BOOL after
%%   another element starts a new byte;</li>
%% <li>an INT (16 bits, signed, big-endian) and a STRING start at an even byte;</li>
%% <li>a STRING[N] takes N + 2 bytes: its maximum length, its actual length, then N
%%   characters (one byte each; what follows the actual length is not part of it);</li>
%% <li>the whole UDT ends at an even byte.</li>
%% </ul>
%% With the seed's lengths (InspectionPointID 16, every other string 48) this gives the
%% seed's offsets exactly: Heartbeat 0.0 ... SendMessage_ECHO 0.7, InspectionStatus 2,
%% ErrorCode 4, InspectionPointID_ECHO 6, PartSerial_ECHO 24, EmployeeOverride_ECHO 74,
%% Inspection_STRING 124, TriggerInspection 174.0 ... SendMessage 174.4,
%% InspectionPointID 176, PartSerial 194, OverrideEmployeeID 244, MessageId 294,
%% MessageId_ECHO 296, MessageStatus 298, MessageResult 300. MessageResult as a
%% STRING[48] ends at byte 349, so the UDT is 350 bytes; the seed's "348 bytes
%% (depending on string length)" is MessageResult as a STRING[46]. Other custom
%% lengths move the later members as TIA Portal moves them.
%%
%% Over Modbus the UDT lies in holding registers from a base register: byte B is in
%% register `base + B div 2', the even byte in the register's high half (S7 and Modbus
%% are both big-endian), so bit B.b is register bit `8 + b' for an even B and `b' for
%% an odd one.
-module(cell_inspect_udt).

-compile({no_auto_import, [size/1]}).

-export([default_lengths/0, check_lengths/1, layout/1, size/1, offset/2, encode/2,
         decode/2, string_bytes/2, string_value/2, header/2, register/1, register_bit/2,
         address/1]).

-export_type([lengths/0, element/0, kind/0]).

-type lengths() :: #{cell_inspect_tags:length_class() => 1..254}.
-type kind() :: bool | int | {string, 1..254}.
-type element() :: #{tag := cell_inspect_tags:tag(), kind := kind(),
                     byte := non_neg_integer(), bit := 0..7 | none}.

%% @doc The lengths of the seed's table: InspectionPointID 16, the others 48.
-spec default_lengths() -> lengths().
default_lengths() ->
    #{point_id => 16, serial => 48, employee => 48, string => 48, result => 48}.

%% @doc Checks string lengths given as options (an S7 STRING holds 1 to 254
%% characters); missing ones take the seed's.
-spec check_lengths(term()) -> {ok, lengths()} | {error, {bad_option, atom()}}.
check_lengths(L) when is_map(L) ->
    Merged = maps:merge(default_lengths(), L),
    case [K || {K, V} <- maps:to_list(Merged),
               not (maps:is_key(K, default_lengths()) andalso is_integer(V)
                    andalso V >= 1 andalso V =< 254)] of
        [] -> {ok, Merged};
        [K | _] when is_atom(K) -> {error, {bad_option, K}};
        [_ | _] -> {error, {bad_option, lengths}}
    end;
check_lengths(_) ->
    {error, {bad_option, lengths}}.

%% @doc Every tag at its offset, in the order of the UDT.
-spec layout(lengths()) -> [element()].
layout(Lengths) ->
    place(cell_inspect_tags:all(), Lengths, 0, none, []).

%% Next: the first free byte; Bits: `none', or `{Byte, Bit}' the next bit of a BOOL run.
place([], _, _, _, Acc) ->
    lists:reverse(Acc);
place([Tag | Rest], Lengths, Next, Bits, Acc) ->
    case kind_of(Tag, Lengths) of
        bool ->
            {Byte, Bit} = case Bits of
                              {B, N} when N < 8 -> {B, N};
                              {B, 8} -> {B + 1, 0};
                              none -> {Next, 0}
                          end,
            E = #{tag => Tag, kind => bool, byte => Byte, bit => Bit},
            place(Rest, Lengths, Byte + 1, {Byte, Bit + 1}, [E | Acc]);
        Kind ->
            Byte = even(Next),
            E = #{tag => Tag, kind => Kind, byte => Byte, bit => none},
            place(Rest, Lengths, Byte + bytes(Kind), none, [E | Acc])
    end.

kind_of(Tag, Lengths) ->
    case cell_inspect_tags:kind(Tag) of
        {string, Class} -> {string, maps:get(Class, Lengths)};
        K -> K
    end.

even(N) -> N + N rem 2.

bytes(int) -> 2;
bytes({string, N}) -> N + 2.

%% @doc The size of the UDT in bytes.
-spec size([element()]) -> pos_integer().
size(Layout) ->
    even(lists:max([B + case K of bool -> 1; _ -> bytes(K) end
                    || #{byte := B, kind := K} <- Layout])).

%% @doc Where a tag lies: `{Byte, Bit}' for a BOOL, `{Byte, none}' otherwise.
-spec offset(cell_inspect_tags:tag(), [element()]) -> {non_neg_integer(), 0..7 | none}.
offset(Tag, Layout) ->
    [{B, Bit}] = [{B, Bit} || #{tag := T, byte := B, bit := Bit} <- Layout, T =:= Tag],
    {B, Bit}.

%% @doc The bytes of the whole UDT. Strings are the PLC's bytes (one a character);
%% a tag without a value is 0, false or empty.
-spec encode([element()], #{cell_inspect_tags:tag() => boolean() | integer() | binary()}) ->
          binary().
encode(Layout, Values) ->
    Size = size(Layout),
    lists:foldl(fun(#{tag := T} = E, Bin) -> put(E, maps:get(T, Values, zero(E)), Bin) end,
                <<0:Size/unit:8>>, Layout).

zero(#{kind := bool}) -> false;
zero(#{kind := int}) -> 0;
zero(#{kind := {string, _}}) -> <<>>.

put(#{kind := bool, byte := B, bit := Bit}, V, Bin) ->
    <<Pre:B/binary, Byte, Post/binary>> = Bin,
    Mask = 1 bsl Bit,
    New = case V of
              true -> Byte bor Mask;
              false -> Byte band (bnot Mask)
          end,
    <<Pre/binary, New, Post/binary>>;
put(#{kind := int, byte := B}, V, Bin) ->
    splice(Bin, B, <<V:16/signed>>);
put(#{kind := {string, N}, byte := B}, V, Bin) ->
    splice(Bin, B, string_bytes(N, V)).

splice(Bin, At, Part) ->
    <<Pre:At/binary, _:(byte_size(Part))/binary, Post/binary>> = Bin,
    <<Pre/binary, Part/binary, Post/binary>>.

%% @doc The values of every tag in the bytes of a UDT.
-spec decode([element()], binary()) -> #{cell_inspect_tags:tag() => boolean() | integer() | binary()}.
decode(Layout, Bin) ->
    maps:from_list([{T, get(E, Bin)} || #{tag := T} = E <- Layout]).

get(#{kind := bool, byte := B, bit := Bit}, Bin) ->
    <<_:B/binary, Byte, _/binary>> = Bin,
    (Byte bsr Bit) band 1 =:= 1;
get(#{kind := int, byte := B}, Bin) ->
    <<_:B/binary, V:16/signed, _/binary>> = Bin,
    V;
get(#{kind := {string, N}, byte := B}, Bin) ->
    <<_:B/binary, S:(N + 2)/binary, _/binary>> = Bin,
    string_value(N, S).

%% @doc An S7 STRING[Max]: maximum length, actual length, the characters, then zeros.
%% Longer values are cut to `Max'.
-spec string_bytes(1..254, binary()) -> binary().
string_bytes(Max, V) ->
    Chars = binary:part(V, 0, min(Max, byte_size(V))),
    Len = byte_size(Chars),
    <<Max, Len, Chars/binary, 0:((Max - Len) * 8)>>.

%% @doc The value of an S7 STRING declared as STRING[Max]: the actual length says how
%% many characters count. A PLC's own maximum (the first byte) may differ from the
%% declared one; the value never reaches past either, nor past the bytes given.
-spec string_value(1..254, binary()) -> binary().
string_value(Max, <<PlcMax, Len, Chars/binary>>) ->
    binary:part(Chars, 0, lists:min([Len, PlcMax, Max, byte_size(Chars)]));
string_value(_, _) ->
    <<>>.

%% @doc The first register of an S7 STRING over Modbus: maximum length in the high
%% byte, actual length in the low byte.
-spec header(1..254, non_neg_integer()) -> 0..65535.
header(Max, Len) -> Max bsl 8 bor min(Len, Max).

%% @doc The register (from the UDT's base) of a byte.
-spec register(non_neg_integer()) -> non_neg_integer().
register(Byte) -> Byte div 2.

%% @doc The bit inside its register (0 = least significant) of bit `Bit' of a byte.
-spec register_bit(non_neg_integer(), 0..7) -> 0..15.
register_bit(Byte, Bit) when Byte rem 2 =:= 0 -> 8 + Bit;
register_bit(_Byte, Bit) -> Bit.

%% @doc An element's S7 address inside its data block, as TIA Portal writes it:
%% `DBX174.0', `DBW2', `DBB6' (a STRING's first byte).
-spec address(element()) -> binary().
address(#{kind := bool, byte := B, bit := Bit}) ->
    iolist_to_binary(["DBX", integer_to_list(B), $., integer_to_list(Bit)]);
address(#{kind := int, byte := B}) ->
    iolist_to_binary(["DBW", integer_to_list(B)]);
address(#{kind := {string, _}, byte := B}) ->
    iolist_to_binary(["DBB", integer_to_list(B)]).
