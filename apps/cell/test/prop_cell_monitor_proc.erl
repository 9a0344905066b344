%% A PropEr state-machine model of the monitor as a process (seed 000 §2.4.2): the real
%% `cell_monitor' in a running cell, the PLC simulated by the HAL as in
%% cell_monitor_SUITE, written from the seed's text and what a machine's owner expects
%% of it, never from its code (prop_cell_monitor drives its pure core in simulated
%% time; this one checks the process that carries the core's decisions out).
%%
%% Commands: the emergency-stop circuit opened and closed, the service key turned, the
%% door unlocked and locked, the air lost and back, a drive's error that its reset
%% clears after some pulses (or that three do not clear), the operator's Retry of a
%% drive handed over, the drive repaired, and the monitor's process killed. After each
%% the cell is awaited (woken by its events, log lines and commanded outputs, with a
%% deadline) until it shows what the model says, and checked:
%% <ul>
%% <li>the emergency stop is on exactly while the circuit is open, shown as an alarm,
%%   and every task is stopped at once when it opens;</li>
%% <li>the service mode follows the key;</li>
%% <li>an unlocked door is a warning, low air is a warning, each gone when put right;</li>
%% <li>a drive in error is reset with pulses of its reset output, three at most: the
%%   error clearing ends it all; three that do not clear it hand it to the operator as
%%   an error, and the pulses stop; Retry pulses again, up to three more;</li>
%% <li>the monitor killed comes back and takes the cell over as it is: the flags and
%%   warnings stay what the inputs say, an emergency stop it raised is released by its
%%   successor when the circuit closes.</li>
%% </ul>
%% The monitor runs under a supervisor of the test's own with the product's child spec:
%% in the product, a kill of the monitor restarts the controller after it
%% (`rest_for_one'), ten times a minute at most, which a thousand runs would exhaust.
%% The cell is started once; each run begins from a healthy machine with every task
%% started. A kill is left out while a drive is in error: what a new monitor owes a
%% drive its predecessor was resetting the seed does not say.
%%
%% The circuit is also opened or closed while no monitor runs (between a kill and the
%% restart): its successor releases an emergency stop its predecessor raised when it
%% finds the circuit closed (the seed has the EmergencyStop property follow the
%% voltage).
%%
%% Sequential only: the monitor's view is a function of the latest inputs, one PLC
%% image; commands racing from two processes would leave the model no state to check
%% each one against but the last, which the sequential runs already check after every
%% command.
%%
%% Each run costs real time, most of it a drive's resets (a pulse, then a wait that
%% doubles, three times a round: with the 100 ms wait the settings once allowed at
%% least, a round took 730 ms and a run 0.45 s) and, for every other command, the PLC's
%% poll. Both are set short through the monitor's settings and the connection's
%% options, no shorter than leaves the check sure on a busy machine: the PLC is polled
%% every 2 ms, a pulse lasts 10 ms and the first wait 20 ms, ten polls to see the error
%% a pulse cleared before the next pulse.
%% 1,000 runs take about two minutes on a machine of two cores (470 s before), about
%% five with both cores kept busy by other work.
-module(prop_cell_monitor_proc).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([circuit/1, key/1, door/1, air/1, drive_fault/1, retry/0, repair/0, kill/1]).
-export([prop_monitor/0]).

-define(IDS, [load, work, unload]).
-define(TAB, prop_cell_monitor_proc).
-define(WAIT, 10000).
-define(ATTEMPTS, 3).
%% The PLC's poll period and the drive's first wait after a reset (see the module's
%% doc).
-define(POLL_MS, 2).
-define(RESET_WAIT_MS, 20).

-record(m, {circuit = true :: boolean(),
            key = false :: boolean(),
            door = true :: boolean(),
            air = true :: boolean(),
            drive = ok :: ok | failed,
            heal = 0 :: non_neg_integer(),     %% the pulse that clears the error, 0: none
            pulses = 0 :: non_neg_integer(),   %% since the error came
            tasks_off = false :: boolean()}).

monitor_proc_test_() ->
    {setup, fun setup/0, fun cleanup/1,
     fun(_) ->
             [{timeout, 600, ?_assert(proper:quickcheck(prop_monitor(),
                                                        [{to_file, user}, {numtests, 1000}]))}]
     end}.

prop_monitor() ->
    ok = listen(),
    ?FORALL(Cmds, commands(?MODULE),
            begin
                Fresh = fresh(),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                ?WHENFAIL(io:format(user, "Fresh: ~p~nHistory: ~p~nState: ~p~nResult: ~p~n",
                                    [Fresh, History, State, Result]),
                          aggregate(command_names(Cmds), Fresh =:= ok andalso Result =:= ok))
            end).

%% -------------------------------------------------------------------------------------
%% The model
%% -------------------------------------------------------------------------------------

initial_state() -> #m{}.

