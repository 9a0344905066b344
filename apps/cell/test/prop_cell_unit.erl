%% A PropEr state-machine property of units. The model is written from seed 001: the
%% arrows of its two sequence diagrams (arrow/2 below, one clause per arrow), Halt,
%% and the step sequences of each state; from the IPC-2541 mapping units report by;
%% and from the controller's commands and the operator's answers as units take them —
%% never by calling the code under test. A real unit (cell_test_unit, whose every
%% sequence is a cell_test_seq the test completes or aborts) runs in a real cell under
%% the real controller; its sequences run several steps in one go or one per cycle,
%% chosen at random per state for each run.
%%
%% Commands: the unit's buttons (GoHome, Start, Stop, ButtonX, ButtonY, a fault from
%% outside), sequences completing and aborting, Halt and its release, the cell's
%% Start, Pause, Stop and emergency stop, answers to the unit's errors, and killing
%% the unit's process.
%%
%% Postconditions: each command's result; every transition the unit made, recorded
%% through its task_state events, one by one against the path the model takes, and
%% each against the diagrams (no forbidden transition); the state, the IPC-2541 state,
%% the cell state, which sequence waits (or holds) and the unit's error.
-module(prop_cell_unit).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, initial_state/1, command/1, precondition/2, postcondition/3,
         next_state/3]).
-export([button/1, complete/0, fail/1, halt/1, controller/1, estop/1, answer/1, kill/0]).
-export([arrow/2, forbidden/1, ipc/1, setup/1, teardown/0, drain/0]).

-define(UNIT, u).
-define(TAB, prop_cell_unit_tab).

