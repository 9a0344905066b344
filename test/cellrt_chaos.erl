%% @doc The chaos test of the default cell (`make chaos', and its bounded form in
%% chaos_SUITE): the built release runs the simulated router, both lanes, its physics
%% twenty times faster than the real machine, panels arriving often, faults on. While
%% it produces, the node is killed with SIGKILL at random moments and started again on
%% the same root folder (Start pressed again, as the operator would), and single
%% processes inside it are killed (tasks, handshake links, HAL workers, the statistics
%% and their writer, the physics, the web feed, the events, other services). An
%% operator inside the node answers every error as an operator at the machine would:
%% where the right answer depends on where the product physically is ("Product
%% transfer interrupted", a restart after a crash, the router's reconcile questions,
%% "Product lost"), it looks at the simulated machine (router_sim's world) and picks
%% among the answers true for it; for the others (a jam, say) it chooses among those
%% offered. Either way by a seeded random per kind of error (another true one where the
%% runtime refuses one). A panel the fixture holds that no record knows of it takes out
%% of the machine by hand (router_sim:take_out/2) before it answers Retry.
%%
%% At the end no new panel arrives, the line drains, the cell is stopped, and every
%% serial is reconciled against the simulated machine's own record of where each
%% panel physically is (router_sim's world and its ledger of what it delivered, what
%% fell into the scrap bin and what the operator's hand took out, saved before the
%% sensors show a move) with the cell's
%% record (cell_stats' histories and summaries, the tasks' products):
%%
%% <ul>
%% <li>lost: physically delivered, in the machine or in the scrap bin but not recorded
%%   so by the cell (unknown, still in the cell, held by no task, or left when it is
%%   in the bin or taken out by hand), or gone from the machine without a trace;</li>
%% <li>duplicated: left the machine twice, in two places at once, or recorded as
%%   leaving the cell twice (or both leaving and scrapped, or in the cell and out);</li>
%% <li>double-held: held by two tasks at once for two seconds or more, or after the
%%   cell stopped;</li>
%% <li>wedged: the cell Started, panels in it or waiting, and no product moved for
%%   60 s while no error was raised;</li>
%% <li>left but recorded scrapped: the next machine has it, the cell says scrapped;</li>
%% <li>books: the statistics' totals (in, out, scrapped, in the cell) against the
%%   machine's ledger (panels that entered it, delivered, in the scrap bin or taken out
%%   by hand, still in it), every panel of difference counted.</li>
%% </ul>
%%
%% The harness waits on conditions with deadlines: the node's exit (its start script
%% runs in the foreground under a port), the node answering ping, the cell's events
%% forwarded by the operator process it loads into the node. The random pauses
%% between kills are the chaos itself, never a wait for something to happen.
-module(cellrt_chaos).

-export([main/1, run/1, default_opts/0, reconcile/1, books/2]).
%% Run inside the cell's node.
-export([agent_start/4, targets/0, view/0, held/0, machine/0]).

-define(BOOT_MS, 180000).
-define(DOWN_MS, 60000).
-define(DRAIN_MS, 600000).
-define(WEDGE_MS, 60000).
-define(DOUBLE_MS, 2000).
-define(WHO, <<"chaos operator">>).
%% The alarm of a cell that stopped by itself after an internal fault.
-define(STOPPED, <<"cell:stopped">>).
-define(PROC_LOG_EVERY, 10).
-define(PROGRESS, [item_identifier_read, item_transfer_in, item_transfer_out,
                   item_work_start, item_work_complete, item_work_abort, product_saved]).

%%====================================================================
%% make chaos
%%====================================================================

%% @doc `erl -run cellrt_chaos main': the size and the seed from CHAOS_NODE_KILLS
%% (200), CHAOS_PROC_KILLS (1000), CHAOS_SEED (the time); halts with 0 when every
%% column is 0.
-spec main([string()]) -> no_return().
main(_Args) ->
    Opts = default_opts(),
    Result = try run(Opts)
             catch C:R:St ->
                     io:format("chaos: the run broke off: ~p:~p~n~p~n", [C, R, St]),
                     erlang:halt(2)
             end,
    erlang:halt(case Result of #{clean := true} -> 0; _ -> 1 end).

%% @doc The options of `make chaos', from the environment.
-spec default_opts() -> map().
default_opts() ->
    Top = cellrt_rel:top(),
    Out = filename:join([Top, "_build", "chaos"]),
    Seed = env_int("CHAOS_SEED", erlang:system_time(millisecond) rem 1000000),
    #{node_kills => env_int("CHAOS_NODE_KILLS", 200),
      proc_kills => env_int("CHAOS_PROC_KILLS", 1000),
      seed => Seed,
      root => env_str("CHAOS_ROOT", filename:join(Out, "root")),
      node => env_str("CHAOS_NODE", "cellrt_chaos_" ++ os:getpid()),
      web_port => env_str("CHAOS_WEB_PORT", "0"),
      shdr_port => env_str("CHAOS_SHDR_PORT", "0"),
      out => Out,
      wedge_ms => env_int("CHAOS_WEDGE_S", ?WEDGE_MS div 1000) * 1000,
      doc => filename:join([Top, "docs", "chaos.md"]),
      command => io_lib:format("CHAOS_NODE_KILLS=~b CHAOS_PROC_KILLS=~b CHAOS_SEED=~b make chaos",
                               [env_int("CHAOS_NODE_KILLS", 200),
                                env_int("CHAOS_PROC_KILLS", 1000), Seed]),
      log => fun(Fmt, Args) -> io:format("chaos: " ++ Fmt ++ "~n", Args) end}.

%%====================================================================
%% The run
%%====================================================================

%% @doc Runs the chaos test with these options (see default_opts/0; the caller's node
%% is distributed); returns the counts, the serials at fault, and `clean' when every
%% column is 0. Writes the report to `out'/chaos.md, and to `doc' at full size (200
%% node kills and 1000 process kills or more).
-spec run(map()) -> map().
run(#{node_kills := NK, proc_kills := PK, seed := Seed, root := Root} = Opts) ->
    T0 = erlang:monotonic_time(millisecond),
    Node = list_to_atom(maps:get(node, Opts) ++ "@localhost"),
    Cookie = list_to_atom("cellrt_chaos_" ++ integer_to_list(Seed)),
    true = erlang:set_cookie(Node, Cookie),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    ok = write_settings(Root),
    H0 = #{opts => Opts, node => Node, cookie => Cookie, port => undefined,
           rand => rand:seed_s(exsss, {Seed, 23, 5}), boots => 0,
           node_kills => 0, deaths => 0, proc_kills => 0, by_kind => #{},
           answers => #{}, refused => 0, candidates => #{}, double => #{},
           wedged => [], stalled => [], agent => undefined, drained => false,
           restarts => 0, silent_stops => []},
    log(H0, "seed ~b: ~b node kills, ~b process kills; root ~ts; node ~s",
        [Seed, NK, PK, Root, Node]),
    Shares = shares(PK, NK + 1),
    H2 = try
             finish(lists:foldl(fun({I, Share}, H) -> cycle(I, Share, H) end, H0,
                                lists:zip(lists:seq(1, NK + 1), Shares)))
         catch
             C:R:St ->
                 %% A node left running would hold the root folder and the ports.
                 _ = case catch erpc:call(Node, os, getpid, [], 10000) of
                         OsPid when is_list(OsPid) -> os:cmd("kill -9 " ++ OsPid);
                         _ -> ok
                     end,
                 erlang:raise(C, R, St)
         end,
    Secs = (erlang:monotonic_time(millisecond) - T0) div 1000,
    Result = report(H2, Secs),
    Result.

%% The process kills spread over the node's lives.
shares(PK, Lives) ->
    [PK div Lives + case I =< PK rem Lives of true -> 1; false -> 0 end
     || I <- lists:seq(1, Lives)].

%% One life of the node: booted, Start pressed, its process kills at random moments,
%% then (but for the last life) a SIGKILL at a random moment.
cycle(I, Share, #{opts := #{node_kills := NK}} = H) ->
    Last = I =:= NK + 1,
    try
        %% Each life shows the line moving before it is hurt, and again before the
        %% node is killed: a life that wedged the line is seen.
        H1 = await_progress(up(H)),
        H2 = proc_kills(Share, H1),
        case Last of
            true ->
                H2;
            false ->
                %% (A life the line stood still in is not waited for twice.)
                {Ms, H3} = uniform(3000, case maps:get(life_quiet, H2, false) of
                                             true -> H2;
                                             false -> await_progress(H2)
                                         end),
                H4 = pause(Ms, H3),
                sigkill(H4)
        end
    catch
        throw:{node_down, Status, HD} ->
            HD1 = HD#{deaths := maps:get(deaths, HD) + 1, port := undefined,
                      agent := undefined},
            log(HD1, "life ~b: the node died by itself (exit status ~p); started again "
                "as a supervisor would", [I, Status]),
            case Last of
                true -> cycle(I, 0, HD1);
                false -> HD1
            end
    end.

%% Boots the node if it is not up, loads the operator, presses Start.
up(#{port := undefined, node := Node, opts := Opts, boots := B} = H) ->
    Env = [{"CELLRT_ROOT", maps:get(root, Opts)},
           {"CELLRT_NODE", atom_to_list(Node)},
           {"CELLRT_COOKIE", atom_to_list(maps:get(cookie, H))},
           {"CELLRT_WEB_PORT", maps:get(web_port, Opts)},
           {"CELLRT_SHDR_PORT", maps:get(shdr_port, Opts)}],
    T0 = erlang:monotonic_time(millisecond),
    Port = open_port({spawn_executable, cellrt_rel:bin()},
                     [{args, ["foreground"]}, {env, Env}, exit_status, stderr_to_stdout,
                      binary]),
    H1 = H#{port := Port, boots := B + 1},
    ok = await_pong(Node, T0 + ?BOOT_MS, H1),
    true = monitor_node(Node, true),
    {Mod, Beam, File} = code:get_object_code(?MODULE),
    {module, Mod} = call(H1, code, load_binary, [Mod, File, Beam]),
    ok = cellrt_rel:await_boot(Node, ?BOOT_MS),
    ok = call(H1, router_sim, ready, [60000]),
    OsPid = call(H1, os, getpid, []),
    #{seed := Seed, wedge_ms := WedgeMs} = Opts,
    {ok, Agent} = call(H1, ?MODULE, agent_start, [self(), Seed, B + 1, WedgeMs]),
    _ = erlang:monitor(process, Agent),
    Started = call(H1, cell_controller, start, [?WHO]),
    log(H1, "node up (boot ~b, OS pid ~s) in ~.1f s; Start: ~p",
        [B + 1, OsPid, (erlang:monotonic_time(millisecond) - T0) / 1000, Started]),
    H1#{ospid => OsPid, agent := Agent, life_quiet => false};
up(H) ->
    H.

%% A ping waits for its answer; between two that were refused the harness waits for
%% the node's console output, or a moment.
await_pong(Node, Deadline, #{port := Port} = H) ->
    case net_adm:ping(Node) of
        pong ->
            ok;
        pang ->
            Left = Deadline - erlang:monotonic_time(millisecond),
            Left > 0 orelse error({node_not_up, Node}),
            receive
                {Port, {data, _}} -> await_pong(Node, Deadline, H);
                {Port, {exit_status, S}} -> throw({node_down, S, H#{port := undefined}})
            after min(Left, 200) ->
                await_pong(Node, Deadline, H)
            end
    end.

%% SIGKILL of the node's VM, waited for until its exit is seen.
sigkill(#{ospid := OsPid, port := Port, node := Node, node_kills := K} = H) ->
    Held = held_safe(H),
    H1 = check_double(H),
    _ = os:cmd("kill -9 " ++ OsPid),
    Status = receive
                 {Port, {exit_status, S}} -> S
             after ?DOWN_MS ->
                 error({node_did_not_die, OsPid})
             end,
    receive {nodedown, Node} -> ok after ?DOWN_MS -> error({no_nodedown, Node}) end,
    H2 = drop_agent_messages(H1),
    log(H2, "node kill ~b (exit ~p), products held then: ~ts",
        [K + 1, Status, serials_text([S || {S, _} <- Held])]),
    H2#{node_kills := K + 1, port := undefined, agent := undefined}.

%% Messages of a node gone.
drop_agent_messages(#{port := Port} = H) ->
    receive
        {Port, _} -> drop_agent_messages(H);
        {'DOWN', _, process, _, _} -> drop_agent_messages(H);
        {nodedown, _} -> drop_agent_messages(H)
    after 0 ->
        H
    end.

%% Process kills at random moments.
proc_kills(0, H) ->
    H;
proc_kills(N, H) ->
    {Ms, H1} = uniform(1500, H),
    H2 = pause(Ms, H1),
    H3 = check_double(proc_kill(H2)),
    proc_kills(N - 1, H3).

proc_kill(#{proc_kills := K, by_kind := By} = H) ->
    Targets = call(H, ?MODULE, targets, []),
    Kinds = lists:usort([Kind || {Kind, _, _} <- Targets]),
    {KI, H1} = uniform(length(Kinds), H),
    Kind = lists:nth(KI, Kinds),
    Of = [T || {K1, _, _} = T <- Targets, K1 =:= Kind],
    {PI, H2} = uniform(length(Of), H1),
    {Kind, Pid, Name} = lists:nth(PI, Of),
    true = call(H2, erlang, exit, [Pid, kill]),
    K1 = K + 1,
    H3 = H2#{proc_kills := K1, by_kind := By#{Kind => maps:get(Kind, By, 0) + 1}},
    case K1 rem ?PROC_LOG_EVERY of
        0 -> log(H3, "process kill ~b: ~s ~ts (~ts)",
                 [K1, Kind, Name, kinds_text(maps:get(by_kind, H3))]);
        _ -> ok
    end,
    H3.

%% A serial two tasks hold: a candidate when first seen, double-held when still held
%% by both ?DOUBLE_MS later (a handover holds both for far less).
check_double(H) ->
    case held_safe(H) of
        unavailable -> H;
        Held -> check_double(Held, H)
    end.

check_double(Held, #{candidates := C, double := D} = H) ->
    Now = erlang:monotonic_time(millisecond),
    Twice = maps:from_list(
              [{S, lists:usort([T || {S1, T} <- Held, S1 =:= S])}
               || S <- lists:usort([S || {S, _} <- Held]),
                  length([x || {S1, _} <- Held, S1 =:= S]) > 1]),
    C1 = maps:map(fun(S, Tasks) ->
                          case maps:get(S, C, undefined) of
                              {Tasks, Since} -> {Tasks, Since};
                              _ -> {Tasks, Now}
                          end
                  end, Twice),
    Confirmed = [{S, Tasks} || {S, {Tasks, Since}} <- maps:to_list(C1), Now - Since >= ?DOUBLE_MS],
    [log(H, "~ts held by ~ts", [S, lists:join(" and ", [atom_to_list(T) || T <- Tasks])])
     || {S, Tasks} <- Confirmed, not maps:is_key(S, D)],
    H#{candidates := C1, double := maps:merge(D, maps:from_list(Confirmed))}.

%% What the tasks hold, or `unavailable' while the controller's tree starts anew (its
%% registry's tables are made again): that sample is skipped.
held_safe(H) ->
    try call(H, ?MODULE, held, [])
    catch
        throw:{node_down, _, _} = Down -> throw(Down);
        error:{exception, badarg, [{ets, _, _, _} | _]} -> unavailable
    end.

%% Waits for a product to move, or the operator in the node to say none moved for
%% the window.
await_progress(#{opts := #{wedge_ms := WedgeMs}} = H) ->
    %% The operator reports at the end of a window; the window may have begun just
    %% before this wait.
    Deadline = erlang:monotonic_time(millisecond) + 2 * WedgeMs + 30000,
    await_progress(Deadline, H).

await_progress(Deadline, #{port := Port} = H) ->
    Wedges = quiet_reports(H),
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {Port, {data, _}} ->
            await_progress(Deadline, H);
        {Port, {exit_status, S}} ->
            throw({node_down, S, H#{port := undefined}});
        {chaos, {progress, _}} ->
            H;
        {'DOWN', _, process, Agent, Why} when Agent =:= map_get(agent, H) ->
            await_progress(Deadline, respawn_agent(Why, H));
        {chaos, Report} ->
            H1 = note(Report, H),
            case quiet_reports(H1) of
                Wedges -> await_progress(Deadline, H1);
                _ -> H1#{life_quiet => true}
            end
    after Left ->
        log(H, "no product moved and the operator in the node reported nothing: cell ~p, "
            "request ~p", [catch call(H, cell_controller, state, []),
                           catch call(H, cell_registry, control, [request])]),
        H
    end.

quiet_reports(H) ->
    lists:sum([length(maps:get(K, H)) || K <- [wedged, stalled, silent_stops]]).

%% Waits `Ms', taking what the operator in the node reports meanwhile.
pause(Ms, H) ->
    pause_until(erlang:monotonic_time(millisecond) + Ms, H).

pause_until(Deadline, #{port := Port} = H) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {Port, {data, _}} ->
            pause_until(Deadline, H);
        {Port, {exit_status, S}} ->
            throw({node_down, S, H#{port := undefined}});
        {chaos, Report} ->
            pause_until(Deadline, note(Report, H));
        {'DOWN', _, process, Agent, Why} when Agent =:= map_get(agent, H) ->
            pause_until(Deadline, respawn_agent(Why, H));
        {'DOWN', _, process, _, _} ->
            pause_until(Deadline, H);
        {nodedown, _} ->
            pause_until(Deadline, H)
    after Left ->
        H
    end.

%% The operator in the node stopped (its events' owner gone for long, say).
respawn_agent(Why, #{opts := #{seed := Seed, wedge_ms := WedgeMs}, boots := B} = H) ->
    log(H, "the operator in the node stopped (~p): started again", [Why]),
    {ok, A} = call(H, ?MODULE, agent_start, [self(), Seed, B, WedgeMs]),
    _ = erlang:monitor(process, A),
    H#{agent := A}.

%% What the operator in the node reports.
note({answer, Caption, Solution, ok}, #{answers := A} = H) ->
    _ = Caption,
    H#{answers := A#{Solution => maps:get(Solution, A, 0) + 1}};
note({answer, Caption, Solution, {error, Why}}, #{refused := R} = H) ->
    log(H, "answer ~s to \"~ts\" refused: ~p", [Solution, Caption, Why]),
    H#{refused := R + 1};
note({wedged, What}, #{wedged := W} = H) ->
    log(H, "WEDGED: Started, no product moved for the window and no error: ~ts",
        [tasks_text(What)]),
    H#{wedged := [What | W]};
note({stalled, What}, #{stalled := W} = H) ->
    log(H, "stalled: no product moved for the window, errors answered meanwhile: ~ts",
        [tasks_text(What)]),
    H#{stalled := [What | W]};
note({restarted, Ms, Result}, #{restarts := R} = H) ->
    log(H, "the cell's tasks restarted after an internal fault: Start pressed again "
        "after ~b ms: ~p", [Ms, Result]),
    H#{restarts := R + 1};
note({operator_fault, C, R}, H) ->
    log(H, "the operator in the node could not read the cell for a moment: ~p:~0p", [C, R]),
    H;
note({silent_stop, What}, #{silent_stops := S} = H) ->
    log(H, "the cell stood stopped for the window, panels in it, and no event told the "
        "operator: ~ts", [tasks_text(What)]),
    H#{silent_stops := [What | S]};
note({progress, _}, H) ->
    H;
note({state, _}, H) ->
    H.

%% The end: no new panel, the line drains, Stop, the books read, the node stopped.
finish(H) ->
    try
        H1 = up(H),
        ok = call(H1, cell_settings, put, [router_sim, #{arrival_ms => 3600000}, ?WHO]),
        log(H1, "no new panels: the line drains", []),
        H2 = drain(erlang:monotonic_time(millisecond) + ?DRAIN_MS, H1),
        _ = [Agent ! stop_producing || Agent <- [maps:get(agent, H2)], is_pid(Agent)],
        ok = call(H2, cell_controller, stop, [?WHO]),
        H3 = await_off(erlang:monotonic_time(millisecond) + ?DOWN_MS, H2),
        H4 = check_double(H3),
        View = call(H4, ?MODULE, view, []),
        H5 = stop_node(H4),
        H5#{view => View}
    catch
        throw:{node_down, Status, HD} ->
            log(HD, "the node died by itself during the drain (exit status ~p); started "
                "again", [Status]),
            finish(HD#{deaths := maps:get(deaths, HD) + 1, port := undefined,
                       agent := undefined})
    end.

drain(Deadline, H) ->
    case call(H, ?MODULE, machine, []) of
        #{panels := [], upstream := []} ->
            log(H, "drained", []),
            H#{drained := true};
        #{panels := Panels, upstream := Up} ->
            Wedged = quiet_reports(H),
            Left = Deadline - erlang:monotonic_time(millisecond),
            case Left > 0 of
                false ->
                    log(H, "the line did not drain in ~b s: ~ts in the machine, ~b waiting",
                        [?DRAIN_MS div 1000, serials_text(Panels), length(Up)]),
                    H;
                true ->
                    H1 = next_report(Deadline, H),
                    case quiet_reports(H1) of
                        Wedged -> drain(Deadline, H1);
                        _ ->
                            log(H1, "the line stopped draining: ~ts in the machine",
                                [serials_text(Panels)]),
                            H1
                    end
            end
    end.

%% The next report of the operator in the node (a product moved, say), or the deadline.
next_report(Deadline, #{port := Port} = H) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {Port, {data, _}} -> next_report(Deadline, H);
        {Port, {exit_status, S}} -> throw({node_down, S, H#{port := undefined}});
        {'DOWN', _, process, Agent, Why} when Agent =:= map_get(agent, H) ->
            respawn_agent(Why, H);
        {chaos, Report} -> note(Report, H)
    after Left ->
        H
    end.

await_off(Deadline, H) ->
    case call(H, cell_controller, state, []) of
        off ->
            H;
        State ->
            case Deadline - erlang:monotonic_time(millisecond) > 0 of
                true ->
                    await_off(Deadline, next_report(Deadline, H));
                false ->
                    log(H, "the cell did not stop in ~b s (~p)", [?DOWN_MS div 1000, State]),
                    H
            end
    end.

stop_node(#{port := Port, node := Node} = H) ->
    _ = rpc:cast(Node, init, stop, []),
    receive
        {Port, {exit_status, _}} -> ok
    after ?DOWN_MS ->
        _ = os:cmd("kill -9 " ++ maps:get(ospid, H))
    end,
    H#{port := undefined}.

%% A call into the node; a node that died meanwhile is told by its exit.
call(#{node := Node, port := Port} = H, M, F, A) ->
    try
        erpc:call(Node, M, F, A, ?BOOT_MS)
    catch
        error:{erpc, _} = Why ->
            receive
                {Port, {exit_status, S}} -> throw({node_down, S, H#{port := undefined}})
            after ?DOWN_MS ->
                error({call_failed, M, F, Why})
            end
    end.

%%====================================================================
%% The books
%%====================================================================

%% @doc Every serial the machine made or the cell knows, in the columns: `lost',
%% `duplicated', `left_scrapped' (each a list of `{Serial, Why}'), and how many are
%% `ok'; what the machine says in `phys'. `View' is what view/0 returns.
-spec reconcile(map()) -> map().
reconcile(#{world := W, products := Products, held := Held}) ->
    Places = places(W),
    Ledger = maps:get(ledger, W, []),
    Next = maps:get(next, W),
    Made = lists:usort([S || {S, _} <- Places] ++ [S || {S, _} <- Ledger]),
    Numbers = [number(S) || S <- Made],
    Vanished = [N || N <- lists:seq(1, Next - 1), not lists:member(N, Numbers)],
    HeldBy = fun(S) -> [T || {S1, T} <- Held, S1 =:= S] end,
    Cell = fun(S) -> maps:get(S, Products, #{status => unknown, lefts => 0, scraps => 0,
                                            in_open => false, in_product => false}) end,
    Rows = [classify(S, [P || {S1, P} <- Places, S1 =:= S] ++
                         [{left, How} || {S1, How} <- Ledger, S1 =:= S],
                     Cell(S), HeldBy(S))
            || S <- lists:usort(Made ++ maps:keys(Products))],
    Gone = [{vanished_serial(N, Products), [io_lib:format("panel no. ~b gone from the machine "
                                                         "without a trace", [N])]}
            || N <- Vanished],
    #{lost => [{S, Why} || {S, lost, Why} <- Rows] ++ Gone,
      duplicated => [{S, Why} || {S, duplicated, Why} <- Rows],
      left_scrapped => [{S, Why} || {S, left_scrapped, Why} <- Rows],
      ok => length([x || {_, ok, _} <- Rows]),
      phys => #{delivered => length([x || {_, delivered} <- Ledger]),
                scrapped => length([x || {_, scrapped} <- Ledger]),
                removed => length([x || {_, removed} <- Ledger]),
                in_machine => length([x || {_, {machine, _}} <- Places]),
                waiting => length([x || {_, {upstream, _}} <- Places]),
                made => Next - 1}}.

vanished_serial(N, Products) ->
    case [S || S <- maps:keys(Products), number(S) =:= N] of
        [S | _] -> S;
        [] -> iolist_to_binary(io_lib:format("no. ~b", [N]))
    end.

%% Where the machine has each serial: `{upstream, Lane}' (not in the cell yet) or
%% `{machine, Where}'. A frame in a fixture is not the product.
places(W) ->
    [{S, {upstream, L}} || {L, Q} <- maps:to_list(maps:get(upstream, W)), S <- Q]
    ++ [{S, {machine, {Where, L}}} || Where <- [loading, work, unloading],
                                      {L, {S, Pos}} <- maps:to_list(maps:get(Where, W)),
                                      Pos =/= frame]
    ++ [{S, {machine, gripper}} || S <- [maps:get(gripper, W)], S =/= empty].

classify(S, Phys, #{status := Status, lefts := Lefts, scraps := Scraps} = C, Held) ->
    Dup = [Why || {true, Why} <-
                      [{length(Phys) > 1, io_lib:format("the machine has it ~ts", [phys_text(Phys)])},
                       {Lefts > 1, io_lib:format("the cell recorded it leaving ~b times", [Lefts])},
                       {Lefts >= 1 andalso Scraps >= 1, "the cell recorded it leaving and scrapped"},
                       {maps:get(in_open, C) andalso maps:get(in_product, C),
                        "the cell has it both in the cell and gone"},
                       {length(Held) > 1, "held by two tasks"}]],
    case {Dup, Phys, Status} of
        {[_ | _], _, _} ->
            {S, duplicated, lists:join("; ", Dup) ++ "; cell: " ++ status_text(Status, Held)};
        {[], [{left, delivered}], out} ->
            {S, ok, ""};
        {[], [{left, delivered}], scrapped} ->
            {S, left_scrapped, "delivered to the next machine; the cell recorded it scrapped"};
        {[], [{left, delivered}], _} ->
            {S, lost, "delivered to the next machine; cell: " ++ status_text(Status, Held)};
        {[], [{left, scrapped}], scrapped} ->
            {S, ok, ""};
        {[], [{left, scrapped}], _} ->
            {S, lost, "in the scrap bin; cell: " ++ status_text(Status, Held)};
        %% Taken out of the machine by the operator's hand: gone like the scrap bin's.
        {[], [{left, removed}], scrapped} ->
            {S, ok, ""};
        {[], [{left, removed}], _} ->
            {S, lost, "taken out of the machine by the operator; cell: "
             ++ status_text(Status, Held)};
        {[], [{machine, _}], in_cell} when Held =/= [] ->
            {S, ok, ""};
        {[], [{machine, Where}], _} ->
            {S, lost, io_lib:format("in the machine (~p); cell: ~ts",
                                    [Where, status_text(Status, Held)])};
        {[], [{upstream, _}], unknown} ->
            {S, ok, ""};
        {[], [{upstream, _}], _} ->
            {S, lost, "still at the previous machine; cell: " ++ status_text(Status, Held)};
        {[], [], _} ->
            {S, lost, "nowhere in the machine nor in its ledger; cell: "
             ++ status_text(Status, Held)}
    end.

%% @doc The statistics' totals (`cell_stats:summary(total)') against the machine's
%% ledger (`phys' of reconcile/1): each count that differs, with the cell's figure and
%% the machine's. A panel entered the cell when it left the previous machine: it was
%% delivered, went into the scrap bin, was taken out by hand, or is in the machine.
-spec books(map(), map()) -> [{string(), integer(), integer()}].
books(#{cell := Cell, in_cell := InCell}, #{delivered := Delivered, scrapped := Bin,
                                            removed := Removed, in_machine := InMachine}) ->
    [{What, C, M} || {What, C, M} <- [{"in", maps:get(in, Cell, 0),
                                       Delivered + Bin + Removed + InMachine},
                                      {"out", maps:get(out, Cell, 0), Delivered},
                                      {"scrapped", maps:get(scrapped, Cell, 0), Bin + Removed},
                                      {"in the cell", InCell, InMachine}],
                     C =/= M].

status_text(in_cell, []) -> "in the cell, held by no task";
status_text(in_cell, Held) -> "in the cell, held by " ++ lists:join(", ", [atom_to_list(T) || T <- Held]);
status_text(unknown, _) -> "unknown";
status_text(Status, _) -> atom_to_list(Status).

phys_text(Phys) ->
    lists:join(" and ", [io_lib:format("~p", [P]) || P <- Phys]).

number(Serial) ->
    case string:split(Serial, "-", trailing) of
        [_, N] -> try binary_to_integer(N) catch error:badarg -> -1 end;
        _ -> -1
    end.

%%====================================================================
%% The report
%%====================================================================

report(#{view := View, opts := Opts} = H, Secs) ->
    Books = reconcile(View),
    %% The cell stopped, a serial two tasks hold is double-held at once.
    #{held := EndHeld} = View,
    Double = maps:merge(maps:get(double, H),
                        maps:from_list([{S, lists:usort([T || {S1, T} <- EndHeld, S1 =:= S])}
                                        || {S, _} <- EndHeld,
                                           length([x || {S1, _} <- EndHeld, S1 =:= S]) > 1])),
    %% A wedge the node's restarts did not clear is reported at each life: counted once,
    %% by the panels it holds, with how often it was seen.
    Wedged = distinct(lists:reverse(maps:get(wedged, H))),
    Phys = maps:get(phys, Books),
    Differ = books(maps:get(total, View), Phys),
    Cols = [{"lost", length(maps:get(lost, Books))},
            {"duplicated", length(maps:get(duplicated, Books))},
            {"double-held", maps:size(Double)},
            {"wedged", length(Wedged)},
            {"left-but-recorded-scrapped", length(maps:get(left_scrapped, Books))},
            {"books", lists:sum([abs(C - M) || {_, C, M} <- Differ])}],
    #{cell := Cell} = maps:get(total, View),
    Totals = io_lib:format(
               "panels made ~b, in ~b, out ~b (delivered ~b), scrapped ~b (in the bin ~b, taken "
               "out by hand ~b), "
               "in the machine ~b, waiting ~b; node kills ~b, node deaths on their own ~b, "
               "boots ~b; process kills ~b (~ts); answers ~ts, refused ~b; Start pressed "
               "again after the tasks restarted ~b; stalls with errors ~b; silent stops ~b; "
               "drained: ~s",
               [maps:get(made, Phys), maps:get(in, Cell, 0), maps:get(out, Cell, 0),
                maps:get(delivered, Phys), maps:get(scrapped, Cell, 0), maps:get(scrapped, Phys),
                maps:get(removed, Phys), maps:get(in_machine, Phys), maps:get(waiting, Phys),
                maps:get(node_kills, H), maps:get(deaths, H), maps:get(boots, H),
                maps:get(proc_kills, H), kinds_text(maps:get(by_kind, H)),
                kinds_text(maps:get(answers, H)), maps:get(refused, H),
                maps:get(restarts, H), length(maps:get(stalled, H)),
                length(maps:get(silent_stops, H)), maps:get(drained, H)]),
    Counts = [io_lib:format("~s ~b", [C, N]) || {C, N} <- Cols],
    log(H, "~ts", [lists:join(", ", Counts)]),
    log(H, "~ts", [Totals]),
    Tables = [table("Lost", maps:get(lost, Books)),
              table("Duplicated", maps:get(duplicated, Books)),
              table("Double-held", [{S, "held by " ++ lists:join(" and ", [atom_to_list(T) || T <- Ts])}
                                    || {S, Ts} <- maps:to_list(Double)]),
              table("Wedged", [{serials_text(maps:get(serials, W)),
                                [io_lib:format("seen ~b time(s), first: ", [N]), tasks_text(W)]}
                               || {W, N} <- Wedged]),
              table("Left but recorded scrapped", maps:get(left_scrapped, Books)),
              books_table(Differ),
              table("Stalled with errors answered (not a column)",
                    [{serials_text(maps:get(serials, W)),
                      [io_lib:format("seen ~b time(s), first: ", [N]), tasks_text(W)]}
                     || {W, N} <- distinct(lists:reverse(maps:get(stalled, H)))]),
              table("Stopped under the operator's feet, no event said so (not a column)",
                    [{serials_text(maps:get(serials, W)), tasks_text(W)}
                     || W <- lists:reverse(maps:get(silent_stops, H))])],
    {{Y, Mo, D}, {Hh, Mi, _}} = calendar:universal_time(),
    Doc = ["# Chaos test\n\n",
           io_lib:format("Written by `~ts` on ~4..0w-~2..0w-~2..0w ~2..0w:~2..0w UTC, OTP ~s, "
                         "in ~b min ~b s: the default cell (both lanes, the physics at 20x, "
                         "faults on) in the built release, killed with SIGKILL and restarted "
                         "on the same root folder, single processes killed inside it, errors "
                         "answered by a seeded operator; then the line drained and every "
                         "serial reconciled against the simulated machine's ledger.\n\n",
                         [maps:get(command, Opts, "make chaos"), Y, Mo, D, Hh, Mi,
                          erlang:system_info(otp_release), Secs div 60, Secs rem 60]),
           io_lib:format("Seed ~b, ~b node kills, ~b process kills.\n\n",
                         [maps:get(seed, Opts), maps:get(node_kills, H), maps:get(proc_kills, H)]),
           "| column | count |\n|---|---|\n",
           [io_lib:format("| ~s | ~b |\n", [C, N]) || {C, N} <- Cols],
           "\nTotals: ", Totals, ".\n", Tables],
    Out = maps:get(out, Opts),
    ok = filelib:ensure_dir(filename:join(Out, "x")),
    ok = file:write_file(filename:join(Out, "chaos.md"), Doc),
    case maps:get(node_kills, H) >= 200 andalso maps:get(proc_kills, H) >= 1000 of
        true -> ok = file:write_file(maps:get(doc, Opts), Doc);
        false -> ok
    end,
    #{counts => maps:from_list(Cols), clean => lists:all(fun({_, N}) -> N =:= 0 end, Cols),
      lost => maps:get(lost, Books), duplicated => maps:get(duplicated, Books),
      double_held => Double, wedged => [W || {W, _} <- Wedged], left_scrapped => maps:get(left_scrapped, Books),
      books => Differ,
      totals => iolist_to_binary(Totals), report => iolist_to_binary(Doc)}.

%% Reports of one stand-still, once each (the first), with how often each was seen.
distinct(Reports) ->
    Keys = lists:foldl(fun(#{serials := S}, Acc) ->
                               case lists:keymember(S, 1, Acc) of
                                   true -> Acc;
                                   false -> Acc ++ [{S, length([x || #{serials := S1} <- Reports,
                                                                     S1 =:= S])}]
                               end
                       end, [], Reports),
    [{hd([R || #{serials := S1} = R <- Reports, S1 =:= S]), N} || {S, N} <- Keys].

table(Title, []) ->
    ["\n## ", Title, "\n\nNone.\n"];
table(Title, Rows) ->
    ["\n## ", Title, "\n\n| serial | what |\n|---|---|\n",
     [io_lib:format("| ~ts | ~ts |\n", [S, Why]) || {S, Why} <- Rows]].

books_table([]) ->
    ["\n## Books\n\nThe statistics' totals agree with the machine's ledger.\n"];
books_table(Rows) ->
    ["\n## Books\n\n| count | the statistics | the machine |\n|---|---|---|\n",
     [io_lib:format("| ~ts | ~b | ~b |\n", [W, C, M]) || {W, C, M} <- Rows]].

tasks_text(#{serials := Serials, tasks := Tasks}) ->
    io_lib:format("products ~ts; tasks: ~ts",
                  [serials_text(Serials),
                   lists:join(", ", [io_lib:format("~s ~0p ~ts", [Id, St, case Se of
                                                                          undefined -> "-";
                                                                          _ -> Se
                                                                      end])
                                     || {Id, St, Se} <- Tasks])]).

serials_text([]) -> "none";
serials_text(Serials) -> lists:join(" ", [io_lib:format("~ts", [S]) || S <- Serials]).

kinds_text(Map) ->
    lists:join(", ", [io_lib:format("~s ~b", [K, N]) || {K, N} <- lists:sort(maps:to_list(Map))]).

%%====================================================================
%% Inside the node
%%====================================================================

%% @doc The processes a kill may hit, by kind.
-spec targets() -> [{atom(), pid(), string()}].
targets() ->
    Tasks = [{T, Id} || #{id := Id, pid := T} <- cell_controller:tasks(), is_pid(T)],
    TaskPids = [P || {P, _} <- Tasks],
    [{task, P, atom_to_list(Id)} || {P, Id} <- Tasks]
    ++ [{Kind, P, Name} || P <- processes(), not lists:member(P, TaskPids),
                           {Kind, Name} <- [kind(P)], Kind =/= none].

kind(P) ->
    try proc_lib:translate_initial_call(P) of
        {supervisor, _, _} -> {none, ""};
        {M, _, _} -> {kind_of(atom_to_list(M)), atom_to_list(M)};
        _ -> {none, ""}
    catch
        _:_ -> {none, ""}                       %% gone meanwhile
    end.

kind_of("cell_handshake_link") -> link;
kind_of("cell_stats") -> stats;
kind_of("cell_stats_writer") -> stats_writer;
kind_of("router_sim") -> sim;
kind_of("cell_web_feed") -> web_feed;
kind_of("cell_events") -> events;
kind_of("cell_hal" ++ _) -> hal;
kind_of("cell_" ++ _) -> other;
kind_of("router_" ++ _) -> other;
kind_of(_) -> none.

%% @doc Every product a task holds, as `{Serial, Task}'.
-spec held() -> [{binary(), atom()}].
held() ->
    [{S, Id} || #{id := Id, serial := S} <- cell_controller:tasks(), is_binary(S)].

%% @doc The panels in the machine and those waiting at the previous machine.
-spec machine() -> #{panels := [binary()], upstream := [binary()]}.
machine() ->
    W = router_sim:world(),
    #{panels => [S || {S, {machine, _}} <- places(W)]
                ++ [S || Where <- [work], {_, {S, frame}} <- maps:to_list(maps:get(Where, W))],
      upstream => [S || {S, {upstream, _}} <- places(W)]}.

%% @doc The machine's world and the cell's books, the cell stopped.
-spec view() -> map().
view() ->
    _ = [cell_stats:flush() || _ <- [1, 2, 3]],
    Keys = lists:usort(lists:append([mnesia:dirty_all_keys(T)
                                     || T <- [cell_trace_open, cell_trace_product,
                                              cell_trace_event]])),
    Open = mnesia:dirty_all_keys(cell_trace_open),
    Gone = mnesia:dirty_all_keys(cell_trace_product),
    Products = maps:from_list([{S, product_view(S, lists:member(S, Open), lists:member(S, Gone))}
                               || S <- Keys]),
    #{world => router_sim:world(), products => Products, held => held(),
      total => cell_stats:summary(total)}.

product_view(S, InOpen, InProduct) ->
    {Status, Events} = case cell_stats:product(S) of
                           {ok, #{status := St, events := Es}} -> {St, Es};
                           {error, not_found} -> {unknown, []}
                       end,
    Count = fun(E) -> length([x || #{event := E1} <- Events, E1 =:= E]) end,
    #{status => Status, lefts => Count(left), scraps => Count(scrapped),
      in_open => InOpen, in_product => InProduct}.

%% @doc Starts the operator in the node: it answers every error (Retry, Ignore or Reset
%% by a seeded random per kind of error, another where one is refused) and tells the
%% harness what it answered, each product that moved, and a cell that made no progress
%% for `WedgeMs'.
-spec agent_start(pid(), integer(), pos_integer(), pos_integer()) -> {ok, pid()}.
agent_start(Harness, Seed, Boot, WedgeMs) ->
    Pid = spawn(fun() ->
                        _ = erlang:monitor(process, Harness),
                        A = subscribe(#{harness => Harness, seed => Seed, boot => Boot,
                                        wedge_ms => WedgeMs, rands => #{}, answered => #{},
                                        errors => 0, timer => undefined,
                                        producing => true}),
                        agent(quiet_timer(A))
                end),
    {ok, Pid}.

%% Subscribed to the cell's events, watching their owner: after a restart of it the
%% operator subscribes again, and reads the errors it may have missed.
subscribe(A) ->
    subscribe(A, ?DOWN_MS).

subscribe(A, Left) ->
    case whereis(cell_events) of
        undefined when Left > 0 ->
            %% Its supervisor starts it again in a moment.
            receive after 50 -> ok end,
            subscribe(A, Left - 50);
        undefined ->
            exit(no_events);
        Pid when is_pid(Pid) ->
            _ = erlang:monitor(process, Pid),
            try cell_events:subscribe([alarm_raised, cell_state, task_state, request
                                       | ?PROGRESS]) of
                ok -> restart_cell(off, answer_waiting(A))
            catch
                exit:_ -> subscribe(A, Left)
            end
    end.

answer_waiting(A) ->
    lists:foldl(fun(Alarm, Acc) -> schedule(Alarm, Acc) end, A,
                [Al || #{kind := error} = Al <- cell_alarms:list()]).

agent(#{harness := H} = A) ->
    receive
        {'DOWN', _, process, H, _} ->
            exit(normal);
        Msg ->
            %% A service it reads may be down for a moment (a kill): the operator
            %% tells the harness and goes on.
            A1 = try handle(Msg, A)
                 catch C:R -> H ! {chaos, {operator_fault, C, R}}, A
                 end,
            agent(A1)
    end.

handle({cell_event, #{type := alarm_raised, alarm := #{kind := error} = Alarm}}, A) ->
    schedule(Alarm, A#{errors := maps:get(errors, A) + 1});
handle({cell_event, #{type := alarm_raised, alarm := #{id := ?STOPPED}}}, A) ->
    %% The cell stopped by itself after an internal fault, and says so.
    restart_cell(off, A);
handle({cell_event, #{type := alarm_raised}}, A) ->
    A;
handle({cell_event, #{type := cell_state, state := State}}, #{harness := H} = A) ->
    H ! {chaos, {state, State}},
    restart_cell(State, A);
handle({cell_event, #{type := task_state, state := State}}, A) ->
    restart_cell(State, A);
handle({cell_event, #{type := request}}, A) ->
    restart_cell(off, A);
handle({cell_event, #{type := Type}}, #{harness := H} = A) ->
    H ! {chaos, {progress, Type}},
    quiet_timer(A#{errors := 0});
handle({press_start, Ms}, #{harness := H} = A) ->
    %% The operator has read the log and presses Start.
    A1 = A#{pressing => false},
    case maps:get(producing, A) andalso cell_registry:control(request) =/= start of
        true ->
            Result = catch cell_controller:start(?WHO),
            H ! {chaos, {restarted, Ms, Result}};
        false ->
            ok
    end,
    A1;
handle(stop_producing, A) ->
    A#{producing := false};
handle({answer, Alarm}, A) ->
    answer(Alarm, A);
handle({timeout, Ref, quiet}, #{timer := Ref} = A) ->
    %% The next window starts whatever this one found.
    quiet(quiet_timer(A));
handle({timeout, _, quiet}, A) ->
    A;
handle({'DOWN', _, process, _, _}, A) ->
    subscribe(A).

%% The cell's tasks came back OFF after an internal fault below the controller: the
%% log asks the operator to check the machine and press Start, and the operator does.
restart_cell(off, #{producing := true} = A) ->
    case {cell_registry:control(request), maps:get(pressing, A, false)} of
        {start, _} ->
            A;
        {_, true} ->
            A;
        _ ->
            {Ms, A1} = agent_rand(<<"start">>, 1000, A),
            _ = erlang:send_after(200 + Ms, self(), {press_start, 200 + Ms}),
            A1#{pressing => true}
    end;
restart_cell(_State, A) ->
    A.

quiet_timer(#{timer := T, wedge_ms := Ms} = A) ->
    _ = T =:= undefined orelse erlang:cancel_timer(T),
    A#{timer := erlang:start_timer(Ms, self(), quiet)}.

%% No product moved for the window: a Started cell with panels in it or waiting for
%% it is wedged if no error was raised meanwhile, stalled if errors were.
quiet(A) ->
    try quiet_check(A)
    catch C:R -> maps:get(harness, A) ! {chaos, {operator_fault, C, R}}, A
    end.

quiet_check(#{harness := H, errors := Errors} = A) ->
    Held = held(),
    #{panels := Panels, upstream := Up} = machine(),
    Errors1 = Errors + length([x || #{kind := error} <- cell_alarms:list()]),
    What = fun() -> #{serials => lists:usort([S || {S, _} <- Held] ++ Panels),
                      tasks => [{Id, St, maps:get(serial, T, undefined)}
                                || #{id := Id, state := St} = T <- cell_controller:tasks()]}
           end,
    Work = Held =/= [] orelse Panels =/= [] orelse Up =/= [],
    case {cell_registry:control(request), Work, Errors1} of
        {start, true, 0} ->
            H ! {chaos, {wedged, What()}};
        {start, true, _} ->
            H ! {chaos, {stalled, What()}};
        {_, true, _} when map_get(producing, A) ->
            %% Stopped under the operator's feet for a whole window: silent unless the
            %% cell's alarm says it stopped by itself. The operator presses Start now
            %% (restart_cell/2).
            case cell_alarms:get(?STOPPED) of
                {ok, _} -> ok;
                {error, not_found} -> H ! {chaos, {silent_stop, What()}}
            end;
        _ ->
            ok
    end,
    restart_cell(off, A#{errors := 0}).

%% The operator answers a moment after the error appears; an error raised again (the
%% same id, raised anew: a Retry that found the machine as it was) is answered again.
schedule(#{id := Id} = Alarm, #{answered := Done} = A) ->
    Key = {Id, maps:get(raised, Alarm, 0)},
    case maps:is_key(Key, Done) of
        true ->
            A;
        false ->
            {Ms, A1} = agent_rand(<<"delay">>, 400, A),
            _ = erlang:send_after(100 + Ms, self(), {answer, Alarm}),
            A1#{answered := Done#{Key => true}}
    end.

answer(#{local_id := <<"held_twice">>, id := Id} = Alarm, A) ->
    %% Reset where the machine does not have it; where it does, this error goes with
    %% the other holder's Reset, and is looked at again meanwhile (the physics
    %% restarting, or the panel moving on, may change the answer).
    case try at_the_machine(Alarm, router_sim:world(), held()) catch exit:_ -> keep end of
        keep ->
            _ = [erlang:send_after(500, self(), {answer, Alarm})
                 || #{id := I} <- cell_alarms:list(), I =:= Id],
            A;
        Choices ->
            try_answer(Alarm, Choices, again, A)
    end;
answer(#{solutions := Offered} = Alarm, A) ->
    %% The operator looks at the machine first (and takes out by hand a panel that no
    %% record holds), then answers among the answers true for it.
    try at_the_machine(Alarm, router_sim:world(), held()) of
        True ->
            case True =/= any andalso [S || S <- Offered, lists:member(S, True)] of
                false -> try_answer(Alarm, Offered, give_up, A);
                [] -> try_answer(Alarm, Offered, give_up, A);
                Choices -> try_answer(Alarm, Choices, again, A)
            end
    catch
        _:_ ->
            %% The machine cannot be seen (its physics restarting with the HAL, or
            %% what the tasks hold not readable a moment): a guess may forget a
            %% product that is there. The operator looks again a moment later, as
            %% long as the error waits.
            look_again(Alarm, A)
    end.

look_again(Alarm, A) ->
    case still_waiting(Alarm) of
        true ->
            {Ms, A1} = agent_rand(<<"look">>, 1000, A),
            _ = erlang:send_after(200 + Ms, self(), {answer, Alarm}),
            A1;
        false ->
            A
    end.

%% The error as it was raised is still listed: not answered, not withdrawn, not raised
%% anew (a new raise is scheduled on its own). Its table between two owners (the
%% controller's tree starting anew): still waiting, looked at again.
still_waiting(#{id := Id} = Alarm) ->
    Raised = maps:get(raised, Alarm, 0),
    try cell_alarms:list() of
        Listed -> [x || #{id := I, raised := R} <- Listed, I =:= Id, R =:= Raised] =/= []
    catch
        error:badarg -> true
    end.

%% One of the answers, at random; one refused (the runtime sees a double holding the
%% answer would make), another of them. All refused: answers true for the machine
%% (`again') are given again a moment later, when a record may have changed; any
%% answer (`give_up') is not.
try_answer(_Alarm, [], give_up, A) ->
    A;
try_answer(Alarm, [], again, A) ->
    {Ms, A1} = agent_rand(<<"again">>, 1000, A),
    _ = erlang:send_after(200 + Ms, self(), {answer, Alarm}),
    A1;
try_answer(#{id := Id, caption := Caption} = Alarm, Choices, Then, #{harness := H} = A) ->
    {I, A1} = agent_rand(Caption, length(Choices), A),
    Solution = lists:nth(I, Choices),
    case catch cell_alarms:answer(Id, Solution, ?WHO) of
        ok ->
            H ! {chaos, {answer, Caption, Solution, ok}},
            A1;
        {error, not_found} ->
            A1;
        Refused ->
            H ! {chaos, {answer, Caption, Solution, {error, Refused}}},
            try_answer(Alarm, Choices -- [Solution], Then, A1)
    end.

%% The answers true for the machine as the operator finds it (`World', router_sim's
%% world; `Held', what the tasks hold), for the questions whose right answer depends on
%% where the product physically is; `any' for the others (a jam: Retry, whatever).
%% A panel in the work fixture that no record holds is taken out by hand first.
%% <ul>
%% <li>"Product transfer interrupted" (`in_transit', `transfer'): Ignore says it is
%%   here, Reset that it is not: Ignore when the machine has it, else Reset.</li>
%% <li>A restart after a crash (`crashed'): Retry goes on with the product as saved,
%%   Reset forgets it: Retry when the machine has it, Reset when it does not, either
%%   when the task holds none.</li>
%% <li>The upper robot's `where' and "Product lost" (`lost'): Retry when the modules are
%%   in the gripper (or, asked where, back in the nest), Ignore when they lie on the
%%   unloading conveyor, else Reset.</li>
%% <li>Another task's `where': Ignore when the panel lies on the loading segment, or
%%   whole in the lane's work fixture with no other task holding it (past the stopper),
%%   else Reset.</li>
%% <li>A product at a station that no record holds (`unheld': a panel in a work
%%   fixture, modules on an unloading conveyor or in the gripper): taken out by hand,
%%   then Retry.</li>
%% <li>A product held by two tasks (`held_twice', Reset the only answer: that task
%%   forgets it, the other keeps it): `keep' (no answer) on the holder whose station
%%   physically has it, Reset on the others; where two holders' stations have it (a
%%   panel in a work fixture the routing robot holds too, say), the one furthest down
%%   the line keeps it, as a hand-over writes the newer record downstream. In no
%%   holder's station, Reset on each.</li>
%% </ul>
-spec at_the_machine(map(), map(), [{binary(), atom()}]) ->
          [cell_alarms:solution()] | any | keep.
at_the_machine(#{local_id := <<"held_twice">>, task := Task}, World, Held) ->
    Serial = case [S || {S, T} <- Held, T =:= Task] of
                 [S | _] -> S;
                 [] -> undefined
             end,
    Holders = [T || {S, T} <- Held, S =:= Serial],
    At = [T || {S, {machine, Place}} <- places(World), S =:= Serial,
               T <- station_tasks(Place), lists:member(T, Holders)],
    Keeper = case lists:sort(fun(X, Y) -> down_the_line(X) =< down_the_line(Y) end, At) of
                 [] -> none;
                 Sorted -> lists:last(Sorted)
             end,
    case Keeper of
        Task -> keep;
        _ -> [reset]
    end;
at_the_machine(#{local_id := Local, task := Task}, World, Held) ->
    Serial = case [S || {S, T} <- Held, T =:= Task] of
                 [S | _] -> S;
                 [] -> undefined
             end,
    InMachine = [S || {S, {machine, _}} <- places(World)],
    Has = lists:member(Serial, InMachine),
    case Local of
        _ when Local =:= <<"in_transit">>; Local =:= <<"transfer">> ->
            [case Has of true -> ignore; false -> reset end];
        <<"crashed">> when Serial =:= undefined -> [retry, reset];
        <<"crashed">> when Has -> [retry];
        <<"crashed">> -> [reset];
        _ when Task =:= upper, Local =:= <<"where">> orelse Local =:= <<"lost">> ->
            [upper_truth(Local, Serial, World)];
        <<"where">> ->
            OnLoading = [x || {S, _} <- maps:values(maps:get(loading, World)), S =:= Serial],
            [case OnLoading =/= [] orelse past_the_stopper(Task, Serial, World, Held) of
                 false -> reset;
                 true -> ignore
             end];
        <<"unheld">> ->
            ok = hand_out(Task, World, Held),
            [retry];
        _ ->
            any
    end.

%% The tasks that may hold a product lying at a place of the machine: in a work
%% fixture, the routing robot routes it where it lies and the upper robot takes charge
%% of its modules there before it lifts them.
station_tasks({loading, front}) -> [loading_front];
station_tasks({loading, rear}) -> [loading_rear];
station_tasks({work, front}) -> [work_front, lower, upper];
station_tasks({work, rear}) -> [work_rear, lower, upper];
station_tasks({unloading, front}) -> [unloading_front];
station_tasks({unloading, rear}) -> [unloading_rear];
station_tasks(gripper) -> [upper].

down_the_line(Task) ->
    maps:get(Task, #{loading_front => 1, loading_rear => 1, work_front => 2, work_rear => 2,
                     lower => 3, upper => 4, unloading_front => 5, unloading_rear => 5}).

%% A loading segment's panel that lies whole in its lane's work fixture, no other task
%% holding it: past the stopper, handed over as it lies (Ignore keeps it).
past_the_stopper(Task, Serial, World, Held) ->
    Lane = maps:get(Task, #{loading_front => front, loading_rear => rear}, none),
    case maps:get(Lane, maps:get(work, World), empty) of
        {Serial, Pos} when Pos =/= frame ->
            [T || {S, T} <- Held, S =:= Serial, T =/= Task] =:= [];
        _ ->
            false
    end.

upper_truth(Local, S, #{gripper := G} = W) ->
    In = fun(Where, Pos) -> [x || {S1, P} <- maps:values(maps:get(Where, W)), S1 =:= S,
                                  Pos =:= any orelse P =:= Pos] =/= [] end,
    if
        G =:= S, S =/= undefined -> retry;                %% in the gripper after all
        Local =:= <<"where">>, S =/= undefined -> case In(work, full) of
                                                     true -> retry;     %% back in the nest
                                                     false -> on_unloading(In)
                                                 end;
        true -> on_unloading(In)
    end.

on_unloading(In) ->
    case In(unloading, any) of
        true -> ignore;
        false -> reset
    end.

%% The operator takes out by hand what lies at the task's station when no task holds
%% it (the error may have been raised just before a task read its product again): a
%% whole panel in a work fixture, modules on an unloading conveyor, or in the upper
%% robot's gripper; then waits a moment for the station's sensor to be read empty.
hand_out(Task, World, Held) ->
    {Where, Lane, Point} = maps:get(Task, #{work_front => {work, front, panel_in_position},
                                            work_rear => {work, rear, panel_in_position},
                                            unloading_front => {unloading, front, panel_at_exit},
                                            unloading_rear => {unloading, rear, panel_at_exit},
                                            upper => {gripper, none, product_present}}),
    Found = case Where of
                gripper -> maps:get(gripper, World);
                _ -> maps:get(Lane, maps:get(Where, World))
            end,
    case Found of
        {S, Pos} when Pos =/= frame -> take_out(S, Where, Lane, Point, Held);
        S when is_binary(S) -> take_out(S, Where, Lane, Point, Held);
        _ -> ok
    end.

take_out(S, Where, Lane, Point, Held) ->
    case lists:keymember(S, 1, Held) of
        true ->
            ok;
        false ->
            Group = case Where of
                        gripper -> upper_io;
                        _ -> router_cell:group(Where, Lane)
                    end,
            {ok, Ref} = cell_hal:watch(Group, Point, {eq, false}),
            _ = router_sim:take_out(Where, Lane),
            receive {cell_hal_watch, Ref, _} -> ok
            after 5000 -> _ = cell_hal:cancel_watch(Ref), ok
            end,
            case Where of
                unloading ->
                    %% Both sensors of the conveyor.
                    {ok, Ref2} = cell_hal:watch(Group, panel_at_entry, {eq, false}),
                    receive {cell_hal_watch, Ref2, _} -> ok
                    after 5000 -> _ = cell_hal:cancel_watch(Ref2), ok
                    end;
                _ ->
                    ok
            end
    end.

%% A seeded random per kind of error (and per boot of the node).
agent_rand(Kind, N, #{rands := Rands, seed := Seed, boot := Boot} = A) ->
    R0 = case maps:find(Kind, Rands) of
             {ok, R} -> R;
             error -> rand:seed_s(exsss, {Seed, erlang:phash2(Kind), Boot})
         end,
    {X, R1} = rand:uniform_s(N, R0),
    {X, A#{rands := Rands#{Kind => R1}}}.

%%====================================================================
%% Helpers
%%====================================================================

%% The default cell, fast and making mistakes: both lanes, a panel arriving every
%% tenth of a second at most, the physics at 20x, faults on.
write_settings(Root) ->
    Objects = #{machine => #{dual_lane => true},
                router_sim => #{time_scale => 0.05, arrival_ms => 100,
                                product_lost_rate => 0.05, reseat_ms => 20000,
                                jam_rate => 0.01, jam_ms => 100000,
                                %% The books match the machine's own serials: a panel
                                %% taken without its code (NOREAD-...) would not.
                                no_read_rate => 0.0,
                                magazine_low_s => 600, magazine_refill_s => 120},
                router => #{transfer_timeout_ms => 3000, motion_timeout_ms => 5000}},
    cell_testkit:write_settings(Root, Objects).

uniform(N, #{rand := R} = H) ->
    {X, R1} = rand:uniform_s(max(N, 1), R),
    {X, H#{rand := R1}}.

log(#{opts := #{log := Log}}, Fmt, Args) ->
    Log(Fmt, Args).

env_int(Name, Default) ->
    case os:getenv(Name) of
        false -> Default;
        "" -> Default;
        Text -> list_to_integer(Text)
    end.

env_str(Name, Default) ->
    case os:getenv(Name) of
        false -> Default;
        "" -> Default;
        Text -> Text
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% The double holding answered from the machine: the holder whose station has the panel
%% keeps it, the other is reset; neither station: both reset.
held_twice_test_() ->
    World = fun(Work, Loading, Gripper) ->
                    #{upstream => #{front => []}, loading => #{front => Loading},
                      work => #{front => Work}, unloading => #{front => empty},
                      gripper => Gripper}
            end,
    Ask = fun(Task, W, Held) -> at_the_machine(#{local_id => <<"held_twice">>, task => Task},
                                               W, Held) end,
    P = <<"P1">>,
    Both = [{P, loading_front}, {P, work_front}],
    InFixture = World({P, full}, empty, empty),
    AtStop = World(empty, {P, stop}, empty),
    [?_assertEqual(keep, Ask(work_front, InFixture, Both)),
     ?_assertEqual([reset], Ask(loading_front, InFixture, Both)),
     ?_assertEqual(keep, Ask(loading_front, AtStop, Both)),
     ?_assertEqual([reset], Ask(work_front, AtStop, Both)),
     %% Only its frame in the fixture, the modules in the gripper: the upper robot's.
     ?_assertEqual(keep, Ask(upper, World({P, frame}, empty, P), [{P, work_front}, {P, upper}])),
     ?_assertEqual([reset], Ask(work_front, World({P, frame}, empty, P),
                                [{P, work_front}, {P, upper}])),
     %% In the fixture held by the work segment and the routing robot: downstream keeps.
     ?_assertEqual(keep, Ask(lower, InFixture, [{P, work_front}, {P, lower}])),
     ?_assertEqual([reset], Ask(work_front, InFixture, [{P, work_front}, {P, lower}])),
     %% Not in the machine: Reset on each.
     ?_assertEqual([reset], Ask(work_front, World(empty, empty, empty), Both)),
     ?_assertEqual([reset], Ask(loading_front, World(empty, empty, empty), Both))].

%% The loading segment's "where": Ignore while the panel is on the loading segment, or
%% lies whole in the lane's work fixture with no other task holding it; else Reset.
where_test_() ->
    World = fun(Work, Loading) ->
                    #{upstream => #{front => []}, loading => #{front => Loading},
                      work => #{front => Work}, unloading => #{front => empty},
                      gripper => empty}
            end,
    Ask = fun(W, Held) -> at_the_machine(#{local_id => <<"where">>, task => loading_front},
                                         W, Held) end,
    P = <<"P1">>,
    Own = [{P, loading_front}],
    [?_assertEqual([ignore], Ask(World(empty, {P, stop}), Own)),
     ?_assertEqual([ignore], Ask(World({P, full}, empty), Own)),
     ?_assertEqual([reset], Ask(World({P, full}, empty), [{P, work_front} | Own])),
     ?_assertEqual([reset], Ask(World({P, frame}, empty), Own)),
     ?_assertEqual([reset], Ask(World({<<"P2">>, full}, empty), Own)),
     ?_assertEqual([reset], Ask(World(empty, empty), Own))].

-endif.
