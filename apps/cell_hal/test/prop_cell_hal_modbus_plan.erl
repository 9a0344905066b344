%% PropEr properties of the Modbus poll planner: for any set of points, the planned
%% requests are within the protocol's limits, read every point back exactly as it was
%% written into a device image, and are as few as an exhaustive search finds.
-module(prop_cell_hal_modbus_plan).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(P, cell_hal_modbus_plan).

properties_test_() ->
    [{timeout, 120, ?_assert(proper:quickcheck(P, [{to_file, user}, {numtests, N}]))}
     || {P, N} <- [{prop_reads_back_what_the_device_holds(), 500},
                   {prop_fewest_requests(), 500}]].

%%--------------------------------------------------------------------
%% Generators: points that do not overlap, each with a value, packed near each other
%%--------------------------------------------------------------------

type() ->
    oneof([bool, byte, sbyte, char, int16, uint16, int32, uint32, int64, uint64, real,
           lreal, date, time, decimal, {string, integer(1, 40)}]).

value(bool) -> boolean();
value(real) -> oneof([-1.5, 0.0, 3.25, 1.0e10]);
value(lreal) -> float();
value({string, N}) -> ?LET(B, list(integer($A, $Z)), list_to_binary(lists:sublist(B, N)));
value(date) -> ?LET(D, integer(0, 49710), calendar:gregorian_days_to_date(719528 + D));
value(decimal) -> binary(16);
value(sbyte) -> integer(-128, 127);
value(int16) -> integer(-32768, 32767);
value(int32) -> integer(-(1 bsl 31), (1 bsl 31) - 1);
value(int64) -> integer(-(1 bsl 63), (1 bsl 63) - 1);
value(uint64) -> integer(0, (1 bsl 64) - 1);
value(uint32) -> integer(0, (1 bsl 32) - 1);
value(time) -> integer(0, (1 bsl 32) - 1);
value(uint16) -> integer(0, 65535);
value(_) -> integer(0, 255).

%% A layout: per table, points placed one after another with small random gaps.
layout() ->
    ?LET({Regs, Coils, Gap, Order},
         {list({type(), integer(0, 3), boolean()}), list({integer(0, 3), boolean()}),
          integer(0, 4), oneof([big, little])},
         {place_registers(Regs, 0, 0, Order), place_bits(Coils, 0, 0), Gap}).

place_registers([], _, _, _) -> [];
place_registers([{Type, Skip, Bits} | Rest], A, I, Order) ->
    Start = A + Skip,
    case Bits andalso Start < 65000 of
        true ->
            %% Two bits in one holding register.
            [{{r, I}, bool, {holding_register, Start, 3}, Order},
             {{r, I + 1}, bool, {holding_register, Start, 12}, Order}
             | place_registers(Rest, Start + 1, I + 2, Order)];
        false ->
            N = cell_hal_type_codec:registers(Type),
            [{{r, I}, Type, {holding_register, Start}, Order}
             | place_registers(Rest, Start + N, I + 1, Order)]
    end.

place_bits([], _, _) -> [];
place_bits([{Skip, Discrete} | Rest], A, I) ->
    Table = case Discrete of true -> discrete_input; false -> coil end,
    [{{c, I}, bool, {Table, A + Skip}, big} | place_bits(Rest, A + Skip + 1, I + 1)].

with_values(Points) ->
    [{K, Type, Field, Order, value(Type)} || {K, Type, Field, Order} <- Points].

%%--------------------------------------------------------------------
%% Properties
%%--------------------------------------------------------------------

prop_reads_back_what_the_device_holds() ->
    ?FORALL({Regs, Bits, Gap}, layout(),
            ?FORALL(Points, with_values(Regs ++ Bits),
                    begin
                        Resolved = [{K, Type, resolve(Type, Field, Order), V}
                                    || {K, Type, Field, Order, V} <- Points],
                        Image = image(Resolved),
                        Plan = ?P:plan([{K, T, F} || {K, T, F, _} <- Resolved], Gap),
                        Requests = ?P:requests(Plan),
                        Read = lists:append([?P:decode(B, reply(R, Image))
                                             || {B, {_, R}} <- lists:zip(Plan, Requests)]),
                        Expected = lists:sort([{K, V} || {K, _, _, V} <- Resolved]),
                        ?WHENFAIL(io:format("plan ~p~nread ~p~n", [Requests, Read]),
                                  lists:all(fun({_, R}) ->
                                                    ok =:= cell_hal_modbus_codec:check_request(R)
                                            end, Requests)
                                  andalso lists:sort(Read) =:= Expected)
                    end)).

