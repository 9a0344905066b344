%% Properties of the beacon's pure logic ({@link cell_beacon}). The model says, from the
%% table in the module's documentation and nothing else, when each condition holds and
%% what a lamp shows: the strongest mode of the rules that hold for it, off when none
%% does.
-module(prop_cell_beacon).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(STATES, [off, down, setup, {ready, idle, blocked}, {ready, idle, starved},
                 {ready, processing, active}, {ready, processing, executing}]).
-define(LAMPS, [red, yellow, green, blue]).
-define(CONDITIONS, [alarm, error, warning, estop, service_mode, off, down, setup, idle,
                     starved, blocked, processing, active, executing]).

%% -------------------------------------------------------------------------------------
%% Properties, run inside eunit
%% -------------------------------------------------------------------------------------

model_test_() -> prop(prop_lamps_follow_the_model()).
order_test_() -> prop(prop_order_does_not_matter()).
monotonic_test_() -> prop(prop_a_rule_only_adds_light()).
outputs_test_() -> prop(prop_outputs_in_both_phases()).
defaults_test_() -> prop(prop_default_rules()).

prop(P) ->
    {timeout, 120, ?_assert(proper:quickcheck(P, [{to_file, user}, {numtests, 500}]))}.

prop_lamps_follow_the_model() ->
    ?FORALL({Cell, Rules}, {cell(), rules()},
            cell_beacon:lamps(Cell, Rules) =:= model_lamps(Cell, Rules)).

prop_order_does_not_matter() ->
    ?FORALL({Cell, Rules, Seed}, {cell(), rules(), integer()},
            begin
                Shuffled = [R || {_, R} <- lists:sort([{erlang:phash2({Seed, I}), R}
                                                        || {I, R} <- enumerate(Rules)])],
                cell_beacon:lamps(Cell, Shuffled) =:= cell_beacon:lamps(Cell, Rules)
            end).

prop_a_rule_only_adds_light() ->
    ?FORALL({Cell, Rules, Rule}, {cell(), rules(), rule()},
            begin
                Before = cell_beacon:lamps(Cell, Rules),
                After = cell_beacon:lamps(Cell, [Rule | Rules]),
                lists:all(fun(L) -> rank(maps:get(L, After)) >= rank(maps:get(L, Before)) end,
                          ?LAMPS)
            end).

prop_outputs_in_both_phases() ->
    ?FORALL(Lamps, lamps(),
            begin
                On = cell_beacon:outputs(Lamps, on),
                Off = cell_beacon:outputs(Lamps, off),
                Blinks = lists:member(blinking, maps:values(Lamps)),
                lists:all(fun(L) ->
                                  case maps:get(L, Lamps) of
                                      off -> not maps:get(L, On) andalso not maps:get(L, Off);
                                      steady -> maps:get(L, On) andalso maps:get(L, Off);
                                      blinking -> maps:get(L, On) andalso not maps:get(L, Off)
                                  end
                          end, ?LAMPS)
                    andalso cell_beacon:blinking(Lamps) =:= Blinks
            end).

%% The defaults as the module's documentation states them.
prop_default_rules() ->
    ?FORALL(Cell, cell(),
            begin
                #{red := Red, yellow := Yellow, green := Green, blue := Blue} =
                    cell_beacon:lamps(Cell, cell_beacon:default_rules()),
                #{state := S, has_alarm := A, has_error := E, has_warning := W} = Cell,
                Red =:= on_off(A, blinking)
                    andalso Blue =:= on_off(E, steady)
                    andalso Yellow =:= on_off(W, steady)
                    andalso Green =:= case S of
                                          {ready, processing, _} -> steady;
                                          {ready, idle, _} -> blinking;
                                          _ -> off
                                      end
            end).

%% -------------------------------------------------------------------------------------
%% The model
%% -------------------------------------------------------------------------------------

model_lamps(Cell, Rules) ->
    maps:from_list(
      [{L, case [M || #{lamp := L1, condition := C, mode := M} <- Rules, L1 =:= L,
                      model_holds(C, Cell)] of
               [] -> off;
               Modes -> case lists:member(blinking, Modes) of
                            true -> blinking;
                            false -> steady
                        end
           end} || L <- ?LAMPS]).

model_holds(alarm, #{has_alarm := A}) -> A;
model_holds(error, #{has_error := E}) -> E;
model_holds(warning, #{has_warning := W}) -> W;
model_holds(estop, #{estop := E}) -> E;
model_holds(service_mode, #{service_mode := S}) -> S;
model_holds(idle, #{state := S}) ->
    lists:member(S, [{ready, idle, starved}, {ready, idle, blocked}]);
model_holds(processing, #{state := S}) ->
    lists:member(S, [{ready, processing, active}, {ready, processing, executing}]);
model_holds(starved, #{state := S}) -> S =:= {ready, idle, starved};
model_holds(blocked, #{state := S}) -> S =:= {ready, idle, blocked};
model_holds(active, #{state := S}) -> S =:= {ready, processing, active};
model_holds(executing, #{state := S}) -> S =:= {ready, processing, executing};
model_holds(State, #{state := S}) -> State =:= S.

rank(off) -> 0;
rank(steady) -> 1;
rank(blinking) -> 2.

on_off(true, Mode) -> Mode;
on_off(false, _) -> off.

enumerate(L) -> lists:zip(lists:seq(1, length(L)), L).

%% -------------------------------------------------------------------------------------
%% Generators
%% -------------------------------------------------------------------------------------

cell() ->
    ?LET({S, Es, Sm, A, E, W}, {oneof(?STATES), boolean(), boolean(), boolean(), boolean(),
                                boolean()},
         #{state => S, estop => Es, service_mode => Sm, has_alarm => A, has_error => E,
           has_warning => W, request => stop}).

rule() ->
    ?LET({L, C, M}, {oneof(?LAMPS), oneof(?CONDITIONS), oneof([steady, blinking])},
         #{lamp => L, condition => C, mode => M}).

rules() -> list(rule()).

lamps() ->
    ?LET(Modes, vector(4, oneof([off, steady, blinking])),
         maps:from_list(lists:zip(?LAMPS, Modes))).
