%% @doc The soak run behind `make soak': the default cell, both lanes, at a high
%% arrival rate (a panel always waiting upstream, the physics twenty times faster than
%% the real machine), faults injected and answered by a simulated operator, the panel
%% and the SHDR adapter running with an agent reading the stream, for `SOAK_MINUTES'
%% (default 30). Every `SOAK_SAMPLE_S' seconds (default 60) it prints the node's memory
%% (total, processes, ETS, binaries), the process count, the longest message queues,
%% the products passed and the size of `Databases/'; at the end the growth from the
%% first sample after the warm-up to the last, and whether the books balance. A run of
%% 30 minutes or more writes `docs/soak.md'.
%%
%% It reports figures; it asserts nothing.
-module(router_soak).

-export([main/1]).

-define(WARMUP_S, 120).

%% @doc Entry point: `erl -run router_soak main Minutes'.
-spec main([string()]) -> no_return().
main([Minutes0]) ->
    Minutes = list_to_integer(Minutes0),
    SampleS = env_int("SOAK_SAMPLE_S", 60),
    ok = router_bench_cell:start(#{settings => settings(), with_panel => true}),
    Operator = spawn_link(fun operator/0),
    Agent = spawn_link(fun() -> agent(cell_shdr:port()) end),
    ok = cell_controller:start(<<"soak">>),
    io:format("soak: ~b min, a sample every ~b s; panel on port ~b, SHDR on port ~b~n",
              [Minutes, SampleS, cell_web:port(), cell_shdr:port()]),
    T0 = erlang:monotonic_time(second),
    Header = io_lib:format("~6s ~9s ~9s ~7s ~7s ~6s ~6s ~9s ~9s ~7s  ~s~n",
                           ["min", "total MB", "procs MB", "ets MB", "bin MB", "procs",
                            "queue", "queued", "out", "db MB", "longest queues"]),
    io:put_chars(Header),
    Samples = loop(T0, Minutes * 60, SampleS, []),
    ok = cell_controller:stop(<<"soak">>),
    Books = books(Operator, Agent),
    Tables = largest_tables(8),
    Report = [Header, [row(S) || S <- Samples], "\n", summary(Samples), Books, Tables],
    io:put_chars(["\n", summary(Samples), Books, Tables]),
    case Minutes >= 30 of
        true -> ok = write_doc(Minutes, SampleS, Report);
        false -> ok
    end,
    router_bench_cell:stop(),
    erlang:halt(0).

%% The machine: both lanes, fast, and making mistakes now and then.
settings() ->
    #{machine => #{dual_lane => true},
      router_sim => #{time_scale => 0.05, arrival_ms => 0, product_lost_rate => 0.05,
                      reseat_ms => 20000, jam_rate => 0.01, jam_ms => 100000,
                      magazine_low_s => 600, magazine_refill_s => 120},
      router => #{transfer_timeout_ms => 3000, motion_timeout_ms => 5000}}.

loop(T0, Duration, SampleS, Acc) ->
    Elapsed = erlang:monotonic_time(second) - T0,
    Sample = sample(Elapsed),
    io:put_chars(row(Sample)),
    case Elapsed >= Duration of
        true ->
            lists:reverse([Sample | Acc]);
        false ->
            receive after min(SampleS, Duration - Elapsed) * 1000 -> ok end,
            loop(T0, Duration, SampleS, [Sample | Acc])
    end.

sample(Elapsed) ->
    Mem = maps:from_list(erlang:memory()),
    Queues = recon:proc_count(message_queue_len, 3),
    Queued = lists:sum([N || P <- processes(),
                             {message_queue_len, N} <- [process_info(P, message_queue_len)]]),
    #{cell := #{out := Out}} = cell_stats:summary(total),
    #{s => Elapsed, total => maps:get(total, Mem), processes => maps:get(processes, Mem),
      ets => maps:get(ets, Mem), binary => maps:get(binary, Mem),
      count => erlang:system_info(process_count), queues => Queues, queued => Queued,
      out => Out, db => dir_size(cell_db:dir())}.

