%% @doc The beacon (seed 000 §2.4.2: "update and blink beacon lights (red, blue, yellow,
%% green) according to machine current status"), as pure functions: from what the cell
%% is doing and a set of rules to what each of the four lamps shows, and from that and
%% the blink phase to the four outputs. {@link cell_monitor} runs it with one blink
%% timer.
%%
%% A rule lights one lamp, steady or blinking, while one condition holds:
%% `#{lamp => red, condition => alarm, mode => blinking}'. The conditions are the
%% cell's flags and states:
%%
%% <table>
%% <tr><th>condition</th><th>holds while</th></tr>
%% <tr><td>`alarm'</td><td>an alarm is active: a dangerous condition (the emergency
%%   stop is one)</td></tr>
%% <tr><td>`error'</td><td>an error waits for an operator's answer: the operator is
%%   needed</td></tr>
%% <tr><td>`warning'</td><td>a warning is active</td></tr>
%% <tr><td>`estop'</td><td>the emergency stop is active</td></tr>
%% <tr><td>`service_mode'</td><td>the cell is in service mode</td></tr>
%% <tr><td>`off', `down', `setup'</td><td>the cell state is OFF, DOWN, SETUP</td></tr>
%% <tr><td>`idle'</td><td>READY-IDLE (STARVED or BLOCKED): running, waiting for
%%   work</td></tr>
%% <tr><td>`starved', `blocked'</td><td>READY-IDLE-STARVED, READY-IDLE-BLOCKED</td></tr>
%% <tr><td>`processing'</td><td>READY-PROCESSING (ACTIVE or EXECUTING): working on a
%%   product</td></tr>
%% <tr><td>`active', `executing'</td><td>READY-PROCESSING-ACTIVE,
%%   READY-PROCESSING-EXECUTING</td></tr>
%% </table>
%%
%% Every rule whose condition holds counts; a lamp several rules light shows the
%% strongest of their modes (blinking over steady), so the order of the rules does not
%% matter and a rule can only ever add light. A lamp no rule lights is off.
%%
%% The default rules: red blinking on an alarm, blue when an error waits for the
%% operator, yellow on a warning, green steady while processing and blinking while
%% idle.
-module(cell_beacon).

-export([lamps/0, conditions/0, default_rules/0, holds/2, lamps/2, outputs/2,
         blinking/1, check_rule/1]).

-export_type([lamp/0, mode/0, condition/0, rule/0, cell/0, phase/0]).

-type lamp() :: red | yellow | green | blue.
-type mode() :: off | steady | blinking.
-type phase() :: on | off.
-type condition() :: alarm | error | warning | estop | service_mode | off | down | setup
                   | idle | starved | blocked | processing | active | executing.
-type rule() :: #{lamp := lamp(), condition := condition(), mode := steady | blinking}.
%% What the beacon reads of the cell: the controller's flags ({@link
%% cell_controller:flags/0}) will do.
-type cell() :: #{state := cell_ipc:state(), estop := boolean(),
                  service_mode := boolean(), has_alarm := boolean(),
                  has_error := boolean(), has_warning := boolean(), atom() => term()}.

%% @doc The lamps, top to bottom of a usual beacon.
-spec lamps() -> [lamp()].
lamps() -> [red, yellow, green, blue].

%% @doc Every condition a rule may name.
-spec conditions() -> [condition()].
conditions() ->
    [alarm, error, warning, estop, service_mode, off, down, setup, idle, starved,
     blocked, processing, active, executing].

