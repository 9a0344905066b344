%% @doc Runs a unit's step sequences (see {@link cell_sequence}), as pure functions the
%% unit's engine ({@link cell_unit_proc}) calls with each event, carrying out the
%% effects they return: outputs to write, HAL watches and timers to arm or cancel, the
%% step entered, IPC-2541 events.
%%
%% Every call answers what the engine must do next:
%% <ul>
%% <li>`continue' — a step is due in a later cycle: send yourself a cycle message
%%     (one step per cycle, or a step coming round a second time in one go);</li>
%% <li>`wait' — nothing until a watch, timer or reply arrives (or Halt holds);</li>
%% <li>`done' — the state's sequence has finished;</li>
%% <li>`{aborted, Where, Reason}' — it was aborted (or an actuator failed): its waits
%%     are cancelled;</li>
%% <li>`estop' — a step was due but the emergency stop is active: none started;</li>
%% <li>`idle' — no sequence runs.</li>
%% </ul>
%%
%% A step's watches and its await deadline live as long as the step; the actuators'
%% as long as their command. Interrupting (Stop, a fault) cancels everything at once:
%% nothing waits for an actuator to finish.
-module(cell_sequence_runner).

-include("cell_sequence.hrl").

-export([new/1, start/4, cycle/2, event/3, set_halt/3, set_service/2, set_order/4, fail/2,
         interrupt/1, secure/1, running/1, held/1, expects/2, describe/1, where/1]).

-export_type([outcome/0, where/0, event/0]).

-type outcome() :: continue | wait | done | {aborted, where(), term()} | estop | idle.
-type where() :: #{module := module() | undefined, step := term(),
                   depth := non_neg_integer()}.
-type event() :: {watch, term(), cell_hal_type:value()} | {timer, term()}
               | {reply, reference(), term()}.
-type ret() :: {outcome(), cell_sequence:seq(), [cell_sequence:effect()]}.