row(#{s := S, total := T, processes := P, ets := E, binary := B, count := C,
      queues := Q, queued := Qd, out := Out, db := Db}) ->
    Longest = case Q of [{_, N, _} | _] -> N; [] -> 0 end,
    io_lib:format("~6.1f ~9.1f ~9.1f ~7.1f ~7.1f ~6b ~6b ~9b ~9b ~7.1f  ~s~n",
                  [S / 60, mb(T), mb(P), mb(E), mb(B), C, Longest, Qd, Out, mb(Db),
                   lists:join(", ", [io_lib:format("~s ~b", [name(I), L]) || {_, L, I} <- Q])]).

%% Growth from the first sample after the warm-up to the last.
summary(Samples) ->
    After = [S || #{s := T} = S <- Samples, T >= ?WARMUP_S],
    case After of
        [First | _] ->
            Last = lists:last(After),
            MaxQ = lists:max([case Q of [{_, N, _} | _] -> N; [] -> 0 end
                              || #{queues := Q} <- Samples]),
            Hours = max(maps:get(s, Last) - maps:get(s, First), 1) / 3600,
            Panels = (maps:get(out, Last) - maps:get(out, First)) / Hours,
            io_lib:format("From minute ~.1f to ~.1f: memory ~.1f -> ~.1f MB (~s), processes "
                          "~b -> ~b, ETS ~.1f -> ~.1f MB, binaries ~.1f -> ~.1f MB; longest "
                          "message queue seen ~b; ~b panels an hour (at 20x the machine's "
                          "speed); Databases/ ~.1f -> ~.1f MB.~n",
                          [maps:get(s, First) / 60, maps:get(s, Last) / 60,
                           mb(maps:get(total, First)), mb(maps:get(total, Last)),
                           pct(maps:get(total, First), maps:get(total, Last)),
                           maps:get(count, First), maps:get(count, Last),
                           mb(maps:get(ets, First)), mb(maps:get(ets, Last)),
                           mb(maps:get(binary, First)), mb(maps:get(binary, Last)),
                           MaxQ, round(Panels), mb(maps:get(db, First)), mb(maps:get(db, Last))]);
        [] ->
            io_lib:format("Shorter than the warm-up (~b s): no growth figures.~n", [?WARMUP_S])
    end.

%% The ETS tables that hold the most memory at the end, with their entries: what the
%% ETS figure above is made of (bounded buffers fill during the first minutes).
largest_tables(N) ->
    Sizes = [{Words * erlang:system_info(wordsize), Name, Size}
             || T <- ets:all(),
                [{memory, Words}, {name, Name}, {size, Size}]
                    <- [[{K, ets:info(T, K)} || K <- [memory, name, size]]],
                is_integer(Words)],
    Top = lists:sublist(lists:reverse(lists:sort(Sizes)), N),
    ["Largest ETS tables at the end: ",
     lists:join(", ", [io_lib:format("~s ~.2f MB (~b entries)", [Name, mb(Bytes), Size])
                       || {Bytes, Name, Size} <- Top]), ".\n"].

%% The operator's answers and the books once the cell has stopped.
books(Operator, Agent) ->
    Operator ! {report, self()},
    Answers = receive {answers, A} -> A after 5000 -> #{} end,
    Agent ! {report, self()},
    Bytes = receive {shdr_bytes, By} -> By after 5000 -> 0 end,
    ok = cell_stats:flush(),
    ok = cell_stats:flush(),
    ok = cell_stats:flush(),
    #{cell := #{in := In, out := Out, scrapped := Scrapped, failed := Failed},
      in_cell := InCell} = cell_stats:summary(total),
    #{counters := #{delivered := Delivered}} = router_sim:world(),
    io_lib:format("Products: in ~b = out ~b + scrapped ~b + in the cell ~b (~s); the machine "
                  "delivered ~b; failed ~b. Operator answers: ~s. SHDR agent read ~.1f MB.~n",
                  [In, Out, Scrapped, InCell,
                   case In =:= Out + Scrapped + InCell of
                       true -> "balanced";
                       false -> "NOT balanced"
                   end, Delivered, Failed,
                   lists:join(", ", [io_lib:format("~s ~b", [K, V])
                                     || {K, V} <- lists:sort(maps:to_list(Answers))]),
                   mb(Bytes)]).

%% A simulated operator: answers every error a moment after it appears, Retry, Ignore
%% and Reset in turn where offered (else the first offered).
operator() ->
    ok = cell_events:subscribe([alarm_raised]),
    operator(#{}).

operator(Answers) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, id := Id,
                                                        solutions := Solutions}}} ->
            receive after 200 -> ok end,
            N = lists:sum(maps:values(Answers)),
            Preferred = lists:nth(N rem 3 + 1, [retry, ignore, reset]),
            Solution = case lists:member(Preferred, Solutions) of
                           true -> Preferred;
                           false -> hd(Solutions)
                       end,
            _ = cell_alarms:answer(Id, Solution, <<"soak operator">>),
            operator(maps:update_with(Solution, fun(X) -> X + 1 end, 1, Answers));
        {cell_event, _} ->
            operator(Answers);
        {report, To} ->
            To ! {answers, Answers},
            operator(Answers)
    end.

