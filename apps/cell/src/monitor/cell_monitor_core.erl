%% @doc The monitor's decisions (seed 000 §2.4.2), as pure functions: what it observes
%% goes in as an event, what it must do comes out as a list of effects, which {@link
%% cell_monitor} carries out. Nothing here sends, reads or waits, so every decision is
%% tested without a process.
%%
%% Observations ({@link event()}): a watched input's value (`unknown' while its
%% connection is down), a connection or hardware object going up or down, the cell's
%% state and flags, the machine's speed override, the monitor's settings, a timer, an
%% operator's answer to one of the monitor's errors, and `start' once everything is
%% attached.
%%
%% Decisions:
%% <ul>
%% <li><b>Emergency stop.</b> The circuit opening (`estop_ok' false) raises the
%%   controller's emergency stop; its closing releases it, if the monitor raised it.
%%   An emergency stop raised from the panel or the shell stays until released
%%   there. While the input is unknown nothing changes.</li>
%% <li><b>Service key.</b> Every turn of the key sets the controller's service mode.
%%   When the key's position becomes known (at start, after a reconnect) it is applied
%%   only if it differs from the service mode in force.</li>
%% <li><b>Door and air.</b> A door not locked, the air pressure low: a warning each,
%%   reset when the input is good again; texts from the settings.</li>
%% <li><b>Drives.</b> A drive's warning bit shows a warning naming it. Its error bit
%%   shows a warning naming it (with its error code) and pulses its reset output:
%%   `drive_reset_attempts' pulses of `drive_reset_pulse_ms', waiting
%%   `drive_reset_wait_ms' after the first and twice as long after each next. If the
%%   error stays, the warning becomes an error for the operator, whose Retry starts
%%   the resets again. No reset is tried while the emergency stop is active (drives
%%   report errors then by design); they start when it is released.</li>
%% <li><b>Speed override.</b> The machine's `speed_override' is written to every
%%   drive's override point, at once and whenever it changes, running or not; in
%%   service mode it is capped at `service_speed_limit'.</li>
%% <li><b>Devices.</b> A connection or hardware object that goes down is reported at
%%   once, as an error or a warning by its severity, and cleared when it is back; at
%%   start a device has `connect_grace_ms' to come up before it is reported. The
%%   outputs of a connection that comes back are written again: a PLC may have put
%%   them in a safe state while the link was down, and the HAL never re-asserts
%%   outputs by itself.</li>
%% <li><b>Beacon.</b> The lamps follow {@link cell_beacon:lamps/2} under the
%%   settings' rules; while any lamp blinks, one timer toggles the phase every half
%%   `blink_period_ms'.</li>
%% </ul>
%%
%% Alarm ids (local to the task `cell'): `door', `air', `drive.<id>' (its error),
%% `drive.<id>.warning', `drive.<id>.failed' (resets did not help),
%% `connection.<id>', `hardware.<id>'.
-module(cell_monitor_core).

-export([new/2, handle/2, info/1]).

-export_type([core/0, event/0, effect/0, timer/0, cell/0]).

-type point() :: cell_monitor_spec:point().
-type device() :: cell_monitor_spec:device().
-type value() :: cell_hal_type:value().
-type cell() :: cell_beacon:cell().
-type timer() :: blink | {grace, device()} | {reset_pulse, atom()} | {reset_wait, atom()}.
-type event() :: {point, point(), value() | unknown}
               | {device, device(), up | {down, binary()}}
               | {cell, cell()}
               | {speed, 1..100}
               | {settings, map()}
               | {timeout, timer()}
               | {answer, binary(), cell_alarms:solution()}
               | start.
-type effect() :: {estop, boolean()}
                | {service_mode, boolean()}
                | {warning, binary(), binary(), binary()}
                | {reset_warning, binary()}
                | {error, binary(), binary(), binary()}
                | {withdraw, binary()}
                | {write, point(), value()}
                | {timer, timer(), non_neg_integer()}
                | {cancel, timer()}
                | {log, cell_log:level(), io:format(), [term()]}
                %% The speed override for an axis or interpolation channel.
                | {override, axis | channel, atom(), 1..100}.