-record(m, {st = booting,            %% the unit's state
            seq = {waiting, booting},%% none | {waiting, Key} | {held, wait | finish, Key}
            halt = false,
            request = stop,
            estop = false,
            auto = false,            %% the cell's Start asks for Automatic
            error = none,            %% none | {Origin, Solutions}
            crash = false,           %% restarted after a crash, not yet in Init
            path = [],               %% the transitions of the last command
            modes = #{}}).

%% -------------------------------------------------------------------------------------
%% Properties, run inside eunit
%% -------------------------------------------------------------------------------------

sequential_test_() ->
    {timeout, 900, ?_assert(proper:quickcheck(prop_sequential(),
                                              [{to_file, user}, {numtests, 200}]))}.

parallel_test_() ->
    {timeout, 900, ?_assert(proper:quickcheck(prop_parallel(),
                                              [{to_file, user}, {numtests, 60}]))}.

prop_sequential() ->
    ?FORALL(Modes, modes(),
            %% Long runs: a unit must boot and be referenced before most arrows can be
            %% taken.
            ?FORALL(Cmds, ?SIZED(Size, resize(3 * Size, commands(?MODULE, initial_state(Modes)))),
                    begin
                        setup(Modes),
                        {History, State, Result} = run_commands(?MODULE, Cmds),
                        teardown(),
                        ?WHENFAIL(io:format(user, "Modes: ~p~nHistory: ~p~nState: ~p~nResult: ~p~n",
                                            [Modes, History, State, Result]),
                                  aggregate(command_names(Cmds), Result =:= ok))
                    end)).

%% Parallel: the unit's buttons, Halt and the cell's commands race each other from two
%% processes; PropEr checks that some interleaving explains every answer. Every
%% transition recorded meanwhile must be an arrow of the diagrams.
prop_parallel() ->
    ?FORALL(Modes, modes(),
            ?FORALL(Cmds, parallel_commands(prop_cell_unit_par, initial_state(Modes)),
                    begin
                        setup(Modes),
                        true = ets:insert(?TAB, {mode, parallel}),
                        {Seq, Par, Result} = run_parallel_commands(prop_cell_unit_par, Cmds),
                        ok = cell_unit:settle(?UNIT),
                        Recorded = drain(),
                        Forbidden = forbidden(Recorded),
                        teardown(),
                        ?WHENFAIL(io:format(user, "Seq: ~p~nPar: ~p~nResult: ~p~nForbidden: ~p~n",
                                            [Seq, Par, Result, Forbidden]),
                                  Result =:= ok andalso Forbidden =:= [])
                    end)).

modes() ->
    ?LET(L, vector(length(cell_test_unit:keys()), elements([several, one])),
         maps:from_list(lists:zip(cell_test_unit:keys(), L))).

%% -------------------------------------------------------------------------------------
%% The diagrams of seed 001
%% -------------------------------------------------------------------------------------

%% Booting precedes both diagrams: the unit's only way out of it is to Init.
arrow(booting, done) -> init;
%% Getting ready; successful operation.
arrow(init, go_home) -> go_home;
arrow(go_home, done) -> idle;
arrow(idle, start) -> automatic;
arrow(automatic, done) -> idle;
arrow(idle, {user, X}) -> {user, X};
arrow({user, _}, done) -> idle;
%% Interrupt states by Stop: GoHome, Idle, Automatic, UserdefinedX, Stopped; and
%% ActionX (second diagram).
arrow(stop, done) -> stopped;
arrow(S, stop) ->
    case interruptible(S) of
        true -> stop;
        false -> none
    end;
%% Error handling of faults, from the same states.
arrow(fault_reaction, done) -> fault;
arrow(S, aborted) ->
    case interruptible(S) of
        true -> fault_reaction;
        false -> none
    end;
%% Reference.
arrow(S, go_home) when S =:= idle; S =:= stopped; S =:= fault -> go_home;
%% Actions: from any non-active state, and back there.
arrow(S, {action, A}) when S =:= init; S =:= idle; S =:= stopped; S =:= fault ->
    {action, A, S};
arrow({action, _, From}, done) -> From;
arrow(_, _) -> none.

interruptible({user, _}) -> true;
interruptible({action, _, _}) -> true;
interruptible(S) -> lists:member(S, [go_home, idle, automatic, stopped]).

%% Transitions that are not an arrow of the diagrams (whatever their trigger).
forbidden(Recorded) ->
    Arrows = [{F, arrow(F, T)} || F <- states(), T <- triggers(), arrow(F, T) =/= none],
    [X || {_, _} = X <- Recorded, not lists:member(X, Arrows)].

states() ->
    [booting, init, go_home, idle, automatic, stop, stopped, fault_reaction, fault,
     {user, x}, {user, y}] ++ [{action, A, F} || A <- [a, b], F <- [init, idle, stopped, fault]].

triggers() ->
    [done, aborted, go_home, start, stop, {user, x}, {user, y}, {action, a}, {action, b}].

%% Halt holds the sequences of these states (Stop and FaultReaction must finish).
haltable({user, _}) -> true;
haltable({action, _, _}) -> true;
haltable(S) -> lists:member(S, [go_home, idle, automatic]).

%% The IPC-2541 state a unit reports.
ipc(#m{estop = true}) -> off;
ipc(#m{st = S} = M) ->
    case halted(M) of
        true -> down;
        false -> plain_ipc(S)
    end.

halted(#m{halt = true, st = S, seq = Seq}) ->
    haltable(S) andalso (Seq =:= none orelse element(1, Seq) =:= held);
halted(_) ->
    false.

plain_ipc(S) when S =:= booting; S =:= go_home -> setup;
plain_ipc({action, _, _}) -> setup;
plain_ipc(S) when S =:= init; S =:= stop; S =:= stopped -> off;
plain_ipc(idle) -> {ready, idle, starved};
plain_ipc(automatic) -> {ready, processing, active};
plain_ipc({user, _}) -> {ready, processing, active};
plain_ipc(S) when S =:= fault_reaction; S =:= fault -> down.

%% -------------------------------------------------------------------------------------
%% Model
%% -------------------------------------------------------------------------------------

initial_state() -> initial_state(#{}).

initial_state(Modes) -> #m{modes = Modes}.

command(#m{seq = Seq, estop = Estop} = M) ->
    Waiting = case Seq of {waiting, _} -> not (Estop andalso M#m.st =:= booting); _ -> false end,
    frequency(
      [{6, {call, ?MODULE, button, [elements([go_home, start, stop])]}},
       {3, {call, ?MODULE, button, [{user, elements([x, y, z])}]}},
       {3, {call, ?MODULE, button, [{action, elements([a, b])}]}},
       {2, {call, ?MODULE, button, [{abort, <<"jammed">>}]}},
       {2, {call, ?MODULE, halt, [bool()]}},
       {3, {call, ?MODULE, controller, [elements([start, pause, stop])]}},
       {1, {call, ?MODULE, estop, [not Estop]}},
       {2, {call, ?MODULE, answer, [elements([retry, reset, ignore])]}},
       {1, {call, ?MODULE, kill, []}}]
      ++ [{12, {call, ?MODULE, complete, []}} || Waiting]
      ++ [{3, {call, ?MODULE, fail, [<<"step failed">>]}} || Waiting]).

precondition(#m{seq = {waiting, _}, estop = Estop, st = St}, {call, _, C, _})
  when C =:= complete; C =:= fail ->
    %% Under the emergency stop no step runs: Booting's is blocked, the others gone.
    not (Estop andalso St =:= booting);
precondition(_M, {call, _, C, _}) when C =:= complete; C =:= fail ->
    false;
precondition(_M, _Call) ->
    true.

next_state(M0, _Res, Call) ->
    step(M0#m{path = []}, Call).

step(M, {call, _, button, [B]}) ->
    case button_result(M, B) of
        ok -> press(M, B);
        _ -> M
    end;
step(#m{seq = {waiting, Key}} = M, {call, _, complete, []}) ->
    case M#m.halt andalso haltable(M#m.st) of
        true -> M#m{seq = {held, finish, Key}};       %% held before its next step
        false -> done(M#m{seq = none})
    end;
step(#m{seq = {waiting, _}} = M, {call, _, fail, [_]}) ->
    failed(M#m{seq = none});
step(M, {call, _, halt, [On]}) ->
    set_halt(M, On);
step(#m{estop = true} = M, {call, _, controller, [start]}) ->
    M;                                                %% the controller refuses it
step(M, {call, _, controller, [start]}) ->
    arrive(set_halt(M#m{request = start, auto = true}, false));
step(M, {call, _, controller, [pause]}) ->
    set_halt(M#m{request = pause}, true);
step(M0, {call, _, controller, [stop]}) ->
    M = M0#m{request = stop, auto = false, halt = false},
    case arrow(M#m.st, stop) of
        none -> M;
        _ -> go(M, stop)
    end;
step(M, {call, _, estop, [true]}) ->
    emergency(M#m{estop = true, request = stop, auto = false, halt = false});
step(#m{st = booting, error = none, estop = true} = M, {call, _, estop, [false]}) ->
    M#m{estop = false, seq = {waiting, booting}};    %% its sequence starts over
step(M, {call, _, estop, [false]}) ->
    M#m{estop = false};
step(M, {call, _, answer, [Solution]}) ->
    case answer_result(M, Solution) of
        ok -> answered(M, Solution);
        _ -> M
    end;
step(M, {call, _, kill, []}) ->
    Exited = [exited || ipc(M) =/= off],
    M#m{st = booting, path = Exited ++ [boot],
        seq = case M#m.estop of true -> none; false -> {waiting, booting} end,
        halt = M#m.request =:= pause, auto = false, error = none, crash = true}.

%% A transition along an arrow, into the next state.
go(#m{st = S, path = P} = M, Trigger) ->
    To = arrow(S, Trigger),
    true = To =/= none,
    M1 = M#m{st = To, path = P ++ [{S, To}], seq = none},
    M2 = case To of
             automatic -> M1#m{auto = false};
             go_home -> M1#m{error = none};           %% GoHome takes the fault back
             _ -> M1
         end,
    enter(M2).

%% Stop ended by a fault: through Stopped, where the fault follows at once (nothing
%% else is asked of Stopped on the way).
pass(#m{st = S, path = P} = M, Trigger) ->
    To = arrow(S, Trigger),
    true = To =/= none,
    M#m{st = To, path = P ++ [{S, To}], seq = none}.

%% A state is entered: its preparation, what the cell's Start asks, its sequence.
enter(#m{st = fault_reaction} = M) ->
    run_sequence(M#m{error = {fault, [reset]}});
enter(#m{st = init, crash = true, request = R} = M) ->
    Error = case R of stop -> none; _ -> {crash, [reset]} end,
    arrive(M#m{crash = false, error = Error});
enter(#m{st = S} = M) when S =:= idle; S =:= stopped; S =:= fault; S =:= init ->
    arrive(M);
enter(M) ->
    run_sequence(M).

%% In a non-active state, the cell's Start asks for GoHome where the unit is not
%% referenced, then Automatic; an error waiting for the operator holds it.
arrive(#m{auto = true, estop = false, error = none, st = S} = M) ->
    case S of
        idle -> go(M, start);
        _ when S =:= init; S =:= stopped; S =:= fault -> go(M, go_home);
        _ -> M
    end;
arrive(M) ->
    M.

run_sequence(#m{st = S, estop = true} = M) when S =:= stop; S =:= fault_reaction ->
    go(M, done);                                      %% no step may start: done at once
run_sequence(#m{st = S} = M) ->
    case M#m.halt andalso haltable(S) of
        true -> M#m{seq = {held, wait, key(S)}};      %% held before its first step
        false -> M#m{seq = {waiting, key(S)}}
    end.

key({action, A, _}) -> {action, A};
key(S) -> S.

%% The sequence is done.
done(#m{st = S} = M) ->
    case arrow(S, done) of
        none -> M;
        _ -> go(M, done)
    end.

%% The sequence was aborted.
failed(#m{st = booting} = M) ->
    M#m{error = {booting, [retry]}};
failed(#m{st = fault_reaction} = M) ->
    go(M, done);                                      %% the seed: directly into Fault
failed(#m{st = stop} = M) ->
    go(pass(M, done), aborted);                       %% Stop ends; the fault follows
failed(M) ->
    go(M, aborted).

set_halt(#m{seq = {held, wait, Key}} = M, false) ->
    M#m{halt = false, seq = {waiting, Key}};
set_halt(#m{seq = {held, finish, _}} = M, false) ->
    done(M#m{halt = false, seq = none});
set_halt(M, On) ->
    M#m{halt = On}.

%% The emergency stop: everything stops at once.
emergency(#m{st = S} = M) ->
    if
        S =:= stop; S =:= fault_reaction -> go(M#m{seq = none}, done);
        S =:= booting -> M#m{seq = none};
        S =:= stopped; S =:= init; S =:= fault -> M#m{seq = none};
        true -> go(M#m{seq = none}, stop)
    end.

press(M, {abort, _}) ->
    case M#m.st of
        stop -> go(pass(M, done), aborted);
        _ -> go(M, aborted)
    end;
press(M, stop) ->
    go(M#m{auto = false}, stop);
press(M, B) ->
    go(M, B).

button_result(#m{estop = true}, B) when B =:= go_home; B =:= start;
                                        element(1, B) =:= user; element(1, B) =:= action ->
    {error, estop_active};
button_result(_M, {user, z}) ->
    {error, {unknown_user_state, z}};
button_result(#m{st = stop}, {abort, _}) ->
    ok;
button_result(#m{st = S}, B) ->
    Trigger = case B of {abort, _} -> aborted; _ -> B end,
    case arrow(S, Trigger) of
        none -> {error, {not_allowed, B, S}};
        _ -> ok
    end.

answer_result(#m{error = none}, _) -> {error, not_found};
answer_result(#m{error = {_, Solutions}}, S) ->
    case lists:member(S, Solutions) of
        true -> ok;
        false -> {error, {not_allowed, Solutions}}
    end.

answered(#m{error = {booting, _}} = M, retry) ->
    M#m{error = none, seq = case M#m.estop of true -> none; false -> {waiting, booting} end};
answered(#m{st = S} = M0, reset) ->
    M = M0#m{error = none, auto = M0#m.request =:= start},
    case lists:member(S, [init, idle, stopped, fault]) of
        true -> arrive(M);
        false -> M
    end.

%% -------------------------------------------------------------------------------------
%% Postconditions
%% -------------------------------------------------------------------------------------

postcondition(M, {call, _, Cmd, Args} = Call, Res) ->
    M1 = next_state(M, Res, Call),
    Expected = expected_result(M, Cmd, Args),
    Verdict = case Res of
                  #{result := Expected} = Obs -> matches(M1, Obs);
                  #{result := Other} -> {result, Cmd, Args, expected, Expected, got, Other};
                  Expected -> true;
                  _ -> false               %% parallel: another interleaving may explain it
              end,
    case Verdict of
        true -> true;
        false -> false;
        Why -> io:format(user, "~nPostcondition of ~p~p failed:~n~p~n", [Cmd, Args, Why]),
               false
    end.

expected_result(M, button, [B]) -> button_result(M, B);
expected_result(#m{seq = {waiting, Key}}, complete, []) -> {completed, Key};
expected_result(#m{seq = {waiting, Key}}, fail, [_]) -> {failed, Key};
expected_result(#m{estop = true}, controller, [start]) -> {error, estop_active};
expected_result(M, answer, [S]) -> answer_result(M, S);
expected_result(_M, _Cmd, _Args) -> ok.

matches(#m{st = St, path = Path, error = Error, request = Request, estop = Estop} = M,
        #{state := State, ipc := Ipc, cell := Cell, path := Recorded, seq := Seq,
          error := ObsError, flags := Flags}) ->
    Checks = [{forbidden, forbidden(Recorded), []},
              {path, Recorded, Path},
              {state, State, St},
              {ipc, Ipc, ipc(M)},
              {cell_state, Cell, ipc(M)},
              {sequence, Seq, seq_view(M#m.seq)},
              {error, ObsError, case Error of none -> none; {Origin, _} -> Origin end},
              {flags, Flags, #{request => Request, estop => Estop, has_error => Error =/= none}}],
    case [{What, got, Got, expected, Want} || {What, Got, Want} <- Checks, Got =/= Want] of
        [] -> true;
        Mismatches -> {mismatch, Mismatches}
    end.

seq_view({held, Step, _Key}) -> {held, Step};
seq_view(Other) -> Other.

%% -------------------------------------------------------------------------------------
%% Commands against the real unit
%% -------------------------------------------------------------------------------------

button(go_home) -> observe(cell_unit:go_home(?UNIT));
button(start) -> observe(cell_unit:start(?UNIT));
button(stop) -> observe(cell_unit:stop(?UNIT));
button({user, X}) -> observe(cell_unit:user_state(?UNIT, X));
button({action, A}) -> observe(cell_unit:action(?UNIT, A));
button({abort, Why}) -> observe(cell_unit:abort(?UNIT, Why)).

complete() -> observe(sent(completed, cell_test_seq:complete(?TAB, ?UNIT))).

fail(Why) -> observe(sent(failed, cell_test_seq:fail(?TAB, ?UNIT, Why))).

sent(_What, none) -> nothing_waits;
sent(What, Key) -> {What, Key}.

halt(true) -> observe(cell_unit:halt(?UNIT));
halt(false) -> observe(cell_unit:resume(?UNIT)).

controller(start) -> observe(cell_controller:start());
controller(pause) -> observe(cell_controller:pause());
controller(stop) -> observe(cell_controller:stop()).

estop(On) -> observe(cell_controller:estop(On)).

answer(Solution) ->
    Id = case [A || #{task := ?UNIT, kind := error, id := A} <- cell_alarms:list()] of
             [A] -> A;
             [] -> <<"u:none">>
         end,
    observe(cell_alarms:answer(Id, Solution, <<"prop">>)).

%% The unit's process is killed; its supervisor starts it again, and it announces
%% itself booting.
kill() ->
    Pid = cell_unit:whereis(?UNIT),
    Ref = monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', Ref, process, Pid, _} -> ok after 10000 -> erlang:error(no_down) end,
    observe(ok, await_boot([])).

await_boot(Acc) ->
    receive
        {cell_event, #{type := task_state, task := ?UNIT} = E} ->
            case recorded(E) of
                boot -> lists:reverse([boot | Acc]);
                ignore -> await_boot(Acc);
                R -> await_boot([R | Acc])
            end
    after 10000 ->
        erlang:error({no_restart, lists:reverse(Acc)})
    end.

observe(Result) ->
    observe(Result, []).

%% What every postcondition looks at, once the unit has settled: no step due.
observe(Result, Before) ->
    case ets:lookup(?TAB, mode) of
        [{mode, parallel}] ->
            %% The command's effect is complete within the call, as linearisation needs.
            ok = cell_controller:sync(),
            ok = cell_unit:settle(?UNIT),
            Result;
        [] ->
            ok = cell_controller:sync(),
            ok = cell_unit:settle(?UNIT),
            ok = cell_controller:sync(),
            ok = cell_alarms:sync(),
            Info = cell_unit:info(?UNIT),
            #{state := Cell, estop := Estop, request := Request, has_error := HasError} =
                cell_controller:flags(),
            #{result => Result, path => Before ++ drain(),
              state => cell_unit:state(?UNIT), ipc => cell_task_proc:state(?UNIT),
              cell => Cell, seq => seq_seen(Info), error => error_seen(),
              flags => #{request => Request, estop => Estop, has_error => HasError}}
    end.

%% The sequence that waits is the one that noted itself last, awaiting the answer it
%% noted; or the unit holds one (Halt); or none runs.
seq_seen(#{sequence := #{sequences := Frames, waiting := Waiting, held := Held}}) ->
    case {cell_test_seq:pending(?TAB, ?UNIT), Waiting, Held, Frames} of
        {_, _, true, [#{step := Step}]} -> {held, Step};
        {{Key, Ref}, [{reply, Ref}], false, [_]} -> {waiting, Key};
        {_, [], false, []} -> none;
        Other -> {unexpected, Other}
    end.

error_seen() ->
    case [L || #{task := ?UNIT, kind := error, local_id := L} <- cell_alarms:list()] of
        [] -> none;
        [<<"fault">>] -> fault;
        [<<"booting">>] -> booting;
        [<<"crashed">>] -> crash;
        Other -> {unexpected, Other}
    end.

%% The unit's transitions since the last look, from its task_state events.
drain() ->
    receive
        {cell_event, #{type := task_state, task := ?UNIT} = E} ->
            case recorded(E) of
                ignore -> drain();
                R -> [R | drain()]
            end
    after 0 ->
        []
    end.

recorded(#{unit_from := undefined}) -> boot;
recorded(#{unit_from := Same, unit_state := Same}) -> ignore;     %% IPC state only
recorded(#{unit_from := From, unit_state := To}) -> {From, To};
recorded(#{cause := exited}) -> exited.

%% -------------------------------------------------------------------------------------
%% A fresh cell for each run
%% -------------------------------------------------------------------------------------

setup(Modes) ->
    Root = root(),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    _ = cell_config:ensure_root(),
    case ets:info(?TAB) of
        undefined -> _ = ets:new(?TAB, [named_table, public]), ok;
        _ -> true = ets:delete_all_objects(?TAB), ok
    end,
    Spec = cell_test_unit:spec(?UNIT, #{tab => ?TAB, modes => Modes}),
    ok = application:set_env(cell, cell_spec, #{tasks => [Spec]}),
    lager_quiet(),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe([task_state]),
    ok = cell_unit:settle(?UNIT),
    flush().

teardown() ->
    ok = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    flush().

root() ->
    case ets:info(prop_cell_unit_root) of
        undefined ->
            Dir = cell_test_dir:new("prop_cell_unit", "root"),
            _ = ets:new(prop_cell_unit_root, [named_table, public]),
            true = ets:insert(prop_cell_unit_root, {dir, Dir}),
            Dir;
        _ ->
            ets:lookup_element(prop_cell_unit_root, dir, 2)
    end.

flush() ->
    receive _ -> flush() after 0 -> ok end.

%% The crash reports of the killed units are expected: keep them off the console.
lager_quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, true),
    ok = application:set_env(lager, crash_log, false).
