%% A PropEr state-machine property of device tasks and the controller. The model is
%% written from seed 000: the state table of §2.2 (arrows 0-9, cited below), the events
%% of §2.3.4, the control interface of §2.3.1 and the error solutions of §2.3.8 — never
%% by calling the code under test. Real task processes (cell_test_task) run under the
%% real controller; every command is followed by cell_controller:sync/0, so the
%% observed states are settled.
%%
%% Postconditions: every task's state, the cell state, the flags, and the exact number
%% of init, step and uninit calls of every task — so a step that runs after a stop or
%% an emergency stop, or a missing uninit, is caught.
-module(prop_cell_task).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([start/0, pause/0, stop/0, estop/1, service/1, event/2, raise_error/2, answer/2,
         set_init/2, reset/1, crash/1, kill/1, product/2]).

-define(TASKS, [t1, t2, t3]).
-define(STARVED, {ready, idle, starved}).
-define(BLOCKED, {ready, idle, blocked}).
-define(ACTIVE, {ready, processing, active}).
-define(EXECUTING, {ready, processing, executing}).

%% One task in the model.
-record(t, {st = off,              %% IPC-2541 state
            err = none,            %% none | {Origin, Solutions}: an error waiting in DOWN
            resume,                %% the READY sub-state a paused task returns to
            resume_step = false,   %% an answered error: a step runs at resume
            product = false,       %% the task holds a product
            initialized = false,   %% init ran, uninit has not
            init_result = ok,      %% what the next init returns
            auto = false,          %% went on by itself after a crash, no step since
            inits = 0, steps = 0, uninits = 0}).

-record(m, {tasks = #{} :: #{atom() => #t{}},
            request = stop, estop = false, service = false}).

%% -------------------------------------------------------------------------------------
%% Properties, run inside eunit
%% -------------------------------------------------------------------------------------

sequential_test_() ->
    {timeout, 600, ?_assert(proper:quickcheck(prop_sequential(),
                                              [{to_file, user}, {numtests, 150}]))}.

parallel_test_() ->
    {timeout, 600, ?_assert(proper:quickcheck(prop_parallel(),
                                              [{to_file, user}, {numtests, 60}]))}.

prop_sequential() ->
    ?FORALL(Cmds, commands(?MODULE),
            begin
                setup(),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                teardown(),
                ?WHENFAIL(io:format(user, "History: ~p~nState: ~p~nResult: ~p~n",
                                    [History, State, Result]),
                          aggregate(command_names(Cmds), Result =:= ok))
            end).

%% Parallel: commands race each other (see prop_cell_task_par for which); PropEr checks
%% that some interleaving explains every answer. Afterwards the settled cell must satisfy the invariants the seed
%% implies whatever the interleaving was.
prop_parallel() ->
    ?FORALL(Cmds, parallel_commands(prop_cell_task_par),
            begin
                setup(),
                true = ets:insert(tab(), {mode, parallel}),
                {Seq, Par, Result} = run_parallel_commands(prop_cell_task_par, Cmds),
                ok = cell_controller:sync(),
                Invariants = invariants(),
                teardown(),
                ?WHENFAIL(io:format(user, "Seq: ~p~nPar: ~p~nResult: ~p~nInvariants: ~p~n",
                                    [Seq, Par, Result, Invariants]),
                          Result =:= ok andalso Invariants =:= ok)
            end).

%% -------------------------------------------------------------------------------------
%% Model
%% -------------------------------------------------------------------------------------

initial_state() ->
    #m{tasks = maps:from_list([{Id, #t{}} || Id <- ?TASKS])}.

