%% The system test of the default cell in the built release: the simulated router runs,
%% the operator starts it and answers its injected errors through the REST API (Retry,
%% Ignore and Reset in turn), stops it; the node is stopped and started again and the
%% line goes on. Through it all no product is lost or counted twice (in = out +
%% scrapped + in the cell, and the simulated machine agrees), the statistics of every
%% task add up to the wall-clock time, and every serial has its history.
%%
%% The suite talks to the release as an operator would (HTTP), and waits on the cell's
%% own events through a small probe it loads into the node over distribution.
-module(router_release_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([run_answer_stop_restart/1, real_mode_vplc_killed/1, make_run_with_vplc/1]).

-define(COOKIE, cellrt_ct_router).
-define(WAIT_MS, 120000).

all() ->
    [run_answer_stop_restart, real_mode_vplc_killed, make_run_with_vplc].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    Bin = cellrt_rel:bin(),
    filelib:is_regular(Bin) orelse ct:fail("no release: build it with `rebar3 release`"),
    [{bin, Bin}, {started_dist, cellrt_rel:start_dist("router_suite")} | Config].

end_per_suite(Config) ->
    cellrt_rel:stop_dist(?config(started_dist, Config)).

run_answer_stop_restart(Config) ->
    %% The priv_dir is shared by every suite of the run: a root of this suite's own.
    Root = filename:join(?config(priv_dir, Config), "router_release_SUITE.root"),
    NodeName = "cellrt_ct_router_" ++ os:getpid(),
    Node = list_to_atom(NodeName ++ "@localhost"),
    Env = [{"CELLRT_ROOT", Root}, {"CELLRT_NODE", NodeName ++ "@localhost"},
           {"CELLRT_COOKIE", atom_to_list(?COOKIE)}, {"CELLRT_WEB_PORT", "0"},
           {"CELLRT_SHDR_PORT", "0"}],
    %% A fast machine that makes mistakes: every third carry slips, a conveyor move
    %% in twenty sticks (for longer than the tasks' watchdog), the magazine runs low.
    ok = router_test_settings:write(Root, #{machine => #{speed_override => 100},
                                           router_sim => #{time_scale => 0.05, arrival_ms => 0,
                                                product_lost_rate => 0.3, reseat_ms => 2000,
                                                jam_rate => 0.05, jam_ms => 80000,
                                                %% Serials checked against the machine's
                                                %% own: no panel taken without its code.
                                                no_read_rate => 0.0,
                                                magazine_low_s => 60, magazine_refill_s => 20},
                                router => #{hal_poll_ms => 10, transfer_timeout_ms => 3000,
                                            motion_timeout_ms => 5000}}),
    Bin = ?config(bin, Config),
    true = erlang:set_cookie(Node, ?COOKIE),
    try
        %% First run: 25 products out, every error answered through the API.
        Op = boot(Bin, Env, Node),
        %% Factory IT sees the cell over MTConnect SHDR from the start.
        Shdr = shdr_snapshot(Node),
        ?assertMatch([<<"* shdrVersion: 2">> | _], Shdr),
        ?assert(lists:any(fun(L) -> binary:match(L, <<"|avail|AVAILABLE">>) =/= nomatch end,
                          Shdr)),
        {200, _, _} = cell_web_client:req(Op, post, "/api/cell/start"),
        Answers1 = run(Op, Node, 25, #{}),
        {200, _, _} = cell_web_client:req(Op, post, "/api/cell/stop"),
        ok = stopped(Op, Node),
        Before = erpc:call(Node, router_release_probe, snapshot, []),
        check_books(Before),
        {0, _} = cellrt(Bin, ["stop"], Env),
        ok = await_down(Node),

        %% Second run, after a restart: the same products are in the cell, the books
        %% are as they were, and the line goes on.
        Op2 = boot(Bin, Env, Node),
        After = erpc:call(Node, router_release_probe, snapshot, []),
        ?assertEqual(maps:get(held, Before), maps:get(held, After)),
        #{total := #{cell := TotalBefore}} = Before,
        #{total := #{cell := TotalAfter}} = After,
        ?assertEqual(maps:with([in, out, scrapped], TotalBefore),
                     maps:with([in, out, scrapped], TotalAfter)),
        {200, InCell, _} = cell_web_client:req(Op2, get, "/api/products"),
        ?assertEqual(maps:get(held, Before), lists:sort([S || #{<<"serial">> := S} <- InCell])),
        {200, _, _} = cell_web_client:req(Op2, post, "/api/cell/start"),
        #{world := #{counters := #{delivered := D0}}} = After,
        Answers2 = run(Op2, Node, D0 + 10, Answers1),
        {200, _, _} = cell_web_client:req(Op2, post, "/api/cell/stop"),
        ok = stopped(Op2, Node),
        End = erpc:call(Node, router_release_probe, snapshot, []),
        check_books(End),

        %% Each answer was given at least once.
        [?assert(maps:get(S, Answers2, 0) >= 1, S) || S <- [retry, ignore, reset]],

        %% Statistics: for every task the states add up to the wall-clock time (the
        %% time the node was down counted as OFF), and the API says the same.
        [?assertEqual({T, Span}, {T, Sum}) || {T, Sum, Span} <- erpc:call(Node, router_release_probe,
                                                                            time_check, [])],
        {200, #{<<"production">> := #{<<"cell">> := ApiCell, <<"tasks">> := ApiTasks}}, _} =
            cell_web_client:req(Op2, get, "/api/statistics?period=total"),
        #{total := #{cell := #{in := In, out := Out, scrapped := Scrapped}}} = End,
        ?assertMatch(#{<<"in">> := In, <<"out">> := Out, <<"scrapped">> := Scrapped}, ApiCell),
        %% The five tasks and the fixture's clamps' unit, each with its time in states.
        ?assertEqual(6, maps:size(ApiTasks)),
        ?assert(maps:is_key(<<"clamps_front">>, ApiTasks), ApiTasks),

        %% Traceability: every serial that entered has its history, and each left at
        %% most once.
        %% (A product that left has its summary on disc; one still in the cell, its
        %% row among the products in the cell.)
        Serials = lists:usort(lists:append([erpc:call(Node, mnesia, dirty_all_keys, [Tab])
                                            || Tab <- [cell_trace_product, cell_trace_open]])),
        ?assertEqual(In, length(Serials)),
        [check_history(Op2, S) || S <- Serials]
    after
        cellrt(Bin, ["stop"], Env)
    end.

%% The default cell as `make run' runs it: in real mode, over Modbus TCP, against a
%% virtual PLC in an OS process of its own. Parts flow; the virtual PLC's process is
%% killed while a product is on its way between two tasks: the cell shows the
%% connection error (REST and SHDR) and holds its products; the virtual PLC is started
%% again on the same port, the operator answers Retry, and the line goes on (the tasks
%% write again the outputs the restarted PLC holds at zero). Then the machine is poked
%% through the virtual PLC's physics (its node named for the suite, `--node', so the
%% suite can call router_sim there) and the cell reacts through its IO over Modbus: the
%% emergency-stop circuit opened stops every task and refuses Start, closed again the
%% line starts again; a door opened is a warning the line runs on with; a drive fault
%% is reset by the monitor; a code reader's no-read is answered Retry. Every serial that
%% entered is in the cell or has left, once,
%% and the statistics of every task add up to the wall-clock time.
real_mode_vplc_killed(Config) ->
    Priv = ?config(priv_dir, Config),
    Root = filename:join(Priv, "router_release_SUITE.real"),
    VRoot = filename:join(Priv, "router_release_SUITE.vplc"),
    NodeName = "cellrt_ct_router_real_" ++ os:getpid(),
    Node = list_to_atom(NodeName ++ "@localhost"),
    Env = [{"CELLRT_ROOT", Root}, {"CELLRT_NODE", NodeName ++ "@localhost"},
           {"CELLRT_COOKIE", atom_to_list(?COOKIE)}, {"CELLRT_WEB_PORT", "0"},
           {"CELLRT_SHDR_PORT", "0"}],
    %% A fast machine without mistakes of its own: the errors are the lost PLC's (the
    %% physics' own slips, jams, no-reads and low magazine off: their defaults are not
    %% zero).
    Sim = #{time_scale => 0.05, arrival_ms => 0, product_lost_rate => 0.0, jam_rate => 0.0,
            no_read_rate => 0.0, magazine_low_s => 0},
    Router = #{hal_poll_ms => 10},
    ok = router_test_settings:write(VRoot, #{router_sim => Sim, router => Router}),
    %% The suite's own clock, for the statistics' span (system time, as theirs).
    Began = erlang:system_time(microsecond),
    {Vplc, Port} = start_vplc(VRoot, 0, vplc_node(1)),
    ok = router_test_settings:write(Root, #{machine => #{simulation_mode => false},
                                            router_sim => Sim,
                                            router => Router#{plc_host => <<"127.0.0.1">>,
                                                              plc_port => Port}}),
    Bin = ?config(bin, Config),
    true = erlang:set_cookie(Node, ?COOKIE),
    try
        Op = boot(Bin, Env, Node),
        %% The cell node knows the virtual PLC's cookie too: the suite's node is
        %% connected to both, and global keeps the three fully connected.
        Cookie = erlang:get_cookie(vplc_node(1)),
        [true = erpc:call(Node, erlang, set_cookie, [vplc_node(N), Cookie]) || N <- [1, 2]],
        {200, _, _} = cell_web_client:req(Op, post, "/api/cell/start"),
        Answers = run(Op, Node, await_left, 3, #{}),
        %% Every task has been seen by the statistics by now: products passed them all.
        Flowing = erlang:system_time(microsecond),
        %% The PLC goes while a product is between two tasks.
        {committed, Link, Serial} =
            erpc:call(Node, router_release_probe, await_committed, [?WAIT_MS], ?WAIT_MS + 5000),
        %% Factory IT's view: an agent connected before the PLC goes.
        Shdr = shdr_connect(Node),
        ct:log("virtual PLC killed while ~s passes ~s", [Serial, Link]),
        kill_vplc(Vplc),
        {alarm, #{id := Id, kind := error}} =
            erpc:call(Node, router_release_probe, await_alarm, [<<"IO connection lost">>, ?WAIT_MS],
                      ?WAIT_MS + 5000),
        {200, Alarms, _} = cell_web_client:req(Op, get, "/api/alarms"),
        ct:log("alarms: ~p", [Alarms]),
        ?assert(lists:any(fun(#{<<"caption">> := C}) -> C =:= <<"IO connection lost">>;
                             (_) -> false
                          end, Alarms), Alarms),
        %% The same error as a FAULT condition over SHDR.
        FaultLine = shdr_await(Shdr, [<<"|FAULT|">>, <<"IO connection lost">>],
                               erlang:monotonic_time(millisecond) + ?WAIT_MS),
        ct:log("SHDR: ~s", [FaultLine]),
        ok = gen_tcp:close(Shdr),
        %% The cell holds its products: each serial still in one task.
        #{held := Held} = erpc:call(Node, router_release_probe, books, []),
        ?assertNotEqual([], Held),
        ?assertEqual(lists:usort(Held), lists:sort(Held)),
        ct:log("held while the PLC is away: ~s (error ~s)", [lists:join(" ", Held), Id]),
        %% The virtual PLC back on the same port; the connection comes up again.
        {Vplc2, Port} = start_vplc(VRoot, Port, vplc_node(2)),
        try
            ok = erpc:call(Node, cell_testkit, await_connection, [router_plc, ?WAIT_MS],
                           ?WAIT_MS + 5000),
            %% The monitor withdraws its error of the lost PLC once it is back: not
            %% one for the operator to answer then.
            ok = erpc:call(Node, router_release_probe, await_gone,
                           [<<"cell:connection.router_plc">>, ?WAIT_MS], ?WAIT_MS + 5000),
            #{total := #{cell := #{out := Out0}}} =
                erpc:call(Node, router_release_probe, books, []),
            %% The operator's Retry to each error; the line goes on.
            Answers2 = run(Op, Node, await_left, Out0 + 3, Answers),
            ?assert(maps:get(retry, Answers2, 0) >= 1),
            %% Retry was enough: every error answered was the lost connection's (a
            %% task's lost IO, the monitor's lost PLC), none a transfer or a move that
            %% timed out because an output the restarted PLC held at zero was not
            %% written again.
            {200, History, _} = cell_web_client:req(Op, get, "/api/alarms/history"),
            ct:log("answers:~n~ts", [[[I, " ", W, "\n"] || #{<<"id">> := I, <<"what">> := W} <- History]]),
            [?assert(binary:longest_common_suffix([I, <<":io">>]) =:= 3 orelse
                         binary:match(I, <<"connection.router_plc">>) =/= nomatch, I)
             || #{<<"id">> := I, <<"what">> := W} <- History,
                lists:member(W, [<<"retry">>, <<"ignore">>, <<"reset">>])],
            %% The machine poked through the virtual PLC's physics.
            Answers3 = machine_events(Op, Node, vplc_node(2), Answers2),
            {200, _, _} = cell_web_client:req(Op, post, "/api/cell/stop"),
            ok = stopped(Op, Node),
            ct:log("answers given: ~p", [Answers3]),
            #{total := #{cell := #{in := In, out := Out, scrapped := Scrapped},
                         in_cell := InCell},
              held := HeldEnd} = erpc:call(Node, router_release_probe, books, []),
            ?assertEqual(In, Out + Scrapped + InCell),
            ?assertEqual(InCell, length(HeldEnd)),
            Serials = lists:usort(lists:append(
                                    [erpc:call(Node, mnesia, dirty_all_keys, [Tab])
                                     || Tab <- [cell_trace_product, cell_trace_open]])),
            ?assertEqual(In, length(Serials)),
            [check_history(Op, S) || S <- Serials],
            check_time(Node, Began, Flowing)
        after
            cellrt(Bin, ["stop"], Env),
            kill_vplc(Vplc2)
        end
    after
        cellrt(Bin, ["stop"], Env),
        kill_vplc(Vplc)
    end.

shdr_connect(Node) ->
    Port = erpc:call(Node, cell_shdr, port, []),
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}, {packet, line}]),
    S.

%% Reads an SHDR connection's lines until one holds every one of `Parts'.
shdr_await(S, Parts, Deadline) ->
    case gen_tcp:recv(S, 0, max(0, Deadline - erlang:monotonic_time(millisecond))) of
        {ok, Line} ->
            case lists:all(fun(P) -> binary:match(Line, P) =/= nomatch end, Parts) of
                true -> string:trim(Line, trailing, "\r\n");
                false -> shdr_await(S, Parts, Deadline)
            end;
        {error, Why} ->
            ct:fail({no_shdr_line, Parts, Why})
    end.

%% Starts scripts/vplc for the router on `Port' (0: one the OS picks), root `Root',
%% its node named `VNode' (for the suite's pokes); returns once it listens: its port
%% (of the OS process) and the port it listens on.
start_vplc(Root, Port, VNode) ->
    Script = filename:join([cellrt_rel:top(), "scripts", "vplc"]),
    P = open_port({spawn_executable, Script},
                  [{args, ["--port", integer_to_list(Port), "--root", Root,
                           "--node", atom_to_list(VNode)]},
                   {line, 4096}, exit_status, stderr_to_stdout, binary]),
    Listening = cell_vplc_os:await_listening(P, erlang:monotonic_time(millisecond) + ?WAIT_MS),
    %% Its cookie, made at its first start, in its root (as the cell under make run
    %% reads it).
    {ok, Cookie} = file:read_file(filename:join([Root, "Distribution", "cookie"])),
    true = erlang:set_cookie(VNode, binary_to_atom(string:trim(Cookie))),
    {P, Listening}.

%% The virtual PLC's node: a name of its own for each start, so a restart never waits
%% for the name of the one killed to be free.
vplc_node(N) ->
    list_to_atom("cellrt_ct_vplc_" ++ os:getpid() ++ "_" ++ integer_to_list(N) ++ "@localhost").

%% The emergency-stop circuit opened and closed, a door opened and closed, a drive
%% faulted and reset by the monitor, a code reader's no-read: each poked in the virtual PLC's physics
%% (router_sim in `VNode') and seen by the cell through its IO over Modbus TCP, as the
%% machine's own would be. Every error meanwhile is answered as in run/5.
machine_events(Op, Node, VNode, Answers0) ->
    ok = erpc:call(Node, router_release_probe, forward, [[estop, alarm_raised, alarm_cleared],
                                                         self()]),
    Poke = fun(F, A) -> ok = erpc:call(VNode, router_sim, F, A) end,
    %% The circuit opens: every task OFF at once, Start refused.
    Poke(press_estop, []),
    _ = await_probe(fun(#{type := estop, active := true}) -> true; (_) -> false end),
    %% The event follows the barrier; sync waits until every task has announced OFF.
    ok = erpc:call(Node, cell_controller, sync, []),
    ?assertEqual([], [T || #{id := T, state := St} <- erpc:call(Node, cell_controller, tasks, []),
                           St =/= off]),
    {409, _, _} = cell_web_client:req(Op, post, "/api/cell/start"),
    %% Closed again: the emergency stop released, the drives ready, Start.
    Poke(release_estop, []),
    _ = await_probe(fun(#{type := estop, active := false}) -> true; (_) -> false end),
    ok = erpc:call(Node, router_release_probe, await_point, [drives_io, lower_ready, true,
                                                             ?WAIT_MS], ?WAIT_MS + 5000),
    {200, _, _} = cell_web_client:req(Op, post, "/api/cell/start"),
    Answers1 = run(Op, Node, await_left, out(Node) + 2, Answers0),
    %% A door opened: a warning; the line runs on with it.
    Poke(open_door, [unloading]),
    _ = await_probe(alarm(alarm_raised, warning, <<"cell:door">>)),
    Answers2 = run(Op, Node, await_left, out(Node) + 1, Answers1),
    ?assert(lists:any(fun(#{id := I}) -> I =:= <<"cell:door">> end,
                      erpc:call(Node, cell_alarms, list, []))),
    Poke(close_door, [unloading]),
    _ = await_probe(alarm(alarm_cleared, warning, <<"cell:door">>)),
    %% A drive faults: a warning while the monitor resets it, gone once it is reset.
    Poke(fault_drive, [conveyor_front]),
    _ = await_probe(alarm(alarm_raised, warning, <<"cell:drive.conveyor_front">>)),
    _ = await_probe(alarm(alarm_cleared, warning, <<"cell:drive.conveyor_front">>)),
    Answers3 = run(Op, Node, await_left, out(Node) + 1, Answers2),
    %% The code reader finds no code on the next panel: the operator's question, whose
    %% Retry reads the panel again (its serial the one the machine has).
    Poke(no_read_next, [front]),
    #{alarm := #{id := NoCode}} =
        await_probe(alarm(alarm_raised, error, <<"loading_front:no_code">>)),
    Path = "/api/alarms/" ++ uri_string:quote(binary_to_list(NoCode)) ++ "/answer",
    {200, _, _} = cell_web_client:req(Op, post, Path, #{solution => retry}),
    _ = await_probe(alarm(alarm_cleared, error, <<"loading_front:no_code">>)),
    run(Op, Node, await_left, out(Node) + 2,
        maps:update_with(retry, fun(X) -> X + 1 end, 1, Answers3)).

alarm(Type, Kind, Id) ->
    fun(#{type := T, alarm := #{id := I, kind := K}}) -> {T, K, I} =:= {Type, Kind, Id};
       (_) -> false
    end.

%% The first event the probe forwarded that `Match' takes, within ?WAIT_MS.
await_probe(Match) ->
    await_probe(Match, erlang:monotonic_time(millisecond) + ?WAIT_MS).

await_probe(Match, Deadline) ->
    receive
        {probe_event, E} ->
            case Match(E) of
                true -> E;
                false -> await_probe(Match, Deadline)
            end
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail(no_event)
    end.

%% The products out by the cell's books.
out(Node) ->
    #{total := #{cell := #{out := Out}}} = erpc:call(Node, router_release_probe, books, []),
    Out.

%% The statistics add up to the wall-clock time: for every task the time counted in
%% its states is the time from when it was first seen to the statistics' last write
%% (exactly), and that span lies within the suite's own clock: at most the time since
%% before the node started (`Began'), at least the time from when products had passed
%% every task (`Flowing', by then each task seen) to the write this check asks for.
%% The tolerance is thus what the clock cannot tell apart: the node's boot and the
%% first products (logged).
check_time(Node, Began, Flowing) ->
    Asked = erlang:system_time(microsecond),
    Checks = erpc:call(Node, router_release_probe, time_check, []),
    Now = erlang:system_time(microsecond),
    ct:log("statistics span per task (s): ~p; the suite's clock: ~.1f s since the node's "
           "start, ~.1f s since products flowed",
           [[{T, Span / 1.0e6} || {T, _, Span} <- Checks], (Now - Began) / 1.0e6,
            (Asked - Flowing) / 1.0e6]),
    %% The five tasks and the fixture's clamps' unit.
    ?assertEqual(6, length(Checks)),
    [begin
         ?assertEqual({T, Span}, {T, Sum}),
         ?assert(Span =< Now - Began, {T, Span, Now - Began}),
         ?assert(Span >= Asked - Flowing, {T, Span, Asked - Flowing})
     end || {T, Sum, Span} <- Checks].

%% Kills the virtual PLC's OS process outright, and waits for its end.
kill_vplc(P) ->
    cell_vplc_os:kill(P, ?WAIT_MS).

%% `make run' (scripts/run) as a user starts it: a virtual PLC, then the cell in real
%% mode connected to it over Modbus TCP; the operator's hand on the machine (the
%% emergency stop pressed and released) reaches the virtual PLC's node; told to stop, the script stops the cell, then
%% the virtual PLC: neither is left running.
make_run_with_vplc(Config) ->
    Root = filename:join(?config(priv_dir, Config), "router_release_SUITE.run"),
    NodeName = "cellrt_ct_router_run_" ++ os:getpid(),
    Node = list_to_atom(NodeName ++ "@localhost"),
    Env = [{"CELLRT_ROOT", Root}, {"CELLRT_NODE", NodeName ++ "@localhost"},
           {"CELLRT_COOKIE", atom_to_list(?COOKIE)}, {"CELLRT_WEB_PORT", "0"},
           {"CELLRT_SHDR_PORT", "0"}, {"CELLRT_VPLC_PORT", "0"}, {"CELLRT_SIM", false}],
    true = erlang:set_cookie(Node, ?COOKIE),
    Script = filename:join([cellrt_rel:top(), "scripts", "run"]),
    Run = open_port({spawn_executable, Script},
                    [{env, Env}, {line, 4096}, exit_status, stderr_to_stdout, binary]),
    try
        Port = await_line(Run, <<"cellrt: the cell in real mode over Modbus TCP, its PLC the "
                                 "virtual PLC at 127.0.0.1 port ">>,
                          erlang:monotonic_time(millisecond) + ?WAIT_MS),
        %% The node's own line once its panel listens: it is up.
        _ = await_line(Run, <<"operator panel on http">>,
                       erlang:monotonic_time(millisecond) + ?WAIT_MS),
        ok = cellrt_rel:await_boot(Node, ?WAIT_MS),
        ?assertMatch(#{simulation_mode := false},
                     erpc:call(Node, cell_spec_helpers, machine_settings, [])),
        ok = erpc:call(Node, cell_testkit, await_connection, [router_plc, ?WAIT_MS],
                       ?WAIT_MS + 5000),
        {ok, #{endpoint := Endpoint}} = erpc:call(Node, cell_hal, info, [router_plc]),
        ct:log("the cell's PLC: ~ts", [Endpoint]),
        %% The operator's hand reaches the machine in the virtual PLC's process: the
        %% emergency stop pressed there comes back over Modbus TCP as the cell's own.
        {Mod, Beam, File} = code:get_object_code(router_release_probe),
        {module, Mod} = erpc:call(Node, code, load_binary, [Mod, File, Beam]),
        ?assertMatch({ok, {vplc, _, _}, [_ | _]},
                     erpc:call(Node, cell_machine_actions, list, [])),
        ?assertEqual({estop, true}, erpc:call(Node, router_release_probe, estop_by_hand,
                                              [<<"press">>, ?WAIT_MS], ?WAIT_MS + 5000)),
        ?assertEqual({estop, false}, erpc:call(Node, router_release_probe, estop_by_hand,
                                               [<<"release">>, ?WAIT_MS], ?WAIT_MS + 5000)),
        {os_pid, Pid} = erlang:port_info(Run, os_pid),
        _ = os:cmd("kill -TERM " ++ integer_to_list(Pid)),
        ?assertEqual(0, await_exit_status(Run)),
        ok = await_down(Node),
        ?assertEqual({error, econnrefused},
                     gen_tcp:connect({127, 0, 0, 1}, binary_to_integer(Port), []))
    after
        %% A case that failed midway stops the script, which stops what it started.
        case erlang:port_info(Run, os_pid) of
            {os_pid, Left} ->
                _ = os:cmd("kill -TERM " ++ integer_to_list(Left)),
                _ = await_exit_status(Run);
            undefined ->
                ok
        end
    end.

%% What follows `Part' in the first line of the port `P' that holds it.
await_line(P, Part, Deadline) ->
    receive
        {P, {data, {_, Line}}} ->
            ct:log("run: ~ts", [Line]),
            case binary:split(Line, Part) of
                [_, Rest] -> Rest;
                [_] -> await_line(P, Part, Deadline)
            end;
        {P, {exit_status, S}} ->
            ct:fail({run_exited, S})
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail({no_line, Part})
    end.

await_exit_status(P) ->
    receive
        {P, {exit_status, S}} -> S;
        {P, {data, {_, Line}}} -> ct:log("run: ~ts", [Line]), await_exit_status(P)
    after ?WAIT_MS ->
        ct:fail(run_not_stopped)
    end.

%% The lines an MTConnect agent receives when it connects, up to the answer to a PING.
shdr_snapshot(Node) ->
    S = shdr_connect(Node),
    ok = gen_tcp:send(S, <<"* PING\n">>),
    Lines = shdr_lines(S, []),
    ok = gen_tcp:close(S),
    Lines.

shdr_lines(S, Acc) ->
    {ok, Line} = gen_tcp:recv(S, 0, 10000),
    case string:trim(Line, trailing, "\r\n") of
        <<"* PONG", _/binary>> -> lists:reverse(Acc);
        L -> shdr_lines(S, [L | Acc])
    end.

%% The books balance, and agree with the simulated machine.
check_books(#{world := #{counters := #{delivered := Delivered, scrapped := PhysScrapped}},
              total := #{cell := #{in := In, out := Out, good := Good, failed := Failed,
                                   scrapped := Scrapped}, in_cell := InCell},
              held := Held}) ->
    ?assertEqual(In, Out + Scrapped + InCell),
    ?assertEqual(InCell, length(Held)),
    ?assertEqual(Delivered, Out),
    ?assertEqual(PhysScrapped, Scrapped),
    ?assertEqual(Out, Good + Failed).

check_history(Op, Serial) ->
    {200, #{<<"status">> := Status, <<"events">> := Events}, _} =
        cell_web_client:req(Op, get, "/api/products/" ++ binary_to_list(Serial) ++ "/history"),
    Kinds = [K || #{<<"event">> := K} <- Events],
    ?assertEqual(<<"entered">>, hd(Kinds)),
    Left = length([K || K <- Kinds, K =:= <<"left">>]),
    case Status of
        <<"out">> -> ?assertEqual(1, Left);
        <<"scrapped">> -> ?assertEqual(0, Left),
                          ?assert(lists:member(<<"scrapped">>, Kinds));
        <<"in_cell">> -> ?assertEqual(0, Left)
    end.

%% Runs the line until `Target' products were delivered, answering every error
%% through the API: Retry, Ignore, Reset in turn where offered, else the first offered.
run(Op, Node, Target, Answers) ->
    run(Op, Node, await, Target, Answers).

%% As run/4, with the probe's wait `Await' (await: the in-VM machine's count of
%% delivered products; await_left: the cell's own count of products out).
run(Op, Node, Await, Target, Answers) ->
    case erpc:call(Node, router_release_probe, Await, [Target, ?WAIT_MS], ?WAIT_MS + 5000) of
        {out, _} ->
            Answers;
        timeout ->
            ct:fail({stuck, erpc:call(Node, cell_controller, tasks, [])});
        {error, #{id := Id, solutions := Solutions}} ->
            %% The answer given least so far among those offered (in this order on a
            %% tie): which errors come, and which answers each offers, is the
            %% machine's chance; every answer is given as soon as an error offers it.
            Offered = [S || S <- [retry, ignore, reset], lists:member(S, Solutions)],
            Solution = case Offered of
                           [] -> hd(Solutions);
                           _ -> hd(lists:sort(fun(A, B) -> maps:get(A, Answers, 0) =<
                                                               maps:get(B, Answers, 0)
                                              end, Offered))
                       end,
            Path = "/api/alarms/" ++ uri_string:quote(binary_to_list(Id)) ++ "/answer",
            {200, _, _} = cell_web_client:req(Op, post, Path, #{solution => Solution}),
            run(Op, Node, Await, Target,
                maps:update_with(Solution, fun(X) -> X + 1 end, 1, Answers))
    end.

%% Waits for OFF after a Stop, answering Retry to an error a move that was finishing
%% raised meanwhile, as the operator would.
stopped(Op, Node) ->
    case erpc:call(Node, router_release_probe, await_state_or_error, [off, ?WAIT_MS],
                   ?WAIT_MS + 5000) of
        ok ->
            ok;
        timeout ->
            ct:fail({not_off, erpc:call(Node, cell_controller, tasks, [])});
        {error, #{id := Id, solutions := Solutions}} ->
            Solution = case lists:member(retry, Solutions) of
                           true -> retry;
                           false -> hd(Solutions)
                       end,
            Path = "/api/alarms/" ++ uri_string:quote(binary_to_list(Id)) ++ "/answer",
            {200, _, _} = cell_web_client:req(Op, post, Path, #{solution => Solution}),
            stopped(Op, Node)
    end.

%% Starts the release, loads the probe into it, logs in as the operator.
boot(Bin, Env, Node) ->
    {0, _} = cellrt(Bin, ["daemon"], Env),
    ok = await_pong(Node, 200),
    {Mod, Beam, File} = code:get_object_code(router_release_probe),
    {module, Mod} = erpc:call(Node, code, load_binary, [Mod, File, Beam]),
    %% The node answers ping while its boot still starts the applications.
    ok = cellrt_rel:await_boot(Node, ?WAIT_MS),
    Port = erpc:call(Node, cell_web, port, []),
    {ok, Op} = cell_web_client:login(cell_web_client:new(Port), "operator", "operator"),
    Op.

%% A ping waits for its answer: each try is a round trip, not a sleep.
await_pong(_Node, 0) ->
    {error, not_up};
await_pong(Node, N) ->
    case net_adm:ping(Node) of
        pong -> ok;
        pang -> await_pong(Node, N - 1)
    end.

await_down(Node) ->
    case net_adm:ping(Node) of
        pang ->
            ok;
        pong ->
            true = monitor_node(Node, true),
            receive {nodedown, Node} -> ok
            after ?WAIT_MS -> {error, still_up}
            end
    end.

cellrt(Bin, Args, Env) ->
    cellrt_rel:run(Bin, Args, Env, 60000).