-record(drive, {spec :: cell_monitor_spec:drive(),
                error = unknown :: boolean() | unknown,
                warning = unknown :: boolean() | unknown,
                code = unknown :: integer() | unknown,
                phase = idle :: idle | pulse | wait | failed,
                attempt = 0 :: non_neg_integer(),
                shown = false :: boolean()}).                  %% its error is on show

-record(dev, {severity :: cell_monitor_spec:severity(),
              status = starting :: starting | up | down,
              detail = <<>> :: binary(),
              was_up = false :: boolean(),
              reported = false :: boolean()}).

-record(core, {io :: #{cell_monitor_spec:role() => point()},
               info :: #{point() => cell_monitor_spec:point_info()},
               kinds :: #{atom() => cell_hal_hw:kind()},
               drives :: #{atom() => #drive{}},
               devices :: #{device() => #dev{}},
               settings :: map(),
               speed :: 1..100,
               cell :: cell(),
               values = #{} :: #{point() => value() | unknown},
               estop_raised = false :: boolean(),
               lamps :: #{cell_beacon:lamp() => cell_beacon:mode()},
               phase = on :: cell_beacon:phase(),
               outputs = #{} :: #{point() => value()},
               applied :: 1..100 | undefined,                %% the override last written
               errors = #{} :: #{binary() => true}}).

-opaque core() :: #core{}.

%%====================================================================
%% API
%%====================================================================

%% @doc A monitor for a validated spec (the `hal' and `monitor' keys), with the
%% monitor's settings, the machine's speed override and the cell's flags as they are
%% now; the effects put the outputs in their first state.
-spec new(#{hal := cell_monitor_spec:hal(), monitor := cell_monitor_spec:monitor()},
          #{settings := map(), speed := 1..100, cell := cell(), estop_raised => boolean()}) ->
          {core(), [effect()]}.
new(#{hal := Hal, monitor := #{io := Io, drives := Drives} = Mon} = Spec,
    #{settings := Settings, speed := Speed, cell := Cell} = Opts) ->
    Info = cell_monitor_spec:points(Hal, Mon),
    Core0 = #core{io = Io, info = Info,
                  kinds = maps:from_list([{Id, K}
                                          || #{id := Id, kind := K} <- maps:get(hardware, Hal)]),
                  drives = maps:from_list([{Id, #drive{spec = D}} || #{id := Id} = D <- Drives]),
                  devices = maps:from_list([{Dev, #dev{severity = S}}
                                            || {Dev, S} <- cell_monitor_spec:devices(Spec)]),
                  settings = Settings, speed = Speed, cell = Cell,
                  %% An emergency stop the circuit raised before (a monitor restarted):
                  %% released when the circuit reads closed.
                  estop_raised = maps:get(estop_raised, Opts, false),
                  lamps = maps:from_list([{L, off} || L <- cell_beacon:lamps()])},
    %% Every output starts from a known state: resets off, lamps and overrides as due.
    {Core1, E1} = lists:foldl(fun(#{reset := P}, {C, E}) -> output(P, false, C, E);
                                 (_, Acc) -> Acc
                              end, {Core0, []}, Drives),
    {Core2, E2} = beacon(Core1, E1),
    overrides(Core2, E2).

%% @doc Decides what an observation leads to.
-spec handle(event(), core()) -> {core(), [effect()]}.
handle({point, P, V}, #core{values = Values} = C) ->
    Old = maps:get(P, Values, unknown),
    case V =:= Old of
        true -> {C, []};
        false -> point_changed(P, Old, V, C#core{values = Values#{P => V}})
    end;
handle({device, Dev, Status}, #core{devices = Devs} = C) ->
    case maps:find(Dev, Devs) of
        {ok, D} -> device(Dev, Status, D, C);
        error -> {C, []}
    end;
handle({cell, Cell}, #core{cell = Old} = C) ->
    cell_changed(Old, Cell, C#core{cell = Cell});
handle({speed, Speed}, C) ->
    overrides(C#core{speed = Speed}, []);
handle({settings, S}, C) ->
    {C1, E1} = beacon(C#core{settings = S}, []),
    {C2, E2} = overrides(C1, E1),
    retext(C2, E2);
handle({timeout, T}, C) ->
    timeout(T, C);
handle({answer, Id, retry}, #core{errors = Errors} = C) ->
    answer(Id, C#core{errors = maps:remove(Id, Errors)});
handle({answer, Id, _Other}, #core{errors = Errors} = C) ->
    {C#core{errors = maps:remove(Id, Errors)}, []};
handle(start, #core{devices = Devs} = C) ->
    Grace = setting(connect_grace_ms, C),
    {C, [{timer, {grace, Dev}, Grace} || {Dev, #dev{status = starting}} <- maps:to_list(Devs)]}.

%% @doc What the monitor sees and does now, for the operator's shell and the tests.
-spec info(core()) -> map().
info(#core{io = Io, values = Values, lamps = Lamps, devices = Devs, drives = Drives,
           outputs = Outputs} = C) ->
    #{beacon => Lamps,
      inputs => maps:from_list([{Role, maps:get(P, Values, unknown)}
                                || {Role, P} <- maps:to_list(Io),
                                   lists:member(Role, cell_monitor_spec:inputs())]),
      outputs => Outputs,
      devices => maps:from_list([{Id, S} || {{_, Id}, #dev{status = S}} <- maps:to_list(Devs)]),
      drives => maps:map(fun(_, #drive{spec = Spec, error = E, warning = W, code = Code,
                                       phase = Ph, attempt = A}) ->
                                 Known = maps:with(maps:keys(Spec),
                                                   #{error => E, warning => W, code => Code}),
                                 Known#{reset => Ph, attempt => A}
                         end, Drives),
      speed_override => effective_speed(C),
      estop_raised => C#core.estop_raised}.

%%====================================================================
%% Inputs
%%====================================================================

point_changed(P, Old, V, #core{io = Io, drives = Drives} = C) ->
    Roles = [R || {R, Q} <- maps:to_list(Io), Q =:= P],
    {C1, E1} = lists:foldl(fun(R, {Ci, Ei}) -> role(R, Old, V, Ci, Ei) end, {C, []},
                           lists:sort(Roles)),
    Uses = [{Id, K} || {Id, #drive{spec = S}} <- lists:sort(maps:to_list(Drives)),
                       K <- [error, warning, code], maps:get(K, S, none) =:= P],
    lists:foldl(fun({Id, K}, {Ci, Ei}) -> drive_input(Id, K, V, Ci, Ei) end, {C1, E1}, Uses).

%% The monitor knows of an emergency stop it raised before the controller's event
%% about it arrives: resets hold from the moment the circuit opened.
role(estop_ok, _Old, false, C, E) ->
    estop_edge(estop_active(C), C#core{estop_raised = true}, E ++ [{estop, true}]);
role(estop_ok, _Old, true, #core{estop_raised = true} = C, E) ->
    estop_edge(estop_active(C), C#core{estop_raised = false}, E ++ [{estop, false}]);
role(service_key, unknown, On, #core{cell = #{service_mode := On}} = C, E) ->
    {C, E};
role(service_key, _Old, On, C, E) when is_boolean(On) ->
    {C, E ++ [{service_mode, On}]};
role(door_locked, _Old, false, C, E) ->
    {C, E ++ [door_warning(C)]};
role(door_locked, _Old, true, C, E) ->
    {C, E ++ [{reset_warning, <<"door">>}]};
role(air_ok, _Old, false, C, E) ->
    {C, E ++ [air_warning(C)]};
role(air_ok, _Old, true, C, E) ->
    {C, E ++ [{reset_warning, <<"air">>}]};
role(_Role, _Old, _V, C, E) ->
    %% unknown (the connection is down: its loss is reported as such), or estop_ok
    %% closing on an emergency stop the monitor did not raise.
    {C, E}.

door_warning(C) ->
    {warning, <<"door">>, setting(door_caption, C), setting(door_text, C)}.

air_warning(C) ->
    {warning, <<"air">>, setting(air_caption, C), setting(air_text, C)}.

%%====================================================================
%% Drives
%%====================================================================

drive_input(Id, K, V, #core{drives = Drives} = C, E) ->
    D = maps:get(Id, Drives),
    D1 = case K of
             error -> D#drive{error = V};
             warning -> D#drive{warning = V};
             code -> D#drive{code = V}
         end,
    C1 = C#core{drives = Drives#{Id := D1}},
    case {K, V} of
        {error, true} -> drive_error(Id, C1, E);
        {error, false} -> drive_ok(Id, C1, E);
        {error, unknown} -> stop_resets(Id, C1, E);
        {warning, true} -> {C1, E ++ [drive_warning(D1)]};
        {warning, false} -> {C1, E ++ [{reset_warning, drive_id(Id, <<".warning">>)}]};
        {warning, unknown} -> {C1, E};
        {code, _} -> drive_code(D1, C1, E)
    end.

%% A drive in error: shown, and reset unless the emergency stop is active.
drive_error(Id, #core{drives = Drives} = C0, E) ->
    #drive{spec = Spec, phase = Phase} = D = maps:get(Id, Drives),
    C = C0#core{drives = Drives#{Id := D#drive{shown = true}}},
    case {Phase, maps:is_key(reset, Spec), estop_active(C)} of
        {idle, true, false} -> pulse(Id, 1, C, E);
        _ -> {C, E ++ [error_warning(maps:get(Id, C#core.drives), C)]}
    end.

%% The error is gone. Its warning is reset even if this monitor never showed it (one
%% that ran before it may have).
drive_ok(Id, C, E) ->
    {C1, E1} = stop_resets(Id, C, E),
    #drive{spec = #{caption := Caption}, shown = Shown} = D = maps:get(Id, C1#core.drives),
    C2 = C1#core{drives = (C1#core.drives)#{Id := D#drive{phase = idle, attempt = 0,
                                                          shown = false}}},
    {C3, E3} = withdraw(drive_id(Id, <<".failed">>), C2, E1),
    {C3, E3 ++ [{reset_warning, drive_id(Id)}]
         ++ [{log, brief, "drive ~ts: error cleared", [Caption]} || Shown]}.

%% No more pulses: the reset output off, the timers cancelled. A drive handed to the
%% operator stays so until answered or its error clears.
stop_resets(Id, #core{drives = Drives} = C, E) ->
    #drive{spec = Spec, phase = Phase} = D = maps:get(Id, Drives),
    C1 = C#core{drives = Drives#{Id := D#drive{phase = idle, attempt = 0}}},
    case Phase of
        pulse ->
            {C2, E2} = output(maps:get(reset, Spec), false, C1, E),
            {C2, E2 ++ [{cancel, {reset_pulse, Id}}]};
        wait ->
            {C1, E ++ [{cancel, {reset_wait, Id}}]};
        _ ->
            {C, E}
    end.

pulse(Id, Attempt, #core{drives = Drives} = C, E) ->
    #drive{spec = #{reset := P, caption := Caption}} = D = maps:get(Id, Drives),
    D1 = D#drive{phase = pulse, attempt = Attempt},
    C1 = C#core{drives = Drives#{Id := D1}},
    {C2, E2} = output(P, true, C1, E),
    {C2, E2 ++ [error_warning(D1, C2),
                {log, brief, "drive ~ts: error~ts; reset ~b of ~b",
                 [Caption, code_text(D1), Attempt, setting(drive_reset_attempts, C)]},
                {timer, {reset_pulse, Id}, setting(drive_reset_pulse_ms, C)}]}.

drive_code(#drive{error = true, phase = Phase} = D, C, E) when Phase =/= failed ->
    {C, E ++ [error_warning(D, C)]};
drive_code(#drive{warning = true} = D, C, E) ->
    {C, E ++ [drive_warning(D)]};
drive_code(_D, C, E) ->
    {C, E}.

error_warning(#drive{spec = #{id := Id, caption := Caption} = Spec, phase = Phase,
                     attempt = A} = D, C) ->
    Doing = case {maps:is_key(reset, Spec), Phase, estop_active(C)} of
                {false, _, _} -> "Check the drive.";
                {true, _, true} ->
                    "It will be reset when the emergency stop is released.";
                {true, idle, false} -> "Check the drive.";
                {true, _, false} ->
                    io_lib:format("The cell is resetting it (reset ~b of ~b).",
                                  [A, setting(drive_reset_attempts, C)])
            end,
    {warning, drive_id(Id), text(["Drive ", Caption, " in error"]),
     text(["The drive ", Caption, " reports an error", code_text(D), ". ", Doing])}.

drive_warning(#drive{spec = #{id := Id, caption := Caption}} = D) ->
    {warning, drive_id(Id, <<".warning">>), text(["Drive ", Caption, " warns"]),
     text(["The drive ", Caption, " reports a warning", code_text(D),
           ". It runs on; check it at the next stop."])}.

code_text(#drive{code = Code}) when is_integer(Code), Code =/= 0 ->
    io_lib:format(" (code ~b, 0x~.16B)", [Code, Code]);
code_text(_) ->
    "".

%%====================================================================
%% Devices
%%====================================================================

device(_Dev, up, #dev{status = up}, C) ->
    {C, []};
device(Dev, up, #dev{status = Status} = D, C) ->
    E0 = [{cancel, {grace, Dev}} || Status =:= starting],
    {C1, E1} = case D#dev.reported of
                   true ->
                       Back = {log, brief, "~ts is back", [device_name(Dev, C)]},
                       clear_device(Dev, D, C, E0 ++ [Back]);
                   false -> {C, E0}
               end,
    %% A warning a monitor before this one left is reset when the device is first seen up.
    E2 = E1 ++ [{reset_warning, device_id(Dev)}
                || Status =:= starting, D#dev.severity =:= warning],
    C2 = set_dev(Dev, D#dev{status = up, was_up = true, reported = false, detail = <<>>}, C1),
    reassert(Dev, C2, E2);
device(Dev, {down, Detail}, #dev{status = starting} = D, C) ->
    {set_dev(Dev, D#dev{detail = Detail}, C), []};
device(Dev, {down, Detail}, #dev{status = up} = D, C) ->
    report(Dev, D#dev{status = down, detail = Detail}, C, []);
device(Dev, {down, Detail}, #dev{status = down, reported = true, severity = warning} = D, C)
  when Detail =/= D#dev.detail ->
    %% A warning's text follows the latest reason.
    report(Dev, D#dev{detail = Detail}, C, []);
device(Dev, {down, Detail}, #dev{status = down} = D, C) ->
    {set_dev(Dev, D#dev{detail = Detail}, C), []}.

set_dev(Dev, D, #core{devices = Devs} = C) ->
    C#core{devices = Devs#{Dev := D}}.

report(Dev, #dev{severity = Sev} = D, C, E) ->
    Id = device_id(Dev),
    {Caption, Text} = device_text(Dev, D, C),
    C1 = set_dev(Dev, D#dev{reported = true}, C),
    case Sev of
        warning -> {C1, E ++ [{warning, Id, Caption, Text}]};
        error -> raise(Id, Caption, Text, C1, E)
    end.

clear_device(Dev, #dev{severity = warning}, C, E) ->
    {C, E ++ [{reset_warning, device_id(Dev)}]};
clear_device(Dev, #dev{severity = error}, C, E) ->
    withdraw(device_id(Dev), C, E).

device_text({connection, Id} = Dev, #dev{was_up = WasUp, detail = Detail}, C) ->
    Caption = case WasUp of
                  true -> ["Connection to ", atom_to_binary(Id), " lost"];
                  false -> ["Cannot connect to ", atom_to_binary(Id)]
              end,
    {text(Caption),
     text([device_name(Dev, C), " is not connected", detail(Detail),
           ". The cell keeps trying to connect; tasks that use its IO wait until it is "
           "back. Check the cable and that the device is on."])};
device_text({hardware, _} = Dev, #dev{detail = Detail}, C) ->
    {text([device_name(Dev, C), " not connected"]),
     text([device_name(Dev, C), " is not connected", detail(Detail),
           ". Operations that need it fail until it is back. Check its cable and "
           "power."])}.

detail(<<>>) -> "";
detail(D) -> [": ", D].

device_name({connection, Id}, _C) ->
    ["PLC connection ", atom_to_binary(Id)];
device_name({hardware, Id}, #core{kinds = Kinds}) ->
    Kind = case maps:get(Id, Kinds, camera) of
               camera -> "Camera ";
               code_reader -> "Code reader ";
               laser_marker -> "Laser marker ";
               axis -> "Axis ";
               channel -> "Interpolation channel "
           end,
    [Kind, atom_to_binary(Id)].

%% The outputs of a connection that came back are written again.
reassert({connection, Conn}, #core{outputs = Outputs, info = Info} = C, E) ->
    {C, E ++ [{write, P, V} || {P, V} <- lists:sort(maps:to_list(Outputs)),
                               maps:get(connection, maps:get(P, Info)) =:= Conn]};
reassert({hardware, Id}, #core{kinds = Kinds} = C, E) ->
    %% An axis or channel that came back (a new process) runs at 100 % until told.
    case maps:get(Id, Kinds, camera) of
        K when K =:= axis; K =:= channel -> {C, E ++ [{override, K, Id, effective_speed(C)}]};
        _ -> {C, E}
    end.

%%====================================================================
%% The cell's flags: beacon, emergency stop, service mode
%%====================================================================

cell_changed(Old, New, #core{estop_raised = Raised} = C) ->
    {C1, E1} = beacon(C, []),
    {C2, E2} = estop_edge(maps:get(estop, Old) orelse Raised, C1, E1),
    case maps:get(service_mode, Old) =:= maps:get(service_mode, New) of
        true -> {C2, E2};
        false -> overrides(C2, E2)
    end.

%% The emergency stop is active while the controller says so or while the circuit the
%% monitor watches is open, whichever it learnt of first.
estop_edge(WasActive, C, E) ->
    case {WasActive, estop_active(C)} of
        {false, true} -> estop_holds_resets(C, E);
        {true, false} -> estop_released(C, E);
        _ -> {C, E}
    end.

%% Resets under way stop; the drives' warnings say they wait for the release.
estop_holds_resets(#core{drives = Drives} = C, E) ->
    lists:foldl(fun({Id, #drive{error = true, phase = Phase}}, {Ci, Ei}) when Phase =/= failed ->
                        {Ci1, Ei1} = stop_resets(Id, Ci, Ei),
                        {Ci1, Ei1 ++ [error_warning(maps:get(Id, Ci1#core.drives), Ci1)]};
                   (_, Acc) ->
                        Acc
                end, {C, E}, lists:sort(maps:to_list(Drives))).

estop_released(#core{drives = Drives} = C, E) ->
    lists:foldl(fun({Id, #drive{error = true, phase = idle}}, {Ci, Ei}) ->
                        drive_error(Id, Ci, Ei);
                   (_, Acc) ->
                        Acc
                end, {C, E}, lists:sort(maps:to_list(Drives))).

estop_active(#core{cell = #{estop := On}, estop_raised = Raised}) -> On orelse Raised.

beacon(#core{cell = Cell, lamps = Old} = C, E) ->
    Lamps = cell_beacon:lamps(Cell, setting(beacon, C)),
    Timer = case {cell_beacon:blinking(Old), cell_beacon:blinking(Lamps)} of
                {false, true} -> [{timer, blink, half_period(C)}];
                {true, false} -> [{cancel, blink}];
                _ -> []
            end,
    Phase = case cell_beacon:blinking(Lamps) of
                true -> C#core.phase;
                false -> on
            end,
    lamp_outputs(C#core{lamps = Lamps, phase = Phase}, E ++ Timer).

lamp_outputs(#core{io = Io, lamps = Lamps, phase = Phase} = C, E) ->
    Outs = cell_beacon:outputs(Lamps, Phase),
    lists:foldl(fun(L, {Ci, Ei}) ->
                        case maps:find(lamp_role(L), Io) of
                            {ok, P} -> output(P, maps:get(L, Outs), Ci, Ei);
                            error -> {Ci, Ei}
                        end
                end, {C, E}, cell_beacon:lamps()).

lamp_role(red) -> beacon_red;
lamp_role(yellow) -> beacon_yellow;
lamp_role(green) -> beacon_green;
lamp_role(blue) -> beacon_blue.

half_period(C) -> setting(blink_period_ms, C) div 2.

%%====================================================================
%% Speed override
%%====================================================================

effective_speed(#core{speed = Speed, cell = #{service_mode := true}} = C) ->
    min(Speed, setting(service_speed_limit, C));
effective_speed(#core{speed = Speed}) ->
    Speed.

overrides(#core{drives = Drives, info = Info, applied = Applied, kinds = Kinds} = C, E) ->
    Speed = effective_speed(C),
    Points = [{P, Scale} || {_, #drive{spec = #{override := P, override_scale := Scale}}}
                                <- lists:sort(maps:to_list(Drives))],
    %% Axes and channels take the override as a command (seed 000 §2.4: applied to
    %% the axes even while the machine runs).
    Motion = [{K, Id} || {Id, K} <- lists:sort(maps:to_list(Kinds)),
                         K =:= axis orelse K =:= channel],
    {C1, E1} = lists:foldl(fun({P, Scale}, {Ci, Ei}) ->
                                   #{type := T} = maps:get(P, Info),
                                   V = cell_monitor_spec:override_value(T, Speed, Scale),
                                   output(P, V, Ci, Ei)
                           end, {C, E}, Points),
    case (Points =/= [] orelse Motion =/= []) andalso Speed =/= Applied of
        true ->
            Why = case Speed < C#core.speed of
                      true -> " (the service mode limit)";
                      false -> ""
                  end,
            Logs = [{log, brief, "speed override ~b %~ts on ~b drives",
                     [Speed, Why, length(Points)]} || Points =/= []]
                ++ [{log, brief, "speed override ~b %~ts on ~b axes and channels",
                     [Speed, Why, length(Motion)]} || Motion =/= []],
            {C1#core{applied = Speed},
             E1 ++ [{override, K, Id, Speed} || {K, Id} <- Motion] ++ Logs};
        false ->
            {C1, E1}
    end.

%%====================================================================
%% Timers and answers
%%====================================================================

timeout(blink, #core{phase = Phase} = C) ->
    Next = case Phase of on -> off; off -> on end,
    case cell_beacon:blinking(C#core.lamps) of
        true ->
            {C1, E1} = lamp_outputs(C#core{phase = Next}, []),
            {C1, E1 ++ [{timer, blink, half_period(C)}]};
        false ->
            {C, []}
    end;
timeout({grace, Dev}, #core{devices = Devs} = C) ->
    case maps:find(Dev, Devs) of
        {ok, #dev{status = starting} = D} -> report(Dev, D#dev{status = down}, C, []);
        _ -> {C, []}
    end;
timeout({reset_pulse, Id}, #core{drives = Drives} = C) ->
    case maps:get(Id, Drives) of
        #drive{phase = pulse, attempt = A, spec = #{reset := P}} = D ->
            C1 = C#core{drives = Drives#{Id := D#drive{phase = wait}}},
            Wait = setting(drive_reset_wait_ms, C) bsl (A - 1),
            {C2, E2} = output(P, false, C1, []),
            {C2, E2 ++ [{timer, {reset_wait, Id}, Wait}]};
        _ ->
            {C, []}
    end;
timeout({reset_wait, Id}, #core{drives = Drives} = C) ->
    case maps:get(Id, Drives) of
        #drive{phase = wait, error = true, attempt = A} ->
            case A < setting(drive_reset_attempts, C) of
                true -> pulse(Id, A + 1, C, []);
                false -> give_up(Id, C)
            end;
        _ ->
            {C, []}
    end.

%% Resets did not clear the error: the operator is needed.
give_up(Id, #core{drives = Drives} = C) ->
    #drive{spec = #{caption := Caption}, attempt = A} = D = maps:get(Id, Drives),
    C1 = C#core{drives = Drives#{Id := D#drive{phase = failed}}},
    Text = text(["The drive ", Caption, " still reports an error", code_text(D), " after ",
                 integer_to_list(A), " resets. Check the drive, then press Retry to "
                 "reset it again."]),
    raise(drive_id(Id, <<".failed">>), text(["Drive ", Caption, " cannot be reset"]), Text,
          C1, [{reset_warning, drive_id(Id)}]).

answer(Id, #core{drives = Drives, devices = Devs} = C) ->
    DriveIds = [{drive_id(DId, <<".failed">>), DId} || DId <- maps:keys(Drives)],
    DevIds = [{device_id(Dev), Dev} || Dev <- maps:keys(Devs)],
    case {lists:keyfind(Id, 1, DriveIds), lists:keyfind(Id, 1, DevIds)} of
        {{_, DId}, _} ->
            D = maps:get(DId, Drives),
            C1 = C#core{drives = Drives#{DId := D#drive{phase = idle, attempt = 0}}},
            case D of
                #drive{error = true} -> drive_error(DId, C1, []);
                _ -> {C1, []}
            end;
        {false, {_, Dev}} ->
            case maps:get(Dev, Devs) of
                #dev{status = down} = D -> report(Dev, D, C, []);
                _ -> {C, []}
            end;
        {false, false} ->
            {C, []}
    end.

%%====================================================================
%% Settings and texts
%%====================================================================

%% Texts of warnings on show follow the settings.
retext(#core{io = Io, values = Values, drives = Drives} = C, E) ->
    Door = [door_warning(C) || {ok, P} <- [maps:find(door_locked, Io)],
                               maps:get(P, Values, unknown) =:= false],
    Air = [air_warning(C) || {ok, P} <- [maps:find(air_ok, Io)],
                             maps:get(P, Values, unknown) =:= false],
    DriveTexts = [error_warning(D, C) || {_, #drive{error = true, phase = Ph} = D}
                                             <- lists:sort(maps:to_list(Drives)),
                                         Ph =/= failed],
    {C, E ++ Door ++ Air ++ DriveTexts}.

setting(Key, #core{settings = S}) ->
    maps:get(Key, S).

%%====================================================================
%% Effects shared
%%====================================================================

%% An output changes only when its value does.
output(P, V, #core{outputs = Outputs} = C, E) ->
    case Outputs of
        #{P := V} -> {C, E};
        _ -> {C#core{outputs = Outputs#{P => V}}, E ++ [{write, P, V}]}
    end.

raise(Id, Caption, Text, #core{errors = Errors} = C, E) ->
    {C#core{errors = Errors#{Id => true}}, E ++ [{error, Id, Caption, Text}]}.

withdraw(Id, #core{errors = Errors} = C, E) ->
    case maps:take(Id, Errors) of
        {true, Rest} -> {C#core{errors = Rest}, E ++ [{withdraw, Id}]};
        error -> {C, E}
    end.

drive_id(Id) -> <<"drive.", (atom_to_binary(Id))/binary>>.

drive_id(Id, Suffix) -> <<(drive_id(Id))/binary, Suffix/binary>>.

device_id({connection, Id}) -> <<"connection.", (atom_to_binary(Id))/binary>>;
device_id({hardware, Id}) -> <<"hardware.", (atom_to_binary(Id))/binary>>.

text(IoData) -> unicode:characters_to_binary(IoData).
