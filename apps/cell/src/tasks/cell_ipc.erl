%% @doc The IPC-2541 equipment states of seed 000 §2.2, as pure functions.
%%
%% The seed's transition table, exactly:
%%
%% <table>
%% <tr><th>arrow</th><th>current state</th><th>typical trigger</th><th>new state</th></tr>
%% <tr><td>0</td><td>OFF</td><td>Start requested</td><td>SETUP</td></tr>
%% <tr><td>1</td><td>SETUP</td><td>Initialization succeeded</td><td>any READY sub-state</td></tr>
%% <tr><td>2</td><td>any READY sub-state</td><td>ResetException thrown</td><td>SETUP</td></tr>
%% <tr><td>3</td><td>STARVED</td><td>Product received</td><td>ACTIVE</td></tr>
%% <tr><td>4</td><td>ACTIVE</td><td>Processing done</td><td>BLOCKED</td></tr>
%% <tr><td>5</td><td>DOWN</td><td>Error cleared or Start requested while paused</td><td>any READY sub-state</td></tr>
%% <tr><td>6</td><td>READY</td><td>Error occurred or Pause requested</td><td>DOWN</td></tr>
%% <tr><td>7</td><td>SETUP</td><td>Error occurred during initialization</td><td>DOWN</td></tr>
%% <tr><td>8</td><td>DOWN</td><td>Error cleared</td><td>SETUP</td></tr>
%% <tr><td>9</td><td>DOWN</td><td>Stop requested</td><td>OFF</td></tr>
%% </table>
%%
%% Within READY, the sub-state follows the events of §2.3.4 (arrows 3 and 4 are two of
%% them): Starved → STARVED, Unstarved → ACTIVE, Blocked → BLOCKED, Unblocked → ACTIVE,
%% ItemWorkStart → EXECUTING, ItemWorkPause → ACTIVE, ItemWorkResume → EXECUTING,
%% ItemWorkComplete → ACTIVE; the other events change nothing. The emergency stop takes
%% any state to OFF. No other transition exists.
%%
%% Priority, lowest first (the order of the seed's `IpcState' enumeration): OFF, DOWN,
%% SETUP, BLOCKED, STARVED, ACTIVE, EXECUTING. The cell's state is the task state of
%% highest priority.
-module(cell_ipc).

-export([states/0, arrow/2, check/3, event_state/2, priority/1, of_priority/1, cell_state/1,
         is_ready/1, name/1, code/1]).

-export_type([state/0, ready/0, event/0, cause/0]).

-type ready() :: {ready, idle, starved} | {ready, idle, blocked}
               | {ready, processing, active} | {ready, processing, executing}.
-type state() :: off | down | setup | ready().
-type event() :: equipment_starved | equipment_unstarved | equipment_blocked
               | equipment_unblocked | item_identifier_read | item_transfer_in
               | item_work_start | item_work_pause | item_work_resume
               | item_work_complete | item_work_abort | item_transfer_out.
-type cause() :: {arrow, 0..9} | {event, event()} | estop.

-define(STARVED, {ready, idle, starved}).
-define(BLOCKED, {ready, idle, blocked}).
-define(ACTIVE, {ready, processing, active}).
-define(EXECUTING, {ready, processing, executing}).

%% @doc Every state, lowest priority first.
-spec states() -> [state()].
states() ->
    [off, down, setup, ?BLOCKED, ?STARVED, ?ACTIVE, ?EXECUTING].

%% @doc The arrow of the seed's table that leads from one state to another, if any.
-spec arrow(state(), state()) -> {ok, 0..9} | error.
arrow(off, setup) -> {ok, 0};
arrow(setup, To) -> case is_ready(To) of true -> {ok, 1}; false -> setup_to(To) end;
arrow(down, To) -> case is_ready(To) of true -> {ok, 5}; false -> down_to(To) end;
arrow(From, To) ->
    case is_ready(From) of
        true -> ready_to(From, To);
        false -> error
    end.

