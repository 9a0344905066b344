%% PropEr generators for settings objects: valid values of a schema's types, and
%% values that break them, each labelled with the reason it must be refused.
-module(cell_settings_gen).

-include_lib("proper/include/proper.hrl").

-export([object/1, valid/1, invalid/1, value_case/1]).


object(Mod) ->
    ?LET(Pairs, [{N, valid(T)} || #{name := N, type := T} <- Mod:fields()],
         maps:from_list(Pairs)).

valid(boolean) -> boolean();
valid(integer) -> integer();
valid({integer, Min, Max}) -> integer(bound(Min), bound(Max));
valid(float) -> float();
valid({float, Min, Max}) -> float(float(Min), float(Max));
valid(string) -> text(1024);
valid({string, Max}) -> text(Max);
valid({enum, L}) -> oneof([elements(L), ?LET(A, elements(L), atom_to_binary(A, utf8))]);
valid({list, T}) -> ?LET(N, range(0, 4), vector(N, valid(T)));
valid({list, T, Max}) -> ?LET(N, range(0, Max), vector(N, valid(T)));
valid({object, cell_test_axis_settings = Mod}) ->
    ?SUCHTHAT(O, object(Mod), maps:get(low, O) =< maps:get(high, O));
valid({object, Mod}) -> object(Mod);
valid({optional, T}) -> oneof([undefined, null, valid(T)]).

bound(unbounded) -> inf;
bound(B) -> B.

text(Max) ->
    ?LET(Chars, ?SIZED(S, resize(min(S, Max), list(oneof([range($a, $z), range(16#a0, 16#17f),
                                                           range(16#4e00, 16#4e20)])))),
         unicode:characters_to_binary(lists:sublist(Chars, Max))).

%% {ok, Value} for a value the type accepts, {Why, Value} for one it refuses.
value_case(T) ->
    frequency([{3, ?LET(V, valid(T), {ok, V})}, {5, invalid(T)}]).

invalid(boolean) ->
    {wrong_type, oneof([integer(), <<"true">>, null, 1.0])};
invalid({integer, Min, Max}) ->
    oneof([{wrong_type, oneof([float(), <<"1">>, true, null])}]
          ++ [{out_of_range, integer(inf, Min - 1)} || Min =/= unbounded]
          ++ [{out_of_range, integer(Max + 1, inf)} || Max =/= unbounded]);
invalid(integer) -> invalid({integer, unbounded, unbounded});
invalid({float, Min, Max}) ->
    oneof([{wrong_type, oneof([<<"1.5">>, false, [1.0]])}]
          ++ [{out_of_range, oneof([float(inf, Min - 1.0e-9), integer(inf, ceil(Min) - 1)])}
              || Min =/= unbounded]
          ++ [{out_of_range, oneof([float(Max + 1.0e-9, inf), integer(floor(Max) + 1, inf)])}
              || Max =/= unbounded]);
invalid(float) -> invalid({float, unbounded, unbounded});
invalid({string, Max}) ->
    oneof([{too_long, ?LET({S, Extra}, {text(Max), text(3)},
                           unicode:characters_to_binary(
                             [lists:duplicate(Max - string:length(S), $x), S, $y, Extra]))},
           {not_utf8, ?LET(B, binary(), <<B/binary, 255>>)},
           {wrong_type, oneof([integer(), true, [$a]])}]);
invalid(string) -> invalid({string, 1024});
invalid({enum, L}) ->
    Names = [atom_to_binary(A, utf8) || A <- L],
    oneof([{not_one_of, ?SUCHTHAT(B, proper_unicode:utf8(10), not lists:member(B, Names))},
           {not_one_of, elements([perhaps, undefined, nothing])},
           {wrong_type, oneof([integer(), 1.5, [<<"none">>]])}]);
invalid({optional, T}) -> invalid(T).
