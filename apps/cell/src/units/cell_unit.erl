%% @doc Units (seed 001): the second kind of device task, with the Zeugwerk lifecycle
%% — Booting, Init, GoHome, Idle, Automatic, Stop, Stopped, FaultReaction, Fault,
%% user-defined states and actions — and a step sequence per state. This module is
%% the behaviour a unit module implements and the API that presses a unit's buttons;
%% {@link cell_unit_proc} is the engine, {@link cell_unit_fsm} the two diagrams.
%%
%% A unit module declares what the unit is made of, in one callback:
%%
%% ```
%% -module(picker_unit).
%% -behaviour(cell_unit).
%% -export([unit/1]).
%%
%% unit(Args) ->
%%     #{sequences => #{go_home => picker_home,
%%                      automatic => {picker_automatic, Args},
%%                      stop => picker_stop,
%%                      fault_reaction => picker_fault_reaction,
%%                      {action, release_part} => picker_release},
%%       actions => [release_part],
%%       actuators => #{vertical_lift => {cell_cylinder, #{...}}},
%%       safe_outputs => [{magnet, false}]}.
%% '''
%%
%% <ul>
%% <li>`sequences' — the sequence module (see {@link cell_sequence}) of a state, with
%%     its args: `booting' (equipment ready: fieldbus parameters), `go_home',
%%     `automatic', `stop', `fault_reaction', `idle' and `stopped' (run while the unit
%%     waits there), `{user, X}' and `{action, A}'. A state without one is done at
%%     once. Init and Fault wait for the operator and run none.</li>
%% <li>`user_states', `actions' — their names; each needs a sequence. A user state
%%     starts from Idle only; an action from Init, Idle, Stopped or Fault, and returns
%%     there.</li>
%% <li>`actuators' — name to `{Module, Opts}' ({@link cell_actuator}), shared by the
%%     unit's sequences.</li>
%% <li>`idle' — the unit's READY sub-state in Idle: `starved' (default), `blocked',
%%     `active' or `executing'.</li>
%% <li>`safe_outputs' — `[{Point, Value}]' written, besides the actuators' own safe
%%     positions, on the emergency stop and when the unit's process ends.</li>
%% </ul>
%%
%% A unit sits in the cell spec like a task (`id', `module', `zone', `lane', `io',
%% `settings', `args'); the cell tells the two kinds apart by their callbacks. Its
%% buttons: {@link go_home/1}, {@link start/1}, {@link stop/1}, {@link user_state/2},
%% {@link action/2}, {@link abort/2} (a fault from outside: another unit, a monitor),
%% {@link halt/1} and {@link resume/1}. A device task (or another unit) commands a
%% unit with standing orders, {@link order/3}: `clamp => true', say, which the unit's
%% sequences read (`cell_sequence:order/3') and await (`{order, clamp, {eq, true}}');
%% the asker sees the result on the machine's sensors. The cell's Start, Pause, Stop, emergency stop
%% and service mode reach it as they reach tasks (see {@link cell_unit_proc}).
-module(cell_unit).

-export([check/1, is_unit_module/1]).
-export([go_home/1, start/1, stop/1, user_state/2, action/2, abort/2, halt/1, resume/1]).
-export([order/3]).
-export([state/1, info/1, settle/1, whereis/1]).

-export_type([declaration/0, sequence_key/0, button/0]).

-type sequence_key() :: booting | go_home | idle | automatic | stop | stopped
                      | fault_reaction | {user, atom()} | {action, atom()}.
-type declaration() :: #{sequences := #{sequence_key() => {module(), map()}},
                         actuators := #{atom() => {module(), map()}},
                         user_states := [atom()],
                         actions := [atom()],
                         idle := cell_unit_fsm:ready(),
                         safe_outputs := [{cell_sequence:point(), cell_hal_type:value()}]}.
-type button() :: go_home | start | stop | {user, atom()} | {action, atom()}
                | {abort, term()}.
-type unit_ref() :: pid() | atom().
-type button_error() :: {not_allowed, button(), cell_unit_fsm:state()} | estop_active
                      | {unknown_user_state, atom()} | {unknown_action, atom()}.

-callback unit(Args :: map()) -> map().

-define(KEYS, [sequences, actuators, user_states, actions, idle, safe_outputs]).
-define(READY, [starved, blocked, active, executing]).

%% -------------------------------------------------------------------------------------
%% Buttons
%% -------------------------------------------------------------------------------------

%% @doc GoHome: reference the unit (from Init, Idle, Stopped, Fault). From Fault it
%% takes the fault's error back: the operator chose to reference.
-spec go_home(unit_ref()) -> ok | {error, button_error()}.
go_home(U) -> button(U, go_home).

%% @doc Start: Idle → Automatic.
-spec start(unit_ref()) -> ok | {error, button_error()}.
start(U) -> button(U, start).