command(M) ->
    frequency([{3, {call, ?MODULE, circuit, [not M#m.circuit]}},
               {2, {call, ?MODULE, key, [not M#m.key]}},
               {2, {call, ?MODULE, door, [not M#m.door]}},
               {2, {call, ?MODULE, air, [not M#m.air]}},
               {2, {call, ?MODULE, kill, [boolean()]}}]
              ++ [{2, {call, ?MODULE, drive_fault, [range(1, 5)]}} || M#m.drive =:= ok]
              ++ [{4, {call, ?MODULE, retry, []}} || M#m.drive =:= failed]
              ++ [{2, {call, ?MODULE, repair, []}} || M#m.drive =:= failed]).

%% A drive's error comes and is retried while the circuit is closed (no resets during
%% an emergency stop).
precondition(M, {call, _, drive_fault, _}) -> M#m.drive =:= ok andalso M#m.circuit;
precondition(M, {call, _, retry, []}) -> M#m.drive =:= failed andalso M#m.circuit;
precondition(M, {call, _, repair, []}) -> M#m.drive =:= failed;
precondition(M, {call, _, kill, _}) -> M#m.drive =:= ok;
precondition(_, _) -> true.

next_state(M, _, {call, _, circuit, [In]}) ->
    M#m{circuit = In, tasks_off = M#m.tasks_off orelse not In};
next_state(M, _, {call, _, key, [On]}) -> M#m{key = On};
next_state(M, _, {call, _, door, [Locked]}) -> M#m{door = Locked};
next_state(M, _, {call, _, air, [Ok]}) -> M#m{air = Ok};
next_state(M, _, {call, _, drive_fault, [Heal]}) -> resets(M#m{heal = Heal, pulses = 0});
next_state(M, _, {call, _, retry, []}) -> resets(M);
next_state(M, _, {call, _, repair, []}) -> M#m{drive = ok};
next_state(M, _, {call, _, kill, [In]}) -> next_state(M, none, {call, ?MODULE, circuit, [In]}).

%% Up to three pulses: the error clears at the pulse that heals it, or the drive is
%% handed to the operator.
resets(#m{heal = Heal, pulses = P} = M) when Heal > P, Heal =< P + ?ATTEMPTS ->
    M#m{drive = ok, pulses = Heal};
resets(#m{pulses = P} = M) ->
    M#m{drive = failed, pulses = P + ?ATTEMPTS}.

%% What the cell shows when it has settled.
view(M) ->
    #{estop => not M#m.circuit, estop_alarm => not M#m.circuit, service => M#m.key,
      door => not M#m.door, air => not M#m.air, drive => false,
      drive_failed => M#m.drive =:= failed}.

postcondition(M, {call, _, _, _} = Call, Res) ->
    M1 = next_state(M, Res, Call),
    Pulses = case Call of
                 {call, _, drive_fault, _} -> M1#m.pulses;
                 _ -> M1#m.pulses - M#m.pulses
             end,
    Ok = case Call of
             {call, _, Drive, _} when Drive =:= drive_fault; Drive =:= retry ->
                 Res =:= {lists:duplicate(Pulses, pulse), view(M1), no_more};
             {call, _, circuit, [false]} ->
                 Res =:= {view(M1), all_off};
             {call, _, kill, [false]} ->
                 Res =:= {view(M1), all_off};
             _ ->
                 Res =:= view(M1)
         end,
    Ok orelse io:format(user, "~nFailed ~p: ~p~nexpected ~p~n", [Call, Res, view(M1)]),
    Ok.

%% -------------------------------------------------------------------------------------
%% Commands: each acts on the PLC (or the monitor) and returns what the cell shows
%% once it shows the model's picture, or what it showed at the deadline
%% -------------------------------------------------------------------------------------

circuit(In) ->
    ok = cell_hal_sim:set({general, estop_voltage}, In),
    Want = #{estop => not In, estop_alarm => not In},
    case In of
        true -> settled(Want);
        false -> {settled(Want), await(fun() -> states() =:= [off, off, off] end, all_off)}
    end.

key(On) ->
    ok = cell_hal_sim:set({general, service_key}, On),
    settled(#{service => On}).

door(Locked) ->
    ok = cell_hal_sim:set({general, door_locked}, Locked),
    settled(#{door => not Locked}).

air(Ok) ->
    ok = cell_hal_sim:set({general, air_ok}, Ok),
    settled(#{air => not Ok}).

%% The drive's error clears at its Heal-th reset pulse since it came (5: after two
%% rounds of resets).
drive_fault(Heal) ->
    true = ets:insert(?TAB, [{heal, Heal}, {pulses, 0}]),
    ok = cell_hal_sim:set({axes, x_code}, 17),
    ok = cell_hal_sim:set({axes, x_error}, true),
    resets_seen().

%% Taken back from the operator once the hand-over is gone or a pulse comes.
retry() ->
    ok = cell_alarms:answer(<<"cell:drive.x_axis.failed">>, retry, <<"operator">>),
    case await_or_pulse(fun() -> not maps:get(drive_failed, view_now()) end) of
        timeout -> {[], view_now(), not_retried};
        _ -> resets_seen()
    end.

repair() ->
    ok = cell_hal_sim:set({axes, x_error}, false),
    settled(#{drive => false, drive_failed => false}).

%% The pulses until the drive is settled (its error cleared, or handed over), what the
%% cell shows then, and whether a pulse came after.
resets_seen() ->
    Pulses = pulses([]),
    View = view_now(),
    More = receive {x_reset, true} -> one_more after 0 -> no_more end,
    {Pulses, View, More}.

%% Each pulse rises and falls; the resets end with the error cleared (no alarm of the
%% drive) or with the drive handed over.
pulses(Acc) ->
    Done = fun() -> V = view_now(),
                    Cleared = device(x_error) =:= {ok, false}
                        andalso not maps:get(drive, V) andalso not maps:get(drive_failed, V),
                    (Cleared orelse maps:get(drive_failed, V))
                        andalso device(x_reset) =:= {ok, false} end,
    receive
        {x_reset, true} ->
            receive {x_reset, false} -> pulses([pulse | Acc])
            after ?WAIT -> lists:reverse([stuck | Acc])
            end
    after 0 ->
            case await_or_pulse(Done) of
                pulse -> pulses(Acc);
                done -> lists:reverse(Acc);
                timeout -> lists:reverse([timeout | Acc])
            end
    end.

%% Waits until the drive has settled or a pulse comes.
await_or_pulse(Done) ->
    Deadline = erlang:monotonic_time(millisecond) + ?WAIT,
    await_or_pulse(Done, Deadline).

await_or_pulse(Done, Deadline) ->
    case Done() of
        true ->
            %% A pulse that rose and fell before the look (its message sent as it rose)
            %% is not done.
            receive {x_reset, true} = P -> self() ! P, pulse after 0 -> done end;
        false ->
            Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
            receive
                {x_reset, true} = P -> self() ! P, pulse;
                {cell_event, _} -> await_or_pulse(Done, Deadline);
                {cell_log, _} -> await_or_pulse(Done, Deadline);
                {cell_hal, _, _} -> await_or_pulse(Done, Deadline)
            after Left -> timeout
            end
    end.

%% Killed, and the circuit set (opened, closed or left) while no monitor runs (its
%% supervisor held suspended meanwhile): its successor starts under the test's
%% supervisor, finds the HAL's pieces there and takes them over (it says so for each).
kill(In) ->
    _ = drain(),
    Sup = ets:lookup_element(?TAB, sup, 2),
    Old = whereis(cell_monitor),
    ok = sys:suspend(Sup),
    Ref = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', Ref, process, Old, _} -> ok end,
    ok = cell_hal_sim:set({general, estop_voltage}, In),
    ok = sys:resume(Sup),
    case taken_over() of
        ok when In -> settled(#{estop => false, estop_alarm => false});
        ok -> {settled(#{estop => true, estop_alarm => true}),
               await(fun() -> states() =:= [off, off, off] end, all_off)};
        Timeout -> Timeout
    end.

taken_over() ->
    receive
        {cell_log, #{text := Text}} ->
            case binary:match(Text, <<"taken over as it is">>) of
                nomatch -> taken_over();
                _ -> ok
            end
    after ?WAIT -> {timeout, not_restarted}
    end.

%% -------------------------------------------------------------------------------------
%% Observing the cell
%% -------------------------------------------------------------------------------------

%% The whole view once the part a command changes shows what it should.
settled(Want) ->
    _ = await(fun() -> maps:with(maps:keys(Want), view_now()) =:= Want end, settled),
    %% The monitor has handled everything before this call is answered.
    _ = cell_monitor:info(),
    view_now().

view_now() ->
    F = cell_controller:flags(),
    Alarms = [Id || #{id := Id} <- cell_alarms:list()],
    #{estop => maps:get(estop, F), service => maps:get(service_mode, F),
      estop_alarm => lists:member(<<"cell:estop">>, Alarms),
      door => lists:member(<<"cell:door">>, Alarms),
      air => lists:member(<<"cell:air">>, Alarms),
      drive => lists:member(<<"cell:drive.x_axis">>, Alarms),
      drive_failed => lists:member(<<"cell:drive.x_axis.failed">>, Alarms)}.

%% Waits for a condition, woken by the cell's events, log lines and outputs.
await(Cond, What) ->
    await(Cond, What, erlang:monotonic_time(millisecond) + ?WAIT).

await(Cond, What, Deadline) ->
    case Cond() of
        true ->
            What;
        false ->
            Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
            receive
                {cell_event, _} -> await(Cond, What, Deadline);
                {cell_log, _} -> await(Cond, What, Deadline);
                {cell_hal, _, _} -> await(Cond, What, Deadline)
            after Left -> {timeout, What}
            end
    end.

states() -> [cell_task_proc:state(Id) || Id <- ?IDS].

device(P) -> cell_hal_sim:get({axes, P}).

%% -------------------------------------------------------------------------------------
%% The cell, started once; the monitor moved under a supervisor of the test's own
%% -------------------------------------------------------------------------------------

setup() ->
    Root = filename:join(["/tmp", "prop_cell_monitor_proc", os:getpid()]),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    _ = ets:new(?TAB, [named_table, public]),
    %% The tasks tell their notify process of each step: nobody here needs to know.
    Sink = spawn(fun Sink() -> receive _ -> Sink() end end),
    Tasks = [cell_test_task:spec(Id, ?TAB, Sink) || Id <- ?IDS],
    Spec = #{name => <<"monitor model">>, tasks => Tasks,
             hal => cell_monitor_test_cell:hal([], #{poll_ms => ?POLL_MS}),
             monitor => cell_monitor_test_cell:monitor()},
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_settings:put(monitor, #{drive_reset_pulse_ms => 10,
                                      drive_reset_wait_ms => ?RESET_WAIT_MS}, <<"model">>),
    %% A blank PLC opens the circuit and the monitor stops the cell: closed again, and
    %% released, before the monitor is replaced. (Replaced at once, the cell once
    %% stayed stopped with the circuit closed and no alarm. Likely: the first monitor
    %% decided the stop before the controller ran, so cell_controller:estop/2 set the
    %% flag and the call was kept for a retry, and the monitor went before the retry;
    %% its successor, finding the circuit closed, knew of no stop of its own. It now
    %% takes the circuit's stop as its own: replaced_monitor_releases_its_estop in
    %% cell_monitor_SUITE.)
    ok = cell_events:subscribe(),
    [ok = cell_hal_sim:set({general, P}, true) || P <- [estop_voltage, door_locked, air_ok]],
    released = await(fun() -> not maps:get(estop, cell_controller:flags()) end, released),
    ok = cell_events:unsubscribe(),
    {ok, MonSpec} = supervisor:get_childspec(cell_controller_sup, cell_monitor),
    ok = supervisor:terminate_child(cell_controller_sup, cell_monitor),
    %% A kill is a restart: far more than the product's ten a minute, on purpose.
    {ok, Sup} = cell_test_sup:start_link([MonSpec], #{intensity => 1000, period => 1}),
    unlink(Sup),
    true = ets:insert(?TAB, {sup, Sup}),
    ok = cell_log:set_level(monitor, verbose),
    {Root, Sup, Sink}.

%% The process that runs the property hears the cell's events, log lines and commanded
%% outputs (each wakes a wait) and every edge of the drive's reset output.
listen() ->
    ok = cell_events:subscribe(),
    ok = cell_log:subscribe(),
    [ok = cell_hal:subscribe(G, P)
     || G <- [general, axes],
        #{name := P, dir := out} <- cell_monitor_test_io:points(#{part => G})],
    Self = self(),
    ok = cell_hal_sim:on_change({axes, x_reset}, fun(V) -> Self ! {x_reset, V}, healed(V) end).

%% A rising edge of the reset counts; at the Heal-th the drive's error clears.
healed(true) ->
    N = ets:update_counter(?TAB, pulses, 1),
    [{0, {axes, x_error}, false} || N =:= ets:lookup_element(?TAB, heal, 2)];
healed(false) ->
    [].

cleanup({Root, Sup, Sink}) ->
    exit(Sink, kill),
    cell_test_sup:stop(Sup),
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok = cell_hal_sim_sup:stop_device(plc1),
    ok = application:unset_env(cell, cell_spec),
    ets:delete(?TAB),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    ok.

%% Each run from a healthy machine, the drive well, every task started.
fresh() ->
    _ = drain(),
    true = ets:insert(?TAB, [{heal, 0}, {pulses, 0}]),
    [ok = cell_hal_sim:set({general, P}, true) || P <- [estop_voltage, door_locked, air_ok]],
    ok = cell_hal_sim:set({general, service_key}, false),
    ok = cell_hal_sim:set({axes, x_error}, false),
    Healthy = view(#m{}),
    case await(fun() -> view_now() =:= Healthy end, healthy) of
        healthy ->
            _ = cell_controller:start(),
            ok = cell_controller:sync(),
            Started = await(fun() -> not lists:member(off, states()) end, started),
            _ = drain(),
            case Started of
                started -> ok;
                Other -> Other
            end;
        Other ->
            {Other, view_now()}
    end.

drain() ->
    receive M -> [M | drain()] after 0 -> [] end.
