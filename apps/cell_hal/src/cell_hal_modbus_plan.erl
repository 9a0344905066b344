%% @doc Which Modbus requests read an IO image, and what their replies mean. Pure.
%%
%% A point's field, as a group module declares it:
%% <table>
%% <tr><th>field</th><th>table, function codes</th><th>types</th><th>directions</th></tr>
%% <tr><td>`{coil, Address}'</td><td>coils: read 1, write 5</td><td>bool</td>
%%   <td>in, out</td></tr>
%% <tr><td>`{discrete_input, Address}'</td><td>discrete inputs: read 2</td><td>bool</td>
%%   <td>in</td></tr>
%% <tr><td>`{holding_register, Address}'</td><td>holding registers: read 3, write 6
%%   (one register) or 16</td><td>all</td><td>in, out</td></tr>
%% <tr><td>`{input_register, Address}'</td><td>input registers: read 4</td><td>all</td>
%%   <td>in</td></tr>
%% <tr><td>`{holding_register, Address, Bit}'</td><td>one bit (0 = least significant)
%%   of a holding register: read 3, write 22 (mask write: the other bits stay as the
%%   device has them)</td><td>bool</td><td>in, out</td></tr>
%% <tr><td>`{input_register, Address, Bit}'</td><td>one bit of an input register: read 4
%%   </td><td>bool</td><td>in</td></tr>
%% </table>
%% Addresses are the protocol's, from 0 (register "40001" is holding register 0). A value
%% of several registers starts at its address (see {@link cell_hal_type_codec} for the
%% layouts). The group instance's options may set `unit' (a device behind a gateway)
%% and `word_order' (`big' or `little') for its points; the connection gives the
%% defaults.
%%
%% Reads are planned per unit and table: points sorted by address, and adjacent ones
%% (or ones at most `max_gap' registers or bits apart) read by one request up to the
%% protocol's limit (125 registers, 2000 bits). The greedy left-to-right cut gives the
%% fewest requests for sorted spans; a value is never split across two requests.
-module(cell_hal_modbus_plan).

-export([field/4, plan/2, requests/1, decode/2, keys/1, refused_groups/3, write_request/3,
         describe/1]).

-export_type([field/0, table/0, block/0, plan/0]).

-type table() :: coil | discrete_input | holding_register | input_register.
-type field() :: #{unit := cell_hal_modbus_codec:unit_id(),
                   table := table(),
                   address := cell_hal_modbus_codec:address(),
                   bit := none | 0..15,
                   word_order := cell_hal_type_codec:word_order()}.
-type key() :: term().
-type block() :: #{unit := cell_hal_modbus_codec:unit_id(),
                   table := table(),
                   start := cell_hal_modbus_codec:address(),
                   count := pos_integer(),
                   points := [{key(), Offset :: non_neg_integer(), cell_hal_type:type(),
                               field()}]}.
-type plan() :: [block()].

%% The longest STRING(N) one read request can carry: 125 registers of 2 bytes.
-define(MAX_STRING, 250).
-define(IS_TABLE(T), (T =:= coil orelse T =:= discrete_input orelse T =:= holding_register
                      orelse T =:= input_register)).

%% @doc Checks a declared field against a point's direction and type and resolves it
%% with the unit and word order in force (`Defaults' holds the connection's `unit' and
%% `word_order', `GroupOpts' may override them).
-spec field(in | out, cell_hal_type:type(), term(), #{unit := cell_hal_modbus_codec:unit_id(),
                                                      word_order := cell_hal_type_codec:word_order(),
                                                      atom() => term()}) ->
          {ok, field()} | {error, atom()}.
field(Dir, Type, Field, Opts) ->
    case parse(Field) of
        {ok, Table, Address, Bit} ->
            Resolved = #{unit => maps:get(unit, Opts), table => Table, address => Address,
                         bit => Bit, word_order => maps:get(word_order, Opts)},
            check_field(Dir, Type, Resolved);
        error ->
            {error, bad_field}
    end.

parse({Table, A}) when ?IS_TABLE(Table), is_integer(A) -> {ok, Table, A, none};
parse({Table, A, Bit}) when (Table =:= holding_register orelse Table =:= input_register),
                            is_integer(A), is_integer(Bit) ->
    {ok, Table, A, Bit};
parse(_) -> error.