%% @doc The rules a new cell starts with.
-spec default_rules() -> [rule()].
default_rules() ->
    [#{lamp => red, condition => alarm, mode => blinking},
     #{lamp => blue, condition => error, mode => steady},
     #{lamp => yellow, condition => warning, mode => steady},
     #{lamp => green, condition => processing, mode => steady},
     #{lamp => green, condition => idle, mode => blinking}].

%% @doc Whether a condition holds for the cell.
-spec holds(condition(), cell()) -> boolean().
holds(alarm, #{has_alarm := A}) -> A;
holds(error, #{has_error := E}) -> E;
holds(warning, #{has_warning := W}) -> W;
holds(estop, #{estop := E}) -> E;
holds(service_mode, #{service_mode := S}) -> S;
holds(off, #{state := S}) -> S =:= off;
holds(down, #{state := S}) -> S =:= down;
holds(setup, #{state := S}) -> S =:= setup;
holds(idle, #{state := S}) -> element_of(S, 2) =:= idle;
holds(processing, #{state := S}) -> element_of(S, 2) =:= processing;
holds(starved, #{state := S}) -> element_of(S, 3) =:= starved;
holds(blocked, #{state := S}) -> element_of(S, 3) =:= blocked;
holds(active, #{state := S}) -> element_of(S, 3) =:= active;
holds(executing, #{state := S}) -> element_of(S, 3) =:= executing.

element_of({ready, _, _} = S, N) -> element(N, S);
element_of(_, _) -> none.

%% @doc What each lamp shows for the cell under the rules.
-spec lamps(cell(), [rule()]) -> #{lamp() => mode()}.
lamps(Cell, Rules) ->
    Dark = maps:from_list([{L, off} || L <- lamps()]),
    lists:foldl(fun(#{lamp := L, condition := C, mode := M}, Acc) ->
                        case holds(C, Cell) of
                            true -> Acc#{L := strongest(M, maps:get(L, Acc))};
                            false -> Acc
                        end
                end, Dark, Rules).

strongest(blinking, _) -> blinking;
strongest(_, blinking) -> blinking;
strongest(steady, _) -> steady;
strongest(_, steady) -> steady;
strongest(off, off) -> off.

%% @doc The lamps' outputs in a blink phase: a steady lamp is lit in both, a blinking
%% one only in `on'.
-spec outputs(#{lamp() => mode()}, phase()) -> #{lamp() => boolean()}.
outputs(Lamps, Phase) ->
    maps:map(fun(_, off) -> false;
                (_, steady) -> true;
                (_, blinking) -> Phase =:= on
             end, Lamps).

%% @doc Whether any lamp blinks (the blink timer is needed).
-spec blinking(#{lamp() => mode()}) -> boolean().
blinking(Lamps) ->
    lists:member(blinking, maps:values(Lamps)).

%% @doc Checks a rule given by code or configuration.
-spec check_rule(term()) -> ok | {error, {bad_rule, term()}}.
check_rule(#{lamp := L, condition := C, mode := M} = R) when map_size(R) =:= 3 ->
    case lists:member(L, lamps()) andalso lists:member(C, conditions())
        andalso (M =:= steady orelse M =:= blinking) of
        true -> ok;
        false -> {error, {bad_rule, R}}
    end;
check_rule(R) ->
    {error, {bad_rule, R}}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

cell(State, Flags) ->
    maps:merge(#{state => State, estop => false, service_mode => false, has_alarm => false,
                 has_error => false, has_warning => false}, Flags).

default_rules_test_() ->
    L = fun(State, Flags) -> lamps(cell(State, Flags), default_rules()) end,
    [?_assertEqual(#{red => off, yellow => off, green => off, blue => off}, L(off, #{})),
     ?_assertEqual(#{red => off, yellow => off, green => blinking, blue => off},
                   L({ready, idle, starved}, #{})),
     ?_assertEqual(#{red => off, yellow => off, green => blinking, blue => off},
                   L({ready, idle, blocked}, #{})),
     ?_assertEqual(#{red => off, yellow => off, green => steady, blue => off},
                   L({ready, processing, executing}, #{})),
     ?_assertEqual(#{red => off, yellow => off, green => steady, blue => off},
                   L({ready, processing, active}, #{})),
     ?_assertEqual(#{red => off, yellow => steady, green => steady, blue => off},
                   L({ready, processing, executing}, #{has_warning => true})),
     ?_assertEqual(#{red => off, yellow => off, green => off, blue => steady},
                   L(down, #{has_error => true})),
     ?_assertEqual(#{red => blinking, yellow => off, green => off, blue => off},
                   L(off, #{estop => true, has_alarm => true})),
     ?_assertEqual(#{red => off, yellow => off, green => off, blue => off}, L(setup, #{})),
     ?_assertEqual(#{red => off, yellow => off, green => off, blue => off}, L(down, #{}))].

strongest_mode_wins_test_() ->
    Rules = [#{lamp => red, condition => error, mode => steady},
             #{lamp => red, condition => alarm, mode => blinking}],
    Both = cell(down, #{has_error => true, has_alarm => true}),
    [?_assertEqual(blinking, maps:get(red, lamps(Both, Rules))),
     ?_assertEqual(blinking, maps:get(red, lamps(Both, lists:reverse(Rules)))),
     ?_assertEqual(steady, maps:get(red, lamps(cell(down, #{has_error => true}), Rules)))].

every_condition_test_() ->
    Cases = [{alarm, cell(off, #{has_alarm => true}), cell(off, #{})},
             {error, cell(off, #{has_error => true}), cell(off, #{})},
             {warning, cell(off, #{has_warning => true}), cell(off, #{})},
             {estop, cell(off, #{estop => true}), cell(off, #{})},
             {service_mode, cell(down, #{service_mode => true}), cell(down, #{})},
             {off, cell(off, #{}), cell(down, #{})},
             {down, cell(down, #{}), cell(setup, #{})},
             {setup, cell(setup, #{}), cell(off, #{})},
             {idle, cell({ready, idle, blocked}, #{}), cell({ready, processing, active}, #{})},
             {starved, cell({ready, idle, starved}, #{}), cell({ready, idle, blocked}, #{})},
             {blocked, cell({ready, idle, blocked}, #{}), cell({ready, idle, starved}, #{})},
             {processing, cell({ready, processing, active}, #{}),
              cell({ready, idle, starved}, #{})},
             {active, cell({ready, processing, active}, #{}),
              cell({ready, processing, executing}, #{})},
             {executing, cell({ready, processing, executing}, #{}),
              cell({ready, processing, active}, #{})}],
    [?_assertEqual(lists:sort(conditions()), lists:sort([C || {C, _, _} <- Cases]))
     | lists:append([[?_assert(holds(C, Yes)), ?_assertNot(holds(C, No))]
                     || {C, Yes, No} <- Cases])].

outputs_test_() ->
    Lamps = #{red => blinking, yellow => steady, green => off, blue => blinking},
    [?_assertEqual(#{red => true, yellow => true, green => false, blue => true},
                   outputs(Lamps, on)),
     ?_assertEqual(#{red => false, yellow => true, green => false, blue => false},
                   outputs(Lamps, off)),
     ?_assert(blinking(Lamps)),
     ?_assertNot(blinking(Lamps#{red := steady, blue := off}))].

check_rule_test_() ->
    [?_assertEqual(ok, check_rule(#{lamp => red, condition => alarm, mode => steady})),
     ?_assertMatch({error, {bad_rule, _}},
                   check_rule(#{lamp => purple, condition => alarm, mode => steady})),
     ?_assertMatch({error, {bad_rule, _}},
                   check_rule(#{lamp => red, condition => raining, mode => steady})),
     ?_assertMatch({error, {bad_rule, _}},
                   check_rule(#{lamp => red, condition => alarm, mode => off})),
     ?_assertMatch({error, {bad_rule, _}},
                   check_rule(#{lamp => red, condition => alarm, mode => steady, x => 1})),
     ?_assertMatch({error, {bad_rule, _}}, check_rule(red))].
-endif.
