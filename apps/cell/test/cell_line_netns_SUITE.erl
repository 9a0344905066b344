%% A line of two cells across a real network boundary: each cell node in a Linux network
%% namespace of its own (cell_netns), joined by a veth link the test cuts and heals while
%% products pass. The upstream cell runs the first segment (`src'), the downstream cell
%% the last one (`sink') and the link between them. The test drives both nodes over
%% their control channels, never over the line's network.
%%
%% Cuts are silent (every packet dropped: the nodes learn of it from their distribution
%% ticks), clean (dropped, and both nodes drop the connection at once) or asymmetric
%% (one direction dropped), made when a transfer is in a chosen phase and healed end by
%% end in both orders; either node is killed during a cut. After each: nothing lost, nothing
%% out twice, nothing stuck (every product fed is out within a deadline), no task
%% crashed on a call that timed out, and a cell that lost its neighbour told the
%% operator within seconds.
%%
%% CELLRT_NETNS_ROUNDS (default 1) repeats the round of phases and cuts (ten cuts a
%% round, two more once: 20 rounds make 202 cuts). A cut in the
%% release phase (after the link received `release', before `owned' reached upstream)
%% is settled by the link's fence after the heal: upstream's copy is not sent out a
%% second time, whatever its operator answers.
%%
%% Needs root (namespaces, tc); without it the suite fails, saying what is missing.
-module(cell_line_netns_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, groups/0, suite/0, init_per_suite/1, end_per_suite/1, init_per_group/2,
         end_per_group/2, init_per_testcase/2, end_per_testcase/2]).
-export([silent_neighbour_told/1, partitions_in_every_phase/1,
         upstream_killed_during_partition/1, downstream_killed_during_partition/1,
         release_phase_partition/1, upstream_killed_in_release_partition_answered_where/1,
         link_restarted_during_partition/1]).

%% A product moves for this long on each segment: a window in each phase to cut in.
-define(DELAY, 150).
%% Products flow, are cut, healed and out again within this.
-define(FLOW_MS, 60000).
%% A cell tells its operator its neighbour is out of reach within this (the line's
%% distribution ticks: at most 1.25 net_ticktime, see cell_peers).
-define(TOLD_MS, 10000).

%% A round of cuts takes about a minute on a busy machine: the timetrap grows with them.
suite() ->
    [{timetrap, {minutes, 10 + rounds()}}].

rounds() ->
    list_to_integer(os:getenv("CELLRT_NETNS_ROUNDS", "1")).

all() ->
    [{group, tcp}, {group, tls}].

%% Every case over the plain distribution; the cuts in every phase again over TLS, as
%% the cells of a line on several PCs speak it (README).
groups() ->
    [{tcp, [], [silent_neighbour_told, partitions_in_every_phase,
                upstream_killed_during_partition, downstream_killed_during_partition,
                release_phase_partition, upstream_killed_in_release_partition_answered_where,
                link_restarted_during_partition]},
     {tls, [], [partitions_in_every_phase]}].

init_per_group(tls, Config) ->
    [{tls, filename:join(?config(priv_dir, Config), "tls")} | Config];
init_per_group(_Group, Config) ->
    Config.

end_per_group(_Group, _Config) ->
    ok.

%% The suite needs root and iproute2 (scripts/setup test installs it): without them it
%% fails, saying what is missing, rather than passing unrun.
init_per_suite(Config) ->
    ok = cell_netns:required(),
    Config.

end_per_suite(_Config) ->
    ok.

init_per_testcase(Case, Config) ->
    Net0 = cell_netns:create([up, down]),
    Holder = try
        Net1 = case ?config(tls, Config) of
                   undefined -> Net0;
                   Dir -> cell_netns:tls(Net0, filename:join(Dir, atom_to_list(Case)))
               end,
        Net = cell_netns:start_node(cell_netns:start_node(Net1, up, []), down, []),
        put_net(holder(), Net)
    catch
        C:R:St ->
            ok = cell_netns:destroy(Net0),
            erlang:raise(C, R, St)
    end,
    %% A folder of the group's own: a link's fence outlives a case.
    Group = case ?config(tls, Config) of undefined -> "tcp"; _ -> "tls" end,
    Base = filename:join([?config(priv_dir, Config), Group, atom_to_list(Case)]),
    [{net, Holder}, {base, Base}, {ref, make_ref()} | Config].

end_per_testcase(_Case, Config) ->
    Holder = ?config(net, Config),
    Net = get_net(Holder),
    ok = cell_netns:destroy(Net),
    exit(Holder, kill),
    ok.

%% -------------------------------------------------------------------------------------

%% The downstream cell goes silent while a product moves between the cells (upstream
%% calls the link across the cut): each cell tells its operator within seconds, no task
%% crashes, and after the heal the line goes on with nothing lost or out twice.
silent_neighbour_told(Config) ->
    start_cells(Config),
    Fed = run_cycle(Config, #{phase => commit, cut => silent, heal => [up, down]}, 0),
    finish(Config, Fed).

%% A cut in each phase of a transfer (offer, commit, release, owned, complete), silent,
%% clean and asymmetric, healed in both orders. In the release phase the cut that
%% matters is the one that keeps `owned' from upstream: downstream's packets dropped.
partitions_in_every_phase(Config) ->
    start_cells(Config),
    Cycles = [#{phase => P, cut => C, heal => H}
              || _ <- lists:seq(1, rounds()), P <- [offer, commit, release, owned, complete],
                 {C, H} <- [{phase_cut(P, silent), [up, down]}, {clean, [down, up]}]]
        ++ [#{phase => owned, cut => {silent, up}, heal => [up, down]},
            #{phase => commit, cut => {silent, up}, heal => [down, up]}],
    Fed = lists:foldl(fun(C, N) -> run_cycle(Config, C, N) end, 0, Cycles),
    ct:pal("~p cuts, ~p products", [length(Cycles), Fed]),
    finish(Config, Fed).

%% The upstream node is killed during a silent cut while downstream has committed to
%% its product; it comes back on its folder after the heal, the operator answers, and
%% every product is out once.
upstream_killed_during_partition(Config) ->
    killed_during_partition(Config, up, commit).

%% The downstream node (the link's) is killed during a silent cut while it moves in a
%% product it owns on disk; it comes back on its folder after the heal.
downstream_killed_during_partition(Config) ->
    killed_during_partition(Config, down, owned).

killed_during_partition(Config, Killed, Phase) ->
    start_cells(Config),
    N0 = run_cycle(Config, #{phase => commit, cut => clean, heal => [up, down]}, 0),
    {Who, Spec} = watch(Phase),
    %% One product: a second would wait in the feed, which is the test's, in the
    %% memory of the upstream node.
    Since = call(Config, Who, cell_line_recorder, mark, []),
    Fed = feed(Config, N0, 1),
    {ok, _} = await(Config, Who, Spec, Since),
    [Other] = [up, down] -- [Killed],
    Told = call(Config, Other, cell_line_recorder, mark, []),
    ok = cut(Config, silent),
    %% The products out so far, counted by the downstream node's recorder, which a
    %% kill of that node forgets.
    Before = call(Config, down, cell_line_recorder, outs, []),
    Net = cell_netns:kill_node(net(Config), Killed),
    _ = put_net(?config(net, Config), Net),
    {ok, _} = await_told(Config, Other, Told),
    ok = cell_netns:heal(Net, silent, [down, up]),
    _ = put_net(?config(net, Config), cell_netns:start_node(Net, Killed, [])),
    start_cell(Config, Killed),
    ok = call(Config, Killed, cell_controller, start, []),
    Earlier = case Killed of down -> Before; up -> [] end,
    await_outs(Config, Fed - length(Earlier)),
    finish(Config, Fed, Earlier).

%% Upstream's release reaches the link, and the link's `owned' and answer do not come
%% back (the downstream node's packets are dropped). Upstream's copy waits to be
%% settled with the link (its operator, who answers Ignore to whatever is asked, is not
%% asked to place it); after the heal the link's fence (it released that generation,
%% downstream owns it) has upstream drop the copy, and refuses an offer of it: the
%% product is out once, and no task crashed.
release_phase_partition(Config) ->
    start_cells(Config),
    Fed = run_cycle(Config, #{phase => release, cut => {silent, down}, heal => [down, up]}, 0),
    finish(Config, Fed).

%% The upstream node is killed during a release-phase cut, once its task holds its copy
%% again (marked in transit: it saw the link's node go), and started again on its folder
%% while the cut lasts: the link cannot be asked, so its operator is. This operator
%% answers from where the product is: sent out or held by the downstream cell, RESET
%% (not here); else IGNORE. Nothing is out twice, nothing lost, no task crashed.
upstream_killed_in_release_partition_answered_where(Config) ->
    start_cells(Config),
    Since = call(Config, up, cell_line_recorder, mark, []),
    Fed = feed(Config, 0, 1),
    S = serial(1),
    {ok, _} = await(Config, up, {phase, src, leaving}, Since),
    Cut = {silent, down},
    ok = cut(Config, Cut),
    {ok, _} = await(Config, up, {in_transit, src}, Since),
    Net = cell_netns:kill_node(net(Config), up),
    _ = put_net(?config(net, Config), cell_netns:start_node(Net, up, [])),
    start_cell(Config, up, #{answers => manual}),
    ok = call(Config, up, cell_controller, start, []),
    {ok, {alarm, #{id := Id, description := Text}}} =
        await(Config, up, {alarm, <<"in_transit">>}, 0),
    %% The question says the other cell may hold or have shipped the product.
    ?assertNotEqual(nomatch, binary:match(Text, <<"may already have sent it on">>)),
    Answer = case lists:member(S, call(Config, down, cell_line_recorder, outs, []))
                 orelse held(Config, down, sink) =:= S of
                 true -> reset;
                 false -> ignore
             end,
    ok = call(Config, up, cell_alarms, answer, [Id, Answer, <<"suite">>]),
    ok = cell_netns:heal(net(Config), Cut, [down, up]),
    await_outs(Config, Fed),
    [?assertEqual([], crashes(Config, C), {task_crashed, C, timeline(Config)})
     || C <- [up, down]],
    ct:pal("upstream asked after its restart, answered ~p", [Answer]),
    finish(Config, Fed).

%% The link (on the downstream node) is stopped and started again by its supervisor
%% during a cut, in the release phase (its fence says it released the product and
%% downstream owns it: the new link reads that from its file) and in the commit phase
%% (the transfer ends with the old link: before release the product is upstream's).
link_restarted_during_partition(Config) ->
    start_cells(Config),
    Cycles = [#{phase => release, cut => {silent, down}, heal => [down, up],
                during => fun restart_link/1},
              #{phase => commit, cut => silent, heal => [up, down],
                during => fun restart_link/1}],
    Fed = lists:foldl(fun(C, N) -> run_cycle(Config, C, N) end, 0, Cycles),
    finish(Config, Fed).

restart_link(Config) ->
    ok = call(Config, down, supervisor, terminate_child, [cell_handshake_sup, x1]),
    {ok, _} = call(Config, down, supervisor, restart_child, [cell_handshake_sup, x1]),
    ok.

held(Config, Which, Task) ->
    case call(Config, Which, cell_task_proc, info, [Task]) of
        #{product := #{serial := S}} -> S;
        _ -> undefined
    end.

%% -------------------------------------------------------------------------------------

%% Feeds two products, cuts when the transfer of the first reaches `phase', waits until
%% both cells told their operators (a cut the nodes see), heals in the order given and
%% waits until everything fed so far is out (`during', if given, is done in the cut,
%% before the heal). The number of products fed so far.
run_cycle(Config, #{phase := Phase, cut := Cut, heal := Order} = Cycle, N0) ->
    {Who, Spec} = watch(Phase),
    Since = call(Config, Who, cell_line_recorder, mark, []),
    %% An offer stands only while downstream does not take it: its cell is paused.
    _ = Phase =:= offer andalso call(Config, down, cell_controller, pause, []),
    N = feed(Config, N0, 2),
    {ok, _} = await(Config, Who, Spec, Since),
    LinkPhase = last_link_phase(Config),
    At = call(Config, down, cell_line_recorder, now_ms, []),
    Marks = [{C, call(Config, C, cell_line_recorder, mark, [])} || C <- told_by(Cut)],
    ok = cut(Config, Cut),
    Told = [{C, await_told(Config, C, Since1)} || {C, Since1} <- Marks],
    [?assertMatch({C, {ok, _}}, {C, T}, {not_told, Phase, Cut, timeline(Config)})
     || {C, T} <- Told],
    ok = (maps:get(during, Cycle, fun(_) -> ok end))(Config),
    ok = cell_netns:heal(net(Config), Cut, Order),
    _ = Phase =:= offer andalso call(Config, down, cell_controller, start, []),
    await_outs(Config, N),
    Outs = call(Config, down, cell_line_recorder, outs, []),
    ?assertEqual([], Outs -- lists:usort(Outs), {out_twice, Phase, Cut, LinkPhase}),
    [?assertEqual([], crashes(Config, C), {task_crashed, Phase, Cut, timeline(Config)})
     || C <- [up, down]],
    ct:pal("cut ~p in ~p (link ~p), told in ~p ms", [Cut, Phase, LinkPhase,
                                                       told_after(Config, At)]),
    N.

%% What marks the moment to cut: offer (the link holds upstream's offer, downstream's
%% cell paused so it cannot commit), commit (downstream took it, upstream moving it
%% out), release (upstream about to call release), owned (downstream owns it, moving
%% in), complete (downstream has it, upstream about to hear `completed').
watch(offer) -> {down, {link_phase, offered}};
watch(commit) -> {down, {phase, sink, moving_in}};
watch(release) -> {up, {phase, src, leaving}};
watch(owned) -> {down, {phase, sink, arriving}};
watch(complete) -> {down, {phase, sink, full}}.

%% The cells that see a cut: the side whose packets are dropped hears nothing from its
%% peer once the peer gives up the connection, so both do.
told_by(_Cut) -> [up, down].

%% The silent cut of a phase: in the release phase the one that keeps `owned' from
%% upstream (downstream's packets dropped), else both ways.
phase_cut(release, silent) -> {silent, down};
phase_cut(_Phase, Cut) -> Cut.

cut(Config, Cut) ->
    cell_netns:cut(net(Config), Cut, [up, down]).

%% -------------------------------------------------------------------------------------

start_cells(Config) ->
    start_cell(Config, up),
    start_cell(Config, down),
    [ok = call(Config, C, cell_controller, start, []) || C <- [up, down]].

%% Each node runs a cell of one segment; the link between them runs downstream.
start_cell(Config, Which) ->
    start_cell(Config, Which, #{}).

%% `Opts': the recorder's (who answers the cell's questions).
start_cell(Config, Which, Opts) ->
    Net = net(Config),
    Root = filename:join(?config(base, Config), atom_to_list(Which)),
    {ok, Recorder} = call(Config, Which, cell_line_recorder, start, [Opts]),
    Spec = cell_line_nodes:spec(Which, cell_netns:node_of(Net, up),
                                cell_netns:node_of(Net, down),
                                #{feed => line_feed, out => line_out,
                                  ref => ?config(ref, Config), notify => Recorder,
                                  delay => ?DELAY}),
    ok = cell_line_nodes:boot(fun(M, F, A) -> call(Config, Which, M, F, A) end, Root, Spec),
    ok = call(Config, Which, cell_line_recorder, subscribe, []).

%% Products N0+1 .. N0+K into the feed; the number fed so far.
feed(Config, N0, K) ->
    Serials = [serial(I) || I <- lists:seq(N0 + 1, N0 + K)],
    ok = call(Config, up, cell_line_recorder, feed, [Serials, src, ?config(ref, Config)]),
    N0 + K.

serial(I) ->
    <<"L-", (integer_to_binary(I))/binary>>.

await(Config, Who, Spec, Since) ->
    case await_on(Config, Who, Spec, Since, ?FLOW_MS) of
        {ok, E} -> {ok, E};
        timeout -> ct:fail({not_seen, Who, Spec, timeline(Config)})
    end.

%% The cell's alarm that its neighbour is out of reach.
await_told(Config, Which, Since) ->
    await_on(Config, Which, {alarm, <<"peer">>}, Since, ?TOLD_MS).

told_after(Config, At) ->
    hd([T - At || {T, {alarm, #{local_id := <<"peer", _/binary>>}}}
                      <- call(Config, down, cell_line_recorder, timeline, []), T >= At]).

%% Every product fed so far is out (and the test fails, showing what each cell saw,
%% if not within the deadline: stuck).
await_outs(Config, N) ->
    case await_on(Config, down, {outs, N}, 0, ?FLOW_MS) of
        {ok, _} -> ok;
        timeout -> ct:fail({stuck, N, timeline(Config)})
    end.

await_on(Config, Which, Spec, Since, Timeout) ->
    cell_netns:call(net(Config), Which, cell_line_recorder, await, [Spec, Since, Timeout],
                    Timeout + 10000).

last_link_phase(Config) ->
    case [P || {link_phase, _, P, _} <- call(Config, down, cell_line_recorder, events, [])] of
        [] -> idle;
        Ps -> lists:last(Ps)
    end.

crashes(Config, Which) ->
    [E || {crashed, E} <- call(Config, Which, cell_line_recorder, events, [])].

timeline(Config) ->
    [{C, catch call(Config, C, cell_line_recorder, timeline, [])} || C <- [up, down]].

%% Every product fed is out exactly once and no task holds one any more, in memory or
%% on disk.
finish(Config, Fed) ->
    finish(Config, Fed, []).

%% `Earlier': the products out on a downstream node killed since.
finish(Config, Fed, Earlier) ->
    %% In the tls group the cells spoke TLS to each other.
    _ = ?config(tls, Config) =/= undefined andalso
        ?assertEqual([tls], lists:usort([element(4, proplists:get_value(address, I))
                                         || C <- [up, down],
                                            {ok, Is} <- [call(Config, C, net_kernel,
                                                              nodes_info, [])],
                                            {_, I} <- Is])),
    Outs = Earlier ++ call(Config, down, cell_line_recorder, outs, []),
    Serials = [serial(I) || I <- lists:seq(1, Fed)],
    ?assertEqual([], Outs -- lists:usort(Outs), out_twice),
    ?assertEqual(lists:sort(Serials), lists:sort(Outs), lost),
    [?assertMatch(#{}, call(Config, C, cell_task_proc, info, [T]))
     || {C, T} <- [{up, src}, {down, sink}]],
    Held = [S || {C, T} <- [{up, src}, {down, sink}],
                 #{product := #{serial := S}} <- [call(Config, C, cell_task_proc, info, [T])]],
    ?assertEqual([], Held, still_held),
    Stored = lists:append(
               [[S || F <- filelib:wildcard(filename:join([?config(base, Config), C, "Data",
                                                          "*.product"])),
                      {ok, #{product := #{serial := S}}} <- [cell_product:load(F)]]
                || C <- ["up", "down"]]),
    ?assertEqual([], Stored, still_on_disk).

%% -------------------------------------------------------------------------------------

call(Config, Which, M, F, A) ->
    cell_netns:call(net(Config), Which, M, F, A).

net(Config) ->
    get_net(?config(net, Config)).

%% The net changes as nodes are killed and started again; a process of the test case's
%% own keeps the latest, for end_per_testcase to remove whatever the case left.
holder() ->
    spawn(fun() -> hold(undefined) end).

hold(Net) ->
    receive
        {put, Net1, From} -> From ! {self(), ok}, hold(Net1);
        {get, From} -> From ! {self(), Net}, hold(Net)
    end.

put_net(Holder, Net) ->
    Holder ! {put, Net, self()},
    receive {Holder, ok} -> Holder end.

get_net(Holder) ->
    Holder ! {get, self()},
    receive {Holder, Net} -> Net end.