%% @doc The sequences of a unit, with its actuators built from their options.
%% `read' (default `cell_hal:read/2') is given to tests; `estop' (default
%% `cell_registry:estop_active/0') by tests and by the unit, which keeps the flag.
-spec new(#{unit := atom(), io := [atom()], actuators := #{atom() => {module(), map()}},
            read => fun(), estop => fun()}) ->
          {ok, cell_sequence:seq()} | {error, {actuator, atom(), term()}}.
new(#{unit := Unit, io := Io, actuators := Specs} = Opts) ->
    Seq = #seq{unit = Unit, io = Io, read = maps:get(read, Opts, fun cell_hal:read/2),
               estop = maps:get(estop, Opts, fun cell_registry:estop_active/0)},
    Resolve = fun(P) ->
                      try {ok, cell_sequence:resolve(Seq, P)}
                      catch throw:{cell_sequence, abort, Why} -> {error, Why}
                      end
              end,
    maps:fold(fun(Name, {Mod, AOpts}, {ok, #seq{actuators = Acts} = S}) ->
                      case Mod:new(Name, AOpts, Resolve) of
                          {ok, State} -> {ok, S#seq{actuators = Acts#{Name => {Mod, State}}}};
                          {error, Why} -> {error, {actuator, Name, Why}}
                      end;
                 (_, _, Error) ->
                      Error
              end, {ok, Seq}, Specs).

%% @doc Starts a state's sequence; its first step runs now. Options: `now' (monotonic
%% ms), `haltable' (whether Halt applies), `halt', `service', `settings'.
-spec start(cell_sequence:seq(), module(), map(), map()) -> ret().
start(Seq0, Mod, Args, Opts) ->
    {Seq1, Cancel} = interrupt(Seq0),
    Seq = Seq1#seq{now = maps:get(now, Opts), haltable = maps:get(haltable, Opts, true),
                   halt = maps:get(halt, Opts, false), service = maps:get(service, Opts, false),
                   settings = maps:get(settings, Opts, #{}), effects = lists:reverse(Cancel)},
    %% The state's entry is this cycle: its first step runs now, whatever the mode;
    %% under the emergency stop the sequence does not even begin.
    case (Seq#seq.estop)() of
        true ->
            finish({estop, Seq});
        false ->
            case push(Seq, Mod, Args, undefined) of
                {ok, Seq2} -> finish(go(Seq2));
                Aborted -> finish(Aborted)
            end
    end.

%% @doc A cycle message arrived: the step that is due runs.
-spec cycle(cell_sequence:seq(), integer()) -> ret().
cycle(#seq{frames = []} = Seq, _Now) -> finish({idle, Seq});
cycle(#seq{held = true} = Seq, _Now) -> finish({wait, Seq});
cycle(#seq{now = Now} = Seq, Now) -> finish(go(Seq));     %% the same millisecond: as it is
cycle(Seq, Now) -> finish(go(Seq#seq{now = Now})).

%% @doc A watch fired, a timer elapsed, an answer came.
-spec event(cell_sequence:seq(), event(), integer()) -> ret().
event(Seq, Event, Now) ->
    finish(handle(Event, Seq#seq{now = Now})).

%% @doc Sets or releases Halt. Set, the sequence holds before its next step, or at
%% once where it only waits for IO; released, it goes on where it held, its await
%% timeout counted afresh.
-spec set_halt(cell_sequence:seq(), boolean(), integer()) -> ret().
set_halt(Seq0, true, Now) ->
    Seq = Seq0#seq{halt = true, now = Now},
    case Seq of
        #seq{frames = [_ | _], held = false, haltable = true, waiting = {Pending, _}} ->
            case io_only(Pending) andalso resumable(Seq) of
                true -> finish({wait, hold_waiting(Seq)});
                false -> finish({wait, Seq})
            end;
        _ ->
            finish({quiet(Seq), Seq})
    end;
set_halt(Seq0, false, Now) ->
    Seq = Seq0#seq{halt = false, now = Now},
    case Seq of
        #seq{held = true, fresh = true} ->
            finish(go(Seq#seq{held = false}));
        #seq{held = true} ->
            %% Held while it waited: its await timeout counts from here.
            finish(go(Seq#seq{held = false, entered = Now}));
        _ ->
            finish({quiet(Seq), Seq})
    end.

%% @doc Service mode on or off, as the steps see it.
-spec set_service(cell_sequence:seq(), boolean()) -> cell_sequence:seq().
set_service(Seq, On) -> Seq#seq{service = On}.

%% @doc A standing order of the unit given or changed (see `cell_unit:order/3'): kept
%% for every sequence, and the waiting step runs again, as for an IO change.
-spec set_order(cell_sequence:seq(), atom(), term(), integer()) -> ret().
set_order(#seq{orders = Orders} = Seq, Key, Value, Now) ->
    case maps:find(Key, Orders) of
        {ok, Value} -> finish({quiet(Seq), Seq});
        _ -> finish(rerun(Seq#seq{orders = Orders#{Key => Value}, now = Now}))
    end.

%% @doc Something the engine was to carry out failed (an output the HAL refused, a
%% watch it could not place): the sequence is aborted with that reason.
-spec fail(cell_sequence:seq(), term()) -> ret().
fail(Seq, Reason) ->
    finish(abort(Seq, Reason)).

%% @doc Stops every sequence at once (Stop, a fault, the emergency stop): their
%% watches and timers are cancelled and the actuators' commands abandoned.
-spec interrupt(cell_sequence:seq()) -> {cell_sequence:seq(), [cell_sequence:effect()]}.
interrupt(Seq0) ->
    Seq = stop_all(Seq0),
    {Seq#seq{effects = []}, lists:reverse(Seq#seq.effects)}.

%% @doc The outputs that leave the actuators safe (emergency stop, crash, shutdown).
-spec secure(cell_sequence:seq()) -> [cell_sequence:effect()].
secure(#seq{actuators = Acts}) ->
    lists:append([[{write, Key, V} || {write, Key, V} <- Mod:secure(S)]
                  || {_, {Mod, S}} <- lists:sort(maps:to_list(Acts))]).

%% @doc True while a sequence runs (waiting, held or due).
-spec running(cell_sequence:seq()) -> boolean().
running(#seq{frames = F}) -> F =/= [].

%% @doc True while Halt holds the sequence.
-spec held(cell_sequence:seq()) -> boolean().
held(#seq{held = H}) -> H.

%% @doc Whether an answer `{Ref, _}' is awaited or expected.
-spec expects(cell_sequence:seq(), reference()) -> boolean().
expects(#seq{replies = R}, Ref) -> maps:get(Ref, R, none) =:= expected.

%% @doc The running sequences, outermost first, with their steps; what the running
%% step waits for; the actuators; the standing orders the unit was given.
-spec describe(cell_sequence:seq()) -> map().
describe(#seq{frames = Frames, step = Step, waiting = Waiting, held = Held, halt = Halt,
              actuators = Acts, orders = Orders}) ->
    Steps = case Frames of
                [] -> [];
                [F | Callers] -> lists:reverse([F#frame{step = Step} | Callers])
            end,
    #{sequences => [#{module => M, step => S, mode => Mode}
                    || #frame{module = M, step = S, mode = Mode} <- Steps],
      waiting => case Waiting of
                     undefined -> [];
                     {Ops, _} -> Ops
                 end,
      halt => Halt, held => Held, orders => Orders,
      actuators => maps:map(fun(_, {Mod, S}) -> Mod:describe(S) end, Acts)}.

%% @doc Where the running sequence is.
-spec where(cell_sequence:seq()) -> where().
where(#seq{frames = []}) -> #{module => undefined, step => undefined, depth => 0};
where(#seq{frames = [#frame{module = M, depth = Depth} | _], step = S}) ->
    #{module => M, step => S, depth => Depth}.

%% -------------------------------------------------------------------------------------
%% Steps
%% -------------------------------------------------------------------------------------

%% The step that is due runs, and in several-steps mode the ones after it while their
%% conditions hold, until one waits or comes round a second time (the seed's
%% `IsNotRepeatable'). Before each, the emergency stop is checked.
%%
%% This is the path every step takes, so it is kept lean: the body is given the #seq
%% as it is (its `fresh' is on_entry/1's answer), a step entered is one update of the
%% #seq, and `Burst', the steps this go has run or is to run, is a pair of plain lists:
%% a go is a handful of steps, and lists:member/2 on them is cheaper than a map. The
%% state's own sequence's steps are kept as they are (compared at once when they are
%% atoms or integers), a sub-sequence's as `{Depth, Step}', which a step of the state's
%% own sequence could equal: so these are kept apart, `{Steps, SubSteps}'.
go(#seq{frames = [#frame{depth = 1} | _], step = Step} = Seq) ->
    go(Seq, {[Step], []});
go(#seq{frames = [#frame{depth = Depth} | _], step = Step} = Seq) ->
    go(Seq, {[], [{Depth, Step}]}).

go(#seq{estop = Estop} = Seq, Burst) ->
    case Estop() of
        true -> {estop, Seq};
        false -> run_body(Seq, Burst)
    end.

run_body(#seq{frames = [#frame{body = Body} | _], step = Step, fresh = Fresh} = Seq, Burst) ->
    case Fresh andalso Seq#seq.halt andalso Seq#seq.haltable andalso resumable(Seq) of
        true ->
            {wait, Seq#seq{held = true}};
        false ->
            Result = try Body(Step, Seq)
                     catch throw:{cell_sequence, abort, Why} -> {abort, Why, Seq}
                     end,
            result(Result, Step, Burst)
    end.

%% What the body of `Step' returned. Every result but `wait' leaves the step (see
%% leave_step/1); `wait' keeps it, its body having run (wait/3).
result({next, Next, #seq{} = Seq}, _Step, Burst) ->
    continue_or_go(enter(Seq, Next), Burst);
result({wait, Pending, Deadline, #seq{} = Seq}, _Step, _Burst) ->
    wait(Seq, Pending, Deadline);
result({done, #seq{} = Seq}, _Step, Burst) ->
    pop(Seq, Burst);
result({abort, Why, #seq{} = Seq}, _Step, _Burst) ->
    abort(Seq, Why);
result({call, Mod, Args, Next, #seq{} = Seq}, _Step, Burst) ->
    case push(leave_step(Seq), Mod, Args, Next) of
        {ok, Seq2} -> continue_or_go(Seq2, Burst);
        Aborted -> Aborted
    end;
result(Other, Step, _Burst) ->
    erlang:error({bad_step_result, Step, Other}).

%% A step was entered: in several-steps mode it runs now, unless this go has run it.
continue_or_go(#seq{frames = [#frame{mode = several, depth = 1} | _], step = Step} = Seq,
               {Steps, SubSteps}) ->
    case lists:member(Step, Steps) of
        false -> go(Seq, {[Step | Steps], SubSteps});
        true -> {continue, Seq}
    end;
continue_or_go(#seq{frames = [#frame{mode = several, depth = Depth} | _], step = Step} = Seq,
               {Steps, SubSteps}) ->
    case lists:member({Depth, Step}, SubSteps) of
        false -> go(Seq, {Steps, [{Depth, Step} | SubSteps]});
        true -> {continue, Seq}
    end;
continue_or_go(Seq, _Burst) ->
    {continue, Seq}.

%% A step is entered: the previous step's watches and deadline go.
enter(Seq0, Step) ->
    #seq{frames = [#frame{module = Mod, depth = Depth} | _], now = Now,
         effects = Effects} = Seq = leave_step(Seq0),
    Seq#seq{step = Step, fresh = true, entered = Now,
            effects = [{step, Depth, Mod, Step} | Effects]}.

leave_step(#seq{armed = Armed, latched = Latched, waiting = undefined, held = false} = Seq)
  when map_size(Armed) =:= 0, map_size(Latched) =:= 0 ->
    %% The common case of a step that waited for nothing: nothing to undo.
    Seq;
leave_step(#seq{armed = Armed} = Seq) ->
    Seq1 = maps:fold(fun(deadline, _, S) -> cell_sequence:effect(S, {cancel_timer, deadline});
                        (Key, _, S) -> cell_sequence:effect(S, {cancel_watch, Key})
                     end, Seq, Armed),
    Seq1#seq{armed = #{}, latched = #{}, waiting = undefined, held = false}.

%% A (sub-)sequence starts, its first step entered; `Next' is where its caller goes
%% on when it is done.
push(#seq{frames = Frames, step = Calling} = Seq0, Mod, Args, Next) ->
    Callers = case Frames of
                  [] -> [];
                  [Caller | Older] -> [Caller#frame{step = Calling} | Older]
              end,
    %% No step until init/2 names the first.
    Seq = Seq0#seq{frames = [#frame{module = Mod, body = fun Mod:step/2, args = Args,
                                    return = Next, depth = length(Frames) + 1} | Callers],
                   step = undefined},
    try Mod:init(Args, Seq) of
        {ok, First, #seq{frames = [F | Rest]} = Seq1} ->
            {ok, enter(Seq1#seq{frames = [F#frame{mode = mode(Mod, Args)} | Rest]}, First)}
    catch
        throw:{cell_sequence, abort, Why} -> abort(Seq, Why)
    end.

%% A (sub-)sequence is done: its caller goes on at the step it named.
pop(Seq0, Burst) ->
    #seq{frames = [#frame{return = Return} | Rest]} = Seq = end_frame(leave_step(Seq0)),
    case Rest of
        [] -> {done, Seq#seq{frames = []}};
        _ -> continue_or_go(enter(Seq#seq{frames = Rest}, Return), Burst)
    end.

%% The sequence's timers go with it.
end_frame(#seq{frames = [#frame{timers = Names} | _]} = Seq) ->
    lists:foldl(fun(Name, #seq{actuators = A} = S) ->
                        case maps:find(Name, A) of
                            {ok, {Mod, State}} ->
                                {_, Effects} = Mod:interrupt(State),
                                cell_sequence:actuator_effects(
                                  S#seq{actuators = maps:remove(Name, A)}, Name, Effects);
                            error ->
                                S
                        end
                end, Seq, Names).

abort(Seq, Why) ->
    Where = where(Seq),
    {{aborted, Where, Why}, stop_all(Seq)}.

stop_all(#seq{frames = []} = Seq0) ->
    Seq = leave_step(Seq0),
    interrupt_actuators(Seq#seq{replies = #{}, held = false});
stop_all(Seq0) ->
    #seq{frames = [_ | Rest]} = Seq = end_frame(leave_step(Seq0)),
    stop_all(Seq#seq{frames = Rest}).

interrupt_actuators(#seq{actuators = Acts} = Seq) ->
    maps:fold(fun(Name, {Mod, S}, Acc) ->
                      {S1, Effects} = Mod:interrupt(S),
                      cell_sequence:actuator_effects(
                        Acc#seq{actuators = (Acc#seq.actuators)#{Name => {Mod, S1}}},
                        Name, Effects)
              end, Seq, Acts).

%% The step waits: its IO conditions are watched, its deadline armed (each once).
wait(#seq{armed = Armed0, now = Now} = Seq0, Pending, Deadline) ->
    Seq1 = lists:foldl(fun({io, _, Cond} = Op, #seq{armed = A} = S) ->
                               {io, G, P, _} = Key = cell_sequence:op_key(S, Op),
                               case maps:is_key(Key, A) of
                                   true -> S;
                                   false -> cell_sequence:effect(S#seq{armed = A#{Key => true}},
                                                                 {watch, Key, {G, P}, Cond})
                               end;
                          (_, S) ->
                               S
                       end, Seq0, Pending),
    Seq2 = case {Deadline, maps:find(deadline, Armed0)} of
               {infinity, _} -> Seq1;
               {{At, _}, {ok, At}} -> Seq1;
               {{At, _}, _} ->
                   cell_sequence:effect(Seq1#seq{armed = (Seq1#seq.armed)#{deadline => At}},
                                        {timer, deadline, max(0, At - Now)})
           end,
    Seq = Seq2#seq{waiting = {Pending, Deadline}, fresh = false},
    case Seq#seq.halt andalso Seq#seq.haltable andalso io_only(Pending)
        andalso resumable(Seq) of
        true -> {wait, hold_waiting(Seq)};
        false -> {wait, Seq}
    end.

%% Halt takes hold of a step that only waits for IO: nothing of ours moves, so the
%% unit can stay here; the step's body runs again at resume.
hold_waiting(#seq{armed = Armed} = Seq) ->
    Seq1 = maps:fold(fun(deadline, _, S) -> cell_sequence:effect(S, {cancel_timer, deadline});
                        (Key, _, S) -> cell_sequence:effect(S, {cancel_watch, Key})
                     end, Seq, Armed),
    Seq1#seq{armed = #{}, held = true}.

%% Actuators, timers and answers are operations under way; IO conditions and orders
%% are not ours.
io_only(Pending) ->
    lists:all(fun({io, _, _}) -> true; ({order, _, _}) -> true; (_) -> false end, Pending).

%% -------------------------------------------------------------------------------------
%% Events
%% -------------------------------------------------------------------------------------

handle({watch, {io, _, _, _} = Key, V}, #seq{armed = A, latched = L} = Seq) ->
    case maps:is_key(Key, A) of
        true -> rerun(Seq#seq{armed = maps:remove(Key, A), latched = L#{Key => V}});
        false -> {quiet(Seq), Seq}
    end;
handle({watch, {act, Name, Tag}, V}, Seq) ->
    actuator(Seq, Name, {watch, Tag, V});
handle({timer, {act, Name, Tag}}, Seq) ->
    actuator(Seq, Name, {timer, Tag});
handle({timer, deadline}, #seq{waiting = {Pending, {_, Ms}}, held = false,
                               frames = [_ | _], step = Step, armed = A} = Seq) ->
    abort(Seq#seq{armed = maps:remove(deadline, A)}, {await_timeout, Step, Pending, Ms});
handle({timer, deadline}, Seq) ->
    {quiet(Seq), Seq};
handle({reply, Ref, Term}, #seq{replies = R} = Seq) ->
    case maps:find(Ref, R) of
        {ok, expected} -> rerun(Seq#seq{replies = R#{Ref => {Term}}});
        _ -> {quiet(Seq), Seq}
    end.

%% An actuator's watch or timer: it may be done (the step waiting runs again) or have
%% failed (the running sequence is aborted, awaited or not).
actuator(#seq{actuators = Acts} = Seq, Name, Event) ->
    case maps:find(Name, Acts) of
        {ok, {Mod, S}} ->
            Before = Mod:status(S),
            {S1, Effects} = Mod:event(Event, S),
            Seq1 = cell_sequence:actuator_effects(Seq#seq{actuators = Acts#{Name => {Mod, S1}}},
                                                  Name, Effects),
            case {Before, Mod:status(S1)} of
                {{error, _}, _} -> rerun(Seq1);
                {_, {error, Why}} -> abort(Seq1, {actuator, Name, Mod, Why});
                _ -> rerun(Seq1)
            end;
        error ->
            {quiet(Seq), Seq}
    end.

%% Something the waiting step may be waiting for has happened: its body runs again.
rerun(#seq{waiting = {_, _}, held = false} = Seq) -> go(Seq);
rerun(Seq) -> {quiet(Seq), Seq}.

quiet(#seq{frames = []}) -> idle;
quiet(_) -> wait.

%% -------------------------------------------------------------------------------------

finish({Outcome, #seq{effects = E} = Seq}) ->
    {Outcome, Seq#seq{effects = []}, lists:reverse(E)}.

%% Whether the sequence may hold before the step it is in.
resumable(#seq{frames = [#frame{module = Mod} | _], step = Step}) ->
    case erlang:function_exported(Mod, resumable, 1) of
        true -> Mod:resumable(Step);
        false -> true
    end.

mode(Mod, Args) ->
    case maps:find(mode, Args) of
        {ok, M} when M =:= several; M =:= one -> M;
        {ok, Bad} -> erlang:error({bad_sequence_mode, Mod, Bad});
        error ->
            case erlang:function_exported(Mod, mode, 0) of
                true -> Mod:mode();
                false -> several
            end
    end.
