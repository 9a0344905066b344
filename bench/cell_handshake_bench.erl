%% @doc Handshake benchmarks: products passed through a line of conveyor segments
%% (cell_line_task, no physical delay), each hand-over a full transfer of seed 000
%% §2.3.6 (offer, commit, release, complete).
%%
%% <ul>
%% <li>the protocol alone: products kept on a RAM-backed folder, beside a raw message
%%     round trip between two processes measured in the same run. The cell's statistics
%%     are stopped here (they are not the protocol); a line of 2 is
%%     measured again with them, the whole cell;</li>
%% <li>durable: products on the disk, flushed at every commit point, beside the disk's
%%     own rate of the same small write + fsync + rename (+ folder fsync) in the same
%%     folder and run;</li>
%% <li>several lines at once on the disk: do concurrent commits pass more transfers per
%%     second than one writer can fsync?</li>
%% </ul>
-module(cell_handshake_bench).

-export([run/0]).

-define(RAM, "/dev/shm").
%% Rounds of products through one running cell on the RAM folder, the median rate
%% reported: a shared host's speed moves by a fifth from one second to the next.
-define(ROUNDS, 5).

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    RoundTrips = round_trips(),
    RamRoot = filename:join(?RAM, "cellrt-bench-" ++ os:getpid()),
    DiskRoot = filename:join(os:getenv("CELLRT_ROOT", "_build/bench/root"), "handshake"),
    Ram2 = line_rate(RamRoot, 1, 2, {?ROUNDS, 2000}, detached),
    Floor = protocol_floor(RamRoot, {?ROUNDS, 2000}, true),
    FloorBare = protocol_floor(RamRoot, {?ROUNDS, 2000}, false),
    Ram10 = line_rate(RamRoot, 1, 10, {?ROUNDS, 500}, detached),
    Lat = latency(RamRoot, 300),
    Cell2 = line_rate(RamRoot, 1, 2, {?ROUNDS, 1000}, attached),
    Cell2Off = line_rate(RamRoot, 1, 2, {?ROUNDS, 1000}, unjournaled),
    DiskUnit = disk_rate(DiskRoot, 400),
    Disk2 = line_rate(DiskRoot, 1, 2, {?ROUNDS, 150}, attached),
    Disk2Off = line_rate(DiskRoot, 1, 2, {?ROUNDS, 150}, unjournaled),
    Disk10 = line_rate(DiskRoot, 1, 10, {1, 60}, attached),
    DiskLines = line_rate(DiskRoot, 4, 5, {1, 60}, attached),
    _ = os:cmd("rm -rf '" ++ RamRoot ++ "'"),
    #{median := LM, p99 := LP} = cell_bench:stats(Lat),
    [#{title => "Transfers per second, line of 2, RAM folder", unit => "transfers/s",
       ours => Ram2, peer => RoundTrips, peer_name => "raw message round trips/s",
       better => higher, goal => ">= 20000 transfers/s",
       note => "A transfer through a line of 2 is a new product saved at the first "
               "segment, offer, commit, release with the product saved by its new "
               "owner, completion, the product sent out and forgotten at the last, and "
               "the cell state kept (the controller hears of its changes only): about "
               "20 messages between processes (one of them to the benchmark) and five "
               "record writes. The statistics are stopped (the next "
               "figure has them). Each figure on the RAM folder is the median of five "
               "rounds through one running cell."},
     #{title => "Transfers per second, line of 2, RAM folder, beside the protocol's floor",
       unit => "transfers/s", ours => Ram2, peer => Floor,
       peer_name => "the same link and record writes between two bare processes",
       better => higher,
       note => "The protocol's floor: the cell's own link process between two bare "
               "processes that make the four calls, the cast and the five product-file "
               "writes of a transfer through a line of 2, on the same RAM folder, with "
               "no task engine (no state machine, no step callback, no events, no "
               "registry). No task engine on this link and these files passes it; the "
               "ratio is what the engine costs. The next figure is the floor beside "
               "the same without the writes: what the five writes cost a transfer."},
     #{title => "The protocol's floor, line of 2, RAM folder", unit => "transfers/s",
       ours => Floor, peer => FloorBare,
       peer_name => "the same without the record writes", better => higher},
     #{title => "Transfers per second, line of 2, RAM folder, whole cell", unit => "transfers/s",
       ours => Cell2, peer => RoundTrips, peer_name => "raw message round trips/s",
       better => higher,
       note => "The same with the cell's statistics counting every event and writing "
               "each product's history to the database (three history records and a "
               "row per transfer) as the line runs, on the same two cores."},
     #{title => "Transfers per second, line of 2, RAM folder, whole cell, beside the trace "
                "journal off", unit => "transfers/s", ours => Cell2, peer => Cell2Off,
       peer_name => "the same with the trace journal stopped", better => higher,
       note => "The whole cell as above, with the trace journal (cell_trace_journal: "
               "four records a product through a line of 2: its taking by the first segment "
               "and its transfers in and out, each on the disk before its task goes on, "
               "none flushed in a RAM folder) beside the same cell with the journal "
               "stopped, the statistics then taking every event as it comes."},
     #{title => "Transfers per second, line of 10, RAM folder", unit => "transfers/s",
       ours => Ram10, peer => RoundTrips, peer_name => "raw message round trips/s",
       better => higher},
     #{title => "One product through a line of 2, RAM folder, median", unit => "ms",
       ours => LM / 1000, peer => 1000 / RoundTrips, peer_name => "one raw round trip",
       better => lower},
     #{title => "One product through a line of 2, RAM folder, p99", unit => "ms",
       ours => LP / 1000, peer => 1000 / RoundTrips, peer_name => "one raw round trip",
       better => lower},
     #{title => "Transfers per second, line of 2, durable", unit => "transfers/s",
       ours => Disk2, peer => DiskUnit, peer_name => "write+fsync+rename/s, same disk",
       better => higher,
       note => "A line of 2 also saves each new product at the first segment and "
               "removes it at the last, both durably: three flushes per transfer here, "
               "and the trace journal's records (the next figure). The median of five "
               "rounds."},
     #{title => "Transfers per second, line of 2, durable, beside the trace journal off",
       unit => "transfers/s", ours => Disk2, peer => Disk2Off,
       peer_name => "the same with the trace journal stopped", better => higher,
       note => "Each product's four journal records flushed before their tasks go on, "
               "records of both tasks sharing flushes (group commit), beside the same "
               "line with the journal stopped."},
     #{title => "Transfers per second, line of 10, durable", unit => "transfers/s",
       ours => Disk10, peer => DiskUnit, peer_name => "write+fsync+rename/s, same disk",
       better => higher, goal => ">= 0.5 of the disk's rate"},
     #{title => "Transfers per second, 4 lines of 5 at once, durable", unit => "transfers/s",
       ours => DiskLines, peer => DiskUnit, peer_name => "write+fsync+rename/s, one writer",
       better => higher, goal => "more transfers than one writer's fsyncs"}].

