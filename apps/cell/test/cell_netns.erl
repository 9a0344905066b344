%% Cell nodes in Linux network namespaces of their own, for tests across a real network
%% boundary: each node has its own network stack, address and epmd, and the traffic
%% between them crosses a veth link the test can cut and heal.
%%
%% Two namespaces are joined by one veth pair; more by a veth each to a bridge in a
%% namespace of its own. The nodes are started with `ip netns exec' as peers whose
%% control channel is their standard input and output (peer's `standard_io'), so the
%% test node drives them, and hears from them, whatever happens to their network: it
%% is not part of their distribution at all.
%%
%% Cuts, on the namespaces' own links only:
%% <ul>
%% <li>`silent': a `blackhole' queueing discipline on the link, which drops every
%%   packet it would send without a word; on both ends nothing passes, on one end
%%   (`{silent, From}') only the packets from `From' are lost (an asymmetric cut). The
%%   nodes learn of it only from their distribution ticks.</li>
%% <li>`clean': silent on both ends, and both nodes drop their connection at once
%%   (`erlang:disconnect_node/1'): a cut the nodes see as it happens, as when a cable
%%   is pulled from a switch that reports it.</li>
%% </ul>
%% `heal/3' lifts a cut end by end, in the order given.
%%
%% With `tls/2' the nodes speak the distribution over TLS as the cells of a line on
%% several PCs do (README, "A line of cells on several PCs"): a certificate per node,
%% for its address, signed by an authority of the net's own, and peers verified both
%% ways.
%%
%% Every name made here (namespaces `crt_<run>_<n>', veth ends `crt_<run>_<n>') has the
%% run's own tag, so runs side by side never meet, and `destroy/1' removes all of it,
%% also the epmd daemons the nodes started inside their namespaces.
-module(cell_netns).

-export([available/0, required/0, create/1, destroy/1, tls/2, start_node/3, stop_node/2, node_of/2,
         call/5, call/6, os_pid/2, kill_node/2, cut/3, heal/3, names/1, line_vm_args/0]).

-export_type([net/0]).

-opaque net() :: #{run := string(),
                   names := [atom()],
                   %% Per cell: its namespace, the device of its end and its address.
                   ends := #{atom() => #{ns := string(), dev := string(),
                                         addr := string(),
                                         port => {string(), string()}}},
                   %% Namespaces to delete, the bridge's among them.
                   nss := [string()],
                   cookie := atom(),
                   peers := #{atom() => {pid(), node()}},
                   %% Per cell, the options file of its TLS distribution.
                   tls => #{atom() => file:filename()}}.

-define(CALL_TIMEOUT, 30000).

%% @doc Whether namespaces can be made here (root, iproute2 and the blackhole qdisc):
%% `ok' or why not.
-spec available() -> ok | {error, string()}.
available() ->
    Tag = "crt_" ++ run_tag() ++ "_probe",
    case sh(["ip netns add ", Tag]) of
        {0, _} ->
            R = case sh(["ip -n ", Tag, " link set lo up && tc -n ", Tag,
                         " qdisc add dev lo root blackhole && tc -n ", Tag,
                         " qdisc del dev lo root"]) of
                    {0, _} -> ok;
                    {_, Out} -> {error, "tc blackhole qdisc: " ++ Out}
                end,
            {0, _} = sh(["ip netns del ", Tag]),
            R;
        {_, Out} ->
            {error, "ip netns add: " ++ Out}
    end.

%% @doc For a suite's `init_per_suite': `ok', or the suite fails saying what is missing
%% (root, iproute2, the blackhole qdisc) rather than passing unrun.
-spec required() -> ok.
required() ->
    case os:cmd("id -u") of
        "0\n" ->
            case available() of
                ok -> ok;
                {error, Why} -> ct:fail("network namespaces unavailable: " ++ Why)
            end;
        _ ->
            ct:fail("network namespaces need root")
    end.

