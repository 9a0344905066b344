%% @doc Trace journal benchmarks ({@link cell_trace_journal}): records of the product's
%% way made durable before the cell acts, by group commit.
%%
%% <ul>
%% <li>one writer on the disk, beside the disk's own rate of the same frame appended
%% and flushed (write + fdatasync, {@link cell_file:append/3}) in the same folder by one
%% process: what the journal costs one task;</li>
%% <li>many writers on the disk, beside the same raw rate: records per second when
%% many tasks' records share one flush;</li>
%% <li>one and many writers on a RAM folder (nothing flushed), beside the same appends
%% with no journal process.</li>
%% </ul>
-module(cell_trace_journal_bench).

-export([run/0]).

-define(RAM, "/dev/shm").
-define(WRITERS, 16).
-define(ROUNDS, 5).
-define(DISK_PEER, "the same frame appended + fdatasync, one writer, same folder, "
                   "no journal process").
-define(RAM_PEER, "the same frame appended, one writer, same folder, no journal process").

-spec run() -> [cell_bench:result()].
run() ->
    quiet(),
    DiskRoot = filename:join(os:getenv("CELLRT_ROOT", "_build/bench/root"), "journal"),
    RamRoot = filename:join(?RAM, "cellrt-journal-bench-" ++ os:getpid()),
    %% Ours and the peer's in turns, the medians: a shared disk's speed moves by several
    %% times from one second to the next.
    [Disk1, DiskN, DiskRaw] =
        medians([[journal_rate(DiskRoot, 1, 200), journal_rate(DiskRoot, ?WRITERS, 50),
                  raw_rate(DiskRoot, 200)] || _ <- lists:seq(1, ?ROUNDS)]),
    [Ram1, RamN, RamRaw] =
        medians([[journal_rate(RamRoot, 1, 5000), journal_rate(RamRoot, ?WRITERS, 1000),
                  raw_rate(RamRoot, 5000)] || _ <- lists:seq(1, ?ROUNDS)]),
    _ = os:cmd("rm -rf '" ++ RamRoot ++ "'"),
    [#{title => "Trace journal, one writer, disk", unit => "records/s",
       ours => Disk1, peer => DiskRaw,
       peer_name => ?DISK_PEER,
       better => higher,
       note => "A task's record of a product's way (taken, transferred in or out, an "
               "answer) is on the disk before the task goes on. One writer alone pays "
               "one flush per record, as the raw appends do. Every figure here is the "
               "median of five rounds, ours and the peer's measured in turns."},
     #{title => io_lib:format("Trace journal, ~b writers at once, disk", [?WRITERS]),
       unit => "records/s", ours => DiskN, peer => DiskRaw,
       peer_name => ?DISK_PEER,
       better => higher,
       note => "Group commit: the records that come while a flush is under way are "
               "written and flushed together, each writer answered when its own record "
               "is on the disk; the ratio is how many records share a flush."},
     #{title => "Trace journal, one writer, RAM folder", unit => "records/s",
       ours => Ram1, peer => RamRaw,
       peer_name => ?RAM_PEER,
       better => higher,
       note => "A folder in RAM is never flushed; what the ratio shows is the cost of "
               "the call to the journal process."},
     #{title => io_lib:format("Trace journal, ~b writers at once, RAM folder", [?WRITERS]),
       unit => "records/s", ours => RamN, peer => RamRaw,
       peer_name => ?RAM_PEER,
       better => higher}].

medians(Rounds) ->
    [maps:get(median, cell_bench:stats([lists:nth(I, R) || R <- Rounds]))
     || I <- lists:seq(1, length(hd(Rounds)))].

%% Records per second through the journal from `Writers' processes, `Per' each.
journal_rate(Root, Writers, Per) ->
    {ok, Journal} = start(Root),
    Me = self(),
    T0 = erlang:monotonic_time(microsecond),
    Pids = [spawn_link(fun() ->
                               [{ok, _} = cell_trace_journal:append(record(W))
                                || _ <- lists:seq(1, Per)],
                               Me ! {done, self()}
                       end) || W <- lists:seq(1, Writers)],
    [receive {done, P} -> ok end || P <- Pids],
    T1 = erlang:monotonic_time(microsecond),
    stop(Journal),
    Writers * Per / ((T1 - T0) / 1000000).

%% The same frames appended to a file of the same folder by one process with the same
%% call, no journal process between (each flushed, except in a folder held in RAM).
raw_rate(Root, N) ->
    Path = filename:join([Root, "Databases", "raw.journal"]),
    ok = filelib:ensure_dir(Path),
    _ = file:delete(Path),
    {ok, File} = cell_file:append_file(Path),
    Frame = cell_trace_journal:encode((record(1))#{id => {1, 1}, at => 0}),
    T0 = erlang:monotonic_time(microsecond),
    [ok = cell_file:append(File, Frame, #{}) || _ <- lists:seq(1, N)],
    T1 = erlang:monotonic_time(microsecond),
    ok = cell_file:close_append(File),
    ok = file:delete(Path),
    N / ((T1 - T0) / 1000000).

record(W) ->
    #{type => item_transfer_out, task => bench, item => <<"B-", (integer_to_binary(W))/binary>>,
      zone => <<"Bench">>, lane => <<"1">>}.

%% A journal in the root's database folder, empty.
start(Root) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, Root),
    true = os:putenv("CELLRT_ROOT", Root),
    _ = file:delete(filename:join([Root, "Databases", "cell_trace.journal"])),
    {ok, _} = application:ensure_all_started(cell_base),
    {ok, Pid} = cell_trace_journal:start_link(),
    unlink(Pid),
    {ok, Pid}.

quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false).

stop(Pid) ->
    ok = gen_server:stop(Pid),
    ok = application:stop(cell_base).