command(#m{tasks = Tasks} = M) ->
    Ready = [Id || {Id, #t{st = {ready, _, _}}} <- maps:to_list(Tasks)],
    Waiting = [Id || {Id, #t{err = {_, _}}} <- maps:to_list(Tasks)],
    Id = elements(?TASKS),
    frequency(
      [{4, {call, ?MODULE, start, []}},
       {2, {call, ?MODULE, pause, []}},
       {2, {call, ?MODULE, stop, []}},
       {1, {call, ?MODULE, estop, [not M#m.estop]}},
       {1, {call, ?MODULE, service, [bool()]}},
       {2, {call, ?MODULE, set_init, [Id, oneof([ok, {error, solutions()}])]}},
       {1, {call, ?MODULE, kill, [Id]}},
       {1, {call, ?MODULE, answer, [Id, elements(cell_alarms:solutions())]}}]
      ++ [{8, {call, ?MODULE, event, [elements(Ready), event()]}} || Ready =/= []]
      ++ [{3, {call, ?MODULE, raise_error, [elements(Ready), solutions()]}} || Ready =/= []]
      ++ [{1, {call, ?MODULE, reset, [elements(Ready)]}} || Ready =/= []]
      ++ [{1, {call, ?MODULE, crash, [elements(Ready)]}} || Ready =/= []]
      ++ [{2, {call, ?MODULE, product, [elements(Ready), bool()]}} || Ready =/= []]
      ++ [{6, {call, ?MODULE, answer, [elements(Waiting), elements(cell_alarms:solutions())]}}
          || Waiting =/= []]).

event() ->
    elements([starved, unstarved, blocked, unblocked, work_start, work_complete,
              {work_pause, <<"p">>}, work_resume, {work_abort, <<"a">>},
              {transfer_in, <<"S1">>}, {transfer_out, <<"S1">>},
              {identifier_read, <<"S1">>}]).

solutions() ->
    ?LET(S, non_empty(list(elements(cell_alarms:solutions()))), lists:usort(S)).

precondition(#m{tasks = Tasks}, {call, _, Cmd, [Id | _]})
  when Cmd =:= event; Cmd =:= raise_error; Cmd =:= reset; Cmd =:= crash; Cmd =:= product ->
    is_ready((maps:get(Id, Tasks))#t.st);
precondition(_M, _Call) ->
    true.

%% The model's transitions.
next_state(M, _Res, {call, _, start, []}) ->
    case M#m.estop of
        true -> M;                                         %% refused
        false -> each(fun start_task/2, M#m{request = start})
    end;
next_state(M, _Res, {call, _, pause, []}) ->
    each(fun(T, _) -> pause_task(T) end, M#m{request = pause});
next_state(M, _Res, {call, _, stop, []}) ->
    each(fun(T, _) -> stop_task(T) end, M#m{request = stop});
next_state(M, _Res, {call, _, estop, [true]}) ->
    %% Any state → OFF at once, uninit run, error gone; Start needed afterwards.
    each(fun(#t{st = off} = T, _) -> T;
            (T, _) -> (uninit(T))#t{st = off, err = none, resume = undefined,
                                    resume_step = false}
         end, M#m{estop = true, request = stop});
next_state(M, _Res, {call, _, estop, [false]}) ->
    M#m{estop = false};
next_state(M, _Res, {call, _, service, [true]}) ->
    %% Service mode: DOWN after the current motion (arrow 6), like Pause.
    each(fun(T, _) -> pause_task(T) end, M#m{service = true});
next_state(M, _Res, {call, _, service, [false]}) ->
    M#m{service = false};
next_state(M, _Res, {call, _, set_init, [Id, Result]}) ->
    update(Id, fun(T) -> T#t{init_result = Result} end, M);
next_state(M, _Res, {call, _, event, [Id, Event]}) ->
    update(Id, fun(#t{st = S} = T) -> step(T#t{st = event_state(Event, S)}) end, M);
next_state(M, _Res, {call, _, raise_error, [Id, Solutions]}) ->
    %% Arrow 6: an error in READY.
    update(Id, fun(#t{st = S} = T) ->
                       (step(T))#t{st = down, err = {step, Solutions}, resume = S}
               end, M);
next_state(M, _Res, {call, _, product, [Id, Has]}) ->
    update(Id, fun(T) -> (step(T))#t{product = Has} end, M);
next_state(M, _Res, {call, _, reset, [Id]}) ->
    %% Arrow 2: ResetException: uninit, SETUP, init again.
    update(Id, fun(T) -> init(uninit(step(T)), M) end, M);
next_state(M, _Res, {call, _, crash, [Id]}) ->
    %% The step crashes; the dying task secures its outputs, so does its restart.
    update(Id, fun(T) -> restart(uninit(step(T)), M) end, M);
next_state(M, _Res, {call, _, kill, [Id]}) ->
    update(Id, fun(T) -> restart(T, M) end, M);
next_state(M, _Res, {call, _, answer, [Id, Solution]}) ->
    #t{err = Err} = maps:get(Id, M#m.tasks),
    case Err of
        {Origin, Solutions} ->
            case lists:member(Solution, Solutions) of
                true -> update(Id, fun(T) -> answered(Origin, Solution, T#t{err = none}, M) end, M);
                false -> M
            end;
        none ->
            M
    end.

%% Start: OFF → SETUP (arrow 0) → init; a paused task resumes (arrow 5).
start_task(#t{st = off} = T, M) ->
    init(T, M);
start_task(#t{st = down, err = none, resume = R, resume_step = Step} = T, _M) ->
    T1 = T#t{st = R, resume = undefined, resume_step = false},
    case Step of true -> step(T1); false -> T1 end;
start_task(T, _M) ->
    T.

%% Pause: READY → DOWN (arrow 6).
pause_task(#t{st = {ready, _, _} = S} = T) -> T#t{st = down, resume = S};
pause_task(T) -> T.

%% Stop: READY → DOWN (6) → OFF (9); DOWN → OFF (9), through uninit.
stop_task(#t{st = off} = T) -> T;
stop_task(T) -> (uninit(T))#t{st = off, err = none, resume = undefined, resume_step = false}.

%% SETUP: init succeeded → READY (arrow 1) and the first step; failed → DOWN (arrow 7).
%% A Pause pending meanwhile holds the task at its first step boundary (arrow 6).
init(#t{init_result = Result} = T0, M) ->
    T = T0#t{inits = T0#t.inits + 1, initialized = true},
    case Result of
        {error, Solutions} -> T#t{st = down, err = {init, Solutions}};
        ok -> first_step(T#t{st = initial(T)}, M)
    end.

first_step(#t{st = S} = T, #m{request = start}) -> step(T#t{st = S});
first_step(#t{st = S} = T, #m{request = pause}) ->
    T#t{st = down, resume = S, resume_step = true}.

initial(#t{product = true}) -> ?ACTIVE;
initial(#t{product = false}) -> ?STARVED.

%% Answers (seed 000 §2.3.8).
answered(step, reset, T, M) ->
    init(uninit(T), M);                                    %% arrow 8
answered(step, _RetryIgnoreClose, #t{resume = R} = T, #m{request = start}) ->
    step(T#t{st = R, resume = undefined});                 %% arrow 5: the step goes on
answered(step, _RetryIgnoreClose, T, #m{request = pause}) ->
    T#t{resume_step = true};                               %% stays DOWN, paused
answered(init, retry, T, M) ->
    init(T, M);                                            %% arrow 8
answered(init, reset, T, M) ->
    init(uninit(T), M);                                    %% arrow 8
answered(init, _IgnoreClose, T, M) ->
    first_step(T#t{st = initial(T)}, M);                   %% arrow 5
answered(crash, reset, T, M) ->
    init(T#t{product = false}, M);                         %% arrow 8, product forgotten
answered(crash, _Retry, T, M) ->
    init(T, M).                                            %% arrow 8

%% A restarted task: outputs secured. If the cell runs, it initialises and reconciles
%% (the test task's reconcile agrees) and goes on by itself, as after a Retry; the
%% operator is asked (DOWN, an error) only when it crashes again after going on by
%% itself before its first step waited.
restart(T0, #m{request = Request, estop = Estop} = M) ->
    T = (uninit(T0#t{initialized = true}))#t{err = none, resume = undefined,
                                             resume_step = false},
    case Request =/= stop andalso not Estop of
        true when T0#t.auto -> T#t{st = down, err = {crash, [retry, reset]}};
        true -> init(T#t{auto = true}, M);
        false -> T#t{st = off}
    end.

uninit(#t{initialized = true, uninits = N} = T) -> T#t{uninits = N + 1, initialized = false};
uninit(T) -> T.

step(#t{steps = N} = T) -> T#t{steps = N + 1, auto = false}.

%% Seed 000 §2.3.4.
event_state(starved, _) -> ?STARVED;
event_state(unstarved, _) -> ?ACTIVE;
event_state(blocked, _) -> ?BLOCKED;
event_state(unblocked, _) -> ?ACTIVE;
event_state(work_start, _) -> ?EXECUTING;
event_state({work_pause, _}, _) -> ?ACTIVE;
event_state(work_resume, _) -> ?EXECUTING;
event_state(work_complete, _) -> ?ACTIVE;
event_state(_NoChange, S) -> S.

%% Seed 000 §2.2: OFF lowest, EXECUTING highest.
priority(off) -> 0;
priority(down) -> 1;
priority(setup) -> 2;
priority(?BLOCKED) -> 3;
priority(?STARVED) -> 4;
priority(?ACTIVE) -> 5;
priority(?EXECUTING) -> 6.

is_ready({ready, _, _}) -> true;
is_ready(_) -> false.

each(F, #m{tasks = Tasks} = M) ->
    M#m{tasks = maps:map(fun(_, T) -> F(T, M) end, Tasks)}.

update(Id, F, #m{tasks = Tasks} = M) ->
    M#m{tasks = maps:put(Id, F(maps:get(Id, Tasks)), Tasks)}.

%% Sequential runs compare everything observed; parallel runs only what each call
%% answered (a snapshot taken while other commands run cannot be linearised).
postcondition(M, {call, _, Cmd, Args}, Res) ->
    M1 = next_state(M, Res, {call, ?MODULE, Cmd, Args}),
    Expected = expected_result(M, Cmd, Args),
    Verdict = case Res of
                  #{result := Expected} = Obs -> matches(M1, Obs);
                  #{result := Other} -> {result, Cmd, Args, expected, Expected, got, Other};
                  Expected -> true;
                  _ -> false        %% parallel: another interleaving may explain it
              end,
    case Verdict of
        true -> true;
        false -> false;
        Why -> io:format(user, "~nPostcondition of ~p~p failed:~n~p~n", [Cmd, Args, Why]),
               false
    end.

expected_result(#m{estop = true}, start, []) -> {error, estop_active};
expected_result(M, answer, [Id, Solution]) ->
    case (maps:get(Id, M#m.tasks))#t.err of
        none -> {error, not_found};
        {_, Solutions} ->
            case lists:member(Solution, Solutions) of
                true -> ok;
                false -> {error, {not_allowed, Solutions}}
            end
    end;
expected_result(_, _, _) -> ok.

matches(#m{tasks = Tasks} = M, #{tasks := Observed, cell := Cell, flags := Flags}) ->
    Mismatch = [{Id, expected, model_view(T), got, maps:get(Id, Observed)}
                || {Id, T} <- maps:to_list(Tasks), model_view(T) =/= maps:get(Id, Observed)],
    ExpectedCell = lists:foldl(fun(#t{st = S}, Acc) ->
                                       case priority(S) > priority(Acc) of
                                           true -> S;
                                           false -> Acc
                                       end
                               end, off, maps:values(Tasks)),
    ExpectedFlags = #{estop => M#m.estop, request => M#m.request,
                      has_error => lists:any(fun(#t{err = E}) -> E =/= none end,
                                             maps:values(Tasks))},
    case {Mismatch, Cell =:= ExpectedCell, Flags =:= ExpectedFlags} of
        {[], true, true} -> true;
        _ -> {mismatch, Mismatch, cell, Cell, ExpectedCell, flags, Flags, ExpectedFlags}
    end.

model_view(#t{st = S, inits = I, steps = St, uninits = U, err = E}) ->
    #{state => S, inits => I, steps => St, uninits => U,
      error => case E of none -> none; {Origin, _} -> Origin end}.

%% -------------------------------------------------------------------------------------
%% Commands against the real cell
%% -------------------------------------------------------------------------------------

start() -> observe(cell_controller:start()).
pause() -> observe(cell_controller:pause()).
stop() -> observe(cell_controller:stop()).
estop(On) -> observe(cell_controller:estop(On)).
service(On) -> observe(cell_controller:service_mode(On)).

set_init(Id, Result) ->
    true = ets:insert(tab(), {{init_result, Id}, Result}),
    observe(ok).

event(Id, Event) -> command(Id, {event, Event}).
raise_error(Id, Solutions) -> command(Id, {error, Solutions}).
reset(Id) -> command(Id, reset).
product(Id, true) -> command(Id, {product, cell_product:new(<<"S-", (atom_to_binary(Id, utf8))/binary>>, <<"r">>)});
product(Id, false) -> command(Id, {product, undefined}).

crash(Id) ->
    ok = cell_events:subscribe([task_crashed]),
    Pid = cell_task_proc:whereis(Id),
    Ref = monitor(process, Pid),
    ok = cell_test_task:command(Id, ref(Id), crash),
    await_restart(Id, Ref).

kill(Id) ->
    ok = cell_events:subscribe([task_crashed]),
    case cell_task_proc:whereis(Id) of
        undefined ->
            %% A concurrent kill: the task is restarting; its restart is this one's too.
            await_crashed(Id),
            observe(ok);
        Pid ->
            Ref = monitor(process, Pid),
            exit(Pid, kill),
            await_restart(Id, Ref)
    end.

%% The restarted task publishes task_crashed while it boots; then it is settled after
%% a sync.
await_restart(Id, Ref) ->
    receive {'DOWN', Ref, process, _, _} -> ok after 5000 -> erlang:error(no_down) end,
    await_crashed(Id),
    observe(ok).

await_crashed(Id) ->
    receive
        {cell_event, #{type := task_crashed, task := Id}} -> ok
    after 5000 ->
        erlang:error({no_restart, Id})
    end.

answer(Id, Solution) ->
    observe(cell_alarms:answer(alarm_id(Id), Solution, <<"prop">>)).

alarm_id(Id) ->
    case [A || #{task := T, kind := error, id := A} <- cell_alarms:list(), T =:= Id] of
        [A] -> A;
        [] -> <<(atom_to_binary(Id, utf8))/binary, ":none">>
    end.

command(Id, Command) ->
    ok = cell_test_task:command(Id, ref(Id), Command),
    observe(ok).

%% What every postcondition looks at, after the cell has settled.
observe(Result) ->
    case ets:lookup(tab(), mode) of
        [{mode, parallel}] ->
            %% The command's effect happens within the call, as linearisation needs.
            ok = cell_controller:sync(),
            Result;
        [] ->
            observe_all(Result)
    end.

observe_all(Result) ->
    ok = cell_controller:sync(),
    Tab = tab(),
    Tasks = maps:from_list(
              [{Id, begin
                        C = cell_test_task:counts(Tab, Id),
                        Err = case [O || #{task := T, kind := error, local_id := O}
                                             <- cell_alarms:list(), T =:= Id] of
                                  [] -> none;
                                  [<<"step">>] -> step;
                                  [<<"init">>] -> init;
                                  [<<"crashed">>] -> crash
                              end,
                        #{state => cell_task_proc:state(Id), inits => maps:get(init, C),
                          steps => maps:get(step, C), uninits => maps:get(uninit, C),
                          error => Err}
                    end} || Id <- ?TASKS]),
    #{state := Cell, estop := Estop, request := Request, has_error := HasError} =
        cell_controller:flags(),
    #{result => Result, tasks => Tasks, cell => Cell,
      flags => #{estop => Estop, request => Request, has_error => HasError}}.

%% -------------------------------------------------------------------------------------
%% Invariants after a parallel run
%% -------------------------------------------------------------------------------------

invariants() ->
    #{state := Cell, estop := Estop, request := Request} = cell_controller:flags(),
    States = [cell_task_proc:state(Id) || Id <- ?TASKS],
    Errors = [Id || #{task := Id, kind := error} <- cell_alarms:list()],
    Down = [Id || Id <- ?TASKS, cell_task_proc:state(Id) =:= down],
    Checks =
        [{estop_means_off, not Estop orelse lists:all(fun(S) -> S =:= off end, States)},
         {stop_means_off, Request =/= stop orelse lists:all(fun(S) -> S =:= off end, States)},
         {pause_means_not_ready, Request =/= pause orelse not lists:any(fun is_ready/1, States)},
         {cell_state_is_highest, Cell =:= lists:foldl(fun(S, A) ->
                                                              case priority(S) > priority(A) of
                                                                  true -> S;
                                                                  false -> A
                                                              end
                                                      end, off, States)},
         {errors_only_when_down, lists:all(fun(Id) -> lists:member(Id, Down) end, Errors)},
         {one_error_per_task, length(Errors) =:= length(lists:usort(Errors))}],
    case [Name || {Name, false} <- Checks] of
        [] -> ok;
        Failed -> {failed, Failed, States, Request, Estop, Cell}
    end.

%% -------------------------------------------------------------------------------------
%% A fresh cell for each run
%% -------------------------------------------------------------------------------------

setup() ->
    Root = filename:join(["/tmp", "prop_cell_task", os:getpid()]),
    %% No product of an earlier run may be found by this one.
    _ = os:cmd("rm -rf '" ++ Root ++ "/Data'"),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    _ = cell_config:ensure_root(),
    Tab = case ets:info(prop_cell_task_tab) of
              undefined -> ets:new(prop_cell_task_tab, [named_table, public]);
              _ -> ets:delete_all_objects(prop_cell_task_tab), prop_cell_task_tab
          end,
    Specs = [cell_test_task:spec(Id, Tab, self()) || Id <- ?TASKS],
    true = ets:insert(Tab, [{{ref, Id}, maps:get(ref, maps:get(args, S))}
                            || #{id := Id} = S <- Specs]),
    ok = application:set_env(cell, cell_spec, #{tasks => Specs}),
    lager_quiet(),
    {ok, _} = application:ensure_all_started(cell),
    flush().

teardown() ->
    ok = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    flush().

tab() -> prop_cell_task_tab.

ref(Id) -> ets:lookup_element(tab(), {ref, Id}, 2).

flush() ->
    receive _ -> flush() after 0 -> ok end.

%% The crash reports of the scripted crashes are expected: keep them off the console.
lager_quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, true),
    ok = application:set_env(lager, crash_log, false).