%% -------------------------------------------------------------------------------------

%% Transfers per second through `Lines' lines of `Len' segments, `Per' products each
%% round, the median of `Rounds' rounds through one running cell; the statistics
%% running (`attached') or stopped (`detached'), or running with the trace journal
%% stopped (`unjournaled').
line_rate(Root, Lines, Len, {Rounds, Per}, Stats) ->
    {Specs, Feeds, Refs} = lines(Lines, Len),
    start_line(Root, Specs, Stats),
    Rates = [begin
                 T0 = erlang:monotonic_time(microsecond),
                 [feed(Feed, Ref, Src, Per)
                  || {Feed, Ref, Src} <- lists:zip3(Feeds, Refs, srcs(Lines))],
                 await_out(Lines * Per),
                 T1 = erlang:monotonic_time(microsecond),
                 Lines * Per * (Len - 1) / ((T1 - T0) / 1000000)
             end || _ <- lists:seq(1, Rounds)],
    ok = cell_controller:stop(),
    stop_cell(),
    maps:get(median, cell_bench:stats(Rates)).

%% Microseconds for one product through a line of 2 (one transfer), one at a time.
latency(Root, N) ->
    {Specs, [Feed], [Ref]} = lines(1, 2),
    start_line(Root, Specs, detached),
    Samples = [begin
                   T0 = erlang:monotonic_time(microsecond),
                   feed(Feed, Ref, hd(srcs(1)), 1),
                   await_out(1),
                   erlang:monotonic_time(microsecond) - T0
               end || _ <- lists:seq(1, N)],
    ok = cell_controller:stop(),
    stop_cell(),
    Samples.

lines(Lines, Len) ->
    Self = self(),
    Built = [begin
                 Feed = ets:new(feed, [ordered_set, public]),
                 Out = ets:new(out, [set, public]),
                 Ref = make_ref(),
                 Seg = fun(I) -> list_to_atom(lists:flatten(io_lib:format("l~p_s~p", [L, I]))) end,
                 Link = fun(I) -> list_to_atom(lists:flatten(io_lib:format("l~p_h~p", [L, I]))) end,
                 Tasks = [#{id => Seg(I), module => cell_line_task,
                            zone => <<"Bench">>, lane => iolist_to_binary(io_lib:format("~p-~p", [L, I])),
                            args => #{prev => case I of 1 -> undefined; _ -> Link(I - 1) end,
                                      next => case I of Len -> undefined; _ -> Link(I) end,
                                      feed => Feed, out => Out, ref => Ref,
                                      notify => case I of Len -> Self; _ -> undefined end,
                                      phases => false}}
                          || I <- lists:seq(1, Len)],
                 Links = [#{id => Link(I), from => Seg(I), to => Seg(I + 1)} || I <- lists:seq(1, Len - 1)],
                 {Tasks, Links, Feed, Ref}
             end || L <- lists:seq(1, Lines)],
    Specs = #{tasks => lists:append([T || {T, _, _, _} <- Built]),
              links => lists:append([Ls || {_, Ls, _, _} <- Built])},
    {Specs, [F || {_, _, F, _} <- Built], [R || {_, _, _, R} <- Built]}.

srcs(Lines) ->
    [list_to_atom(lists:flatten(io_lib:format("l~p_s1", [L]))) || L <- lists:seq(1, Lines)].

feed(Feed, Ref, Src, N) ->
    Base = erlang:unique_integer([positive]) * 100000,
    true = ets:insert(Feed, [{Base + I, <<"B-", (integer_to_binary(Base + I))/binary>>}
                             || I <- lists:seq(1, N)]),
    cell_task_proc:whereis(Src) ! {Ref, fed},
    ok.

await_out(0) ->
    ok;
await_out(N) ->
    receive
        {line_out, _, _} -> await_out(N - 1)
    after 60000 ->
        erlang:error({products_missing, N})
    end.

%% -------------------------------------------------------------------------------------
%% Peers
%% -------------------------------------------------------------------------------------

%% Round trips per second between two bare processes, for about a second.
round_trips() ->
    Echo = spawn_link(fun Loop() -> receive {From, M} -> From ! M, Loop() end end),
    T0 = erlang:monotonic_time(microsecond),
    N = ping(Echo, 0, T0 + 1000000),
    T1 = erlang:monotonic_time(microsecond),
    unlink(Echo),
    exit(Echo, kill),
    N / ((T1 - T0) / 1000000).

ping(Echo, N, Until) ->
    case N rem 1000 =:= 0 andalso erlang:monotonic_time(microsecond) >= Until of
        true ->
            N;
        false ->
            Echo ! {self(), N},
            receive N -> ok end,
            ping(Echo, N + 1, Until)
    end.

%% Transfers per second of the protocol alone: the cell's own link between two bare
%% processes making what a line of 2 makes per transfer (four calls, the `owned' cast,
%% five product-file writes, or none), the median of `Rounds' rounds of `Per' products.
protocol_floor(Root, {Rounds, Per}, Writes) ->
    Dir = filename:join(Root, "protocol-floor"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    {ok, Link} = cell_handshake_link:start_link(#{id => bench_protocol_floor,
                                                  from => undefined, to => undefined}),
    Self = self(),
    Sides = [spawn_link(fun() -> floor_side(Role, Link, filename:join(Dir, Name), Writes, Self) end)
             || {Role, Name} <- [{up, "up.product"}, {down, "down.product"}]],
    [receive {attached, S} -> ok end || S <- Sides],
    Rates = [begin
                 T0 = erlang:monotonic_time(microsecond),
                 [S ! {go, Per} || S <- Sides],
                 [receive {done, S} -> ok end || S <- Sides],
                 Per / ((erlang:monotonic_time(microsecond) - T0) / 1000000)
             end || _ <- lists:seq(1, Rounds)],
    [begin unlink(P), exit(P, kill) end || P <- [Link | Sides]],
    maps:get(median, cell_bench:stats(Rates)).

