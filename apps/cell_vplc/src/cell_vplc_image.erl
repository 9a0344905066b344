%% @doc The register map of a virtual PLC, and what it answers: pure, no sockets, no
%% processes.
%%
%% The map is the one the cell's real-mode HAL uses: each point of the served Modbus
%% connection at the unit, table and address its group declares (the same fields the
%% Modbus driver resolves, {@link cell_hal_modbus_plan:field/4}), a value of several
%% registers over consecutive addresses in the connection's word order. A request is
%% answered from the point values the simulation holds, read through a function the
%% caller gives; a write returns the point values it sets, each checked against its
%% point's type, for the caller to hand to the simulation.
%%
%% Refusals, as a PLC gives them: a function other than 1..6, 15, 16, 22, 23 is
%% exception 1; an address no point holds (in the table asked, within the span asked)
%% exception 2; a quantity outside Modbus limits, a malformed request or a value a
%% point's type cannot hold exception 3; a unit id the map does not serve exception 11
%% (no answer from the device behind the address). A frame that is not Modbus TCP at
%% all is {@link answer/3}'s `close': nothing after it in the stream can be trusted.
-module(cell_vplc_image).

-export([new/1, units/1, size/1, answer/3]).

-export_type([image/0, point/0, read_fun/0]).

-type key() :: {atom(), atom()}.
-type table() :: coil | discrete_input | holding_register | input_register.
%% A point of the served connection: its HAL key, type and resolved Modbus field.
-type point() :: {key(), cell_hal_type:type(),
                  #{unit := 0..255, table := table(), address := 0..65535,
                    bit := none | 0..15, word_order := big | little, atom() => term()}}.