%% An MTConnect agent: connected to the SHDR adapter, reading everything it sends.
agent(Port) ->
    {ok, Sock} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, true}]),
    agent(Sock, 0).

agent(Sock, Bytes) ->
    receive
        {tcp, Sock, Data} -> agent(Sock, Bytes + byte_size(Data));
        {tcp_closed, Sock} -> agent_closed(Bytes);
        {report, To} -> To ! {shdr_bytes, Bytes}, agent(Sock, Bytes)
    end.

agent_closed(Bytes) ->
    receive {report, To} -> To ! {shdr_bytes, Bytes} end.

write_doc(Minutes, SampleS, Report) ->
    Top = case os:getenv("CELLRT_TOP") of false -> "."; T -> T end,
    {{Y, Mo, D}, _} = calendar:universal_time(),
    Doc = ["# Soak run\n\n",
           io_lib:format("Written by `make soak` (SOAK_MINUTES=~b, a sample every ~b s) on "
                         "~4..0w-~2..0w-~2..0w, ~p schedulers, OTP ~s: the default cell with "
                         "both lanes, a panel always waiting upstream, the physics at 20x "
                         "the machine's speed, faults injected and answered by a simulated "
                         "operator, the panel and SHDR running with an agent reading.\n\n",
                         [Minutes, SampleS, Y, Mo, D, erlang:system_info(schedulers_online),
                          erlang:system_info(otp_release)]),
           "```\n", Report, "```\n"],
    file:write_file(filename:join([Top, "docs", "soak.md"]), Doc).

dir_size(Dir) ->
    filelib:fold_files(Dir, ".*", true, fun(F, Acc) -> Acc + filelib:file_size(F) end, 0).

%% A process as recon names it: registered name, else where it is.
name(Info) ->
    case [N || N <- Info, is_atom(N)] of
        [Name | _] -> atom_to_list(Name);
        [] -> io_lib:format("~0p", [proplists:get_value(current_function, Info)])
    end.

mb(Bytes) -> Bytes / 1048576.

pct(A, B) ->
    P = 100 * (B - A) / max(A, 1),
    io_lib:format("~s~.1f%", [case P >= 0 of true -> "+"; false -> "" end, P]).

env_int(Name, Default) ->
    case os:getenv(Name) of
        false -> Default;
        Text -> list_to_integer(Text)
    end.
