%% Keeps the feed and out tables of a node's line segment alive for the node suite,
%% and holds a task at the moment a test cuts the network.
-module(cell_handshake_nodes_SUITE_keeper).

-export([start/0, hold_released/2, connected/2]).

-spec start() -> ok.
start() ->
    Self = self(),
    Pid = spawn(fun() ->
                        _ = ets:new(line_feed, [named_table, public, ordered_set]),
                        _ = ets:new(line_out, [named_table, public, set]),
                        Self ! {self(), ready},
                        receive stop -> ok end
                end),
    receive {Pid, ready} -> ok end.

%% The downstream task `Task' stops when the link's `released' (the product left
%% upstream) reaches it, before it acts on it: it tells `Test' `{released_at_task,
%% TaskPid, Ref}' and goes on when it gets `{go, Ref}'. A debug function of sys runs
%% in the task's process before each event is handled, so the pause is at that exact
%% point however busy the machine is; it is removed once it has held the task.
-spec hold_released(atom(), pid()) -> reference().
hold_released(Task, Test) ->
    Ref = make_ref(),
    %% gen_statem's debug events are `{in, {EventType, Content}, State}'.
    Hold = fun(St, {in, Event, _State}, _ProcState) ->
                   case released(Event) of
                       true ->
                           Test ! {released_at_task, self(), Ref},
                           receive {go, Ref} -> done end;
                       false ->
                           St
                   end;
              (St, _Event, _ProcState) ->
                   St
           end,
    ok = sys:install(cell_task_proc:whereis(Task), {Hold, held}),
    Ref.

released({info, Msg}) -> released(Msg);
released({cell_handshake, _Link, {released, _, _}, _Status}) -> true;
released(_) -> false.

%% `true' once this node is connected to `Node', within `Timeout' ms. A connect that
%% met the cell's own reconnecting (cell_peers tries from either side) may fail; the
%% node's `nodeup' still comes when either attempt gets through.
-spec connected(node(), timeout()) -> boolean().
connected(Node, Timeout) ->
    ok = net_kernel:monitor_nodes(true),
    Result = lists:member(Node, nodes()) orelse net_kernel:connect_node(Node)
        orelse receive
                   {nodeup, Node} -> true
               after Timeout -> lists:member(Node, nodes())
               end,
    ok = net_kernel:monitor_nodes(false),
    Result.
