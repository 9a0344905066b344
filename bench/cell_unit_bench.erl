%% @doc Unit benchmarks:
%% <ul>
%% <li>steps per second of a sequence whose steps complete at once (a ring of ten,
%%     each counting itself), one step per cycle and several steps in one go, beside
%%     a bare gen_statem doing the same counts, one per self-message or ten per
%%     message;</li>
%% <li>the delay from a sensor change (the simulated PLC's input set) to the entry
%%     of the step after the one awaiting it, median and p99, beside a bare HAL watch
%%     on the same input: the same polls, the unit's own cost on top.</li>
%% </ul>
-module(cell_unit_bench).

-export([run/0]).

-define(STEP_MS, 300).
-define(STEP_TURNS, 9).
-define(RING, 10).
-define(SAMPLES, 200).
-define(POLL_MS, 2).

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    {ok, _} = application:ensure_all_started(cell_hal),
    ok = cell_hal:add_connection(#{id => bench_plc, driver => cell_hal_sim,
                                   opts => #{poll_ms => ?POLL_MS}}),
    ok = cell_hal:add_group(#{id => bench_io, module => cell_bench_unit,
                              connection => bench_plc}),
    {ok, _} = cell_hal:subscribe_connection(bench_plc),
    ok = await_up(),
    Results = step_rate(one) ++ step_rate(several) ++ sensor_delay(),
    ok = cell_hal:remove_group(bench_io),
    ok = cell_hal:remove_connection(bench_plc),
    Results.

%% -------------------------------------------------------------------------------------
%% Steps per second
%% -------------------------------------------------------------------------------------

step_rate(Mode) ->
    Counter = counters:new(1, []),
    start_cell(#{bench => steps, counter => Counter, steps => ?RING, mode => Mode}),
    ok = cell_controller:start(),
    PeerCounter = counters:new(1, []),
    Burst = case Mode of one -> 1; several -> ?RING end,
    {ok, Peer} = cell_bench_step_peer:start(PeerCounter, Burst),
    Unit = cell_task_proc:whereis(bench_unit),
    {Ours, PeerRate} = cell_bench:alternating_rates({Unit, Counter}, {Peer, PeerCounter},
                                                    #{turns => ?STEP_TURNS, ms => ?STEP_MS}),
    exit(Peer, kill),
    ok = cell_controller:stop(),
    stop_cell(),
    Title = case Mode of
                one -> "Steps per second, one step per cycle";
                several -> "Steps per second, several steps in one go (ring of 10)"
            end,
    [#{title => Title, unit => "steps/s", ours => Ours, peer => PeerRate,
       peer_name => case Mode of
                        one -> "bare gen_statem, a step per self-message";
                        several -> "bare gen_statem, 10 steps per self-message"
                    end,
       better => higher}].


%% -------------------------------------------------------------------------------------
%% From a sensor change to the next step
%% -------------------------------------------------------------------------------------

sensor_delay() ->
    ok = set(false),
    start_cell(#{bench => sensor, notify => self()}),
    ok = cell_controller:start(),
    ok = cell_unit:settle(bench_unit),
    Ours = [ours(N rem 2 =:= 1) || N <- lists:seq(1, ?SAMPLES)],
    ok = cell_controller:stop(),
    stop_cell(),
    ok = set(false),
    Peers = [peer(N rem 2 =:= 1) || N <- lists:seq(1, ?SAMPLES)],
    #{median := OM, p99 := OP} = cell_bench:stats(Ours),
    #{median := PM, p99 := PP} = cell_bench:stats(Peers),
    Note = io_lib:format("Sensor to step: the simulated PLC polled every ~b ms, so both "
                         "figures hold up to a poll period of waiting; the difference is "
                         "the unit's own cost.", [?POLL_MS]),
    [#{title => "Sensor change to the next step's entry, median", unit => "ms",
       ours => OM / 1000, peer => PM / 1000, peer_name => "bare HAL watch, same input",
       better => lower, note => Note},
     #{title => "Sensor change to the next step's entry, p99", unit => "ms",
       ours => OP / 1000, peer => PP / 1000, peer_name => "bare HAL watch, same input",
       better => lower}].

%% The unit waits for the sensor to take `On': set it, and time until the unit enters
%% the step after.
ours(On) ->
    T0 = erlang:monotonic_time(microsecond),
    ok = set(On),
    receive
        {entered, On, T1} ->
            %% Its next watch is placed before the next change.
            ok = cell_unit:settle(bench_unit),
            T1 - T0
    after 5000 ->
        erlang:error({no_step, On})
    end.

peer(On) ->
    {ok, Ref} = cell_hal:watch(bench_io, sensor, {eq, On}),
    T0 = erlang:monotonic_time(microsecond),
    ok = set(On),
    receive
        {cell_hal_watch, Ref, On} -> erlang:monotonic_time(microsecond) - T0
    after 5000 ->
        erlang:error({no_watch, On})
    end.

set(On) ->
    cell_hal_sim:set({bench_io, sensor}, On).

await_up() ->
    case cell_hal:status(bench_plc) of
        up -> ok;
        down -> receive {cell_hal_conn, bench_plc, up} -> ok after 5000 -> erlang:error(no_plc) end
    end.

%% -------------------------------------------------------------------------------------

start_cell(Args) ->
    _ = application:load(cell),
    Unit = #{id => bench_unit, module => cell_bench_unit, zone => <<"Bench">>,
             lane => <<"1">>, io => [bench_io], args => Args},
    ok = application:set_env(cell, cell_spec, #{name => <<"bench">>, tasks => [Unit]}),
    {ok, _} = application:ensure_all_started(cell),
    ok.

stop_cell() ->
    ok = application:stop(cell).

%% Benchmarks print figures, not the cell's log.
quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).
