%% @doc Device task benchmarks:
%% <ul>
%% <li>emergency stop: from the stop until every task of N has stopped stepping and
%%     secured its outputs (one in ten stepping every 10 ms, the others idle), beside
%%     a bare fan-out: N idle processes told to stop, until the last one answers;</li>
%% <li>idle cost of 1000 waiting tasks: memory per task and CPU, beside 1000 idle bare
%%     gen_statem processes;</li>
%% <li>step rate of a task whose step never waits, beside a bare gen_statem doing the
%%     same counter increment in the same self-message loop.</li>
%% </ul>
-module(cell_task_bench).

-export([run/0]).

-define(STEP_MS, 300).
-define(STEP_TURNS, 9).
-define(IDLE_SECONDS, 5).

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    %% The step rate and the idle cost first, on a node that has done nothing else
    %% yet: the database work a thousand emergency stops leave behind would be
    %% measured with them.
    Steps = step_rate(),
    Idle = idle(1000),
    Estop = [estop(N, Reps) || {N, Reps} <- [{10, 300}, {100, 200}, {1000, 150}]],
    lists:append(Estop) ++ Idle ++ Steps.

%% -------------------------------------------------------------------------------------
%% Emergency stop
%% -------------------------------------------------------------------------------------

estop(N, Reps) ->
    Counter = counters:new(1, [write_concurrency]),
    Never = make_ref(),
    Specs = [#{id => list_to_atom("bench_" ++ integer_to_list(I)),
               module => cell_bench_task, zone => <<"Bench">>,
               lane => integer_to_binary(I),
               args => #{mode => case I rem 10 of 0 -> tick; _ -> wait end,
                         never => Never, counter => Counter, notify => self()}}
             || I <- lists:seq(1, N)],
    start_cell(Specs),
    Ours = [estop_once(N) || _ <- lists:seq(1, Reps)],
    stop_cell(),
    Peers = [fanout_once(N) || _ <- lists:seq(1, Reps)],
    #{median := OM, p99 := OP} = cell_bench:stats(Ours),
    #{median := PM, p99 := PP} = cell_bench:stats(Peers),
    [#{title => io_lib:format("E-stop reaction, ~p tasks, median", [N]), unit => "ms",
       ours => OM / 1000, peer => PM / 1000, peer_name => "bare fan-out to N processes",
       better => lower},
     maps:merge(#{title => io_lib:format("E-stop reaction, ~p tasks, p99", [N]), unit => "ms",
                  ours => OP / 1000, peer => PP / 1000,
                  peer_name => "bare fan-out to N processes", better => lower},
                case N of 1000 -> #{goal => "p99 < 5 ms"}; _ -> #{} end)].

estop_once(N) ->
    ok = cell_controller:estop(false),
    ok = cell_events:subscribe([task_state]),
    ok = cell_controller:start(),
    ok = running(N),
    ok = cell_events:unsubscribe(),
    flush_secured(),
    T0 = erlang:monotonic_time(microsecond),
    ok = cell_controller:estop(true),
    Last = collect_secured(N, T0),
    Last - T0.

%% The cell running, as the emergency stop finds it in production: every task READY
%% and at its wait, the controller and the statistics done with the start's events.
running(N) ->
    ok = ready(N, sets:new([{version, 2}])),
    ok = cell_controller:sync(),
    _ = sys:get_state(cell_stats),
    _ = [sys:get_state(P) || P <- cell_registry:pids()],
    ok.