setup_to(down) -> {ok, 7};
setup_to(_) -> error.

down_to(setup) -> {ok, 8};
down_to(off) -> {ok, 9};
down_to(_) -> error.

ready_to(?STARVED, ?ACTIVE) -> {ok, 3};
ready_to(?ACTIVE, ?BLOCKED) -> {ok, 4};
ready_to(_, setup) -> {ok, 2};
ready_to(_, down) -> {ok, 6};
ready_to(_, _) -> error.

%% @doc Checks that a transition is allowed for its cause: an arrow of the table, an
%% event of §2.3.4 inside READY, or the emergency stop.
-spec check(state(), state(), cause()) -> ok | {error, {illegal, state(), state(), cause()}}.
check(From, To, estop) when To =:= off, From =/= off ->
    ok;
check(From, To, {event, Event} = Cause) ->
    case is_ready(From) andalso event_state(Event, From) =:= To of
        true -> ok;
        false -> {error, {illegal, From, To, Cause}}
    end;
check(From, To, {arrow, N} = Cause) ->
    case arrow(From, To) of
        {ok, N} -> ok;
        %% Arrows 3 and 4 are the Unstarved and ItemWorkComplete-then-Blocked examples;
        %% the sub-state changes themselves are checked as events.
        _ -> {error, {illegal, From, To, Cause}}
    end;
check(From, To, Cause) ->
    {error, {illegal, From, To, Cause}}.

%% @doc The state an event leaves a READY task in (§2.3.4).
-spec event_state(event(), ready()) -> ready().
event_state(equipment_starved, _) -> ?STARVED;
event_state(equipment_unstarved, _) -> ?ACTIVE;
event_state(equipment_blocked, _) -> ?BLOCKED;
event_state(equipment_unblocked, _) -> ?ACTIVE;
event_state(item_work_start, _) -> ?EXECUTING;
event_state(item_work_pause, _) -> ?ACTIVE;
event_state(item_work_resume, _) -> ?EXECUTING;
event_state(item_work_complete, _) -> ?ACTIVE;
event_state(item_identifier_read, S) -> S;
event_state(item_transfer_in, S) -> S;
event_state(item_work_abort, S) -> S;
event_state(item_transfer_out, S) -> S.

%% @doc 0 (OFF) to 6 (EXECUTING): the seed's `IpcState' values.
-spec priority(state()) -> 0..6.
priority(off) -> 0;
priority(down) -> 1;
priority(setup) -> 2;
priority(?BLOCKED) -> 3;
priority(?STARVED) -> 4;
priority(?ACTIVE) -> 5;
priority(?EXECUTING) -> 6.

%% @doc The state of a priority (the inverse of {@link priority/1}).
-spec of_priority(0..6) -> state().
of_priority(0) -> off;
of_priority(1) -> down;
of_priority(2) -> setup;
of_priority(3) -> ?BLOCKED;
of_priority(4) -> ?STARVED;
of_priority(5) -> ?ACTIVE;
of_priority(6) -> ?EXECUTING.

%% @doc The seed's `IpcState' code of a state (same as its priority).
-spec code(state()) -> 0..6.
code(S) -> priority(S).

%% @doc The cell's state: the task state of highest priority; OFF for no tasks.
-spec cell_state([state()]) -> state().
cell_state(States) ->
    lists:foldl(fun(S, Acc) ->
                        case priority(S) > priority(Acc) of
                            true -> S;
                            false -> Acc
                        end
                end, off, States).

-spec is_ready(term()) -> boolean().
is_ready({ready, idle, starved}) -> true;
is_ready({ready, idle, blocked}) -> true;
is_ready({ready, processing, active}) -> true;
is_ready({ready, processing, executing}) -> true;
is_ready(_) -> false.