%% @doc Stop: interrupts GoHome, Idle, Automatic, user states, actions, and Stopped
%% again; the unit's Stop sequence runs, then it is Stopped.
-spec stop(unit_ref()) -> ok | {error, button_error()}.
stop(U) -> button(U, stop).

%% @doc ButtonX: Idle → the user-defined state `X'.
-spec user_state(unit_ref(), atom()) -> ok | {error, button_error()}.
user_state(U, X) -> button(U, {user, X}).

%% @doc ButtonY: the action `A', from Init, Idle, Stopped or Fault, back there when done.
-spec action(unit_ref(), atom()) -> ok | {error, button_error()}.
action(U, A) -> button(U, {action, A}).

%% @doc A fault from outside the unit (the diagrams' "aborted"): FaultReaction, then
%% Fault, with `Reason' shown to the operator.
-spec abort(unit_ref(), term()) -> ok | {error, button_error()}.
abort(U, Reason) -> button(U, {abort, Reason}).

%% @doc Halt: the running sequence holds at its next resumable point.
-spec halt(unit_ref()) -> ok.
halt(U) -> gen_statem:call(pid(U), {halt, true}).

%% @doc Releases Halt: the sequence goes on where it held.
-spec resume(unit_ref()) -> ok.
resume(U) -> gen_statem:call(pid(U), {halt, false}).

button(U, B) -> gen_statem:call(pid(U), {button, B}).

%% @doc Gives the unit a standing order: `Key' is `Value' until a next order of that
%% key. The unit keeps it in every state (a unit in Fault or Stopped follows it once
%% back in Automatic) but not across a restart of its process, so the asker gives it
%% again while it waits for the result; `{error, not_running}' when the unit has no
%% process now (it restarts).
-spec order(unit_ref(), atom(), term()) -> ok | {error, not_running}.
order(U, Key, Value) when is_atom(Key) ->
    case pid_of(U) of
        undefined ->
            {error, not_running};
        Pid ->
            try gen_statem:call(Pid, {order, Key, Value})
            catch
                %% Ended before or while it took the order: its successor has none.
                exit:{_Why, {gen_statem, call, _}} -> {error, not_running}
            end
    end.

pid_of(Pid) when is_pid(Pid) -> Pid;
pid_of(Id) when is_atom(Id) -> ?MODULE:whereis(Id).

%% -------------------------------------------------------------------------------------
%% Looking at a unit
%% -------------------------------------------------------------------------------------

%% @doc The unit's lifecycle state (its IPC-2541 state is `cell_task_proc:state/1').
-spec state(unit_ref()) -> cell_unit_fsm:state().
state(U) -> gen_statem:call(pid(U), unit_state).

%% @doc The IPC-2541 state, the lifecycle state, the sequences running and their
%% steps, what the running step waits for, Halt, the actuators, the error waiting for
%% the operator and why the unit is in Fault.
-spec info(unit_ref()) -> map().
info(U) -> gen_statem:call(pid(U), info).

%% @doc Returns once the unit waits for something outside itself: no step is due.
-spec settle(unit_ref()) -> ok.
settle(U) -> gen_statem:call(pid(U), settle).

%% @doc The pid of a running unit.
-spec whereis(atom()) -> pid() | undefined.
whereis(Id) -> cell_task_proc:whereis(Id).

pid(Pid) when is_pid(Pid) -> Pid;
pid(Id) when is_atom(Id) ->
    case ?MODULE:whereis(Id) of
        undefined -> erlang:error({no_such_unit, Id});
        Pid -> Pid
    end.

%% -------------------------------------------------------------------------------------
%% Declarations
%% -------------------------------------------------------------------------------------

%% @doc Whether a module implements this behaviour.
-spec is_unit_module(term()) -> boolean().
is_unit_module(Mod) when is_atom(Mod) ->
    code:ensure_loaded(Mod) =:= {module, Mod} andalso erlang:function_exported(Mod, unit, 1);
is_unit_module(_) ->
    false.

%% @doc A unit's declaration for its spec, checked and with defaults; the first fault
%% is named: `{bad_unit, Key, Why}'.
-spec check(cell_task:spec()) -> {ok, declaration()} | {error, {bad_unit, term(), term()}}.
check(#{module := Mod} = Spec) ->
    case Mod:unit(maps:get(args, Spec, #{})) of
        Decl when is_map(Decl) ->
            case maps:keys(Decl) -- ?KEYS of
                [] -> check_decl(Decl, maps:get(io, Spec, []));
                [Bad | _] -> {error, {bad_unit, Bad, unknown_key}}
            end;
        Other ->
            {error, {bad_unit, unit, {not_a_map, Other}}}
    end.

check_decl(Decl, Io) ->
    Users = maps:get(user_states, Decl, []),
    Actions = maps:get(actions, Decl, []),
    Steps = [fun() -> names(user_states, Users) end,
             fun() -> names(actions, Actions) end,
             fun() -> sequences(maps:get(sequences, Decl, #{}), Users, Actions) end,
             fun() -> actuators(maps:get(actuators, Decl, #{}), Io) end,
             fun() -> member(idle, maps:get(idle, Decl, starved), ?READY) end,
             fun() -> safe_outputs(maps:get(safe_outputs, Decl, []), Io) end],
    case first_error(Steps) of
        ok ->
            {ok, #{sequences => maps:map(fun(_, V) -> with_args(V) end,
                                         maps:get(sequences, Decl, #{})),
                   actuators => maps:get(actuators, Decl, #{}),
                   user_states => Users, actions => Actions,
                   idle => maps:get(idle, Decl, starved),
                   safe_outputs => maps:get(safe_outputs, Decl, [])}};
        Error ->
            Error
    end.

first_error([]) -> ok;
first_error([F | Rest]) ->
    case F() of
        ok -> first_error(Rest);
        Error -> Error
    end.

names(Key, Names) ->
    case is_list(Names) andalso lists:all(fun is_atom/1, Names)
        andalso length(lists:usort(Names)) =:= length(Names) of
        true -> ok;
        false -> {error, {bad_unit, Key, "a list of distinct names"}}
    end.

member(Key, V, Allowed) ->
    case lists:member(V, Allowed) of
        true -> ok;
        false -> {error, {bad_unit, Key, V}}
    end.

sequences(Seqs, Users, Actions) when is_map(Seqs) ->
    Allowed = [booting, go_home, idle, automatic, stop, stopped, fault_reaction]
        ++ [{user, U} || U <- Users] ++ [{action, A} || A <- Actions],
    Needed = [{user, U} || U <- Users] ++ [{action, A} || A <- Actions],
    case [K || K <- maps:keys(Seqs), not lists:member(K, Allowed)] of
        [K | _] when K =:= init; K =:= fault ->
            {error, {bad_unit, {sequence, K}, "Init and Fault wait for the operator: no sequence"}};
        [K | _] ->
            {error, {bad_unit, {sequence, K}, "not a state of this unit"}};
        [] ->
            case [K || K <- Needed, not maps:is_key(K, Seqs)] of
                [K | _] ->
                    {error, {bad_unit, {sequence, K}, "every user state and action needs one"}};
                [] ->
                    first_error([fun() -> sequence_module(K, V) end
                                 || {K, V} <- lists:sort(maps:to_list(Seqs))])
            end
    end;
sequences(_, _, _) ->
    {error, {bad_unit, sequences, "a map"}}.

sequence_module(Key, V) ->
    {Mod, Args} = with_args(V),
    Loaded = is_atom(Mod) andalso code:ensure_loaded(Mod) =:= {module, Mod},
    case Loaded andalso is_map(Args)
        andalso erlang:function_exported(Mod, init, 2)
        andalso erlang:function_exported(Mod, step, 2) of
        true ->
            case maps:get(mode, Args, several) of
                M when M =:= several; M =:= one -> ok;
                Bad -> {error, {bad_unit, {sequence, Key}, {mode, Bad}}}
            end;
        false ->
            {error, {bad_unit, {sequence, Key}, {not_a_sequence_module, V}}}
    end.

with_args({Mod, Args}) -> {Mod, Args};
with_args(Mod) -> {Mod, #{}}.

actuators(Acts, Io) when is_map(Acts) ->
    Callbacks = [{new, 3}, {command, 3}, {event, 2}, {status, 1}, {interrupt, 1},
                 {secure, 1}, {describe, 1}, {format_error, 2}],
    IsActuator = fun({Mod, Opts}) when is_atom(Mod), is_map(Opts) ->
                         code:ensure_loaded(Mod) =:= {module, Mod}
                             andalso lists:all(fun({F, A}) -> erlang:function_exported(Mod, F, A) end,
                                               Callbacks);
                    (_) ->
                         false
                 end,
    case [Name || {Name, V} <- lists:sort(maps:to_list(Acts)), not (is_atom(Name) andalso IsActuator(V))] of
        [Name | _] ->
            {error, {bad_unit, {actuator, Name}, "{Module, Opts} of a cell_actuator module"}};
        [] ->
            case cell_sequence_runner:new(#{unit => check, io => Io, actuators => Acts,
                                            read => fun(_, _) -> {error, not_yet_read} end,
                                            estop => fun() -> false end}) of
                {ok, _} -> ok;
                {error, {actuator, Name, Why}} -> {error, {bad_unit, {actuator, Name}, Why}}
            end
    end;
actuators(_, _) ->
    {error, {bad_unit, actuators, "a map"}}.

safe_outputs(L, Io) when is_list(L) ->
    case lists:all(fun({P, _V}) -> is_atom(P) andalso Io =/= [] orelse is_point(P);
                      (_) -> false
                   end, L) of
        true -> ok;
        false -> {error, {bad_unit, safe_outputs, "[{Point, Value}] of the unit's IO"}}
    end;
safe_outputs(_, _) ->
    {error, {bad_unit, safe_outputs, "a list"}}.

is_point({G, P}) -> is_atom(G) andalso is_atom(P);
is_point(_) -> false.
