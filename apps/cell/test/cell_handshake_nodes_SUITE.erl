%% Handshakes across nodes: a line of cells, one BEAM node each, the upstream segment
%% on one node and the downstream segment on another, over Erlang distribution. The
%% link runs on the downstream node. Products pass; the downstream node is killed in
%% the middle of a transfer and started again on the same folder: every product is out
%% or owned exactly once, on disk and in memory, across both nodes.
%%
%% Network cuts (the distribution between the two cells cut by a wrong cookie and a
%% disconnect, healed by the right cookie and a connect) in the release phase: the link
%% has let the product go and downstream owns it on disk, but `owned' has not reached
%% upstream when the cut comes. Downstream sends the product out during the cut; after
%% the heal the product is not sent out again, whether upstream stays up (its copy is
%% settled with the link), or its node is killed and started again during the cut and
%% the operator answers its question wrongly ("it is here") or rightly.
-module(cell_handshake_nodes_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([products_pass_between_nodes/1, downstream_node_killed_mid_transfer/1,
         release_cut_settled_after_heal/1, upstream_killed_in_release_cut_operator_ignores/1,
         upstream_killed_in_release_cut_operator_resets/1]).

-define(TIMEOUT, 20000).

all() ->
    [products_pass_between_nodes, downstream_node_killed_mid_transfer,
     release_cut_settled_after_heal, upstream_killed_in_release_cut_operator_ignores,
     upstream_killed_in_release_cut_operator_resets].

init_per_suite(Config) ->
    %% The test node joins the distribution so it can start peers and watch them, as a
    %% hidden node: it is not one of the line's cells. A visible one would be part of
    %% global's cluster, and when the downstream node comes back global may cut the
    %% test node off from it to keep the cluster whole, losing a product's `line_out'
    %% message on the way.
    _ = os:cmd("epmd -daemon"),
    Started = case node() of
                  nonode@nohost ->
                      %% The peers are @localhost: the same host name keeps global's
                      %% view of the cluster in one piece.
                      Name = list_to_atom("hs_nodes_" ++ os:getpid() ++ "@localhost"),
                      %% The cells tick at a line's pace (cell_peers): a node that
                      %% ticked slower would be dropped by them whenever it is idle.
                      {ok, _} = net_kernel:start(Name, #{name_domain => shortnames,
                                                         hidden => true, net_ticktime => 5}),
                      true;
                  _ ->
                      false
              end,
    [{started_dist, Started} | Config].

end_per_suite(Config) ->
    case ?config(started_dist, Config) of
        true -> ok = net_kernel:stop();
        false -> ok
    end.

init_per_testcase(Case, Config) ->
    Base = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Delay = case Case of downstream_node_killed_mid_transfer -> 400; _ -> 0 end,
    %% The first product to reach the downstream segment stops there in the middle of
    %% its move, so the node is killed mid-transfer however busy the machine is.
    Hold = Case =:= downstream_node_killed_mid_transfer,
    Up = start_peer(up, Config),
    Down = start_peer(down, Config),
    Cells = #{up => #{node => Up, root => filename:join(Base, "up")},
              down => #{node => Down, root => filename:join(Base, "down")}},
    [{cells, Cells}, {delay, Delay}, {hold, Hold}, {ref, make_ref()} | Config].

