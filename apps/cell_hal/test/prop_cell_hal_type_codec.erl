%% PropEr properties of the point types and their encodings: every value a type accepts
%% survives Modbus registers (both word orders) and ADS bytes, and any bytes of the
%% right size decode to a value the type accepts.
-module(prop_cell_hal_type_codec).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(T, cell_hal_type).
-define(TC, cell_hal_type_codec).

properties_test_() ->
    [{timeout, 120, ?_assert(proper:quickcheck(P, [{to_file, user}, {numtests, N}]))}
     || {P, N} <- [{prop_registers_roundtrip(), 3000},
                   {prop_ads_roundtrip(), 3000},
                   {prop_any_registers_decode(), 3000},
                   {prop_any_ads_bytes_decode(), 3000},
                   {prop_word_orders_mirror(), 1000},
                   {prop_check_idempotent(), 2000},
                   {prop_conditions_total(), 2000}]].

type() ->
    oneof([bool, byte, sbyte, char, int16, uint16, int32, uint32, int64, uint64, real,
           lreal, date, time, decimal, {string, integer(1, 300)}]).

order() -> oneof([big, little]).

value(bool) -> boolean();
value(real) -> oneof([?LET(F, float(), element(2, ?T:check(real, clamp(F)))),
                      nan, infinity, neg_infinity]);
value(lreal) -> oneof([float(), nan, infinity, neg_infinity]);
value({string, N}) ->
    ?LET(Bytes, list(integer(1, 255)), list_to_binary(lists:sublist(Bytes, N)));
value(date) ->
    ?LET(Days, integer(0, 49710), calendar:gregorian_days_to_date(719528 + Days));
value(decimal) -> binary(16);
value(T) ->
    {Lo, Hi} = range(T),
    frequency([{1, Lo}, {1, Hi}, {6, integer(Lo, Hi)}]).

clamp(F) -> max(-3.4e38, min(3.4e38, F)).

range(byte) -> {0, 255};
range(sbyte) -> {-128, 127};
range(char) -> {0, 255};
range(int16) -> {-32768, 32767};
range(uint16) -> {0, 65535};
range(int32) -> {-(1 bsl 31), (1 bsl 31) - 1};
range(uint32) -> {0, (1 bsl 32) - 1};
range(int64) -> {-(1 bsl 63), (1 bsl 63) - 1};
range(uint64) -> {0, (1 bsl 64) - 1};
range(time) -> {0, (1 bsl 32) - 1}.

typed_value() -> ?LET(T, type(), {T, value(T)}).

prop_registers_roundtrip() ->
    ?FORALL({{T, V}, O}, {typed_value(), order()},
            begin
                {ok, V} = ?T:check(T, V),
                Bin = ?TC:encode_registers(T, V, O),
                byte_size(Bin) =:= 2 * ?TC:registers(T) andalso
                    ?TC:decode_registers(T, Bin, O) =:= V
            end).

prop_ads_roundtrip() ->
    ?FORALL({T, V}, typed_value(),
            begin
                Bin = ?TC:encode_ads(T, V),
                byte_size(Bin) =:= ?TC:ads_size(T) andalso ?TC:decode_ads(T, Bin) =:= V
            end).

%% Whatever a device holds, it reads as a value the type accepts (a wrong value can be
%% a misconfiguration, never a crash of the worker).
prop_any_registers_decode() ->
    ?FORALL({T, O}, {type(), order()},
            ?FORALL(Bin, binary(2 * ?TC:registers(T)),
                    begin
                        V = ?TC:decode_registers(T, Bin, O),
                        {ok, V} =:= ?T:check(T, V)
                    end)).

prop_any_ads_bytes_decode() ->
    ?FORALL(T, type(),
            ?FORALL(Bin, binary(?TC:ads_size(T)),
                    begin
                        V = ?TC:decode_ads(T, Bin),
                        {ok, V} =:= ?T:check(T, V)
                    end)).

%% The `little' word order is the `big' one with the 16-bit words reversed.
prop_word_orders_mirror() ->
    ?FORALL({T, V}, ?SUCHTHAT({T, _}, typed_value(),
                              lists:member(T, [int32, uint32, int64, uint64, real, lreal,
                                               date, time])),
            begin
                Big = ?TC:encode_registers(T, V, big),
                Little = ?TC:encode_registers(T, V, little),
                Little =:= list_to_binary(lists:reverse([<<W:16>> || <<W:16>> <= Big]))
            end).

prop_check_idempotent() ->
    ?FORALL({T, X}, {type(), oneof([int(), real(), boolean(), binary(), atom(),
                                    {int(), int(), int()}])},
            case ?T:check(T, X) of
                {ok, V} -> ?T:check(T, V) =:= {ok, V};
                error -> true
            end).

%% A condition is accepted or refused, and an accepted one can be evaluated on every
%% value of its type.
prop_conditions_total() ->
    ?FORALL({{T, V}, Op, {_, R}}, {typed_value(), oneof([eq, ne, gt, ge, lt, le]),
                                   typed_value()},
            case ?T:check_cond(T, {Op, R}) of
                {ok, C} -> is_boolean(?T:holds(C, V));
                error -> true
            end).
