%% @doc A line of cells across two nodes: transfers per second between two cell nodes
%% (one task each, the link on the downstream node, as the line tests build them with
%% cell_line_nodes), beside the same line of two tasks and their link in one cell on one
%% node, measured in the same run. Both lines run on nodes started for the benchmark
%% (peer), over Erlang distribution on the loopback, their product files on a RAM folder:
%% the ratio is what the distribution costs a transfer (its calls and messages between
%% the nodes), not the disk.
-module(cell_line_bench).

-export([run/0]).
%% On the cell nodes: the process that owns a node's tables and counts what is out.
-export([keeper/1]).

-define(RAM, "/dev/shm").
%% Rounds through one running line, the median reported (see cell_handshake_bench).
-define(ROUNDS, 5).
-define(PER, 1000).
%% A round that has not finished by then has lost a product.
-define(ROUND_MS, 120000).

-spec run() -> [cell_bench:result()].
run() ->
    Root = filename:join(?RAM, "cellrt-line-bench-" ++ os:getpid()),
    try
        One = line_rate(Root, one),
        Two = line_rate(Root, two),
        [#{title => "Transfers per second, line of 2 across two nodes, RAM folder",
           unit => "transfers/s", ours => Two, peer => One,
           peer_name => "the same line in one cell on one node", better => higher,
           note => "Two cell nodes on one host (loopback distribution), the first "
                   "segment's cell on one, the last segment's and the link between them "
                   "on the other, as the line tests build them; beside the same two tasks "
                   "and link in one cell on one node. Both started for the run, products "
                   "on a RAM folder, the median of five rounds of 1000 products through "
                   "one running line. Across the nodes, upstream's offer and release "
                   "are calls to the link on the other node, and the link's signals and "
                   "answers come back over the distribution: each is encoded, sent over "
                   "TCP and decoded on the other node, a wake-up of both nodes' "
                   "schedulers, where one node passes it between processes."}]
    after
        _ = os:cmd("rm -rf '" ++ Root ++ "'")
    end.

%% Transfers per second through a line of 2 on one node (`one') or across two (`two').
line_rate(Root0, Layout) ->
    Root = filename:join(Root0, atom_to_list(Layout)),
    Nodes = start_nodes(Root, Layout),
    try
        Keepers = maps:map(fun(_, {_, Node}) -> start_keeper(Node) end, Nodes),
        {_, Up} = maps:get(up, Nodes),
        {_, Down} = maps:get(down, Nodes, maps:get(up, Nodes)),
        Ref = make_ref(),
        {_, {Feed, UpOut}} = maps:get(up, Keepers),
        {DownKeeper, {_, DownOut}} = maps:get(down, Keepers, maps:get(up, Keepers)),
        Args = fun(Out) -> #{feed => Feed, out => Out, ref => Ref, notify => DownKeeper,
                             phases => false} end,
        Specs = case Layout of
                    one ->
                        #{up => #{tasks => [task(src, (Args(UpOut))#{next => x1}),
                                            task(sink, (Args(UpOut))#{prev => x1})],
                                  links => [#{id => x1, from => src, to => sink}]}};
                    two ->
                        #{up => cell_line_nodes:spec(up, Up, Down, Args(UpOut)),
                          down => cell_line_nodes:spec(down, Up, Down, Args(DownOut))}
                end,
        maps:foreach(fun(Which, Spec) ->
                             {_, Node} = maps:get(Which, Nodes),
                             ok = cell_line_nodes:boot(
                                    fun(M, F, A) -> erpc:call(Node, M, F, A) end,
                                    filename:join(Root, atom_to_list(Which)), Spec)
                     end, Specs),
        %% Downstream first: the link's node is up when upstream's task first calls it.
        [ok = erpc:call(N, cell_controller, start, [])
         || W <- [down, up], {_, N} <- [maps:get(W, Nodes, none)]],
        Rates = [round_rate(Up, DownKeeper, Feed, Ref, R) || R <- lists:seq(1, ?ROUNDS)],
        maps:get(median, cell_bench:stats(Rates))
    after
        maps:foreach(fun(_, {Peer, _}) -> catch peer:stop(Peer) end, Nodes)
    end.

%% One round: `?PER' products fed at once, timed until the last is out.
round_rate(Up, Keeper, Feed, Ref, Round) ->
    Serials = [<<"B-", (integer_to_binary(Round))/binary, "-", (integer_to_binary(I))/binary>>
               || I <- lists:seq(1, ?PER)],
    Target = Round * ?PER,
    T0 = erlang:monotonic_time(microsecond),
    true = erpc:call(Up, ets, insert,
                     [Feed, [{Round * ?PER + I, S} || {I, S} <- lists:enumerate(Serials)]]),
    erpc:call(Up, cell_task_proc, whereis, [src]) ! {Ref, fed},
    Keeper ! {await, self(), Target},
    receive
        {out, Keeper, Target} -> ok
    after ?ROUND_MS ->
        erlang:error({products_missing, Round})
    end,
    T1 = erlang:monotonic_time(microsecond),
    ?PER / ((T1 - T0) / 1000000).

task(Id, Args) ->
    #{id => Id, module => cell_line_task, zone => atom_to_binary(Id, utf8),
      lane => <<"Line">>, args => Args}.

%% -------------------------------------------------------------------------------------

%% The cell nodes of a layout, each `{Peer, Node}': `up' alone (one), or `up' and `down'.
start_nodes(Root, Layout) ->
    Whiches = case Layout of one -> [up]; two -> [up, down] end,
    Paths = lists:append([["-pa", P] || P <- code:get_path(),
                                        not lists:prefix(code:lib_dir(), P)]),
    maps:from_list(
      [begin
           Name = list_to_atom(lists:flatten(io_lib:format("cellrt_line_bench_~s_~s_~s",
                                                           [os:getpid(), Layout, W]))),
           %% The environment's root would win over the application's.
           {ok, Peer, Node} = peer:start_link(
                                #{name => Name, host => "localhost",
                                  args => cell_bench:vm_flags() ++
                                      ["-setcookie", atom_to_list(erlang:get_cookie()) | Paths],
                                  env => [{"CELLRT_ROOT", filename:join(Root, atom_to_list(W))}]}),
           {W, {Peer, Node}}
       end || W <- Whiches]).

%% The keeper of a node and its tables.
start_keeper(Node) ->
    Pid = erlang:spawn(Node, ?MODULE, keeper, [self()]),
    receive {keeper, Pid, Tables} -> {Pid, Tables}
    after 30000 -> erlang:error({no_keeper, Node})
    end.

%% @doc On a cell node: owns the node's feed and out tables (which live as long as it
%% does), tells `Boss' of them, and counts the products out (the last segment's
%% `{line_out, Task, Serial}'), answering `{await, From, N}' once N are out in all.
-spec keeper(pid()) -> no_return().
keeper(Boss) ->
    Feed = ets:new(line_feed, [ordered_set, public]),
    Out = ets:new(line_out, [set, public]),
    Boss ! {keeper, self(), {Feed, Out}},
    count(0, []).

count(N, Waiting) ->
    receive
        {line_out, _, _} ->
            N1 = N + 1,
            {Now, Later} = lists:partition(fun({_, Target}) -> Target =< N1 end, Waiting),
            [From ! {out, self(), Target} || {From, Target} <- Now],
            count(N1, Later);
        {await, From, Target} when Target =< N ->
            From ! {out, self(), Target},
            count(N, Waiting);
        {await, From, Target} ->
            count(N, [{From, Target} | Waiting])
    end.