%% @doc The state as the seed writes it: `READY-IDLE-STARVED'.
-spec name(state()) -> binary().
name(off) -> <<"OFF">>;
name(down) -> <<"DOWN">>;
name(setup) -> <<"SETUP">>;
name({ready, idle, starved}) -> <<"READY-IDLE-STARVED">>;
name({ready, idle, blocked}) -> <<"READY-IDLE-BLOCKED">>;
name({ready, processing, active}) -> <<"READY-PROCESSING-ACTIVE">>;
name({ready, processing, executing}) -> <<"READY-PROCESSING-EXECUTING">>.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

ready() -> [?STARVED, ?BLOCKED, ?ACTIVE, ?EXECUTING].

%% The table, read row by row from the seed, against arrow/2 for every pair of states.
table_test() ->
    Expected = [{off, setup, 0}]
        ++ [{setup, R, 1} || R <- ready()]
        ++ [{R, setup, 2} || R <- ready()]
        ++ [{?STARVED, ?ACTIVE, 3}, {?ACTIVE, ?BLOCKED, 4}]
        ++ [{down, R, 5} || R <- ready()]
        ++ [{R, down, 6} || R <- ready()]
        ++ [{setup, down, 7}, {down, setup, 8}, {down, off, 9}],
    Actual = [{F, T, N} || F <- states(), T <- states(), {ok, N} <- [arrow(F, T)]],
    ?assertEqual(lists:sort(Expected), lists:sort(Actual)).

no_other_ways_to_off_test() ->
    [?assertEqual(error, arrow(S, off)) || S <- states(), S =/= down].

estop_test_() ->
    [?_assertEqual(ok, check(S, off, estop)) || S <- states(), S =/= off]
        ++ [?_assertMatch({error, _}, check(off, off, estop)),
            ?_assertMatch({error, _}, check(?ACTIVE, down, estop))].

events_test_() ->
    [?_assertEqual(?STARVED, event_state(equipment_starved, ?BLOCKED)),
     ?_assertEqual(?ACTIVE, event_state(equipment_unstarved, ?STARVED)),
     ?_assertEqual(?BLOCKED, event_state(equipment_blocked, ?ACTIVE)),
     ?_assertEqual(?ACTIVE, event_state(equipment_unblocked, ?BLOCKED)),
     ?_assertEqual(?EXECUTING, event_state(item_work_start, ?ACTIVE)),
     ?_assertEqual(?ACTIVE, event_state(item_work_pause, ?EXECUTING)),
     ?_assertEqual(?EXECUTING, event_state(item_work_resume, ?ACTIVE)),
     ?_assertEqual(?ACTIVE, event_state(item_work_complete, ?EXECUTING)),
     ?_assertEqual(?BLOCKED, event_state(item_transfer_in, ?BLOCKED)),
     ?_assertEqual(?EXECUTING, event_state(item_work_abort, ?EXECUTING)),
     ?_assertEqual(ok, check(?STARVED, ?ACTIVE, {event, equipment_unstarved})),
     ?_assertMatch({error, _}, check(down, ?ACTIVE, {event, equipment_unstarved})),
     ?_assertMatch({error, _}, check(?STARVED, ?BLOCKED, {event, equipment_unstarved}))].

cell_state_test_() ->
    [?_assertEqual(off, cell_state([])),
     ?_assertEqual(off, cell_state([off, off])),
     ?_assertEqual(setup, cell_state([down, setup, off])),
     ?_assertEqual(?STARVED, cell_state([down, ?BLOCKED, ?STARVED])),
     ?_assertEqual(?EXECUTING, cell_state([?EXECUTING, down, ?ACTIVE]))].

names_test_() ->
    [?_assertEqual(<<"READY-IDLE-STARVED">>, name(?STARVED)),
     ?_assertEqual(<<"READY-PROCESSING-EXECUTING">>, name(?EXECUTING)),
     ?_assertEqual(<<"OFF">>, name(off))].
-endif.