%% The greedy cut reads the points with as few requests as any cut of the sorted spans.
prop_fewest_requests() ->
    ?FORALL({Regs, Bits, Gap}, layout(),
            begin
                Points = [{K, T, resolve(T, F, O)} || {K, T, F, O} <- Regs ++ Bits],
                Planned = length(?P:plan(Points, Gap)),
                Planned =:= fewest(Points, Gap)
            end).

resolve(Type, Field, Order) ->
    {ok, F} = ?P:field(in, Type, Field, #{unit => 1, word_order => Order}),
    F.

%% The device image: register or bit address per table to its content.
image(Points) ->
    lists:foldl(fun put_point/2, #{}, Points).

put_point({_, bool, #{table := T, address := A, bit := none}, V}, Img)
  when T =:= coil; T =:= discrete_input ->
    Img#{{T, A} => V};
put_point({_, bool, #{table := T, address := A, bit := Bit}, V}, Img) when Bit =/= none ->
    W = maps:get({T, A}, Img, 0),
    Img#{{T, A} => case V of true -> W bor (1 bsl Bit); false -> W end};
put_point({_, Type, #{table := T, address := A, word_order := O}, V}, Img) ->
    Words = [W || <<W:16>> <= cell_hal_type_codec:encode_registers(Type, V, O)],
    lists:foldl(fun({I, W}, M) -> M#{{T, A + I} => W} end, Img,
                lists:zip(lists:seq(0, length(Words) - 1), Words)).

reply({read_coils, S, N}, Img) -> [maps:get({coil, A}, Img, false) || A <- seq(S, N)];
reply({read_discrete_inputs, S, N}, Img) ->
    [maps:get({discrete_input, A}, Img, false) || A <- seq(S, N)];
reply({read_holding_registers, S, N}, Img) ->
    << <<(maps:get({holding_register, A}, Img, 0)):16>> || A <- seq(S, N) >>.

seq(S, N) -> lists:seq(S, S + N - 1).

%% Exhaustive minimum: per unit and table, cut the spans sorted by start into runs;
%% a run is readable by one request when each next span starts within the gap of the
%% run so far and the run fits the limit. Dynamic programming over the cut points.
fewest(Points, Gap) ->
    Groups = lists:foldl(fun({_, Type, #{table := T, address := A} = F}, M) ->
                                 End = A + span(Type, F) - 1,
                                 maps:update_with(T, fun(L) -> [{A, End} | L] end,
                                                  [{A, End}], M)
                         end, #{}, Points),
    lists:sum([min_runs(lists:sort(Spans), Gap, limit(T)) || {T, Spans} <- maps:to_list(Groups)]).

span(_, #{table := T}) when T =:= coil; T =:= discrete_input -> 1;
span(_, #{bit := B}) when B =/= none -> 1;
span(Type, _) -> cell_hal_type_codec:registers(Type).

limit(T) when T =:= coil; T =:= discrete_input -> 2000;
limit(_) -> 125.

min_runs(Spans, Gap, Limit) ->
    Arr = list_to_tuple(Spans),
    N = tuple_size(Arr),
    %% Best(i): fewest runs for spans i..N.
    Best = lists:foldl(
             fun(I, Memo) ->
                     Memo#{I => lists:min([1 + maps:get(J + 1, Memo)
                                           || J <- lists:seq(I, N), one_run(Arr, I, J, Gap, Limit)])}
             end, #{N + 1 => 0}, lists:seq(N, 1, -1)),
    maps:get(1, Best).

one_run(Arr, I, J, Gap, Limit) ->
    {Start, _} = element(I, Arr),
    one_run(Arr, I + 1, J, Gap, Limit, Start, element(2, element(I, Arr))).

one_run(_, K, J, _, _, _, _) when K > J -> true;
one_run(Arr, K, J, Gap, Limit, Start, End) ->
    {A, E} = element(K, Arr),
    NewEnd = max(End, E),
    A =< End + 1 + Gap andalso NewEnd - Start + 1 =< Limit andalso
        one_run(Arr, K + 1, J, Gap, Limit, Start, NewEnd).
