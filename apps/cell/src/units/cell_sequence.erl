%% @doc Step sequences (seed 001): the behaviour of a sequence module and the functions
%% its steps use on the `seq()' they are given.
%%
%% A unit runs one sequence per state (GoHome, Automatic, Stop, a user state, an
%% action ...; see {@link cell_unit}). A sequence is a module whose steps are the
%% branches of the seed's `CASE _step.Index OF':
%%
%% ```
%% -module(picker_automatic).
%% -behaviour(cell_sequence).
%% -export([init/2, step/2]).
%%
%% init(_Args, Seq) -> {ok, automatic_begin, Seq}.          % OnStart
%%
%% step(automatic_begin, Seq) ->
%%     cell_sequence:next(Seq, begin_vertical_up);           % SetNext
%% step(begin_vertical_up, Seq0) ->
%%     Seq = cell_sequence:on_entry(Seq0, fun(S) ->            % IF _step.OnEntry()
%%                                                cell_cylinder:move_up(S, vertical_lift)
%%                                        end),
%%     cell_sequence:await(Seq, vertical_lift, wait_part_at_end);
%% step(wait_part_at_end, Seq) ->
%%     cell_sequence:await(Seq, {io, part_is_at_end, {eq, true}}, move_right);
%% ...
%% step(Other, Seq) ->
%%     cell_sequence:abort(Seq, {unhandled_step, Other}).
%% '''
%%
%% A step's body runs when the step is entered (`on_entry/1' is true then) and again
%% whenever something it waits for happens: the seed's cyclic evaluation, driven by
%% messages instead of a PLC cycle, so a waiting sequence costs nothing. A body
%% returns what comes next, built by these functions:
%%
%% <ul>
%% <li>{@link next/2} — SetNext: the step to go to.</li>
%% <li>{@link await/3}, {@link await/4}, {@link await2/4} — Await / Await2: the next step
%% once every operation is done; the sequence is aborted if one fails, and if the
%% optional timeout (ms from entering the step) passes first. An operation is an
%% actuator or timer by name (done when its last command is), `{io, Point, Cond}' (an
%% IO point reached a condition, see `cell_hal:watch/3'; `Point' is a name in the
%% unit's first IO group or `{Group, Name}'), or `{reply, Ref}' (the unit received
%% `{Ref, Term}', an answer to a request the step made; {@link reply/2} gives it), or
%% `{order, Key, {eq | ne, Value}}' (the unit's standing order `Key', given from
%% outside with `cell_unit:order/3', is, or is not, `Value'; none given is `undefined';
%% {@link order/3} reads it).</li>
%% <li>{@link done/1} — the sequence has finished (the seed's SetBusy(FALSE)): the unit's
%% state is done.</li>
%% <li>{@link abort/2} — Abort(Reason): the unit goes into FaultReaction, the reason
%% shown to the operator (see {@link format_reason/1}).</li>
%% <li>{@link call/4} — runs a sub-sequence, then goes on at the given step; an abort in it
%% aborts the caller.</li>
%% </ul>
%%
%% Several steps in one go, or one per cycle (the seed's REPEAT loop, or without it):
%% `mode/0' returns `several' (the default) or `one'; `mode' in the sequence's args
%% overrides it. With `several', a step whose condition already holds leads straight
%% into the next, until a step waits or comes round a second time; with `one', each
%% step's body runs in its own event, so other events interleave.
%%
%% Halt (seed 001): a flag on the running sequence and its sub-sequences. The sequence
%% holds before entering its next step (a resumable point), or at once while it only
%% waits for IO conditions, and goes on where it was when Halt is released.
%% `resumable(Step)' (optional, default true) says whether the sequence may hold
%% before entering `Step'; {@link halted/1} lets a step react sooner.
%%
%% Outputs ({@link out/3}) and actuator commands are carried out by the unit's engine
%% once the step has returned, in order; reads ({@link in/2}, {@link read/2}) read the
%% HAL's table directly.
-module(cell_sequence).

-include("cell_sequence.hrl").

-export([on_entry/1, on_entry/2, step/1, unit/1, args/1, arg/3, get/2, get/3, put/3, halted/1,
         service_mode/1, settings/1, setting/3]).
-export([next/2, await/3, await/4, await2/4, done/1, abort/2, call/4]).
-export([in/2, read/2, out/3, command/3, local_actuator/4, reply/2, expect_reply/2,
         order/3]).
-export([starved/1, unstarved/1, blocked/1, unblocked/1, work_start/1, work_complete/1]).
-export([log/4, format_reason/1]).
%% For the runner and actuators.
-export([resolve/2, effect/2, actuator_effects/3, op_key/2]).

-export_type([seq/0, result/0, op/0, point/0, effect/0]).

-type seq() :: #seq{}.
-type point() :: atom() | {atom(), atom()}.
-type op() :: atom() | {io, point(), cell_hal_type:condition()} | {reply, reference()}
            | {order, atom(), {eq | ne, term()}}.
-type deadline() :: infinity | {integer(), non_neg_integer()}.
-type result() :: {next, term(), seq()}
                | {wait, [op()], deadline(), seq()}
                | {done, seq()}
                | {abort, term(), seq()}
                | {call, module(), map(), term(), seq()}.
%% What the engine carries out for a sequence or an actuator; keys tell it which
%% watch or timer a later message belongs to.
-type effect() :: {write, {atom(), atom()}, cell_hal_type:value()}
                | {watch, term(), {atom(), atom()}, cell_hal_type:condition()}
                | {cancel_watch, term()}
                | {timer, term(), non_neg_integer()}
                | {cancel_timer, term()}
                | {step, pos_integer(), module(), term()}
                | {ipc, cell_ipc:event()}.

-callback init(Args :: map(), seq()) -> {ok, FirstStep :: term(), seq()}.
-callback step(Step :: term(), seq()) -> result().
-callback mode() -> several | one.
-callback resumable(Step :: term()) -> boolean().
-optional_callbacks([mode/0, resumable/1]).

-define(ABORT(Reason), throw({?MODULE, abort, Reason})).

%% -------------------------------------------------------------------------------------
%% The step and its sequence
%% -------------------------------------------------------------------------------------

%% @doc True the first time a step's body runs after the step was entered (the seed's
%% `_step.OnEntry()'): start the step's operations here.
-spec on_entry(seq()) -> boolean().
on_entry(#seq{fresh = F}) -> F.

%% @doc `IF _step.OnEntry() THEN ... END_IF': applies `Fun' to the sequence the first
%% time the step's body runs, and gives the sequence back unchanged after that.
%% ```
%% step(begin_vertical_up, Seq) ->
%%     Seq1 = cell_sequence:on_entry(Seq, fun(S) -> cell_cylinder:move_up(S, vertical_lift) end),
%%     cell_sequence:await(Seq1, vertical_lift, wait_part_at_end);
%% '''
-spec on_entry(seq(), fun((seq()) -> seq())) -> seq().
on_entry(#seq{fresh = true} = Seq, Fun) -> Fun(Seq);
on_entry(Seq, _Fun) -> Seq.

%% @doc The step the sequence is in.
-spec step(seq()) -> term().
step(#seq{step = S}) -> S.

%% @doc The unit's id (the source of its log lines).
-spec unit(seq()) -> atom().
unit(#seq{unit = U}) -> U.

%% @doc The arguments the unit gave the sequence.
-spec args(seq()) -> map().
args(#seq{frames = [#frame{args = A} | _]}) -> A.

%% @doc An argument of the running sequence, or `Default'.
-spec arg(seq(), term(), term()) -> term().
arg(#seq{frames = [#frame{args = A} | _]}, Key, Default) -> value(Key, A, Default).

%% @doc A variable of the running sequence (the seed's VAR section).
-spec get(seq(), term()) -> term().
get(#seq{frames = [#frame{vars = V} | _]}, Key) -> maps:get(Key, V).

%% @doc A variable of the running sequence, or `Default' when it has none.
-spec get(seq(), term(), term()) -> term().
get(#seq{frames = [#frame{vars = V} | _]}, Key, Default) -> value(Key, V, Default).

%% @doc Sets a variable of the running sequence.
-spec put(seq(), term(), term()) -> seq().
put(#seq{frames = [#frame{vars = V} = F | Rest]} = Seq, Key, Value) ->
    Seq#seq{frames = [F#frame{vars = V#{Key => Value}} | Rest]}.

%% @doc True while Halt is asked of this sequence: react as soon as possible, leaving
%% the unit where it can go on from.
-spec halted(seq()) -> boolean().
halted(#seq{halt = H, haltable = A}) -> H andalso A.

%% @doc True in service mode: movements must be limited to harmless speeds.
-spec service_mode(seq()) -> boolean().
service_mode(#seq{service = S}) -> S.

%% @doc The unit's settings, as the snapshot taken at the last Start.
-spec settings(seq()) -> map().
settings(#seq{settings = S}) -> S.

%% @doc A field of the unit's settings, or `Default'.
-spec setting(seq(), term(), term()) -> term().
setting(#seq{settings = S}, Key, Default) -> value(Key, S, Default).

%% -------------------------------------------------------------------------------------
%% What comes next
%% -------------------------------------------------------------------------------------

%% @doc SetNext: go to `Step'.
-spec next(seq(), term()) -> result().
next(Seq, Step) -> {next, Step, Seq}.

%% @doc Await: `Next' once every operation is done; an operation that fails aborts the
%% sequence with its error.
-spec await(seq(), op() | [op()], term()) -> result().
await(Seq, Ops, Next) -> await(Seq, Ops, Next, infinity).

%% @doc Await with a timeout, counted from entering the step: if it passes first, the
%% sequence is aborted, naming the step and what it waited for.
-spec await(seq(), op() | [op()], term(), timeout()) -> result().
await(Seq, Ops, Next, Timeout) when is_list(Ops) ->
    await_all(Seq, Ops, Next, Timeout);
await(Seq, Op, Next, Timeout) ->
    await_all(Seq, [Op], Next, Timeout).

%% @doc Await2: two operations, such as two cylinders moving at once.
-spec await2(seq(), op(), op(), term()) -> result().
await2(Seq, Op1, Op2, Next) -> await_all(Seq, [Op1, Op2], Next, infinity).

await_all(Seq0, Ops, Next, Timeout) ->
    {Statuses, Seq} = lists:mapfoldl(fun status/2, Seq0, Ops),
    case [Why || {error, Why} <- Statuses] of
        [Why | _] ->
            {abort, Why, Seq};
        [] ->
            case [pending(Seq, Op) || {Op, pending} <- lists:zip(Ops, Statuses)] of
                [] ->
                    {next, Next, Seq};
                Pending ->
                    #seq{now = Now, entered = Entered, step = Step} = Seq,
                    case Timeout of
                        infinity ->
                            {wait, Pending, infinity, Seq};
                        Ms when Entered + Ms =< Now ->
                            {abort, {await_timeout, Step, Pending, Ms}, Seq};
                        Ms ->
                            {wait, Pending, {Entered + Ms, Ms}, Seq}
                    end
            end
    end.

%% A pending operation as the engine arms it and the operator reads it: IO points in
%% full.
pending(Seq, {io, Point, Cond}) -> {io, resolve(Seq, Point), Cond};
pending(_Seq, Op) -> Op.

%% An operation: done, pending, or failed.
status(Name, #seq{actuators = Acts} = Seq) when is_atom(Name) ->
    case maps:find(Name, Acts) of
        {ok, {Mod, S}} ->
            case Mod:status(S) of
                idle -> {done, Seq};
                busy -> {pending, Seq};
                {error, Why} -> {{error, {actuator, Name, Mod, Why}}, Seq}
            end;
        error ->
            {{error, {unknown_actuator, Name}}, Seq}
    end;
status({io, Point, Cond} = Op, #seq{latched = Latched, read = Read} = Seq) ->
    {G, P} = Key = resolve(Seq, Point),
    case maps:is_key(op_key(Seq, Op), Latched) of
        true ->
            {done, Seq};
        false ->
            case Read(G, P) of
                {ok, V} ->
                    case cell_hal_type:holds(Cond, V) of
                        true -> {done, Seq#seq{latched = Latched#{op_key(Seq, Op) => V}}};
                        false -> {pending, Seq}
                    end;
                %% Inputs of a connection that is down satisfy nothing; its watch fires
                %% after the reconnect (the unit goes into FaultReaction on the loss).
                {error, disconnected} -> {pending, Seq};
                {error, not_yet_read} -> {pending, Seq};
                {error, Why} -> {{error, {io, Key, Why}}, Seq}
            end
    end;
status({reply, Ref}, #seq{replies = Replies} = Seq) when is_reference(Ref) ->
    case maps:find(Ref, Replies) of
        {ok, {_Term}} -> {done, Seq};
        _ -> {pending, Seq#seq{replies = Replies#{Ref => expected}}}
    end;
status({order, Key, {Cmp, V}}, #seq{orders = Orders} = Seq)
  when is_atom(Key), (Cmp =:= eq orelse Cmp =:= ne) ->
    %% No order given yet is `undefined': `{ne, undefined}' waits for the first.
    case (maps:get(Key, Orders, undefined) =:= V) =:= (Cmp =:= eq) of
        true -> {done, Seq};
        false -> {pending, Seq}
    end;
status(Op, Seq) ->
    {{error, {bad_operation, Op}}, Seq}.

%% @private The key of an IO operation's watch: the resolved point and condition.
-spec op_key(seq(), op()) -> term().
op_key(Seq, {io, Point, Cond}) ->
    {G, P} = resolve(Seq, Point),
    {io, G, P, Cond}.

%% @doc The sequence has finished; its state is done.
-spec done(seq()) -> result().
done(Seq) -> {done, Seq}.

%% @doc Abort(Reason): the unit goes into FaultReaction; the reason is shown to the
%% operator. A binary or string is shown as it is.
-spec abort(seq(), term()) -> result().
abort(Seq, Reason) -> {abort, Reason, Seq}.

%% @doc Runs the sub-sequence `Module' (with `Args') and, once it is done, goes on at
%% `Next'. Halt reaches it; an abort in it aborts this sequence too.
-spec call(seq(), module(), map(), term()) -> result().
call(Seq, Module, Args, Next) -> {call, Module, Args, Next, Seq}.

%% -------------------------------------------------------------------------------------
%% IO, actuators, replies
%% -------------------------------------------------------------------------------------

%% @doc An IO point's value; a point that cannot be read aborts the sequence, naming it.
-spec in(seq(), point()) -> cell_hal_type:value().
in(#seq{read = Read} = Seq, Point) ->
    {G, P} = resolve(Seq, Point),
    case Read(G, P) of
        {ok, V} -> V;
        {error, Why} -> ?ABORT({io, {G, P}, Why})
    end.

%% @doc An IO point's value, or why it cannot be read.
-spec read(seq(), point()) -> {ok, cell_hal_type:value()} | {error, term()}.
read(#seq{read = Read} = Seq, Point) ->
    {G, P} = resolve(Seq, Point),
    Read(G, P).

%% @doc Commands an output (the seed's `_io.MagnetEin.Enable(TRUE)'); written once the
%% step returns. A write the HAL refuses aborts the sequence.
-spec out(seq(), point(), cell_hal_type:value()) -> seq().
out(Seq, Point, Value) ->
    effect(Seq, {write, resolve(Seq, Point), Value}).

%% @doc Starts an actuator's command (the seed's `MoveUpAsync(THIS^)'); await the
%% actuator by its name. An actuator that fails aborts the running sequence at once,
%% awaited or not. A command the actuator refuses aborts the sequence.
-spec command(seq(), atom(), term()) -> seq().
command(#seq{actuators = Acts, read = Read} = Seq, Name, Command) ->
    case maps:find(Name, Acts) of
        {ok, {Mod, S}} ->
            case Mod:command(Command, S, Read) of
                {ok, S1, Effects} ->
                    actuator_effects(Seq#seq{actuators = Acts#{Name => {Mod, S1}}}, Name, Effects);
                {error, Why} ->
                    ?ABORT({actuator, Name, Mod, Why})
            end;
        error ->
            ?ABORT({unknown_actuator, Name})
    end.

%% @doc An actuator the running sequence owns (a timer, say): created the first time,
%% forgotten when the sequence ends. A unit's own actuator of that name must be of
%% that module.
-spec local_actuator(seq(), atom(), module(), map()) -> seq().
local_actuator(#seq{actuators = Acts, frames = [F | Rest]} = Seq, Name, Module, Opts) ->
    case maps:find(Name, Acts) of
        {ok, {Module, _}} ->
            Seq;
        {ok, {Other, _}} ->
            ?ABORT({actuator, Name, Other, {not_a, Module}});
        error ->
            case Module:new(Name, Opts, fun(P) -> {ok, resolve(Seq, P)} end) of
                {ok, S} ->
                    Seq#seq{actuators = Acts#{Name => {Module, S}},
                            frames = [F#frame{timers = [Name | F#frame.timers]} | Rest]};
                {error, Why} ->
                    ?ABORT({actuator, Name, Module, Why})
            end
    end.

%% @doc The answer `{Ref, Term}' an awaited `{reply, Ref}' brought.
-spec reply(seq(), reference()) -> term().
reply(#seq{replies = R}, Ref) ->
    {Term} = maps:get(Ref, R),
    Term.

%% @doc The unit's standing order `Key' as last given with `cell_unit:order/3' (the
%% unit keeps it across its states, not across a restart of its process), or `Default'
%% when none was given.
-spec order(seq(), atom(), term()) -> term().
order(#seq{orders = Orders}, Key, Default) -> value(Key, Orders, Default).

%% @doc Keeps the answer to a request made now for a later step to await (answers to
%% requests nobody awaits or expects are dropped).
-spec expect_reply(seq(), reference()) -> seq().
expect_reply(#seq{replies = R} = Seq, Ref) when is_reference(Ref) ->
    case maps:is_key(Ref, R) of
        true -> Seq;
        false -> Seq#seq{replies = R#{Ref => expected}}
    end.

%% -------------------------------------------------------------------------------------
%% IPC-2541 events (seed 000 §2.3.4), in Automatic and user states
%% -------------------------------------------------------------------------------------

%% @doc The unit waits for a product: READY-IDLE-STARVED.
-spec starved(seq()) -> seq().
starved(Seq) -> effect(Seq, {ipc, equipment_starved}).

%% @doc A product is there: READY-PROCESSING-ACTIVE.
-spec unstarved(seq()) -> seq().
unstarved(Seq) -> effect(Seq, {ipc, equipment_unstarved}).

%% @doc The unit waits for the next one to take its product: READY-IDLE-BLOCKED.
-spec blocked(seq()) -> seq().
blocked(Seq) -> effect(Seq, {ipc, equipment_blocked}).

%% @doc The product was taken: READY-PROCESSING-ACTIVE.
-spec unblocked(seq()) -> seq().
unblocked(Seq) -> effect(Seq, {ipc, equipment_unblocked}).

%% @doc Processing starts: READY-PROCESSING-EXECUTING.
-spec work_start(seq()) -> seq().
work_start(Seq) -> effect(Seq, {ipc, item_work_start}).

%% @doc Processing is complete: READY-PROCESSING-ACTIVE.
-spec work_complete(seq()) -> seq().
work_complete(Seq) -> effect(Seq, {ipc, item_work_complete}).

%% @doc Logs to the unit's log at one of the seed's levels, or as error / warning.
-spec log(seq(), cell_log:level(), io:format(), [term()]) -> seq().
log(#seq{unit = U} = Seq, Level, Format, Args) ->
    ok = cell_log:log(Level, U, Format, Args),
    Seq.

%% -------------------------------------------------------------------------------------
%% Reasons in words
%% -------------------------------------------------------------------------------------

%% @doc Why a sequence was aborted, in words for the operator.
-spec format_reason(term()) -> binary().
format_reason(Reason) ->
    unicode:characters_to_binary(reason(Reason)).

reason(B) when is_binary(B) -> B;
reason({actuator, Name, Mod, Why}) -> Mod:format_error(Name, Why);
reason({await_timeout, Step, Ops, Ms}) ->
    io_lib:format("step ~ts waited more than ~b ms for ~ts",
                  [term(Step), Ms, lists:join(" and ", [op(Op) || Op <- Ops])]);
reason({io, {G, P}, Why}) ->
    ["IO point ", point({G, P}), " ", io_error(Why)];
reason({io_lost, Conn}) ->
    io_lib:format("the connection ~ts to the unit's IO was lost", [Conn]);
reason({unknown_actuator, Name}) ->
    io_lib:format("the unit has no actuator ~ts", [Name]);
reason({unhandled_step, Step}) ->
    io_lib:format("sequence contains unhandled step ~ts", [term(Step)]);
reason({no_io_group, P}) ->
    io_lib:format("IO point ~ts: the unit has no IO group", [P]);
reason({bad_operation, Op}) ->
    io_lib:format("cannot await ~tp: not an actuator, IO condition, reply or order", [Op]);
reason({not_ready, Event, State}) ->
    io_lib:format("the sequence reported ~ts in ~ts; only Automatic and user states can",
                  [Event, cell_unit_fsm:name(State)]);
reason(Reason) ->
    case io_lib:printable_unicode_list(Reason) of
        true -> Reason;
        false -> io_lib:format("~tP", [Reason, 10])
    end.

io_error(disconnected) -> "cannot be reached: its connection is down";
io_error(unknown_point) -> "is not configured";
io_error(not_an_output) -> "is an input and cannot be written";
io_error(not_yet_read) -> "has not been read yet";
io_error({unavailable, Why}) when is_binary(Why) -> ["cannot be read: ", Why];
io_error({bad_value, V}) -> io_lib:format("cannot take the value ~tp", [V]);
io_error({bad_condition, C}) -> io_lib:format("cannot reach the condition ~tp", [C]);
io_error(Why) -> io_lib:format("failed: ~tp", [Why]).

op(Name) when is_atom(Name) -> atom_to_list(Name);
op({io, Point, {Cmp, V}}) -> io_lib:format("~ts ~ts ~tp", [point(Point), cmp(Cmp), V]);
op({reply, _}) -> "an answer";
op({order, Key, {Cmp, V}}) -> io_lib:format("the order ~ts ~ts ~tp", [Key, cmp(Cmp), V]);
op(Op) -> io_lib:format("~tp", [Op]).

point({G, P}) -> [atom_to_list(G), ".", atom_to_list(P)];
point(P) when is_atom(P) -> atom_to_list(P).

cmp(eq) -> "=";
cmp(ne) -> "<>";
cmp(gt) -> ">";
cmp(ge) -> ">=";
cmp(lt) -> "<";
cmp(le) -> "<=".

term(A) when is_atom(A) -> atom_to_list(A);
term(T) -> io_lib:format("~tp", [T]).

%% A value of a map, or `Default': what a step reads most (its arguments, above all),
%% matched here rather than through maps:get/3's call.
value(Key, Map, Default) ->
    case Map of
        #{Key := V} -> V;
        #{} -> Default
    end.

%% -------------------------------------------------------------------------------------
%% For the runner and actuators
%% -------------------------------------------------------------------------------------

%% @private A point as `{Group, Name}': a bare name is in the unit's first IO group.
-spec resolve(seq(), point()) -> {atom(), atom()}.
resolve(_Seq, {G, P}) when is_atom(G), is_atom(P) -> {G, P};
resolve(#seq{io = [G | _]}, P) when is_atom(P) -> {G, P};
resolve(#seq{io = []}, P) -> ?ABORT({no_io_group, P}).

%% @private
-spec effect(seq(), effect()) -> seq().
effect(#seq{effects = E} = Seq, Effect) -> Seq#seq{effects = [Effect | E]}.

%% @private An actuator's effects, its watches and timers keyed by its name.
-spec actuator_effects(seq(), atom(), [cell_actuator:effect()]) -> seq().
actuator_effects(Seq, Name, Effects) ->
    lists:foldl(fun(E, S) -> effect(S, actuator_effect(Name, E)) end, Seq, Effects).

actuator_effect(_Name, {write, Key, V}) -> {write, Key, V};
actuator_effect(Name, {watch, Tag, Key, Cond}) -> {watch, {act, Name, Tag}, Key, Cond};
actuator_effect(Name, {cancel_watch, Tag}) -> {cancel_watch, {act, Name, Tag}};
actuator_effect(Name, {timer, Tag, Ms}) -> {timer, {act, Name, Tag}, Ms};
actuator_effect(Name, {cancel_timer, Tag}) -> {cancel_timer, {act, Name, Tag}}.