end_per_testcase(_Case, Config) ->
    [catch peer:stop(Peer) || {_, #{peer := Peer}} <- maps:to_list(peers(Config))],
    ok.

%% -------------------------------------------------------------------------------------

products_pass_between_nodes(Config) ->
    start_cells(Config),
    Serials = feed(Config, 15),
    [ok = start(Config, C) || C <- [up, down]],
    Out = await_outs(15),
    ?assertEqual(lists:sort(Serials), lists:sort(Out)),
    [ok = peer_call(Config, C, cell_controller, stop, []) || C <- [up, down]],
    check_conservation(Config, Serials).

%% The downstream node dies while a product moves to it (it owns it on disk, marked in
%% transit: the segment holds it there until the kill). Upstream sees the node go and
%% keeps going; the node comes back on its folder, the operator is asked where the
%% product is, and the line completes.
downstream_node_killed_mid_transfer(Config) ->
    start_cells(Config),
    Serials = feed(Config, 3),
    [ok = start(Config, C) || C <- [up, down]],
    await_phase(sink, arriving),
    #{node := Down, peer := Peer} = maps:get(down, peers(Config)),
    OsPid = peer_call(Config, down, os, getpid, []),
    erlang:monitor_node(Down, true),
    _ = os:cmd("kill -9 " ++ OsPid),
    receive {nodedown, Down} -> ok after ?TIMEOUT -> ct:fail(node_not_down) end,
    catch peer:stop(Peer),
    %% The downstream cell again, on the same folder and under the same name.
    Down2 = start_peer(down, Config),
    Cells2 = maps:update_with(down, fun(C) -> C#{node => Down2} end, ?config(cells, Config)),
    Config2 = lists:keystore(hold, 1, lists:keystore(cells, 1, Config, {cells, Cells2}),
                             {hold, false}),
    start_cell(Config2, down),
    ok = start(Config2, down),
    ok = start(Config2, up),
    Out = answer_until_out(Config2, Serials),
    ?assertEqual(lists:sort(Serials), lists:sort(Out)),
    [ok = peer_call(Config2, C, cell_controller, stop, []) || C <- [up, down]],
    check_conservation(Config2, Serials).

%% The cut comes after the link let the product go, before downstream's `owned'
%% reached it and upstream. Downstream sends it out during the cut; upstream holds its
%% copy until the link says what happened. An operator answering "it is here" to
%% whatever upstream asks does not make it leave twice.
release_cut_settled_after_heal(Config) ->
    [S1] = cut_in_release_phase(Config),
    heal(Config),
    [S2] = feed(Config, 1),
    fed(Config),
    %% S1 went out once, during the cut.
    Out = outs_until(Config, S2, ignore),
    ?assertEqual([S2], Out, {sent_out_again, S1}),
    [ok = peer_call(Config, C, cell_controller, stop, []) || C <- [up, down]],
    check_conservation(Config, [S1, S2]).

%% As above, and the upstream node is killed during the cut and started again on its
%% folder, still cut off: the link cannot be asked, so the operator is. One who says
%% "it is here" (IGNORE) does not make the product leave twice: the link refuses the
%% copy after the heal.
upstream_killed_in_release_cut_operator_ignores(Config) ->
    upstream_killed_in_release_cut(Config, ignore).

%% One who answers from where the product is (sent out: not here, RESET).
upstream_killed_in_release_cut_operator_resets(Config) ->
    upstream_killed_in_release_cut(Config, reset).

upstream_killed_in_release_cut(Config, Answer) ->
    [S1] = cut_in_release_phase(Config),
    #{node := Up, peer := Peer} = maps:get(up, peers(Config)),
    OsPid = peer_call(Config, up, os, getpid, []),
    erlang:monitor_node(Up, true),
    _ = os:cmd("kill -9 " ++ OsPid),
    receive {nodedown, Up} -> ok after ?TIMEOUT -> ct:fail(node_not_down) end,
    catch peer:stop(Peer),
    Up2 = start_peer(up, Config),
    Cells2 = maps:update_with(up, fun(C) -> C#{node => Up2} end, ?config(cells, Config)),
    Config2 = lists:keystore(cells, 1, Config, {cells, Cells2}),
    %% Still cut off from the downstream cell.
    cut(Config2),
    start_cell(Config2, up),
    ok = peer_call(Config2, up, cell_events, subscribe, [self(), [alarm_raised]]),
    ok = start(Config2, up),
    %% The question of the product that was leaving, asked before the heal.
    Alarm = await_alarm(up, <<"in_transit">>),
    _ = peer_call(Config2, up, cell_alarms, answer, [maps:get(id, Alarm), Answer, <<"suite">>]),
    heal(Config2),
    [S2] = feed(Config2, 1),
    fed(Config2),
    Out = outs_until(Config2, S2, Answer),
    ?assertEqual([S2], Out, {sent_out_again, S1}),
    [ok = peer_call(Config2, C, cell_controller, stop, []) || C <- [up, down]],
    check_conservation(Config2, [S1, S2]).

%% One product through a cut in the release phase, as it happens on a busy line: the
%% link has let the product go and answered upstream; downstream is held just before
%% it takes the product in (so its `owned' comes after the cut); the cut; the link
%% sees upstream's node go; then downstream goes on, owns the product and sends it
%% out during the cut (its own questions, if any, answered: the product is there).
%% Returns once that is done and upstream holds its copy again, marked in transit.
cut_in_release_phase(Config) ->
    start_cells(Config),
    Serials = feed(Config, 1),
    Ref = peer_call(Config, down, cell_handshake_nodes_SUITE_keeper, hold_released,
                    [sink, self()]),
    ok = peer_call(Config, up, cell_events, subscribe, [self(), [product_saved]]),
    ok = peer_call(Config, down, cell_events, subscribe, [self(), [link_phase, alarm_raised]]),
    [ok = start(Config, C) || C <- [up, down]],
    Sink = receive {released_at_task, P, Ref} -> P after ?TIMEOUT -> ct:fail(not_released) end,
    await_phase(src, released),
    await_link_phase(released),
    cut(Config),
    await_link_phase(idle),
    Sink ! {go, Ref},
    [S] = Serials,
    ok = out_during_cut(Config, S, false, false),
    Serials.

await_link_phase(Phase) ->
    receive
        {cell_event, #{type := link_phase, link := x1, phase := Phase}} -> ok
    after ?TIMEOUT ->
        ct:fail({link_phase_not_reached, Phase})
    end.

out_during_cut(_Config, _S, true, true) ->
    ok;
out_during_cut(Config, S, Out, Held) ->
    receive
        {line_out, sink, S} ->
            out_during_cut(Config, S, true, Held);
        {cell_event, #{type := product_saved, task := src, item := S, in_transit := true}} ->
            out_during_cut(Config, S, Out, true);
        {cell_event, #{type := alarm_raised, alarm := #{task := sink, kind := error,
                                                       id := Id, solutions := Sols}}} ->
            true = lists:member(ignore, Sols),
            _ = peer_call(Config, down, cell_alarms, answer, [Id, ignore, <<"suite">>]),
            out_during_cut(Config, S, Out, Held)
    after ?TIMEOUT ->
        ct:fail({cut_not_settled, S, #{out => Out, upstream_holds => Held}})
    end.

%% The distribution between the two cells cut: the upstream node uses a wrong cookie
%% for the downstream one (both ways: it checks a connection from it with that cookie
%% too), and the connection is dropped.
cut(Config) ->
    #{node := Down} = maps:get(down, ?config(cells, Config)),
    true = peer_call(Config, up, erlang, set_cookie, [Down, line_fence_cut]),
    _ = peer_call(Config, up, erlang, disconnect_node, [Down]),
    ok.

heal(Config) ->
    #{node := Down} = maps:get(down, ?config(cells, Config)),
    Cookie = peer_call(Config, up, erlang, get_cookie, []),
    true = peer_call(Config, up, erlang, set_cookie, [Down, Cookie]),
    %% The cells' own reconnecting (cell_peers) may be trying at this moment from
    %% either side, and an attempt that meets it may fail: the up node connects, or
    %% waits for the connection either side's attempt makes.
    true = peer_call(Config, up, cell_handshake_nodes_SUITE_keeper, connected, [Down, 15000]),
    ok.

%% The first segment waits for `{Ref, fed}' when its feed ran dry.
fed(Config) ->
    Src = peer_call(Config, up, cell_task_proc, whereis, [src]),
    Src ! {?config(ref, Config), fed},
    ok.

await_alarm(Which, Id) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := #{local_id := Id} = A}} ->
            A
    after ?TIMEOUT ->
        ct:fail({no_alarm, Which, Id})
    end.

%% Every product sent out, in order, until `Last' (the line keeps the order, so a
%% product sent out a second time comes before it). Errors raised on either cell
%% meanwhile are answered with `Answer' where it is offered.
outs_until(Config, Last, Answer) ->
    [ok = peer_call(Config, C, cell_events, subscribe, [self(), [alarm_raised]]) || C <- [up, down]],
    %% Those raised before.
    [self() ! {cell_event, #{type => alarm_raised, alarm => A}}
     || C <- [up, down], A <- peer_call(Config, C, cell_alarms, list, [])],
    outs_until(Config, Last, Answer, []).

outs_until(Config, Last, Answer, Acc) ->
    receive
        {line_out, sink, Last} ->
            lists:reverse([Last | Acc]);
        {line_out, sink, S} ->
            outs_until(Config, Last, Answer, [S | Acc]);
        {cell_event, #{type := alarm_raised, alarm := #{task := Task, kind := error,
                                                       id := Id, solutions := Sols}}} ->
            Which = case Task of src -> up; _ -> down end,
            Solution = case lists:member(Answer, Sols) of true -> Answer; false -> hd(Sols) end,
            _ = peer_call(Config, Which, cell_alarms, answer, [Id, Solution, <<"suite">>]),
            outs_until(Config, Last, Answer, Acc)
    after ?TIMEOUT ->
        ct:fail({not_out, Last, lists:reverse(Acc)})
    end.

%% -------------------------------------------------------------------------------------

start_peer(Which, _Config) ->
    Name = list_to_atom("cell_" ++ atom_to_list(Which) ++ "_" ++ os:getpid()),
    Paths = [P || P <- code:get_path(), string:find(P, "_build") =/= nomatch
                                             orelse string:find(P, "_debdeps") =/= nomatch],
    {ok, Peer, Node} = peer:start_link(#{name => Name, host => "localhost",
                                         args => cell_netns:line_vm_args()
                                             ++ lists:append([["-pa", P] || P <- Paths]),
                                         connection => standard_io}),
    true = erlang:register(list_to_atom("peer_" ++ atom_to_list(Which)), Peer),
    Node.

peers(Config) ->
    maps:map(fun(Which, C) ->
                     C#{peer => whereis(list_to_atom("peer_" ++ atom_to_list(Which)))}
             end, ?config(cells, Config)).

peer_call(Config, Which, M, F, A) ->
    #{peer := Peer} = maps:get(Which, peers(Config)),
    peer:call(Peer, M, F, A, ?TIMEOUT).

start_cells(Config) ->
    start_cell(Config, up),
    start_cell(Config, down).

%% Each node runs a cell of one segment; the link between them runs downstream.
start_cell(Config, Which) ->
    #{node := UpNode} = maps:get(up, ?config(cells, Config)),
    #{node := DownNode} = maps:get(down, ?config(cells, Config)),
    #{root := Root} = maps:get(Which, ?config(cells, Config)),
    Spec = cell_line_nodes:spec(Which, UpNode, DownNode,
                                #{feed => line_feed, out => line_out,
                                  ref => ?config(ref, Config), notify => self(),
                                  delay => ?config(delay, Config),
                                  hold => ?config(hold, Config)}),
    %% The feed and out tables live on the node of the task that uses them, owned by a
    %% process that stays.
    ok = peer_call(Config, Which, cell_handshake_nodes_SUITE_keeper, start, []),
    cell_line_nodes:boot(fun(M, F, A) -> peer_call(Config, Which, M, F, A) end, Root, Spec).

start(Config, Which) ->
    peer_call(Config, Which, cell_controller, start, []).

feed(Config, N) ->
    Base = erlang:unique_integer([positive]) * 100,
    Items = [{Base + I, <<"X-", (integer_to_binary(Base + I))/binary>>} || I <- lists:seq(1, N)],
    true = peer_call(Config, up, ets, insert, [line_feed, Items]),
    [S || {_, S} <- Items].

await_phase(Task, Phase) ->
    receive
        {line_phase, Task, Phase} -> ok
    after ?TIMEOUT ->
        ct:fail({phase_not_reached, Task, Phase})
    end.

await_outs(N) ->
    [receive {line_out, sink, S} -> S after ?TIMEOUT -> ct:fail({outs_missing, N}) end
     || _ <- lists:seq(1, N)].

%% Answers, on both nodes, what the cells ask (a restarted task, a product in transit:
%% it is where the cell says) until every product is out.
answer_until_out(Config, Serials) ->
    [ok = peer_call(Config, C, cell_events, subscribe, [self(), [alarm_raised]]) || C <- [up, down]],
    [answer(Config, C, A) || C <- [up, down], A <- peer_call(Config, C, cell_alarms, list, [])],
    answer_loop(Config, length(Serials), []).

answer_loop(_Config, 0, Acc) ->
    lists:reverse(Acc);
answer_loop(Config, N, Acc) ->
    receive
        {line_out, sink, S} ->
            answer_loop(Config, N - 1, [S | Acc]);
        {cell_event, #{type := alarm_raised, alarm := #{task := Task} = A}} ->
            answer(Config, case Task of src -> up; _ -> down end, A),
            answer_loop(Config, N, Acc)
    after ?TIMEOUT ->
        ct:fail({outs_missing, N})
    end.

answer(Config, Which, #{id := Id, kind := error, solutions := Sols}) ->
    Solution = case lists:member(ignore, Sols) of true -> ignore; false -> hd(Sols) end,
    _ = peer_call(Config, Which, cell_alarms, answer, [Id, Solution, <<"suite">>]),
    ok;
answer(_Config, _Which, _Alarm) ->
    ok.

%% Every product fed in is out, waiting in the feed, or owned by exactly one task of
%% the line: on disk (the highest generation, across both nodes' folders) and in memory.
check_conservation(Config, Serials) ->
    %% Each task done with the step it was in (the last product sent out is cleared
    %% from memory and from its file when that step returns), so disk and memory are
    %% read at the same point of its work.
    [ok = peer_call(Config, C, cell_task_proc, sync, [T]) || {C, T} <- [{up, src}, {down, sink}]],
    Cells = ?config(cells, Config),
    Stored = lists:append(
               [[{S, G} || F <- filelib:wildcard(filename:join([Root, "Data", "*.product"])),
                           {ok, #{product := #{serial := S}, gen := G}} <- [cell_product:load(F)]]
                || {_, #{root := Root}} <- maps:to_list(Cells)]),
    Owners = lists:usort([S || {S, _} <- Stored]),
    [begin
         Gens = [G || {S1, G} <- Stored, S1 =:= S],
         ?assertEqual(1, length([G || G <- Gens, G =:= lists:max(Gens)]), {two_owners, S})
     end || S <- Owners],
    InMemory = lists:sort(
                 [S || {C, T} <- [{up, src}, {down, sink}],
                       #{product := #{serial := S}} <- [peer_call(Config, C, cell_task_proc, info, [T])]]),
    ?assertEqual(lists:usort(InMemory), InMemory, duplicate_in_memory),
    ?assertEqual(InMemory, Owners, memory_and_disk_differ),
    Out = [S || {S, _} <- peer_call(Config, down, ets, tab2list, [line_out])],
    Waiting = [S || {_, S} <- peer_call(Config, up, ets, tab2list, [line_feed])],
    ?assertEqual(lists:sort(Serials), lists:sort(Out ++ Owners ++ Waiting), lost_or_extra).
