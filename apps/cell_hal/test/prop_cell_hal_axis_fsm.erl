%% A PropEr state-machine model of an axis, written from PLCopen motion control's state
%% diagram (Part 1, "Function blocks for motion control"), not from the code: the
%% states Disabled, Standstill, Homing, DiscreteMotion, Stopping and ErrorStop, and the
%% rules its text gives:
%% <ul>
%% <li>MC_Power on leaves Disabled for Standstill; power off goes to Disabled from every
%%   state but ErrorStop, aborting what runs;</li>
%% <li>an axis error goes to ErrorStop from any state; the command running fails; only
%%   MC_Reset leaves it, for Standstill (powered) or Disabled (not);</li>
%% <li>MC_Home only from Standstill; Homing is left when the homing is done (the axis
%%   is then homed) or by MC_Stop, and refuses moves;</li>
%% <li>MC_MoveAbsolute, MC_MoveRelative and MC_Halt go to DiscreteMotion from
%%   Standstill or DiscreteMotion, a newer command aborting the running one
%%   (CommandAborted); it ends in Standstill when done;</li>
%% <li>MC_Stop goes to Stopping from Standstill, Homing, DiscreteMotion or Stopping,
%%   aborting what runs; Stopping refuses every motion command and is left for
%%   Standstill only when the stop is done and its Execute is low;</li>
%% <li>every motion command is refused in Disabled and ErrorStop;</li>
%% <li>a coupled motion (SynchronizedMotion, here an interpolation channel's path) is
%%   entered from Standstill or DiscreteMotion or SynchronizedMotion, aborting what
%%   runs; a move, halt or stop aborts it; it ends in Standstill when done;</li>
%% </ul>
%% and what the runtime adds (cell_hal_axis_fsm's documentation): an absolute move needs
%% a homed axis, a target beyond the software limits or a non-positive velocity,
%% acceleration or deceleration is refused with the axis unchanged, and the override
%% is 0–100 %. After each command the axis's state, error code, homed flag and running
%% job are checked against the model, and the effects against what the rules say its
%% NC and the commands' owners must be told.
-module(prop_cell_hal_axis_fsm).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([do/1]).

-define(F, cell_hal_axis_fsm).
-define(TAB, prop_cell_hal_axis_fsm).
-define(LIMITS, {-500, 500}).

-record(m, {state = disabled, power = false, homed = false, error = 0,
            %% The running job: {Kind, Id}, or none.
            job = none,
            stop_held = false, stop_done = false,
            next_id = 1,
            override = 100,
            %% The actual position handed with each command.
            position = 0}).

model_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_axis(), [{to_file, user},
                                                           {numtests, 1000}]))}.

