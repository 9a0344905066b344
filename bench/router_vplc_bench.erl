%% @doc The cost of the real protocol path: panels per hour through the default cell in
%% real mode (`simulation_mode' off), its PLC a virtual PLC (`scripts/vplc', the
%% router's physics served over Modbus TCP on loopback, in an OS process of its own),
%% beside the same cell on the in-VM simulated PLC, in the same run; one lane, a panel
%% always waiting upstream, no faults, the same settings on both sides:
%% <ul>
%% <li>with every physical delay zero: the runtime's ceiling, where the protocol's cost
%%     shows most (every poll and every output written is a Modbus round trip over
%%     loopback to another OS process);</li>
%% <li>with the real machine's delays, run at a quarter of their length and counted
%%     back to machine time (as `router_bench' does): what a user of the machine sees.</li>
%% </ul>
%% Each side runs in two rounds, in the order in-VM, real mode, real mode, in-VM, so
%% that a load on the shared machine that grows or falls through the run falls on both
%% sides alike; each round after a warm-up of a few panels, on a fresh cell root (and
%% a fresh virtual PLC root: its machine starts empty). A side's figure is its panels
%% over its time, both rounds together.
-module(router_vplc_bench).

-export([run/0]).

-define(WARMUP, 2).
-define(ZERO_PANELS, 10).
-define(REAL_PANELS, 3).
-define(REAL_SCALE, 0.25).
-define(TIMEOUT_MS, 120000).

-spec run() -> [cell_bench:result()].
run() ->
    {ZeroVm, ZeroReal} = sides(0.0, ?ZERO_PANELS),
    {RealVm0, RealReal0} = sides(?REAL_SCALE, ?REAL_PANELS),
    {RealVm, RealReal} = {RealVm0 * ?REAL_SCALE, RealReal0 * ?REAL_SCALE},
    Peer = "the same cell on the in-VM simulated PLC",
    Scale = float_to_list(?REAL_SCALE, [{decimals, 2}]),
    [#{title => "Panels per hour, one lane, real mode over Modbus TCP to the virtual PLC, "
                "physical delays zero (the runtime's ceiling)",
       unit => "panels/h", ours => ZeroReal, peer => ZeroVm, peer_name => Peer,
       better => higher},
     #{title => ["Panels per hour, one lane, real mode over Modbus TCP to the virtual PLC, "
                 "real delays (", Scale, " time scale, machine time)"],
       unit => "panels/h", ours => RealReal, peer => RealVm, peer_name => Peer,
       better => higher,
       note => io_lib:format(
                 "Real mode: the cell's HAL polls the virtual PLC over Modbus TCP on "
                 "loopback every 20 ms (hal_poll_ms) and writes its outputs there; the "
                 "virtual PLC answers each request from its simulated PLC's values, a "
                 "write moving the physics at once. In-VM, the cell's HAL polls the "
                 "simulated PLC in its own node at the same period. At zero delay a "
                 "panel takes "
                 "~.2f s through the virtual PLC and ~.2f s in-VM: ~ts. With the delays "
                 "at ~s of the machine's, that time weighs ~b times what it would on the "
                 "machine. Each side: two rounds (in-VM, real mode, real mode, in-VM) of "
                 "~b panels out after ~b of warm-up at zero delay, of ~b after ~b with "
                 "the delays.",
                 [3600 / ZeroReal, 3600 / ZeroVm, path_cost(3600 / ZeroReal - 3600 / ZeroVm),
                  Scale, round(1 / ?REAL_SCALE), ?ZERO_PANELS, ?WARMUP, ?REAL_PANELS,
                  ?WARMUP])}].

%% What the real protocol path costs a panel, in words that fit the figures: a
%% difference under a millisecond (either way) is below what two rounds can tell.
path_cost(Seconds) ->
    case round(1000 * Seconds) of
        Ms when Ms >= 1 ->
            io_lib:format("the difference, ~b ms a panel, is what the real protocol path "
                          "costs", [Ms]);
        Ms when Ms =< -1 ->
            io_lib:format("the real mode was ~b ms a panel faster, which is the runs' "
                          "noise: the real protocol path costs less than that", [-Ms]);
        _ ->
            "the real protocol path costs less than a millisecond a panel, below what "
            "these runs can tell"
    end.

%% Both sides' panels per hour at a time scale, each over two rounds in the order
%% in-VM, real mode, real mode, in-VM: as many panels in each round, so a side's
%% panels over its time is the harmonic mean of its rounds' rates.
sides(Scale, Panels) ->
    Vm1 = measure(vm, Scale, Panels),
    Real1 = measure(vplc, Scale, Panels),
    Real2 = measure(vplc, Scale, Panels),
    Vm2 = measure(vm, Scale, Panels),
    Both = fun(A, B) -> 2 / (1 / A + 1 / B) end,
    {Both(Vm1, Vm2), Both(Real1, Real2)}.

%% Panels per hour of wall-clock time through the cell on `Plc' at a time scale, after
%% a warm-up.
measure(Plc, Scale, Panels) ->
    Settings = router_bench_cell:settings(#{scale => Scale, dual_lane => false}),
    {Vplc, Cell} = case Plc of
                       vm ->
                           {none, #{settings => Settings}};
                       vplc ->
                           V = start_vplc(Settings),
                           {V, #{settings => real_mode(Settings, maps:get(tcp, V)),
                                 plc => real}}
                   end,
    try
        router_bench_cell:panels_per_hour(Cell, #{warmup => ?WARMUP, panels => Panels,
                                                  timeout => ?TIMEOUT_MS})
    after
        stop_vplc(Vplc)
    end.

%% The cell's settings pointed at the virtual PLC on loopback.
real_mode(#{machine := Machine, router := Router} = Settings, Port) ->
    Settings#{machine => Machine#{simulation_mode => false},
              router => Router#{plc_host => <<"127.0.0.1">>, plc_port => Port}}.

%% Starts `scripts/vplc' for the router on a port the OS picks, on a fresh root of its
%% own holding the same settings as the cell's; returns once it listens.
start_vplc(Settings) ->
    Top = os:getenv("CELLRT_TOP"),
    Root = os:getenv("CELLRT_ROOT") ++ ".vplc",
    ok = router_bench_cell:write_settings(Root, Settings),
    P = open_port({spawn_executable, filename:join([Top, "scripts", "vplc"])},
                  [{args, ["--port", "0", "--root", Root]}, {line, 4096}, exit_status,
                   stderr_to_stdout, binary]),
    #{port => P, tcp => await_listening(P, erlang:monotonic_time(millisecond) + ?TIMEOUT_MS)}.

await_listening(P, Deadline) ->
    receive
        {P, {data, {eol, <<"virtual PLC of router_cell listening on ", Rest/binary>>}}} ->
            [_, Port] = binary:split(Rest, <<" port ">>),
            binary_to_integer(Port);
        {P, {data, _}} ->
            await_listening(P, Deadline);
        {P, {exit_status, S}} ->
            error({vplc_exited, S})
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        error(vplc_not_listening)
    end.

%% Stops the virtual PLC as `make run' does (SIGTERM), and waits for its end.
stop_vplc(none) ->
    ok;
stop_vplc(#{port := P}) ->
    {os_pid, Pid} = erlang:port_info(P, os_pid),
    _ = os:cmd("kill -TERM " ++ integer_to_list(Pid)),
    await_exit(P).

await_exit(P) ->
    receive
        {P, {exit_status, _}} -> ok;
        {P, {data, _}} -> await_exit(P)
    after ?TIMEOUT_MS ->
        error(vplc_not_stopped)
    end.
