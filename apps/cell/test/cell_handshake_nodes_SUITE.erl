%% Handshakes across nodes: a line of cells, one BEAM node each, the upstream segment
%% on one node and the downstream segment on another, over Erlang distribution. The
%% link runs on the downstream node. Products pass; the downstream node is killed in
%% the middle of a transfer and started again on the same folder: every product is out
%% or owned exactly once, on disk and in memory, across both nodes.
-module(cell_handshake_nodes_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([products_pass_between_nodes/1, downstream_node_killed_mid_transfer/1]).

-define(TIMEOUT, 20000).

all() ->
    [products_pass_between_nodes, downstream_node_killed_mid_transfer].

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
    Delay = case Case of products_pass_between_nodes -> 0; _ -> 400 end,
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

%% -------------------------------------------------------------------------------------

start_peer(Which, _Config) ->
    Name = list_to_atom("cell_" ++ atom_to_list(Which) ++ "_" ++ os:getpid()),
    Paths = [P || P <- code:get_path(), string:find(P, "_build") =/= nomatch
                                             orelse string:find(P, "_debdeps") =/= nomatch],
    {ok, Peer, Node} = peer:start_link(#{name => Name, host => "localhost",
                                         args => lists:append([["-pa", P] || P <- Paths]),
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