%% A register holds one word of a value, or booleans packed into its bits.
-type slot() :: {key(), cell_hal_type:type(), Word :: non_neg_integer(), big | little}
              | {bits, #{0..15 => key()}}.
-opaque image() :: #{{0..255, table(), 0..65535} => slot()}.
%% The value a point holds in the simulation; `undefined' before anything set it (it
%% reads as zero, as a PLC's fresh memory does).
-type read_fun() :: fun((key()) -> cell_hal_type:value() | undefined).

%% @doc The map of these points; two points on one address are refused, except
%% booleans on distinct bits of one holding register (an S7 UDT's BOOLs).
-spec new([point()]) -> {ok, image()} | {error, {overlap, key(), key()}}.
new(Points) ->
    try
        {ok, lists:foldl(fun add/2, #{}, Points)}
    catch
        throw:{overlap, _, _} = Overlap -> {error, Overlap}
    end.

add({Key, bool, #{unit := U, table := holding_register, address := A, bit := B}}, Map)
  when is_integer(B) ->
    case Map of
        #{{U, holding_register, A} := {bits, #{B := Other}}} -> throw({overlap, Other, Key});
        #{{U, holding_register, A} := {bits, Bits}} ->
            Map#{{U, holding_register, A} := {bits, Bits#{B => Key}}};
        #{{U, holding_register, A} := {Other, _, _, _}} -> throw({overlap, Other, Key});
        _ -> Map#{{U, holding_register, A} => {bits, #{B => Key}}}
    end;
add({Key, Type, #{unit := U, table := T, address := A, word_order := O}}, Map) ->
    N = case T of
            coil -> 1;
            discrete_input -> 1;
            _ -> cell_hal_type_codec:registers(Type)
        end,
    lists:foldl(fun(W, M) ->
                        case M of
                            #{{U, T, A + W} := {Other, _, _, _}} -> throw({overlap, Other, Key});
                            #{{U, T, A + W} := {bits, Bits}} ->
                                throw({overlap, hd(lists:sort(maps:values(Bits))), Key});
                            _ -> M#{{U, T, A + W} => {Key, Type, W, O}}
                        end
                end, Map, lists:seq(0, N - 1)).

%% @doc The unit ids the map serves.
-spec units(image()) -> [0..255].
units(Map) ->
    lists:usort([U || {U, _, _} <- maps:keys(Map)]).

%% @doc How many bits and registers the map holds.
-spec size(image()) -> non_neg_integer().
size(Map) ->
    maps:size(Map).

%% @doc The answer to one request PDU for a unit: the reply PDU and the point values
%% the request writes, in order; or `close' for a PDU that cannot be answered at all.
-spec answer(0..255, binary(), {image(), read_fun()}) ->
          {reply, binary(), [{key(), cell_hal_type:value()}]} | close.
answer(_Unit, <<>>, _) ->
    close;
answer(Unit, <<Fc, _/binary>> = Pdu, {Map, Read}) ->
    case {cell_hal_modbus_codec:decode_request(Pdu), lists:member(Unit, units(Map))} of
        {_, false} ->
            {reply, exception(Fc, 11), []};
        {{error, Why}, true} ->
            {reply, exception(Fc, refusal(Why)), []};
        {{ok, {user_function, _, _}}, true} ->
            {reply, exception(Fc, 1), []};
        {{ok, Req}, true} ->
            try do(Unit, Req, Map, Read) of
                {Reply, Writes} ->
                    {reply, cell_hal_modbus_codec:response_pdu(Req, Reply), Writes}
            catch
                throw:{refuse, Code} -> {reply, exception(Fc, Code), []}
            end
    end.

exception(Fc, Code) ->
    <<(16#80 bor (Fc band 16#7F)), Code>>.

refusal({bad_request, function}) -> 1;
refusal({bad_request, address}) -> 2;
refusal(_) -> 3.

%% What a request reads and writes.
do(U, {read_coils, A, N}, Map, Read) -> {bits(U, coil, A, N, Map, Read), []};
do(U, {read_discrete_inputs, A, N}, Map, Read) ->
    {bits(U, discrete_input, A, N, Map, Read), []};
do(U, {read_holding_registers, A, N}, Map, Read) ->
    {registers(U, holding_register, A, N, Map, Read), []};
do(U, {read_input_registers, A, N}, Map, Read) ->
    {registers(U, input_register, A, N, Map, Read), []};
do(U, {write_single_coil, A, V}, Map, _) ->
    {ok, set_bits(U, A, [V], Map)};
do(U, {write_multiple_coils, A, Bits}, Map, _) ->
    {ok, set_bits(U, A, Bits, Map)};
do(U, {write_single_register, A, V}, Map, Read) ->
    {ok, set_registers(U, A, <<V:16>>, Map, Read)};
do(U, {write_multiple_registers, A, Regs}, Map, Read) ->
    {ok, set_registers(U, A, Regs, Map, Read)};
do(U, {mask_write_register, A, And, Or}, Map, Read) ->
    <<Old:16>> = registers(U, holding_register, A, 1, Map, Read),
    New = (Old band And) bor (Or band (bnot And) band 16#FFFF),
    {ok, set_registers(U, A, <<New:16>>, Map, Read)};
do(U, {read_write_registers, RA, RN, WA, Regs}, Map, Read) ->
    %% The write first, as the specification orders it: the read sees what it wrote.
    Writes = set_registers(U, WA, Regs, Map, Read),
    Written = maps:from_list(Writes),
    Read1 = fun(K) -> maps:get(K, Written, Read(K)) end,
    {registers(U, holding_register, RA, RN, Map, Read1), Writes}.

slot(U, T, A, Map) ->
    case Map of
        #{{U, T, A} := Slot} -> Slot;
        _ -> throw({refuse, 2})
    end.

bits(U, T, A, N, Map, Read) ->
    [case slot(U, T, I, Map) of
         {Key, bool, 0, _} -> Read(Key) =:= true
     end || I <- lists:seq(A, A + N - 1)].

registers(U, T, A, N, Map, Read) ->
    Slots = [slot(U, T, I, Map) || I <- lists:seq(A, A + N - 1)],
    {Words, _} = lists:mapfoldl(
                   fun({bits, Bits}, Cache) ->
                           Word = lists:sum([1 bsl B || {B, Key} <- maps:to_list(Bits),
                                                        Read(Key) =:= true]),
                           {<<Word:16>>, Cache};
                      ({Key, Type, W, O}, Cache) ->
                           Regs = maps:get(Key, Cache, encode(Type, Read(Key), O)),
                           {binary:part(Regs, 2 * W, 2), Cache#{Key => Regs}}
                   end, #{}, Slots),
    iolist_to_binary(Words).

set_bits(U, A, Bits, Map) ->
    [case slot(U, coil, A + I, Map) of
         {Key, bool, 0, _} -> {Key, V}
     end || {I, V} <- lists:enumerate(0, Bits)].

%% Each point the written registers touch gets its registers as they were with the
%% written words put in: a value of several registers written in part keeps the rest.
set_registers(U, A, Regs, Map, Read) ->
    All = [{slot(U, holding_register, A + I, Map), <<W:16>>}
           || {I, W} <- lists:enumerate(0, [W || <<W:16>> <= Regs])],
    %% A register of packed booleans sets each of them from its bit.
    BitWrites = [{Key, (W bsr B) band 1 =:= 1}
                 || {{bits, Bits}, <<W:16>>} <- All, {B, Key} <- lists:sort(maps:to_list(Bits))],
    Words = [Wd || {{_, _, _, _}, _} = Wd <- All],
    BitWrites ++ set_words(Words, Read).

set_words(Words, Read) ->
    Keys = lists:foldl(fun({{K, T, _, O}, _}, Acc) ->
                               case lists:keymember(K, 1, Acc) of
                                   true -> Acc;
                                   false -> Acc ++ [{K, T, O}]
                               end
                       end, [], Words),
    [begin
         Old = encode(T, Read(K), O),
         New = lists:foldl(fun({{K1, _, W, _}, Word}, Bin) when K1 =:= K ->
                                   <<Pre:(2 * W)/binary, _:2/binary, Post/binary>> = Bin,
                                   <<Pre/binary, Word/binary, Post/binary>>;
                              (_, Bin) ->
                                   Bin
                           end, Old, Words),
         {K, checked(T, cell_hal_type_codec:decode_registers(T, New, O))}
     end || {K, T, O} <- Keys].

encode(Type, undefined, _) ->
    <<0:(16 * cell_hal_type_codec:registers(Type))>>;
encode(Type, V, Order) ->
    cell_hal_type_codec:encode_registers(Type, V, Order).

checked(Type, V) ->
    case cell_hal_type:check(Type, V) of
        {ok, V1} -> V1;
        error -> throw({refuse, 3})
    end.