floor_side(Role, Link, Path, Writes, Boss) ->
    {ok, _} = gen_server:call(Link, {attach, Role, Role, self(), none}),
    File = case Writes of
               true -> cell_file:record_file(Path);
               false -> none
           end,
    Boss ! {attached, self()},
    floor_rounds(Role, Link, File, Boss).

floor_rounds(Role, Link, File, Boss) ->
    receive
        {go, N} ->
            [floor_transfer(Role, Link, File, I) || I <- lists:seq(1, N)],
            Boss ! {done, self()},
            floor_rounds(Role, Link, File, Boss)
    end.

%% Upstream: the new product saved, offered, released once committed, forgotten once
%% downstream owns it, and the transfer completed.
floor_transfer(up, Link, File, I) ->
    P = cell_product:new(<<"F-", (integer_to_binary(I))/binary>>, <<"line">>),
    ok = save(File, cell_product:stored(P, 1, undefined), #{}),
    {ok, _} = gen_server:call(Link, {offer, self(), P, 1}),
    link_message(fun({signals, #{not_busy := true}}) -> true; (_) -> false end),
    {ok, _} = gen_server:call(Link, {release, self()}),
    link_message(fun(owned) -> true; (_) -> false end),
    ok = save(File, undefined, #{sync => false}),
    link_message(fun({completed, _}) -> true; (_) -> false end);
%% Downstream: commit on the offer, the product saved in transit once released, owned,
%% completed with the mark cleared, and sent out.
floor_transfer(down, Link, File, _I) ->
    link_message(fun({_, #{available := true}}) -> true; (_) -> false end),
    {{ok, P, G}, _} = gen_server:call(Link, {commit, self()}),
    link_message(fun({{released, _, _}, _}) -> true; (_) -> false end),
    ok = save(File, cell_product:stored(P, G + 1, #{link => bench_protocol_floor,
                                                  from => upstream, phase => in_transit}),
              #{}),
    gen_server:cast(Link, {owned, self()}),
    {ok, _} = gen_server:call(Link, {complete, self()}),
    ok = save(File, cell_product:stored(P, G + 1, undefined), #{sync => false}),
    ok = save(File, undefined, #{}).

save(none, _Stored, _Opts) -> ok;
save(File, Stored, Opts) -> cell_product:save(File, Stored, Opts).

%% The next message of the link that `Wanted' accepts; the link's other news (the
%% signals it also sends) is dropped.
link_message(Wanted) ->
    receive
        {cell_handshake, _, Step} -> link_message(Step, Wanted);
        {cell_handshake, _, Step, Status} -> link_message({Step, Status}, Wanted)
    end.

link_message(Message, Wanted) ->
    case Wanted(Message) of
        true -> ok;
        false -> link_message(Wanted)
    end.

%% The disk's rate of the write a transfer's commit makes: a small term written to a
%% temporary file, flushed, renamed over the target, the folder flushed.
disk_rate(Root, N) ->
    Dir = filename:join(Root, "fsync-peer"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Term = cell_product:stored(cell_product:new(<<"B-1">>, <<"line">>), 1, undefined),
    Path = filename:join(Dir, "peer.product"),
    T0 = erlang:monotonic_time(microsecond),
    [ok = cell_file:write_term(Path, Term) || _ <- lists:seq(1, N)],
    T1 = erlang:monotonic_time(microsecond),
    N / ((T1 - T0) / 1000000).

%% -------------------------------------------------------------------------------------

%% A cell of lines started and running, its statistics attached to its events or not.
start_line(Root, Specs, Stats) ->
    start_cell(Root, Specs),
    %% Detached: no statistics at all. Neither the events nor the trace journal's
    %% records reach them (the journal keeps its records until a reader attaches).
    _ = Stats =:= detached andalso supervisor:terminate_child(cell_controller_sup, cell_stats),
    %% The tasks go on without the journal when it does not run.
    _ = Stats =:= unjournaled andalso
        supervisor:terminate_child(cell_controller_sup, cell_trace_journal),
    ok = cell_controller:start(),
    ok = cell_controller:sync().

start_cell(Root, Spec) ->
    _ = os:cmd("rm -rf '" ++ filename:join(Root, "Data") ++ "'"),
    _ = application:load(cell_base),
    _ = application:load(cell),
    %% The environment's root (the bench's own) would win over the application's.
    true = os:putenv("CELLRT_ROOT", Root),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    ok.

stop_cell() ->
    ok = application:stop(cell).

quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).