prop_axis() ->
    ?FORALL(Cmds, proper_statem:commands(?MODULE),
            begin
                Tab = ets:new(?TAB, [named_table, public]),
                true = ets:insert(Tab, {axis, ?F:new(#{limits => ?LIMITS})}),
                {History, State, Result} = proper_statem:run_commands(?MODULE, Cmds),
                ets:delete(Tab),
                ?WHENFAIL(io:format("history: ~p~nstate: ~p~nresult: ~p~n",
                                    [History, State, Result]),
                          aggregate(proper_statem:command_names(Cmds), Result =:= ok))
            end).

%%--------------------------------------------------------------------

initial_state() ->
    #m{}.

params() ->
    ?LET({V, A, D}, {frequency([{9, range(1, 200)}, {1, oneof([0, -5])}]),
                     range(1, 1000), range(1, 1000)},
         #{velocity => V, acceleration => A, deceleration => D}).

dec() ->
    frequency([{9, range(1, 1000)}, {1, 0}]).

target() ->
    frequency([{9, range(-500, 500)}, {1, oneof([-900, 900])}]).

command(#m{job = Job, next_id = Next}) ->
    Done = case Job of
               none -> [];
               {_, Id} -> [{6, {call, ?MODULE, do, [{event, {done, Id}}]}}]
           end,
    frequency(
      [{3, {call, ?MODULE, do, [{command, {power, boolean()}}]}},
       {3, {call, ?MODULE, do, [{command, {home, range(-10, 10)}}]}},
       {4, {call, ?MODULE, do, [{command, {move_absolute, target(), params()}}]}},
       {3, {call, ?MODULE, do, [{command, {move_relative, range(-600, 600), params()}}]}},
       {3, {call, ?MODULE, do, [{command, {follow, #{range => {target(), target()}}}}]}},
       {2, {call, ?MODULE, do, [{command, {halt, dec()}}]}},
       {2, {call, ?MODULE, do, [{command, {stop, true, dec()}}]}},
       {3, {call, ?MODULE, do, [{command, {stop, false, dec()}}]}},
       {2, {call, ?MODULE, do, [{command, reset}]}},
       {2, {call, ?MODULE, do, [{event, {fault, range(1, 9999)}}]}},
       {1, {call, ?MODULE, do, [{event, {done, range(1, Next + 1)}}]}},
       {1, {call, ?MODULE, do, [{override, oneof([0, 50, 100, 101, -1])}]}},
       {1, {call, ?MODULE, do, [{position, range(-400, 400)}]}}]
      ++ Done).

precondition(_M, _Call) ->
    true.

%% @private Runs one command, event or override on the axis in the table.
do({position, P}) ->
    true = ets:insert(?TAB, {position, P}),
    {position, P};
do(What) ->
    [{axis, A}] = ets:lookup(?TAB, axis),
    P = case ets:lookup(?TAB, position) of [{position, X}] -> X; [] -> 0 end,
    Reply = case What of
                {command, C} -> ?F:command(C, P, A);
                {event, E} -> {A1, Effects} = ?F:event(E, A), {ok, A1, Effects};
                {override, Pct} -> ?F:set_override(Pct, A)
            end,
    case Reply of
        {ok, A2, Effects2} ->
            true = ets:insert(?TAB, {axis, A2}),
            {ok, view(A2), Effects2};
        {error, _} = Error ->
            {Error, view(A)}
    end.

view(A) ->
    Job = case ?F:job(A) of
              undefined -> none;
              #{kind := K, id := Id} -> {K, Id}
          end,
    #{state => ?F:state(A), error => ?F:error_code(A), homed => ?F:homed(A), job => Job}.

%%--------------------------------------------------------------------
%% The rules
%%--------------------------------------------------------------------

next_state(M, _V, {call, _, do, [What]}) ->
    element(2, expect(What, M)).

postcondition(_M, {call, _, do, [{position, _}]}, _Result) ->
    true;
postcondition(M, {call, _, do, [What]}, Result) ->
    {Verdict, M1, Told} = expect(What, M),
    Seen = #{state => M1#m.state, error => M1#m.error, homed => M1#m.homed,
             job => M1#m.job},
    case {Verdict, Result} of
        {accept, {ok, View, Effects}} ->
            View =:= Seen andalso lists:sort(kinds(Effects)) =:= lists:sort(Told);
        {refuse, {{error, _}, View}} ->
            View =:= view_of(M);
        _ ->
            false
    end.

view_of(M) ->
    #{state => M#m.state, error => M#m.error, homed => M#m.homed, job => M#m.job}.

%% What each effect is, with the jobs named as the model names them.
kinds(Effects) ->
    [case E of
         {run, #{kind := K, id := Id}} -> {run, {K, Id}};
         {aborted, #{kind := K, id := Id}} -> {aborted, {K, Id}};
         {done, #{kind := K, id := Id}} -> {done, {K, Id}};
         {failed, #{kind := K, id := Id}, Code} -> {failed, {K, Id}, Code};
         {override, _} -> override;
         Other -> Other
     end || E <- Effects].

%% {accept | refuse, the model after it, the effects expected}.
expect({position, P}, M) ->
    {accept, M#m{position = P}, []};
expect({override, Pct}, #m{override = Old} = M) when Pct >= 0, Pct =< 100 ->
    %% A change is told to the NC.
    {accept, M#m{override = Pct}, [override || Pct =/= Old]};
expect({override, _}, M) ->
    {refuse, M, []};
%% An axis error: ErrorStop from any state; what runs fails; the NC stops the axis.
expect({event, {fault, Code}}, #m{state = error_stop} = M) ->
    {accept, M#m{error = Code}, []};
expect({event, {fault, Code}}, #m{job = Job} = M) ->
    {accept, idle(M#m{state = error_stop, error = Code}),
     [{failed, Job, Code} || Job =/= none] ++ [quick_stop]};
%% The NC's word that a job ended.
expect({event, {done, Id}}, #m{job = {stop, Id} = Job, stop_held = true} = M) ->
    {accept, M#m{stop_done = true}, [{done, Job}]};
expect({event, {done, Id}}, #m{job = {stop, Id} = Job} = M) ->
    {accept, idle(M#m{state = standstill}), [{done, Job}]};
expect({event, {done, Id}}, #m{job = {home, Id} = Job} = M) ->
    {accept, idle(M#m{state = standstill, homed = true}), [{done, Job}]};
expect({event, {done, Id}}, #m{job = {_, Id} = Job} = M) ->
    {accept, idle(M#m{state = standstill}), [{done, Job}]};
expect({event, {done, _}}, M) ->
    {accept, M, []};
%% MC_Reset.
expect({command, reset}, #m{state = error_stop, power = true} = M) ->
    {accept, M#m{state = standstill, error = 0}, []};
expect({command, reset}, #m{state = error_stop} = M) ->
    {accept, M#m{state = disabled, error = 0}, []};
expect({command, reset}, M) ->
    {accept, M, []};
%% MC_Power.
expect({command, {power, On}}, #m{state = error_stop} = M) ->
    {accept, M#m{power = On}, []};
expect({command, {power, true}}, #m{state = disabled} = M) ->
    {accept, M#m{state = standstill, power = true}, [power_on]};
expect({command, {power, true}}, M) ->
    {accept, M, []};
expect({command, {power, false}}, #m{state = disabled} = M) ->
    {accept, M, []};
expect({command, {power, false}}, #m{job = Job} = M) ->
    {accept, idle(M#m{state = disabled, power = false}),
     [{aborted, Job} || Job =/= none] ++ [power_off]};
%% MC_Stop's Execute falling: Stopping is left once the stop is done.
expect({command, {stop, false, _}}, #m{state = stopping, stop_done = true} = M) ->
    {accept, idle(M#m{state = standstill}), []};
expect({command, {stop, false, _}}, #m{state = stopping} = M) ->
    {accept, M#m{stop_held = false}, []};
expect({command, {stop, false, _}}, M) ->
    {accept, M, []};
%% No motion in Disabled or ErrorStop.
expect({command, _}, #m{state = S} = M) when S =:= disabled; S =:= error_stop ->
    {refuse, M, []};
%% MC_Stop from any moving or standing state.
expect({command, {stop, true, Dec}}, M) when Dec > 0 ->
    start(stop, stopping, (M#m{stop_held = true, stop_done = false}));
expect({command, {stop, true, _}}, M) ->
    {refuse, M, []};
expect({command, _}, #m{state = stopping} = M) ->
    {refuse, M, []};
expect({command, {home, _}}, #m{state = standstill} = M) ->
    start(home, homing, M);
expect({command, _}, #m{state = homing} = M) ->
    {refuse, M, []};
expect({command, {home, _}}, M) ->
    {refuse, M, []};
expect({command, {halt, Dec}}, M) when Dec > 0 ->
    start(halt, discrete_motion, M);
expect({command, {halt, _}}, M) ->
    {refuse, M, []};
expect({command, {move_absolute, _, _}}, #m{homed = false} = M) ->
    {refuse, M, []};
expect({command, {move_absolute, To, Params}}, M) ->
    move(To, Params, M);
expect({command, {move_relative, By, Params}}, #m{position = P} = M) ->
    move(P + By, Params, M);
expect({command, {follow, _}}, #m{homed = false} = M) ->
    {refuse, M, []};
expect({command, {follow, #{range := {Lo, Hi}}}}, M) ->
    {Min, Max} = ?LIMITS,
    case Lo >= Min andalso Lo =< Max andalso Hi >= Min andalso Hi =< Max of
        true -> start(follow, synchronized_motion, M);
        false -> {refuse, M, []}
    end.

move(To, #{velocity := V, acceleration := A, deceleration := D}, M) ->
    {Min, Max} = ?LIMITS,
    case V > 0 andalso A > 0 andalso D > 0 andalso To >= Min andalso To =< Max of
        true -> start(move, discrete_motion, M);
        false -> {refuse, M, []}
    end.

%% A new job: whatever ran is aborted, the NC runs the new one.
start(Kind, State, #m{job = Old, next_id = Id} = M) ->
    {accept, M#m{state = State, job = {Kind, Id}, next_id = Id + 1},
     [{aborted, Old} || Old =/= none] ++ [{run, {Kind, Id}}]}.

idle(M) ->
    M#m{job = none, stop_held = false, stop_done = false}.