ready(N, Ready) ->
    case sets:size(Ready) of
        N ->
            ok;
        _ ->
            receive
                {cell_event, #{type := task_state, task := T, state := {ready, _, _}}} ->
                    ready(N, sets:add_element(T, Ready));
                {cell_event, #{type := task_state}} ->
                    ready(N, Ready)
            after 10000 ->
                erlang:error({tasks_not_ready, N - sets:size(Ready)})
            end
    end.

collect_secured(0, Last) ->
    Last;
collect_secured(N, Last) ->
    receive
        {secured, _Id, T} -> collect_secured(N - 1, max(T, Last))
    after 10000 ->
        erlang:error({tasks_not_secured, N})
    end.

flush_secured() ->
    receive {secured, _, _} -> flush_secured() after 0 -> ok end.

fanout_once(N) ->
    Pids = [begin {ok, P} = cell_bench_peer:start_idle(), P end || _ <- lists:seq(1, N)],
    T0 = erlang:monotonic_time(microsecond),
    _ = [P ! {stop, self()} || P <- Pids],
    Last = lists:foldl(fun(P, Acc) ->
                               receive {stopped, P, T} -> max(T, Acc) end
                       end, T0, Pids),
    Last - T0.

%% -------------------------------------------------------------------------------------
%% Idle cost
%% -------------------------------------------------------------------------------------

idle(N) ->
    Never = make_ref(),
    Specs = [#{id => list_to_atom("idle_" ++ integer_to_list(I)), module => cell_bench_task,
               zone => <<"Idle">>, lane => integer_to_binary(I),
               args => #{mode => wait, never => Never, notify => self()}}
             || I <- lists:seq(1, N)],
    start_cell(Specs),
    ok = cell_events:subscribe([task_state]),
    ok = cell_controller:start(),
    ok = running(N),
    ok = cell_events:unsubscribe(),
    %% The counters of the start written: what is measured is the cell at rest.
    ok = cell_stats:flush(),
    Pids = [P || #{pid := P} <- cell_controller:tasks()],
    N = length(Pids),
    _ = [erlang:garbage_collect(P) || P <- Pids],
    OurMem = lists:sum([M || P <- Pids, {memory, M} <- [process_info(P, memory)]]) / N,
    OurCpu = cpu_busy(?IDLE_SECONDS),
    stop_cell(),
    Peers = [begin {ok, P} = cell_bench_peer:start_idle(), P end || _ <- lists:seq(1, N)],
    _ = [erlang:garbage_collect(P) || P <- Peers],
    PeerMem = lists:sum([M || P <- Peers, {memory, M} <- [process_info(P, memory)]]) / N,
    PeerCpu = cpu_busy(?IDLE_SECONDS),
    _ = [exit(P, kill) || P <- Peers],
    [#{title => "Memory per waiting task, 1000 tasks", unit => "KB",
       ours => OurMem / 1024, peer => PeerMem / 1024, peer_name => "idle bare gen_statem",
       better => lower, goal => "< 50 KB"},
     #{title => io_lib:format("CPU of 1000 waiting tasks (node total, ~p s)", [?IDLE_SECONDS]),
       unit => "% of a core", ours => OurCpu, peer => PeerCpu,
       peer_name => "1000 idle bare gen_statem", better => lower, goal => "< 1 %"}].

%% The node's busy time over a window, in percent of one core (all schedulers,
%% including this benchmark's own process, which sleeps in a receive).
cpu_busy(Seconds) ->
    erlang:system_flag(scheduler_wall_time, true),
    S0 = lists:sort(erlang:statistics(scheduler_wall_time)),
    receive after Seconds * 1000 -> ok end,
    S1 = lists:sort(erlang:statistics(scheduler_wall_time)),
    Active = lists:sum([A1 - A0 || {{I, A0, _}, {I, A1, _}} <- lists:zip(S0, S1)]),
    Total = lists:sum([T1 - T0 || {{I, _, T0}, {I, _, T1}} <- lists:zip(S0, S1),
                                  I =< erlang:system_info(schedulers)]),
    Cores = erlang:system_info(schedulers),
    100 * Active / (Total / Cores).

%% -------------------------------------------------------------------------------------
%% Step rate
%% -------------------------------------------------------------------------------------

step_rate() ->
    Counter = counters:new(1, []),
    start_cell([#{id => spinner, module => cell_bench_task, zone => <<"Spin">>,
                  lane => <<"1">>, args => #{mode => spin, counter => Counter}}]),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    PeerCounter = counters:new(1, []),
    {ok, Peer} = cell_bench_peer:start_spin(PeerCounter),
    Spinner = cell_task_proc:whereis(spinner),
    {Ours, PeerRate} = cell_bench:alternating_rates({Spinner, Counter}, {Peer, PeerCounter},
                                                    #{turns => ?STEP_TURNS, ms => ?STEP_MS}),
    exit(Peer, kill),
    ok = cell_controller:stop(),
    stop_cell(),
    [#{title => "Steps per second, a task that never waits", unit => "steps/s",
       ours => Ours, peer => PeerRate, peer_name => "bare gen_statem, same loop",
       better => higher, goal => "ratio >= 0.5"}].

%% -------------------------------------------------------------------------------------

start_cell(Specs) ->
    _ = application:load(cell),
    ok = application:set_env(cell, cell_spec, #{name => <<"bench">>, tasks => Specs}),
    {ok, _} = application:ensure_all_started(cell),
    ok.

stop_cell() ->
    ok = application:stop(cell).

%% Benchmarks print figures, not the cell's log.
quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).