%% @doc Namespaces for the cells `Names', joined in a pair or to a bridge, with lo up.
%% On a failure midway everything made so far is removed again.
-spec create([atom(), ...]) -> net().
create(Names) when length(Names) >= 2 ->
    Run = run_tag(),
    Net0 = #{run => Run, names => Names, ends => #{}, nss => [], peers => #{},
             cookie => list_to_atom("crt_" ++ Run)},
    try
        build(Net0)
    catch
        C:R:St ->
            _ = destroy(Net0#{nss => [ns(Run, I) || I <- lists:seq(0, length(Names))]}),
            erlang:raise(C, R, St)
    end.

build(#{run := Run, names := Names} = Net) ->
    Indexed = lists:zip(lists:seq(1, length(Names)), Names),
    Nss = [ns(Run, I) || {I, _} <- Indexed],
    [ok = cmd(["ip netns add ", N]) || N <- Nss],
    [ok = cmd(["ip -n ", N, " link set lo up"]) || N <- Nss],
    Ends0 = maps:from_list([{Name, #{ns => ns(Run, I), dev => dev(Run, I),
                                     addr => "10.77.0." ++ integer_to_list(I)}}
                            || {I, Name} <- Indexed]),
    {Ends, Extra} = case Indexed of
                [{1, A}, {2, B}] ->
                    #{ns := NA, dev := DA} = maps:get(A, Ends0),
                    #{ns := NB, dev := DB} = maps:get(B, Ends0),
                    ok = cmd(["ip link add ", DA, " netns ", NA, " type veth peer name ", DB,
                              " netns ", NB]),
                    {Ends0, []};
                _ ->
                    Br = ns(Run, 0),
                    ok = cmd(["ip netns add ", Br]),
                    ok = cmd(["ip -n ", Br, " link add ", dev(Run, 0), " type bridge"]),
                    ok = cmd(["ip -n ", Br, " link set ", dev(Run, 0), " up"]),
                    [begin
                         Port = dev(Run, 100 + I),
                         #{ns := N, dev := D} = maps:get(Name, Ends0),
                         ok = cmd(["ip link add ", D, " netns ", N, " type veth peer name ",
                                   Port, " netns ", Br]),
                         ok = cmd(["ip -n ", Br, " link set ", Port, " master ", dev(Run, 0)]),
                         ok = cmd(["ip -n ", Br, " link set ", Port, " up"])
                     end || {I, Name} <- Indexed],
                    %% A cell's end cut both ways drops at its bridge port too.
                    {maps:map(fun(Name, E) ->
                                      {I, Name} = lists:keyfind(Name, 2, Indexed),
                                      E#{port => {Br, dev(Run, 100 + I)}}
                              end, Ends0),
                     [Br]}
            end,
    [begin
         ok = cmd(["ip -n ", N, " addr add ", A, "/24 dev ", D]),
         ok = cmd(["ip -n ", N, " link set ", D, " up"])
     end || #{ns := N, dev := D, addr := A} <- maps:values(Ends0)],
    Net#{ends => Ends, nss => Nss ++ Extra}.

%% @doc Has the nodes started from now on speak the distribution over TLS: makes in
%% `Dir' an authority, and for each cell a key and a certificate for its address signed
%% by it, and the distribution's options file (the README's, peers verified both ways).
-spec tls(net(), file:filename()) -> net().
tls(#{names := Names, ends := Ends} = Net, Dir) ->
    ok = filelib:ensure_path(Dir),
    ok = openssl(Dir, ["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
                       "-keyout", "ca.key", "-out", "ca.pem", "-subj", "/CN=line"]),
    Confs = [{Name, cert(Dir, atom_to_list(Name), maps:get(addr, maps:get(Name, Ends)))}
             || Name <- Names],
    Net#{tls => maps:from_list(Confs)}.

cert(Dir, Name, Addr) ->
    ok = openssl(Dir, ["req", "-newkey", "rsa:2048", "-nodes", "-keyout", Name ++ ".key",
                       "-out", Name ++ ".csr", "-subj", "/CN=" ++ Addr]),
    %% The node's host is its address: the distribution checks it as a name.
    ok = file:write_file(filename:join(Dir, Name ++ ".ext"),
                         ["subjectAltName=DNS:", Addr, ",IP:", Addr, "\n"]),
    ok = openssl(Dir, ["x509", "-req", "-in", Name ++ ".csr", "-CA", "ca.pem",
                       "-CAkey", "ca.key", "-CAcreateserial", "-days", "2",
                       "-extfile", Name ++ ".ext", "-out", Name ++ ".pem"]),
    F = fun(File) -> filename:join(Dir, File) end,
    Common = [{certfile, F(Name ++ ".pem")}, {keyfile, F(Name ++ ".key")},
              {cacertfile, F("ca.pem")}, {verify, verify_peer}],
    Conf = F(Name ++ ".conf"),
    ok = file:write_file(Conf, io_lib:format("~p.~n", [[{server, [{fail_if_no_peer_cert, true}
                                                                   | Common]},
                                                         {client, Common}]])),
    Conf.

openssl(Dir, Args) ->
    case sh(["cd ", Dir, " && openssl ", lists:join(" ", Args)]) of
        {0, _} -> ok;
        {Code, Out} -> erlang:error({openssl_failed, Args, Code, Out})
    end.

%% @doc Stops the nodes still running, ends every process left in the namespaces (the
%% epmd daemons the nodes started) and deletes the namespaces with their links.
-spec destroy(net()) -> ok.
destroy(#{nss := Nss} = Net) ->
    _ = [catch peer:stop(P) || {P, _} <- maps:values(maps:get(peers, Net, #{}))],
    lists:foreach(fun(N) ->
                          {_, Pids} = sh(["ip netns pids ", N]),
                          _ = [sh(["kill -9 ", P]) || P <- string:lexemes(Pids, "\n "),
                                                      P =/= ""],
                          _ = sh(["ip netns del ", N])
                  end, Nss),
    ok.

%% @doc The names of the cells.
-spec names(net()) -> [atom()].
names(#{names := Names}) -> Names.

%% @doc Starts a node for cell `Name' in its namespace: `-name line_netns_<Name>_<run>@
%% <its address>', the net's own cookie, the test node's code path and `Args'.
-spec start_node(net(), atom(), [string()]) -> net().
start_node(#{run := Run, ends := Ends, cookie := Cookie, peers := Peers} = Net, Name, Args) ->
    #{ns := NS, addr := Addr} = maps:get(Name, Ends),
    Paths = [P || P <- code:get_path(), string:find(P, "_build") =/= nomatch
                                             orelse string:find(P, "_debdeps") =/= nomatch],
    NodeName = "line_netns_" ++ atom_to_list(Name) ++ "_" ++ Run,
    Erl = os:find_executable("erl"),
    Tls = case Net of
              #{tls := #{Name := Conf}} ->
                  ["-proto_dist", "inet_tls", "-ssl_dist_optfile", Conf];
              #{} ->
                  []
          end,
    {ok, Peer, Node} =
        peer:start(#{name => NodeName, host => Addr, longnames => true,
                     exec => {os:find_executable("ip"), ["netns", "exec", NS, Erl]},
                     connection => standard_io, wait_boot => 60000,
                     %% The namespace's epmd listens on its address at the default
                     %% port, whatever the test's environment says for its own.
                     env => [{"ERL_EPMD_ADDRESS", false}, {"ERL_EPMD_PORT", false}],
                     args => ["-setcookie", atom_to_list(Cookie),
                              "-kernel", "inet_dist_listen_min", "21700",
                              "-kernel", "inet_dist_listen_max", "21709"]
                              ++ line_vm_args() ++ Tls ++ lists:append([["-pa", P] || P <- Paths]) ++ Args}),
    Net#{peers => Peers#{Name => {Peer, Node}}}.

%% @doc The distribution flags the release gives a cell's node (config/vm.args.src):
%% connected to its neighbours only, and a cut between two nodes never makes a third
%% drop its connections.
-spec line_vm_args() -> [string()].
line_vm_args() ->
    ["-connect_all", "false", "-kernel", "prevent_overlapping_partitions", "false"].

%% @doc Stops the node of a cell (an orderly stop).
-spec stop_node(net(), atom()) -> net().
stop_node(#{peers := Peers} = Net, Name) ->
    {Peer, _} = maps:get(Name, Peers),
    catch peer:stop(Peer),
    Net#{peers => maps:remove(Name, Peers)}.

%% @doc Kills the node of a cell (SIGKILL, as a power cut ends it) and waits until its
%% control channel reports it gone.
-spec kill_node(net(), atom()) -> net().
kill_node(#{peers := Peers} = Net, Name) ->
    {Peer, _} = maps:get(Name, Peers),
    OsPid = os_pid(Net, Name),
    MRef = erlang:monitor(process, Peer),
    {0, _} = sh(["kill -9 ", OsPid]),
    receive {'DOWN', MRef, process, Peer, _} -> ok
    after ?CALL_TIMEOUT -> erlang:error({node_not_gone, Name})
    end,
    Net#{peers => maps:remove(Name, Peers)}.

%% @doc The distribution name of a cell's node.
-spec node_of(net(), atom()) -> node().
node_of(#{peers := Peers}, Name) ->
    {_, Node} = maps:get(Name, Peers),
    Node.

%% @doc Calls a function on a cell's node over its control channel (never the cut
%% network).
-spec call(net(), atom(), module(), atom(), [term()]) -> term().
call(Net, Name, M, F, A) ->
    call(Net, Name, M, F, A, ?CALL_TIMEOUT).

%% @doc As call/5, with a deadline of its own.
-spec call(net(), atom(), module(), atom(), [term()], timeout()) -> term().
call(#{peers := Peers}, Name, M, F, A, Timeout) ->
    {Peer, _} = maps:get(Name, Peers),
    peer:call(Peer, M, F, A, Timeout).

%% @doc The OS process id of a cell's node.
-spec os_pid(net(), atom()) -> string().
os_pid(Net, Name) ->
    call(Net, Name, os, getpid, []).

%% @doc Cuts the cells `Names' off (`silent' or `clean', above; `{silent, Name}' drops
%% only what `Name' sends). A cell's end cut is cut from every other cell: two cells
%% of a pair, one cell of a bridge.
-spec cut(net(), silent | clean | {silent, atom()}, [atom()]) -> ok.
cut(Net, {silent, From}, _Names) ->
    blackhole(Net, From, add);
cut(Net, silent, Names) ->
    [both_ways(Net, N, add) || N <- Names],
    ok;
cut(#{peers := Peers} = Net, clean, Names) ->
    [both_ways(Net, N, add) || N <- Names],
    %% Each cut node drops its connections to every other node, and they to it.
    Pairs = [{A, B} || A <- maps:keys(Peers), B <- maps:keys(Peers), A =/= B,
                       lists:member(A, Names) orelse lists:member(B, Names)],
    _ = [call(Net, A, erlang, disconnect_node, [node_of(Net, B)]) || {A, B} <- Pairs],
    ok.

%% @doc Lifts the cut on the cells' ends, in the order given (a cell not cut is
%% passed over).
-spec heal(net(), silent | clean | {silent, atom()}, [atom()]) -> ok.
heal(Net, _How, Names) ->
    [both_ways(Net, N, del) || N <- Names],
    ok.

both_ways(#{ends := Ends} = Net, Name, Op) ->
    ok = blackhole(Net, Name, Op),
    case maps:get(Name, Ends) of
        #{port := {Br, Port}} -> qdisc(Br, Port, Name, Op);
        #{} -> ok
    end.

blackhole(#{ends := Ends}, Name, Op) ->
    #{ns := NS, dev := Dev} = maps:get(Name, Ends),
    qdisc(NS, Dev, Name, Op).

qdisc(NS, Dev, Name, Op) ->
    case {Op, sh(["tc -n ", NS, " qdisc ", atom_to_list(Op), " dev ", Dev,
                  " root blackhole"])} of
        {_, {0, _}} -> ok;
        %% Healing an end that was not cut.
        {del, {_, _}} -> ok;
        {add, {_, Out}} -> erlang:error({tc_failed, Name, Out})
    end.

%% -------------------------------------------------------------------------------------

run_tag() ->
    %% Short enough for an interface name (15 characters): crt_<6>_<n>.
    <<N:24, _/binary>> = crypto:strong_rand_bytes(4),
    string:lowercase(string:right(integer_to_list(N, 36), 5, $0)).

ns(Run, I) -> "crt_" ++ Run ++ "_" ++ integer_to_list(I).

dev(Run, I) -> "crt_" ++ Run ++ "_" ++ integer_to_list(I).

cmd(Parts) ->
    case sh(Parts) of
        {0, _} -> ok;
        {Code, Out} -> erlang:error({command_failed, lists:flatten(Parts), Code, Out})
    end.

%% A shell command and its status; a port, not os:cmd, for the status.
sh(Parts) ->
    Port = open_port({spawn_executable, "/bin/sh"},
                     [{args, ["-c", lists:flatten(Parts) ++ " 2>&1"]}, exit_status,
                      stderr_to_stdout, binary]),
    collect(Port, []).

collect(Port, Acc) ->
    receive
        {Port, {data, D}} -> collect(Port, [D | Acc]);
        {Port, {exit_status, S}} -> {S, binary_to_list(iolist_to_binary(lists:reverse(Acc)))}
    end.
