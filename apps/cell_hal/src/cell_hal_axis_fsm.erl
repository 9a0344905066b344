%% The state of an axis, as PLCopen motion control has it (Part 1, "Function blocks for
%% motion control", its state diagram): what a command may do in each state, which
%% command a newer one aborts, what a fault and a reset do. Pure: the axis process
%% (simulated NC or TwinCAT NC) feeds it commands and the NC's news and carries out the
%% effects it returns.
%%
%% States (PLCopen's names, in Erlang spelling):
%% <ul>
%% <li>`disabled' — power off (MC_Power.Enable false). Only power on leaves it.</li>
%% <li>`standstill' — powered, not moving: home, a move, halt or stop start here.</li>
%% <li>`homing' — MC_Home running. Only stop (or power off, or a fault) interrupts it;
%%   a move is refused.</li>
%% <li>`discrete_motion' — a move to a position (MC_MoveAbsolute, MC_MoveRelative) or
%%   MC_Halt. A newer move or halt aborts the running one (its owner is told
%%   `aborted', PLCopen's CommandAborted); home is refused (homing starts from
%%   standstill only).</li>
%% <li>`synchronized_motion' — the axis follows a motion computed for several axes at
%%   once (an interpolation channel's path: PLCopen's coupled motion). Entered from
%%   standstill or any motion but homing and stopping (aborting it); a move, halt or
%%   stop aborts it; it ends in standstill when done.</li>
%% <li>`stopping' — MC_Stop: the axis decelerates to a stop and stays here while the
%%   stop's Execute is held, refusing every motion command; it leaves for standstill
%%   once the stop is done and released.</li>
%% <li>`error_stop' — a fault of the axis or its drive, from any state: the NC stops the
%%   axis at once, the running command fails with the fault's code, and every motion
%%   command is refused until MC_Reset, which goes to standstill, or to disabled if
%%   power was switched off meanwhile.</li>
%% </ul>
%% Power off aborts whatever runs and goes to disabled, from any state but error_stop
%% (where it only records that power is off).
%%
%% Beyond PLCopen's diagram, as a machine's owner expects: an absolute move needs the
%% axis homed (its position means nothing before), a target outside the software
%% limits is refused with the axis left as it is, and velocity, acceleration and
%% deceleration must be positive. The speed override (0–100 %) is the axis's, applied
%% to whatever runs as it changes.
-module(cell_hal_axis_fsm).

-export([new/1, command/3, event/2, set_override/2]).
-export([state/1, error_code/1, homed/1, job/1, override/1, powered/1]).

-export_type([axis/0, state/0, command/0, event/0, effect/0, job/0, params/0, motion/0]).

-type state() :: disabled | standstill | homing | discrete_motion | synchronized_motion
               | stopping | error_stop.
-type params() :: #{velocity := number(), acceleration := number(),
                    deceleration := number()}.
-type command() :: {power, boolean()}
                 | {home, number()}
                 | {move_absolute, number(), params()}
                 | {move_relative, number(), params()}
                 | {halt, number()}
                 | {stop, boolean(), number()}
                 | {follow, motion()}
                 | reset.
%% A motion several axes follow together: what the NC runs (opaque here), and the
%% range of this axis's positions along it, held against the software limits.
-type motion() :: #{range := {number(), number()}, atom() => term()}.
%% The NC's news: a job ran to its end, or the axis or its drive faulted.
-type event() :: {done, pos_integer()} | {fault, pos_integer()}.
-type job() :: #{id := pos_integer(),
                 kind := home | move | halt | stop | follow,
                 %% Where it ends (a move, home) or how fast it stops (halt, stop).
                 target => number(), params => params(), deceleration => number(),
                 motion => motion()}.
-type effect() :: {run, job()}          % the NC starts this job (replacing any)
                | {aborted, job()}      % its owner is told CommandAborted
                | {done, job()}         % its owner is told Done
                | {failed, job(), pos_integer()}
                | power_on | power_off
                | quick_stop            % the NC stops the axis at once (a fault)
                | {override, number()}.

-record(axis, {state = disabled :: state(),
               power = false :: boolean(),
               homed = false :: boolean(),
               error = 0 :: non_neg_integer(),
               job :: job() | undefined,
               %% Stopping: whether the stop is done, and whether its Execute is held.
               stop_done = false :: boolean(),
               stop_held = false :: boolean(),
               override = 100 :: number(),
               limits = none :: none | {number(), number()},
               next_id = 1 :: pos_integer()}).

-opaque axis() :: #axis{}.

%% @doc A new axis, disabled and not homed. `limits': the software limits `{Min,
%% Max}' (none: no limits).
-spec new(#{limits => none | {number(), number()}}) -> axis().
new(Opts) ->
    #axis{limits = maps:get(limits, Opts, none)}.

-spec state(axis()) -> state().
state(#axis{state = S}) -> S.

-spec error_code(axis()) -> non_neg_integer().
error_code(#axis{error = E}) -> E.

-spec homed(axis()) -> boolean().
homed(#axis{homed = H}) -> H.

-spec powered(axis()) -> boolean().
powered(#axis{power = P}) -> P.

%% @doc The job the NC runs now (undefined in standstill, disabled, error_stop).
-spec job(axis()) -> job() | undefined.
job(#axis{job = J}) -> J.

-spec override(axis()) -> number().
override(#axis{override = O}) -> O.

%% @doc A command, `Position' the axis's actual position (a relative move is relative to
%% it): the axis and what to do, or why it is refused (the axis unchanged).
-spec command(command(), number(), axis()) -> {ok, axis(), [effect()]} | {error, term()}.
command(reset, _Position, #axis{state = error_stop, power = P} = A) ->
    {ok, A#axis{state = case P of true -> standstill; false -> disabled end, error = 0},
     []};
command(reset, _Position, A) ->
    %% Nothing to reset: done at once (PLCopen's MC_Reset outside ErrorStop).
    {ok, A, []};
command({power, On}, _Position, #axis{state = error_stop} = A) ->
    {ok, A#axis{power = On}, []};
command({power, true}, _Position, #axis{state = disabled} = A) ->
    {ok, A#axis{state = standstill, power = true}, [power_on]};
command({power, true}, _Position, A) ->
    {ok, A, []};
command({power, false}, _Position, #axis{state = disabled} = A) ->
    {ok, A, []};
command({power, false}, _Position, A) ->
    {ok, (idle(A))#axis{state = disabled, power = false}, abort(A) ++ [power_off]};
command({stop, false, _Dec}, _Position, #axis{state = stopping, stop_done = true} = A) ->
    %% The stop's Execute released after it was done.
    {ok, (idle(A))#axis{state = standstill}, []};
command({stop, false, _Dec}, _Position, #axis{state = stopping} = A) ->
    {ok, A#axis{stop_held = false}, []};
command({stop, false, _Dec}, _Position, A) ->
    {ok, A, []};
command(_Motion, _Position, #axis{state = error_stop, error = E}) ->
    {error, {error_stop, E}};
command(_Motion, _Position, #axis{state = disabled}) ->
    {error, disabled};
command({stop, true, Dec}, _Position, A) ->
    case positive([Dec]) of
        true ->
            start(#{kind => stop, deceleration => Dec}, stopping,
                  A#axis{stop_done = false, stop_held = true});
        false ->
            {error, {bad_deceleration, Dec}}
    end;
command(_Motion, _Position, #axis{state = stopping}) ->
    {error, stopping};
command({home, _At}, _Position, #axis{state = homing}) ->
    {error, {busy, homing}};
command({home, At}, _Position, #axis{state = standstill} = A) when is_number(At) ->
    start(#{kind => home, target => At}, homing, A);
command({home, _At}, _Position, #axis{state = S}) ->
    {error, {busy, S}};
command(_Motion, _Position, #axis{state = homing}) ->
    {error, {busy, homing}};
command({halt, Dec}, _Position, A) ->
    case positive([Dec]) of
        true -> start(#{kind => halt, deceleration => Dec}, discrete_motion, A);
        false -> {error, {bad_deceleration, Dec}}
    end;
command({move_absolute, _To, _Params}, _Position, #axis{homed = false}) ->
    {error, not_homed};
command({follow, _Motion}, _Position, #axis{homed = false}) ->
    {error, not_homed};
command({follow, #{range := {Lo, Hi}} = Motion}, _Position, #axis{limits = Limits} = A) ->
    case within(Lo, Limits) andalso within(Hi, Limits) of
        true -> start(#{kind => follow, motion => Motion}, synchronized_motion, A);
        false -> {error, {beyond_limits, {Lo, Hi}, Limits}}
    end;
command({move_absolute, To, Params}, _Position, A) ->
    move(To, Params, A);
command({move_relative, By, Params}, Position, A) when is_number(By) ->
    move(Position + By, Params, A);
command(Command, _Position, _A) ->
    {error, {bad_command, Command}}.

%% @doc The NC's news.
-spec event(event(), axis()) -> {axis(), [effect()]}.
event({fault, Code}, #axis{state = error_stop} = A) ->
    %% A second fault while stopped by the first: the newer code is shown.
    {A#axis{error = Code}, []};
event({fault, Code}, #axis{job = Job} = A) ->
    Failed = [{failed, Job, Code} || Job =/= undefined],
    {(idle(A))#axis{state = error_stop, error = Code}, Failed ++ [quick_stop]};
event({done, Id}, #axis{job = #{id := Id, kind := stop} = Job, stop_held = Held} = A) ->
    case Held of
        true -> {A#axis{stop_done = true}, [{done, Job}]};
        false -> {(idle(A))#axis{state = standstill}, [{done, Job}]}
    end;
event({done, Id}, #axis{job = #{id := Id, kind := home} = Job} = A) ->
    {(idle(A))#axis{state = standstill, homed = true}, [{done, Job}]};
event({done, Id}, #axis{job = #{id := Id} = Job} = A) ->
    {(idle(A))#axis{state = standstill}, [{done, Job}]};
event({done, _Stale}, A) ->
    %% A job aborted before the NC's word of its end came.
    {A, []}.

%% @doc The speed override in percent (0–100), applied to what runs as it changes.
-spec set_override(number(), axis()) -> {ok, axis(), [effect()]} | {error, term()}.
set_override(Pct, A) when is_number(Pct), Pct >= 0, Pct =< 100 ->
    {ok, A#axis{override = Pct}, [{override, Pct} || Pct /= A#axis.override]};
set_override(Pct, _A) ->
    {error, {bad_override, Pct}}.

%%--------------------------------------------------------------------

move(To, Params, #axis{limits = Limits} = A) ->
    case {check_params(Params), within(To, Limits)} of
        {ok, true} -> start(#{kind => move, target => To, params => Params},
                            discrete_motion, A);
        {ok, false} -> {error, {beyond_limits, To, Limits}};
        {Error, _} -> Error
    end.

start(Job0, State, #axis{next_id = Id} = A) ->
    Job = Job0#{id => Id},
    {ok, A#axis{state = State, job = Job, next_id = Id + 1}, abort(A) ++ [{run, Job}]}.

abort(#axis{job = undefined}) -> [];
abort(#axis{job = Job}) -> [{aborted, Job}].

idle(A) ->
    A#axis{job = undefined, stop_done = false, stop_held = false}.

check_params(#{velocity := V, acceleration := Acc, deceleration := Dec}) ->
    case positive([V, Acc, Dec]) of
        true -> ok;
        false -> {error, {bad_params, #{velocity => V, acceleration => Acc,
                                        deceleration => Dec}}}
    end;
check_params(Params) ->
    {error, {bad_params, Params}}.

positive(Xs) ->
    lists:all(fun(X) -> is_number(X) andalso X > 0 end, Xs).

within(X, _) when not is_number(X) -> false;
within(_X, none) -> true;
within(X, {Min, Max}) -> X >= Min andalso X =< Max.
