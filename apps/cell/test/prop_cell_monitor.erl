%% A PropEr state-machine model of the monitor's decisions (seed 000 §2.4.2: service
%% key and emergency voltage written to the controller, drive errors reset, warnings
%% for air pressure and an unlocked door), written from the seed's text and the
%% monitor's table in docs/architecture.md, never from the code. It drives the pure
%% core (cell_monitor_core) in simulated time: the inputs as the PLC would report them
%% (or unknown while its connection is down), the emergency stop from the panel, a
%% drive whose error clears after some reset pulses (or never), an operator's Retry,
%% and time passing to the next drive timer. A small world carries the effects out as
%% the monitor's process does (the controller's flags, the alarms on show, the
%% outputs, the timers) and feeds the controller's flags back.
%%
%% Checked after every command: the emergency stop is on exactly while the circuit is
%% open (once known) or the panel raised it, and the monitor never releases one it did
%% not raise; the service mode follows the key; a door warning while the door is not
%% locked, an air warning while the air is low; a drive in error is shown, pulsed at
%% most `drive_reset_attempts' times (never while the emergency stop is active: the
%% pulses start at its release), the waits growing, then handed to the operator, whose
%% Retry pulses again; the error clearing ends it all; the reset output is on only
%% during a pulse.
-module(prop_cell_monitor).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([input/2, panel_estop/1, drive_error/1, tick/0, retry/0]).
-export([prop_monitor/0]).

-define(TAB, prop_cell_monitor).
-define(ESTOP, {general, estop_voltage}).
-define(KEY, {general, service_key}).
-define(DOOR, {general, door_locked}).
-define(AIR, {general, air_ok}).
-define(X_ERROR, {axes, x_error}).
-define(X_RESET, {axes, x_reset}).
-define(ATTEMPTS, 3).

-record(m, {estop_ok = unknown :: boolean() | unknown,
            key = unknown :: boolean() | unknown,
            door = unknown :: boolean() | unknown,
            air = unknown :: boolean() | unknown,
            xerr = unknown :: boolean() | unknown,
            heal = never :: never | pos_integer(),      %% pulses that clear the error
            mon_raised = false :: boolean(),
            panel = false :: boolean(),
            service = false :: boolean(),
            door_warn = false :: boolean(),
            air_warn = false :: boolean(),
            x_shown = false :: boolean(),
            phase = idle :: idle | pulse | wait | failed,
            attempt = 0 :: non_neg_integer(),
            pulses = 0 :: non_neg_integer()}).          %% since the error came

monitor_test_() ->
    {timeout, 300, ?_assert(proper:quickcheck(prop_monitor(),
                                              [{to_file, user}, {numtests, 1000}]))}.

prop_monitor() ->
    ?FORALL(Cmds, commands(?MODULE),
            begin
                fresh(),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                ets:delete(?TAB),
                ?WHENFAIL(io:format(user, "History: ~p~nState: ~p~nResult: ~p~n",
                                    [History, State, Result]),
                          aggregate(command_names(Cmds), Result =:= ok))
            end).

%% -------------------------------------------------------------------------------------
%% The model
%% -------------------------------------------------------------------------------------

initial_state() -> #m{}.

command(M) ->
    Value = oneof([true, false, unknown]),
    frequency([{3, {call, ?MODULE, input, [estop_ok, Value]}},
               {2, {call, ?MODULE, input, [service_key, Value]}},
               {2, {call, ?MODULE, input, [door_locked, Value]}},
               {2, {call, ?MODULE, input, [air_ok, Value]}},
               {2, {call, ?MODULE, input, [x_error, oneof([false, unknown])]}},
               {3, {call, ?MODULE, drive_error, [oneof([never, never, 1, 2, 3, 4])]}},
               {2, {call, ?MODULE, panel_estop, [not M#m.panel]}}]
              ++ [{20, {call, ?MODULE, tick, []}} || M#m.phase =:= pulse orelse M#m.phase =:= wait]
              ++ [{3, {call, ?MODULE, retry, []}} || M#m.phase =:= failed]).

%% The panel releases only the emergency stop it raised, while the circuit is closed
%% (the controller's own rule); the error comes to a drive not yet in error.
precondition(M, {call, _, panel_estop, [false]}) ->
    M#m.panel andalso not M#m.mon_raised;
precondition(M, {call, _, panel_estop, [true]}) ->
    not M#m.panel andalso not M#m.mon_raised;
precondition(M, {call, _, drive_error, _}) -> M#m.xerr =/= true;
precondition(M, {call, _, tick, []}) -> M#m.phase =:= pulse orelse M#m.phase =:= wait;
precondition(M, {call, _, retry, []}) -> M#m.phase =:= failed;
precondition(_, _) -> true.

estop(M) -> M#m.mon_raised orelse M#m.panel.

next_state(M, _, {call, _, input, [Role, V]}) ->
    settle(input_(Role, V, M));
next_state(M, _, {call, _, drive_error, [Heal]}) ->
    settle(error_comes(M#m{heal = Heal}));
next_state(M, _, {call, _, panel_estop, [On]}) ->
    settle(estop_changed(M, M#m{panel = On}));
next_state(#m{phase = pulse} = M, _, {call, _, tick, []}) ->
    settle(M#m{phase = wait});
next_state(#m{phase = wait, attempt = A} = M, _, {call, _, tick, []}) when A < ?ATTEMPTS ->
    settle(pulse(M, A + 1));
next_state(#m{phase = wait} = M, _, {call, _, tick, []}) ->
    %% The resets did not help: the warning becomes an error for the operator.
    settle(M#m{phase = failed, x_shown = false});
next_state(M, _, {call, _, retry, []}) ->
    %% Retry pulses again an error still there (while its state is unknown, or the
    %% emergency stop is active, the drive waits as a new error would).
    settle(case {M#m.xerr, estop(M)} of
               {true, false} -> pulse(M#m{x_shown = true}, 1);
               {true, true} -> M#m{phase = idle, attempt = 0, x_shown = true};
               _ -> M#m{phase = idle, attempt = 0}
           end);
next_state(M, _, _) ->
    M.

%% The circuit opening is the monitor's emergency stop, whoever raised one before
%% (the panel's is left to the panel only while the circuit is closed).
input_(estop_ok, false, M) ->
    estop_changed(M, M#m{estop_ok = false, mon_raised = true, panel = false});
input_(estop_ok, true, #m{mon_raised = true} = M) ->
    estop_changed(M, M#m{estop_ok = true, mon_raised = false});
input_(estop_ok, V, M) ->
    M#m{estop_ok = V};
input_(service_key, V, M) when is_boolean(V) ->
    M#m{key = V, service = V};
input_(service_key, V, M) ->
    M#m{key = V};
input_(door_locked, V, M) when is_boolean(V) -> M#m{door = V, door_warn = not V};
input_(door_locked, V, M) -> M#m{door = V};
input_(air_ok, V, M) when is_boolean(V) -> M#m{air = V, air_warn = not V};
input_(air_ok, V, M) -> M#m{air = V};
input_(x_error, false, M) ->
    %% The error clearing ends it all.
    M#m{xerr = false, x_shown = false, phase = idle, attempt = 0};
input_(x_error, unknown, #m{phase = failed} = M) ->
    M#m{xerr = unknown};
input_(x_error, unknown, M) ->
    M#m{xerr = unknown, phase = idle, attempt = 0}.

%% The error comes: shown; reset unless the emergency stop is active.
error_comes(#m{phase = failed} = M) ->
    %% Handed to the operator: so it stays until answered or the error clears.
    M#m{xerr = true, x_shown = true, pulses = 0};
error_comes(M) ->
    M1 = M#m{xerr = true, x_shown = true, pulses = 0},
    case estop(M1) of
        true -> M1;
        false -> pulse(M1, 1)
    end.

%% No pulses while the emergency stop is active; they start at its release.
estop_changed(Old, New) ->
    case {estop(Old), estop(New)} of
        {false, true} when New#m.phase =:= pulse; New#m.phase =:= wait ->
            New#m{phase = idle, attempt = 0};
        {true, false} when New#m.xerr =:= true, New#m.phase =:= idle ->
            pulse(New, 1);
        _ ->
            New
    end.

pulse(M, Attempt) ->
    M#m{phase = pulse, attempt = Attempt, pulses = M#m.pulses + 1}.

%% A drive that heals after its Nth pulse reports its error gone.
settle(#m{xerr = true, heal = N, pulses = N} = M) ->
    input_(x_error, false, M);
settle(M) ->
    M.

postcondition(M, Call, World) ->
    M1 = next_state(M, World, Call),
    Want = expected(M1),
    Got = maps:with(maps:keys(Want), World),
    case Got =:= Want of
        true -> true;
        false -> io:format(user, "~nFailed ~p:~n want ~p~n got  ~p~n", [Call, Want, Got]), false
    end.

expected(M) ->
    Timer = case M#m.phase of
                pulse -> #{{reset_pulse, x} => 200};
                wait -> #{{reset_wait, x} => 1000 bsl (M#m.attempt - 1)};
                _ -> #{}
            end,
    #{estop => estop(M),
      service_mode => M#m.service,
      alarms => maps:from_list([{<<"door">>, warning} || M#m.door_warn]
                               ++ [{<<"air">>, warning} || M#m.air_warn]
                               ++ [{<<"drive.x">>, warning} || M#m.x_shown]
                               ++ [{<<"drive.x.failed">>, error} || M#m.phase =:= failed]),
      reset => M#m.phase =:= pulse,
      pulses => M#m.pulses,
      drive_timers => Timer}.

%% -------------------------------------------------------------------------------------
%% The world: the core's effects carried out as the monitor's process does
%% -------------------------------------------------------------------------------------

fresh() ->
    _ = ets:new(?TAB, [named_table, public]),
    Cell = #{state => off, request => stop, estop => false, service_mode => false,
             has_alarm => false, has_error => false, has_warning => false},
    {Core, Effects} = cell_monitor_core:new(cell_monitor_core_tests:spec(),
                                            #{settings => settings(), speed => 50,
                                              cell => Cell}),
    true = ets:insert(?TAB, [{core, Core}, {cell, Cell}, {heal, never},
                             {world, #{estop => false, service_mode => false, alarms => #{},
                                       outputs => #{}, timers => #{}, pulses => 0}}]),
    apply_effects(Effects),
    _ = [handle(E) || E <- [{device, {connection, plc1}, up}, {device, {hardware, camera}, up},
                            start]],
    ok.

settings() -> cell_settings_schema:defaults(cell_monitor_settings).

input(Role, V) ->
    P = maps:get(Role, #{estop_ok => ?ESTOP, service_key => ?KEY, door_locked => ?DOOR,
                         air_ok => ?AIR, x_error => ?X_ERROR}),
    handle({point, P, V}),
    observe().

%% The drive reports an error, which its Nth reset pulse clears (or none does).
drive_error(Heal) ->
    true = ets:insert(?TAB, [{heal, Heal}]),
    world(fun(W) -> W#{pulses := 0} end),
    handle({point, ?X_ERROR, true}),
    observe().

panel_estop(On) ->
    Cell = ets:lookup_element(?TAB, cell, 2),
    world(fun(W) -> W#{estop := On} end),
    cell(Cell#{estop := On}),
    observe().

%% Time passes to the drive's pending timer.
tick() ->
    #{timers := Timers} = ets:lookup_element(?TAB, world, 2),
    [T] = [T || {_, x} = T <- maps:keys(Timers)],
    world(fun(W) -> W#{timers := maps:remove(T, Timers)} end),
    handle({timeout, T}),
    observe().

retry() ->
    handle({answer, <<"drive.x.failed">>, retry}),
    world(fun(#{alarms := A} = W) -> W#{alarms := maps:remove(<<"drive.x.failed">>, A)} end),
    observe().

%% An observation, its effects carried out, then what they made the world report (as
%% messages to the monitor's process, which come after it has done all of them).
handle(Event) ->
    {Core, Effects} = cell_monitor_core:handle(Event, ets:lookup_element(?TAB, core, 2)),
    true = ets:insert(?TAB, {core, Core}),
    apply_effects(Effects),
    case ets:take(?TAB, next) of
        [{next, Next}] -> handle(Next);
        [] -> ok
    end.

cell(Cell) ->
    true = ets:insert(?TAB, {cell, Cell}),
    handle({cell, Cell}).

apply_effects(Effects) ->
    lists:foreach(fun effect/1, Effects).

%% The controller takes the flag and tells the monitor of its new flags.
effect({estop, On}) ->
    world(fun(W) -> W#{estop := On} end),
    flags(estop, On);
effect({service_mode, On}) ->
    world(fun(W) -> W#{service_mode := On} end),
    flags(service_mode, On);
effect({warning, Id, _, _}) ->
    alarm(Id, warning);
effect({error, Id, _, _}) ->
    alarm(Id, error);
effect({reset_warning, Id}) ->
    world(fun(#{alarms := A} = W) ->
                  W#{alarms := case A of
                                   #{Id := warning} -> maps:remove(Id, A);
                                   _ -> A
                               end}
          end);
effect({withdraw, Id}) ->
    world(fun(#{alarms := A} = W) -> W#{alarms := maps:remove(Id, A)} end);
effect({write, P, V}) ->
    #{outputs := Out, pulses := N} = ets:lookup_element(?TAB, world, 2),
    Rising = P =:= ?X_RESET andalso V =:= true andalso maps:get(P, Out, false) =/= true,
    world(fun(W) -> W#{outputs := Out#{P => V}, pulses := N + case Rising of
                                                                 true -> 1;
                                                                 false -> 0
                                                             end}
          end),
    %% The drive's error goes with its Nth pulse.
    _ = Rising andalso ets:lookup_element(?TAB, heal, 2) =:= N + 1
        andalso ets:insert(?TAB, {next, {point, ?X_ERROR, false}}),
    ok;
effect({timer, T, Ms}) ->
    world(fun(#{timers := Ts} = W) -> W#{timers := Ts#{T => Ms}} end);
effect({cancel, T}) ->
    world(fun(#{timers := Ts} = W) -> W#{timers := maps:remove(T, Ts)} end);
effect({log, _, _, _}) ->
    ok.

%% The controller's flags come back to the monitor as an event of their own.
flags(Key, On) ->
    Cell = ets:lookup_element(?TAB, cell, 2),
    true = ets:insert(?TAB, {cell, Cell#{Key := On}}),
    true = ets:insert(?TAB, {next, {cell, Cell#{Key := On}}}),
    ok.

alarm(Id, Kind) ->
    world(fun(#{alarms := A} = W) -> W#{alarms := A#{Id => Kind}} end).

world(Fun) ->
    true = ets:insert(?TAB, {world, Fun(ets:lookup_element(?TAB, world, 2))}).

observe() ->
    #{estop := E, service_mode := S, alarms := A, outputs := Out, timers := Ts, pulses := N} =
        ets:lookup_element(?TAB, world, 2),
    #{estop => E, service_mode => S, alarms => A, reset => maps:get(?X_RESET, Out, false),
      pulses => N, drive_timers => maps:filter(fun({_, X}, _) -> X =:= x; (_, _) -> false end, Ts)}.