check_field(_, _, #{address := A}) when A < 0; A > 65535 ->
    {error, address_out_of_range};
check_field(out, _, #{table := T}) when T =:= discrete_input; T =:= input_register ->
    {error, read_only_table};
check_field(_, Type, #{table := T}) when Type =/= bool, (T =:= coil orelse
                                                        T =:= discrete_input) ->
    {error, bits_hold_bool_only};
check_field(_, _, #{bit := Bit}) when Bit =/= none, (Bit < 0 orelse Bit > 15) ->
    {error, bit_out_of_range};
check_field(_, Type, #{bit := Bit}) when Bit =/= none, Type =/= bool ->
    {error, bits_hold_bool_only};
check_field(_, {string, N}, _) when N > ?MAX_STRING ->
    {error, string_too_long};
check_field(_, Type, #{address := A} = F) ->
    case A + size(Type, F) - 1 =< 65535 of
        true -> {ok, F};
        false -> {error, address_out_of_range}
    end.

%% Registers or bits a point takes in its table.
size(_, #{table := T}) when T =:= coil; T =:= discrete_input -> 1;
size(_, #{bit := Bit}) when Bit =/= none -> 1;
size(Type, _) -> cell_hal_type_codec:registers(Type).

%% @doc The blocks that read the given points with the fewest requests. Points are
%% `{Key, Type, Field}' with fields from {@link field/4}.
-spec plan([{key(), cell_hal_type:type(), field()}], non_neg_integer()) -> plan().
plan(Points, MaxGap) ->
    Spans = lists:sort([{{U, T, A}, A + size(Type, F) - 1, {K, Type, F}}
                        || {K, Type, #{unit := U, table := T, address := A} = F} <- Points]),
    coalesce(Spans, MaxGap, []).

coalesce([], _, Acc) ->
    lists:reverse(Acc);
coalesce([{{U, T, A}, End, P} | Rest], Gap, Acc) ->
    extend(Rest, Gap, block(U, T, A, End, [P]), Acc).

extend([{{U, T, A}, End, P} | Rest], Gap,
       #{unit := U, table := T, start := S, count := C, points := Ps} = B, Acc)
  when A =< S + C + Gap ->
    NewEnd = max(S + C - 1, End),
    case NewEnd - S + 1 =< max_count(T) of
        true -> extend(Rest, Gap, B#{count := NewEnd - S + 1, points := [P | Ps]}, Acc);
        false -> coalesce([{{U, T, A}, End, P} | Rest], Gap, [finish(B) | Acc])
    end;
extend(Rest, Gap, B, Acc) ->
    coalesce(Rest, Gap, [finish(B) | Acc]).

block(U, T, A, End, Ps) ->
    #{unit => U, table => T, start => A, count => End - A + 1, points => Ps}.

finish(#{start := S, points := Ps} = B) ->
    B#{points := [{K, A - S, Type, F} || {K, Type, #{address := A} = F} <- lists:reverse(Ps)]}.

max_count(T) when T =:= coil; T =:= discrete_input ->
    cell_hal_modbus_codec:limit(read_bits);
max_count(_) ->
    cell_hal_modbus_codec:limit(read_registers).

%% @doc The requests of a plan, one a block, with the unit each goes to.
-spec requests(plan()) -> [{cell_hal_modbus_codec:unit_id(), cell_hal_modbus_codec:request()}].
requests(Plan) ->
    [{U, request(B)} || #{unit := U} = B <- Plan].

request(#{table := coil, start := S, count := C}) -> {read_coils, S, C};
request(#{table := discrete_input, start := S, count := C}) -> {read_discrete_inputs, S, C};
request(#{table := holding_register, start := S, count := C}) -> {read_holding_registers, S, C};
request(#{table := input_register, start := S, count := C}) -> {read_input_registers, S, C}.

%% @doc The values of a block's points from the reply to its request.
-spec decode(block(), cell_hal_modbus_codec:reply()) -> [{key(), cell_hal_type:value()}].
decode(#{table := T, points := Ps}, Bits) when T =:= coil; T =:= discrete_input ->
    Tuple = list_to_tuple(Bits),
    [{K, element(Off + 1, Tuple)} || {K, Off, _, _} <- Ps];
decode(#{points := Ps}, Regs) ->
    [{K, value(Type, F, Off, Regs)} || {K, Off, Type, F} <- Ps].

value(_, #{bit := Bit}, Off, Regs) when Bit =/= none ->
    <<_:Off/binary-unit:16, W:16, _/binary>> = Regs,
    (W bsr Bit) band 1 =:= 1;
value(Type, #{word_order := O}, Off, Regs) ->
    N = cell_hal_type_codec:registers(Type),
    <<_:Off/binary-unit:16, Bytes:N/binary-unit:16, _/binary>> = Regs,
    cell_hal_type_codec:decode_registers(Type, Bytes, O).

%% @doc The points a block's request reads: those a refusal of that request leaves
%% without a value.
-spec keys(block()) -> [key()].
keys(#{points := Ps}) ->
    [K || {K, _, _, _} <- Ps].

%% @doc The IO groups a PLC refuses whole: those of which every input in the plan is
%% among the refused keys. Keys are the HAL's `{Group, Point}'; `Outputs' are not
%% counted (a read-back the PLC refuses says nothing of a group's inputs), so a group
%% of outputs only is never refused whole. A group is refused whole however its
%% inputs are spread over requests (and whatever other groups' points share those
%% requests); one of its inputs read is enough to keep it.
-spec refused_groups(plan(), [{atom(), atom()}], #{{atom(), atom()} => true}) -> [atom()].
refused_groups(Plan, Refused, Outputs) ->
    Out = maps:from_list([{K, true} || K <- Refused]),
    Groups = lists:foldl(fun({G, _} = K, Acc) ->
                                 Acc#{G => maps:get(G, Acc, true) andalso is_map_key(K, Out)}
                         end, #{}, [K || B <- Plan, K <- keys(B), not is_map_key(K, Outputs)]),
    lists:sort([G || {G, true} <- maps:to_list(Groups)]).

%% @doc The request that writes a value to an output's field.
-spec write_request(cell_hal_type:type(), field(), cell_hal_type:value()) ->
          {cell_hal_modbus_codec:unit_id(), cell_hal_modbus_codec:request()}.
write_request(bool, #{unit := U, table := coil, address := A}, V) ->
    {U, {write_single_coil, A, V}};
write_request(bool, #{unit := U, address := A, bit := Bit}, V) when Bit =/= none ->
    Mask = 1 bsl Bit,
    {U, {mask_write_register, A, 16#FFFF bxor Mask, case V of true -> Mask; false -> 0 end}};
write_request(Type, #{unit := U, address := A, word_order := O}, V) ->
    case cell_hal_type_codec:encode_registers(Type, V, O) of
        <<W:16>> -> {U, {write_single_register, A, W}};
        Regs -> {U, {write_multiple_registers, A, Regs}}
    end.

%% @doc A field in words for logs and the IO page: "holding register 100 bit 3 (unit 1)".
-spec describe(field()) -> iolist().
describe(#{unit := U, table := T, address := A, bit := Bit}) ->
    [string:replace(atom_to_list(T), "_", " "), $\s, integer_to_list(A),
     case Bit of none -> []; _ -> [" bit ", integer_to_list(Bit)] end,
     " (unit ", integer_to_list(U), ")"].

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

opts() -> #{unit => 1, word_order => big}.

f(Dir, Type, Field) -> field(Dir, Type, Field, opts()).

field_test_() ->
    [?_assertMatch({ok, #{table := coil, address := 0, bit := none, unit := 1}},
                   f(out, bool, {coil, 0})),
     ?_assertMatch({ok, #{table := discrete_input}}, f(in, bool, {discrete_input, 65535})),
     ?_assertEqual({error, read_only_table}, f(out, bool, {discrete_input, 1})),
     ?_assertEqual({error, read_only_table}, f(out, int16, {input_register, 1})),
     ?_assertEqual({error, read_only_table}, f(out, bool, {input_register, 1, 3})),
     ?_assertEqual({error, bits_hold_bool_only}, f(in, int16, {coil, 1})),
     ?_assertEqual({error, bits_hold_bool_only}, f(in, byte, {holding_register, 1, 2})),
     ?_assertMatch({ok, #{bit := 15}}, f(out, bool, {holding_register, 1, 15})),
     ?_assertEqual({error, bit_out_of_range}, f(out, bool, {holding_register, 1, 16})),
     ?_assertEqual({error, bit_out_of_range}, f(in, bool, {input_register, 1, -1})),
     ?_assertEqual({error, address_out_of_range}, f(in, bool, {coil, 65536})),
     ?_assertEqual({error, address_out_of_range}, f(in, bool, {coil, -1})),
     ?_assertMatch({ok, _}, f(in, int32, {holding_register, 65534})),
     ?_assertEqual({error, address_out_of_range}, f(in, int32, {holding_register, 65535})),
     ?_assertMatch({ok, _}, f(in, {string, 250}, {input_register, 0})),
     ?_assertEqual({error, string_too_long}, f(in, {string, 251}, {input_register, 0})),
     ?_assertEqual({error, bad_field}, f(in, bool, {register, 1})),
     ?_assertEqual({error, bad_field}, f(in, bool, {coil, 1, 2})),
     ?_assertEqual({error, bad_field}, f(in, bool, <<".StartButton">>)),
     ?_assertMatch({ok, #{unit := 7, word_order := little}},
                   field(in, int32, {holding_register, 0}, #{unit => 7, word_order => little}))].

pt(K, Type, Field) ->
    {ok, F} = f(in, Type, Field),
    {K, Type, F}.

adjacent_points_share_a_request_test() ->
    Plan = plan([pt(a, int16, {holding_register, 10}), pt(b, int32, {holding_register, 11}),
                 pt(c, real, {holding_register, 13}), pt(d, bool, {holding_register, 15, 0}),
                 pt(e, bool, {holding_register, 15, 1})], 0),
    ?assertEqual([{1, {read_holding_registers, 10, 6}}], requests(Plan)),
    Regs = <<(-2):16, 16#12345678:32, 1.5:32/float, 2#10:16>>,
    ?assertEqual([{a, -2}, {b, 16#12345678}, {c, 1.5}, {d, false}, {e, true}],
                 decode(hd(Plan), Regs)).

gaps_split_unless_allowed_test() ->
    Points = [pt(a, int16, {holding_register, 10}), pt(b, int16, {holding_register, 13})],
    ?assertEqual([{1, {read_holding_registers, 10, 1}}, {1, {read_holding_registers, 13, 1}}],
                 requests(plan(Points, 0))),
    ?assertEqual([{1, {read_holding_registers, 10, 1}}, {1, {read_holding_registers, 13, 1}}],
                 requests(plan(Points, 1))),
    ?assertEqual([{1, {read_holding_registers, 10, 4}}], requests(plan(Points, 2))).

tables_and_units_apart_test() ->
    {ok, F7} = field(in, int16, {holding_register, 1}, #{unit => 7, word_order => big}),
    Plan = plan([pt(a, int16, {holding_register, 0}), {b, int16, F7},
                 pt(c, int16, {input_register, 1}), pt(d, bool, {coil, 2}),
                 pt(e, bool, {discrete_input, 3})], 5),
    ?assertEqual(lists:sort([{1, {read_holding_registers, 0, 1}},
                             {7, {read_holding_registers, 1, 1}},
                             {1, {read_input_registers, 1, 1}}, {1, {read_coils, 2, 1}},
                             {1, {read_discrete_inputs, 3, 1}}]),
                 lists:sort(requests(Plan))).

limits_test_() ->
    Regs = fun(N) -> [pt(I, int16, {holding_register, I}) || I <- lists:seq(0, N - 1)] end,
    Coils = fun(N) -> [pt(I, bool, {coil, I}) || I <- lists:seq(0, N - 1)] end,
    [?_assertEqual([{1, {read_holding_registers, 0, 125}}], requests(plan(Regs(125), 0))),
     ?_assertEqual([{1, {read_holding_registers, 0, 125}}, {1, {read_holding_registers, 125, 1}}],
                   requests(plan(Regs(126), 0))),
     ?_assertEqual([{1, {read_coils, 0, 2000}}], requests(plan(Coils(2000), 0))),
     ?_assertEqual([{1, {read_coils, 0, 2000}}, {1, {read_coils, 2000, 1}}],
                   requests(plan(Coils(2001), 0)))].

values_never_split_test() ->
    Points = [pt(a, {string, 20}, {holding_register, 0}), pt(b, {string, 240}, {holding_register, 10})],
    ?assertEqual([{1, {read_holding_registers, 0, 10}}, {1, {read_holding_registers, 10, 120}}],
                 requests(plan(Points, 0))).

overlapping_points_test() ->
    Plan = plan([pt(a, int32, {holding_register, 0}), pt(b, uint16, {holding_register, 1}),
                 pt(c, int16, {holding_register, 0})], 0),
    ?assertEqual([{1, {read_holding_registers, 0, 2}}], requests(Plan)),
    ?assertEqual([{c, 1}, {a, 16#10002}, {b, 2}],
                 decode(hd(Plan), <<1:16, 2:16>>)).

coil_decode_test() ->
    Plan = plan([pt(a, bool, {coil, 5}), pt(b, bool, {coil, 7})], 2),
    ?assertEqual([{1, {read_coils, 5, 3}}], requests(Plan)),
    ?assertEqual([{a, true}, {b, false}], decode(hd(Plan), [true, true, false])).

%% A refused request leaves exactly the points of its block without a value; the
%% other blocks' points are not touched.
keys_of_a_request_test() ->
    Plan = plan([pt({g, a}, int16, {holding_register, 10}), pt({g, b}, int32, {holding_register, 11}),
                 pt({g, c}, int16, {holding_register, 20}), pt({h, d}, bool, {coil, 3}),
                 pt({h, e}, bool, {coil, 4})], 0),
    ?assertEqual([{1, {read_coils, 3, 2}}, {1, {read_holding_registers, 10, 3}},
                  {1, {read_holding_registers, 20, 1}}],
                 lists:sort(requests(Plan))),
    ByRequest = maps:from_list(lists:zip(requests(Plan), [keys(B) || B <- Plan])),
    ?assertEqual([{g, a}, {g, b}], maps:get({1, {read_holding_registers, 10, 3}}, ByRequest)),
    ?assertEqual([{g, c}], maps:get({1, {read_holding_registers, 20, 1}}, ByRequest)),
    ?assertEqual([{h, d}, {h, e}], maps:get({1, {read_coils, 3, 2}}, ByRequest)),
    %% every point is in exactly one request
    ?assertEqual(5, length(lists:usort(lists:append(maps:values(ByRequest))))).

refused_groups_test_() ->
    %% g spans two requests, one shared with h; k is alone in its own.
    Plan = plan([pt({g, a}, int16, {holding_register, 0}), pt({h, b}, int16, {holding_register, 1}),
                 pt({g, c}, int16, {holding_register, 10}), pt({k, d}, int16, {input_register, 0})],
                0),
    [R0, R10, I0] = [keys(B) || B <- Plan],
    F = fun(Refused) -> refused_groups(Plan, Refused, #{}) end,
    [?_assertEqual([], F([])),
     %% one request of g refused: g still has a point read
     ?_assertEqual([], F(R10)),
     ?_assertEqual([h], F(R0)),
     %% every request of g refused: g, and h whose only point shares one of them
     ?_assertEqual([g, h], F(R0 ++ R10)),
     ?_assertEqual([k], F(I0)),
     ?_assertEqual([g, h, k], F(R0 ++ R10 ++ I0)),
     %% keys of no point of the plan change nothing
     ?_assertEqual([], F([{x, y}])),
     ?_assertEqual([], refused_groups([], [{g, a}], #{})),
     %% outputs are not counted: h is all outputs, never refused whole; g's inputs
     %% alone decide for g
     ?_assertEqual([g], refused_groups(Plan, R0 ++ R10, #{{h, b} => true})),
     ?_assertEqual([g], refused_groups(Plan, [{g, a}], #{{g, c} => true, {h, b} => true})),
     ?_assertEqual([], refused_groups(Plan, [{g, c}], #{{g, c} => true}))].

write_request_test_() ->
    F = fun(Type, Field) -> {ok, R} = f(out, Type, Field), R end,
    [?_assertEqual({1, {write_single_coil, 3, true}}, write_request(bool, F(bool, {coil, 3}), true)),
     ?_assertEqual({1, {mask_write_register, 4, 16#FFF7, 16#0008}},
                   write_request(bool, F(bool, {holding_register, 4, 3}), true)),
     ?_assertEqual({1, {mask_write_register, 4, 16#7FFF, 0}},
                   write_request(bool, F(bool, {holding_register, 4, 15}), false)),
     ?_assertEqual({1, {write_single_register, 9, 16#FFFE}},
                   write_request(int16, F(int16, {holding_register, 9}), -2)),
     ?_assertEqual({1, {write_single_register, 9, 1}},
                   write_request(bool, F(bool, {holding_register, 9}), true)),
     ?_assertEqual({1, {write_multiple_registers, 9, <<16#3F80:16, 0:16>>}},
                   write_request(real, F(real, {holding_register, 9}), 1.0))].

describe_test() ->
    {ok, F} = f(in, bool, {holding_register, 100, 3}),
    ?assertEqual("holding register 100 bit 3 (unit 1)", lists:flatten(describe(F))).
-endif.
