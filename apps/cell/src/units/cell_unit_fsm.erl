%% @doc The lifecycle of a unit (seed 001), as pure functions: the states, the arrows of
%% the seed's two sequence diagrams and no other, the IPC-2541 state a unit reports in
%% each, and what the controller's Start asks of a unit in each state.
%%
%% <pre>
%%  from                                    trigger                  to
%%  booting                                 done                     init
%%  init                                    go_home                  go_home
%%  go_home                                 done                     idle
%%  idle                                    start                    automatic
%%  automatic                               done                     idle
%%  idle                                    {user, X}                {user, X}
%%  {user, X}                               done                     idle
%%  go_home, idle, automatic, {user, X},
%%    stopped, {action, A, _}               stop                     stop
%%  stop                                    done                     stopped
%%  go_home, idle, automatic, {user, X},
%%    stopped, {action, A, _}               aborted                  fault_reaction
%%  fault_reaction                          done                     fault
%%  idle, stopped, fault                    go_home                  go_home
%%  init, idle, stopped, fault              {action, A}              {action, A, From}
%%  {action, A, From}                       done                     From
%% </pre>
%%
%% The first diagram gives every arrow between the predefined and user-defined states,
%% the second those of actions; Booting, the state a unit starts in, precedes both
%% (its only way out is to Init, once the unit's equipment is ready). An action
%% remembers the state it started from, `{action, A, From}', because it returns there.
%%
%% What the diagrams leave out is not allowed: no Stop from Init, Fault or
%% FaultReaction, no fault from Init or Fault, nothing from Booting but Init. Where the
%% engine needs a way the diagrams do not draw, it goes along drawn arrows: a Stop
%% whose sequence is aborted ends (Stop → Stopped) and the fault follows at once
%% (Stopped → FaultReaction); a FaultReaction whose own sequence is aborted ends in
%% Fault directly, as the seed says.
-module(cell_unit_fsm).

-export([next/2, states/1, triggers/1, is_active/1, is_non_active/1, haltable/1, ipc/2,
         on_start/2, name/1]).

-export_type([state/0, non_active/0, trigger/0, ipc_context/0, ready/0]).

-type non_active() :: init | idle | stopped | fault.
-type state() :: booting | non_active() | go_home | automatic | stop | fault_reaction
               | {user, atom()} | {action, atom(), non_active()}.
-type trigger() :: done | aborted | go_home | start | stop | {user, atom()}
                 | {action, atom()}.
-type ready() :: starved | blocked | active | executing.
-type ipc_context() :: #{estop := boolean(),     %% the emergency stop is active
                         halted := boolean(),    %% Halt has taken hold (see ipc/2)
                         ready := ready(),       %% the READY sub-state the sequence reported
                         idle := ready()}.       %% the unit's READY sub-state in Idle

%% @doc The state a trigger leads to, if the diagrams draw that arrow.
-spec next(state(), trigger()) -> {ok, state()} | error.
next(booting, done) -> {ok, init};
next(go_home, done) -> {ok, idle};
next(idle, start) -> {ok, automatic};
next(automatic, done) -> {ok, idle};
next(idle, {user, X}) -> {ok, {user, X}};
next({user, _}, done) -> {ok, idle};
next(stop, done) -> {ok, stopped};
next(fault_reaction, done) -> {ok, fault};
next({action, _, From}, done) -> {ok, From};
next(S, stop) -> stoppable(S, stop);
next(S, aborted) -> stoppable(S, fault_reaction);
next(S, go_home) when S =:= init; S =:= idle; S =:= stopped; S =:= fault -> {ok, go_home};
next(S, {action, A}) ->
    case is_non_active(S) of
        true -> {ok, {action, A, S}};
        false -> error
    end;
next(_, _) -> error.

%% Stop and faults interrupt these states, the active ones and Idle and Stopped.
stoppable(S, To) when S =:= go_home; S =:= idle; S =:= automatic; S =:= stopped ->
    {ok, To};
stoppable({user, _}, To) -> {ok, To};
stoppable({action, _, _}, To) -> {ok, To};
stoppable(_, _) -> error.

%% @doc Every state of a unit with these user-defined states and actions.
-spec states(#{user_states := [atom()], actions := [atom()]}) -> [state()].
states(#{user_states := Us, actions := As}) ->
    [booting, init, go_home, idle, automatic, stop, stopped, fault_reaction, fault]
        ++ [{user, U} || U <- Us]
        ++ [{action, A, From} || A <- As, From <- [init, idle, stopped, fault]].

%% @doc Every trigger of a unit with these user-defined states and actions.
-spec triggers(#{user_states := [atom()], actions := [atom()]}) -> [trigger()].
triggers(#{user_states := Us, actions := As}) ->
    [done, aborted, go_home, start, stop] ++ [{user, U} || U <- Us]
        ++ [{action, A} || A <- As].

%% @doc The seed's non-active states: nothing moves, an action may start.
-spec is_non_active(state()) -> boolean().
is_non_active(S) -> S =:= init orelse S =:= idle orelse S =:= stopped orelse S =:= fault.

%% @doc The states drawn as activations: their sequence runs and ends in `done'.
-spec is_active(state()) -> boolean().
is_active(S) -> not is_non_active(S).

%% @doc Whether Halt holds the state's sequence. Stop and FaultReaction must finish,
%% and Booting only writes parameters: Halt leaves them alone.
-spec haltable(state()) -> boolean().
haltable(S) -> not lists:member(S, [booting, stop, fault_reaction, init, fault]).

%% @doc The IPC-2541 state a unit reports (seed 000 §2.2), so the controller, the panel
%% and SHDR treat units and tasks alike:
%%
%% <pre>
%%  Booting, GoHome                 SETUP (initialising, referencing)
%%  Init                            OFF (not referenced; Start takes it on, as a task's)
%%  Idle                            READY-IDLE-STARVED, or the unit's own `idle'
%%  Automatic, user states          READY-PROCESSING-ACTIVE, or what the sequence
%%                                  reported (STARVED, BLOCKED, EXECUTING)
%%  actions                         SETUP (a service move, not production)
%%  Stop, Stopped                   OFF
%%  FaultReaction, Fault            DOWN
%%  any, once Halt has taken hold   DOWN (paused)
%%  any, during the emergency stop  OFF (the seed: an emergency stop is OFF)
%% </pre>
-spec ipc(state(), ipc_context()) -> cell_ipc:state().
ipc(_, #{estop := true}) -> off;
ipc(S, #{halted := true}) when S =/= booting, S =/= stop, S =/= fault_reaction ->
    case is_non_active(S) andalso S =/= idle of
        true -> plain(S);
        false -> down
    end;
ipc(idle, #{idle := Idle}) -> ready(Idle);
ipc(automatic, #{ready := R}) -> ready(R);
ipc({user, _}, #{ready := R}) -> ready(R);
ipc(S, _) -> plain(S).

plain(booting) -> setup;
plain(go_home) -> setup;
plain({action, _, _}) -> setup;
plain(init) -> off;
plain(stop) -> off;
plain(stopped) -> off;
plain(fault_reaction) -> down;
plain(fault) -> down;
plain(idle) -> {ready, idle, starved};
plain(automatic) -> {ready, processing, active};
plain({user, _}) -> {ready, processing, active}.

ready(starved) -> {ready, idle, starved};
ready(blocked) -> {ready, idle, blocked};
ready(active) -> {ready, processing, active};
ready(executing) -> {ready, processing, executing}.

%% @doc What the cell's Start asks of a unit that arrives in (or is in) a state: to be
%% referenced (GoHome) where it is not, then Automatic. A unit with an error waiting
%% for the operator moves for nobody until it is answered.
-spec on_start(state(), #{error := boolean()}) -> go_home | start | none.
on_start(_, #{error := true}) -> none;
on_start(idle, _) -> start;
on_start(S, _) when S =:= init; S =:= stopped; S =:= fault -> go_home;
on_start(_, _) -> none.

%% @doc A state in words for logs and the panel: `automatic', `user calibrate',
%% `action release_part (from fault)'.
-spec name(state()) -> binary().
name({user, X}) -> iolist_to_binary(["user state ", atom_to_list(X)]);
name({action, A, From}) ->
    iolist_to_binary(["action ", atom_to_list(A), " (from ", atom_to_list(From), ")"]);
name(S) when is_atom(S) -> atom_to_binary(S, utf8).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

-define(DECL, #{user_states => [x], actions => [a]}).

%% Both diagrams, arrow by arrow, as the seed draws them (label → trigger).
drawn() ->
    Active = [go_home, idle, automatic, {user, x}, stopped],
    [{booting, done, init},
     %% Getting ready, successful operation
     {init, go_home, go_home}, {go_home, done, idle},
     {idle, start, automatic}, {automatic, done, idle},
     {idle, {user, x}, {user, x}}, {{user, x}, done, idle}]
    %% Interrupt states by Stop; error handling of faults
    ++ [{S, stop, stop} || S <- Active] ++ [{stop, done, stopped}]
    ++ [{S, aborted, fault_reaction} || S <- Active] ++ [{fault_reaction, done, fault}]
    %% Reference
    ++ [{S, go_home, go_home} || S <- [idle, stopped, fault]]
    %% Actions: from any non-active state and back; interrupted by Stop and faults
    ++ lists:append([[{From, {action, a}, {action, a, From}},
                      {{action, a, From}, done, From},
                      {{action, a, From}, stop, stop},
                      {{action, a, From}, aborted, fault_reaction}]
                     || From <- [init, idle, stopped, fault]]).

every_arrow_and_no_other_test() ->
    Allowed = [{S, T, To} || S <- states(?DECL), T <- triggers(?DECL), {ok, To} <- [next(S, T)]],
    ?assertEqual(lists:sort(drawn()), lists:sort(Allowed)).

no_way_out_of_booting_but_init_test_() ->
    [?_assertEqual(error, next(booting, T)) || T <- triggers(?DECL), T =/= done].

stop_and_faults_leave_these_alone_test_() ->
    [?_assertEqual(error, next(S, T)) || S <- [init, fault, fault_reaction, stop, booting],
                                         T <- [stop, aborted]].

ipc_test_() ->
    C = #{estop => false, halted => false, ready => active, idle => starved},
    [?_assertEqual(setup, ipc(booting, C)),
     ?_assertEqual(off, ipc(init, C)),
     ?_assertEqual(setup, ipc(go_home, C)),
     ?_assertEqual({ready, idle, starved}, ipc(idle, C)),
     ?_assertEqual({ready, idle, blocked}, ipc(idle, C#{idle => blocked})),
     ?_assertEqual({ready, processing, active}, ipc(automatic, C)),
     ?_assertEqual({ready, processing, executing}, ipc(automatic, C#{ready => executing})),
     ?_assertEqual({ready, idle, starved}, ipc({user, x}, C#{ready => starved})),
     ?_assertEqual(setup, ipc({action, a, fault}, C)),
     ?_assertEqual(off, ipc(stop, C)),
     ?_assertEqual(off, ipc(stopped, C)),
     ?_assertEqual(down, ipc(fault_reaction, C)),
     ?_assertEqual(down, ipc(fault, C)),
     %% Halt: paused where something runs; the non-active states keep their own.
     ?_assertEqual(down, ipc(automatic, C#{halted => true})),
     ?_assertEqual(down, ipc(idle, C#{halted => true})),
     ?_assertEqual(down, ipc(go_home, C#{halted => true})),
     ?_assertEqual(off, ipc(stopped, C#{halted => true})),
     ?_assertEqual(off, ipc(stop, C#{halted => true})),
     ?_assertEqual(down, ipc(fault_reaction, C#{halted => true})),
     %% The emergency stop is OFF, whatever the state.
     ?_assertEqual(off, ipc(fault, C#{estop => true})),
     ?_assertEqual(off, ipc(automatic, C#{estop => true, halted => true}))].

on_start_test_() ->
    [?_assertEqual(go_home, on_start(init, #{error => false})),
     ?_assertEqual(go_home, on_start(stopped, #{error => false})),
     ?_assertEqual(go_home, on_start(fault, #{error => false})),
     ?_assertEqual(none, on_start(fault, #{error => true})),
     ?_assertEqual(none, on_start(init, #{error => true})),
     ?_assertEqual(start, on_start(idle, #{error => false})),
     ?_assertEqual(none, on_start(automatic, #{error => false})),
     ?_assertEqual(none, on_start(go_home, #{error => false})),
     ?_assertEqual(none, on_start(stop, #{error => false}))].

haltable_test_() ->
    [?_assert(haltable(S)) || S <- [go_home, idle, automatic, {user, x}, {action, a, idle}]]
        ++ [?_assertNot(haltable(S)) || S <- [booting, stop, fault_reaction, init, fault]].

names_test_() ->
    [?_assertEqual(<<"user state x">>, name({user, x})),
     ?_assertEqual(<<"action a (from fault)">>, name({action, a, fault})),
     ?_assertEqual(<<"fault_reaction">>, name(fault_reaction))].
-endif.
