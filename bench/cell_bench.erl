%% @doc The benchmark runner behind `make bench'.
%%
%% Every module `bench/*_bench.erl' exports `run() -> [result()]'. Each result is one
%% figure of ours measured beside a peer's figure in the same run, so the ratio holds
%% even on a busy or slower machine. The runner prints every figure with its ratio and
%% the command that reproduces it, and rewrites `docs/benchmarks.md' after a full run.
%%
%% `make bench' runs them all; `make bench BENCH=cell_task_bench' runs one module and
%% only prints.
-module(cell_bench).

-export([main/1, stats/1, percentile/2, result/1, alternating_rates/3, vm_flags/0]).
-export([build_c/2, start_c_server/1, stop_c_server/1]).

-export_type([result/0]).

-type result() :: #{title := iodata(),        %% what was measured, with its size
                    unit := iodata(),         %% "ms", "transfers/s" ...
                    ours := number(),
                    peer := number() | undefined,
                    peer_name := iodata(),    %% what the peer is
                    better := higher | lower, %% which way is better
                    goal => iodata(),         %% the issue's goal, said plainly
                    note => iodata()}.

%% @doc Entry points, as `scripts/bench' calls them:
%% <ul>
%% <li>`erl -run cell_bench main run Mod File': runs one module in this VM, prints its
%%     figures and keeps them in `File' for the document;</li>
%% <li>`erl -run cell_bench main doc File...': rewrites `docs/benchmarks.md' from the
%%     kept figures of a full run;</li>
%% <li>`erl -run cell_bench main Mod1 Mod2': runs modules here and only prints.</li>
%% </ul>
%% A full run gives every module a VM of its own: a benchmark starts and stops the
%% cell's applications, and what one leaves behind (a database folder, a connection, a
%% busy scheduler) must not move the next one's figures.
-spec main([string()]) -> no_return().
main(["run", Name, File]) ->
    unicode_out(),
    Mod = list_to_atom(Name),
    Section = run_module(Mod),
    ok = file:write_file(File, term_to_binary(Section)),
    erlang:halt(case Section of {_, {ok, _}} -> 0; _ -> 1 end);
main(["doc" | Files]) ->
    Sections = [binary_to_term(B) || F <- Files, {ok, B} <- [file:read_file(F)]],
    Failed = [M || {M, {error, _}} <- Sections],
    case {length(Sections) =:= length(Files), Failed} of
        {true, []} ->
            ok = write_doc(Sections),
            io:format("~ndocs/benchmarks.md rewritten from ~p module(s)~n", [length(Files)]),
            erlang:halt(0);
        _ ->
            io:format("~ndocs/benchmarks.md kept: ~p of ~p module(s) ran, failed: ~p~n",
                      [length(Sections) - length(Failed), length(Files), Failed]),
            erlang:halt(1)
    end;
main(Names) ->
    unicode_out(),
    Sections = [run_module(list_to_atom(N)) || N <- Names],
    Failed = [M || {M, {error, _}} <- Sections],
    io:format("~n~p benchmark module(s) run, ~p failed~n", [length(Names), length(Failed)]),
    erlang:halt(case Failed of [] -> 0; _ -> 1 end).

%% Titles and units say µs and ×: the console of a VM without a shell is Latin-1.
unicode_out() ->
    ok = io:setopts(standard_io, [{encoding, unicode}]).

run_module(Mod) ->
    io:format("~n== ~s~n", [Mod]),
    T0 = erlang:monotonic_time(millisecond),
    try Mod:run() of
        Results ->
            [print(R, Mod) || R <- Results],
            io:format("   (~.1f s)~n", [(erlang:monotonic_time(millisecond) - T0) / 1000]),
            {Mod, {ok, Results}}
    catch
        Class:Reason:Stack ->
            io:format("   FAILED ~p:~tp~n   ~tp~n", [Class, Reason, Stack]),
            {Mod, {error, Reason}}
    end.

print(R, Mod) ->
    io:format("   ~ts~n      ours ~ts ~ts | ~ts ~ts | ratio ~ts~ts~n      reproduce: ~ts~n",
              [maps:get(title, R), fmt(maps:get(ours, R)), maps:get(unit, R),
               maps:get(peer_name, R), fmt(maps:get(peer, R)), ratio(R),
               case maps:find(goal, R) of {ok, G} -> ["  (goal: ", G, ")"]; error -> "" end,
               command(Mod)]).

command(Mod) ->
    io_lib:format("make bench BENCH=~s", [Mod]).

%% @doc The emulator flags of a cell's node (config/vm.args.src), as scripts/bench
%% found them, for the nodes a benchmark starts of its own.
-spec vm_flags() -> [string()].
vm_flags() ->
    string:lexemes(os:getenv("CELLRT_BENCH_VM_FLAGS", "+K true"), " ").

%% @doc The ratio, oriented so that above 1 means ours is better.
-spec result(result()) -> float() | undefined.
result(#{peer := undefined}) -> undefined;
result(#{peer := P}) when P == 0 -> undefined;
result(#{ours := O, peer := P, better := higher}) -> O / P;
result(#{ours := O, peer := _}) when O == 0 -> undefined;
result(#{ours := O, peer := P, better := lower}) -> P / O.

ratio(R) ->
    case result(R) of
        undefined -> "-";
        X -> io_lib:format("~.2f", [X])
    end.

fmt(undefined) -> "-";
fmt(X) when is_integer(X) -> integer_to_list(X);
fmt(X) when abs(X) >= 100 -> integer_to_list(round(X));
fmt(X) when abs(X) >= 1 -> io_lib:format("~.2f", [X]);
fmt(X) -> io_lib:format("~.4f", [X]).

%% @doc Median, p99 and mean of a list of samples.
-spec stats([number()]) -> #{median := number(), p99 := number(), mean := float(),
                             n := non_neg_integer()}.
stats(Samples) ->
    Sorted = lists:sort(Samples),
    #{median => percentile(Sorted, 50), p99 => percentile(Sorted, 99),
      mean => lists:sum(Sorted) / max(1, length(Sorted)), n => length(Sorted)}.

%% @doc The rates of two counting processes, ours and a peer, measured in `Turns'
%% short turns of `Ms' each, one running while the other is suspended, so the
%% machine's speed, which moves on a shared host, falls on both alike: the median
%% counts per second of each. Both are left running.
-spec alternating_rates({pid(), counters:counters_ref()}, {pid(), counters:counters_ref()},
                        #{turns := pos_integer(), ms := pos_integer()}) ->
          {Ours :: float(), Peer :: float()}.
alternating_rates({Ours, OurCounter}, {Peer, PeerCounter}, #{turns := N, ms := Ms}) ->
    ok = sys:suspend(Peer),
    Turns = [begin
                 ok = sys:resume(Ours),
                 O = rate(OurCounter, Ms),
                 ok = sys:suspend(Ours),
                 ok = sys:resume(Peer),
                 P = rate(PeerCounter, Ms),
                 ok = sys:suspend(Peer),
                 {O, P}
             end || _ <- lists:seq(1, N)],
    ok = sys:resume(Ours),
    ok = sys:resume(Peer),
    #{median := OurRate} = stats([O || {O, _} <- Turns]),
    #{median := PeerRate} = stats([P || {_, P} <- Turns]),
    {OurRate, PeerRate}.

rate(Counter, Ms) ->
    C0 = counters:get(Counter, 1),
    T0 = erlang:monotonic_time(microsecond),
    receive after Ms -> ok end,
    C1 = counters:get(Counter, 1),
    T1 = erlang:monotonic_time(microsecond),
    (C1 - C0) / ((T1 - T0) / 1000000).

%% @doc The nearest-rank percentile of a sorted list.
-spec percentile([number()], 0..100) -> number().
percentile([], _) -> 0;
percentile(Sorted, P) ->
    N = length(Sorted),
    Rank = max(1, min(N, ceil(P / 100 * N))),
    lists:nth(Rank, Sorted).

%% @doc Compiles a C peer linked with libmodbus: `Src' relative to the project's top
%% folder, the program `_build/bench/<Name>'.
-spec build_c(file:filename(), string()) -> file:filename().
build_c(Src0, Name) ->
    Top = case os:getenv("CELLRT_TOP") of false -> "."; T -> T end,
    Out = filename:join([Top, "_build", "bench"]),
    ok = filelib:ensure_path(Out),
    Exe = filename:join(Out, Name),
    Src = filename:join(Top, Src0),
    case os:cmd("gcc -O2 -o '" ++ Exe ++ "' '" ++ Src ++ "' -lmodbus 2>&1 && echo built") of
        "built\n" -> Exe;
        Err -> error({cannot_compile, Src, Err})
    end.

%% @doc Starts a C server peer that listens on a free port and says `port <N>' on its
%% first line.
-spec start_c_server(file:filename()) -> #{port := port(), tcp := inet:port_number()}.
start_c_server(Exe) ->
    P = open_port({spawn_executable, Exe}, [{args, ["0"]}, {line, 4096}, exit_status, binary]),
    receive
        {P, {data, {eol, <<"port ", N/binary>>}}} -> #{port => P, tcp => binary_to_integer(N)}
    after 10000 -> error({server_did_not_start, Exe})
    end.

-spec stop_c_server(#{port := port()}) -> ok.
stop_c_server(#{port := P}) ->
    catch port_close(P),
    flush_port(P).

flush_port(P) ->
    receive {P, _} -> flush_port(P) after 0 -> ok end.

write_doc(Sections) ->
    Top = case os:getenv("CELLRT_TOP") of false -> "."; T -> T end,
    Path = filename:join([Top, "docs", "benchmarks.md"]),
    Rows = [[section(Mod, Results)] || {Mod, {ok, Results}} <- Sections],
    Doc = ["# Benchmarks\n\n",
           "Written by `make bench` on ", machine(), ".\n",
           "Each figure of ours is measured beside a peer's figure in the same run; the ",
           "ratio is oriented so that above 1 means cellrt is better (faster, or less ",
           "delay). Figures move from run to run on a shared 2-core machine: read the ",
           "ratios, not the third digit.\n\n",
           Rows],
    file:write_file(Path, unicode:characters_to_binary(Doc)).

section(Mod, Results) ->
    ["## ", atom_to_list(Mod), "\n\nReproduce: `", command(Mod), "`\n\n",
     "| figure | ours | peer | peer figure | ratio | goal |\n",
     "|---|---|---|---|---|---|\n",
     [["| ", maps:get(title, R), " | ", fmt(maps:get(ours, R)), " ", maps:get(unit, R),
       " | ", maps:get(peer_name, R), " | ", fmt(maps:get(peer, R)), " | ", ratio(R), " | ",
       maps:get(goal, R, ""), " |\n"] || R <- Results],
     [["\n", N, "\n"] || #{note := N} <- Results],
     "\n"].

machine() ->
    {{Y, Mo, D}, _} = calendar:universal_time(),
    Cpu = case file:read_file("/proc/cpuinfo") of
              {ok, Bin} ->
                  case re:run(Bin, "model name\\s*:\\s*([^\\n]+)", [{capture, all_but_first, binary}]) of
                      {match, [M]} -> M;
                      nomatch -> <<"unknown CPU">>
                  end;
              _ -> <<"unknown CPU">>
          end,
    %% Other work on the machine moves the figures: its load when the run ended says
    %% how quiet it was.
    Load = case file:read_file("/proc/loadavg") of
               {ok, L} -> hd(binary:split(L, <<" ">>));
               _ -> <<"unknown">>
           end,
    io_lib:format("~4..0w-~2..0w-~2..0w, ~ts, ~p schedulers, OTP ~s, load average ~ts; "
                  "the VMs with the node's flags (config/vm.args.src): `~ts`",
                  [Y, Mo, D, Cpu, erlang:system_info(schedulers_online),
                   erlang:system_info(otp_release), Load,
                   string:trim(os:getenv("CELLRT_BENCH_VM_FLAGS", ""))]).
