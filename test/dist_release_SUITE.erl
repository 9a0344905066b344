%% System tests of the built release's door to the Erlang distribution: the cookie a
%% node makes for itself when none is given (kept in the cell root, readable by its
%% owner only, the same at every start), a cookie file others can read refused, the
%% distribution listening on loopback unless told otherwise, and two nodes speaking the
%% distribution over TLS (while a node without TLS, or with a certificate of another
%% authority, is refused). The release is the one `make test' builds
%% (`_build/default/rel/cellrt', or `$CELLRT_REL').
-module(dist_release_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("kernel/include/file.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([no_cookie_makes_one_in_the_root/1, well_known_cookie_is_warned_of/1,
         cookie_others_can_read_is_refused/1,
         distribution_listens_on_loopback/1, distribution_bind_opens_it/1,
         line_neighbours_only/1,
         bad_distribution_bind_is_refused/1, tls_distribution_between_two_nodes/1]).

all() ->
    [no_cookie_makes_one_in_the_root, well_known_cookie_is_warned_of,
     cookie_others_can_read_is_refused,
     distribution_listens_on_loopback, distribution_bind_opens_it,
     line_neighbours_only,
     bad_distribution_bind_is_refused, tls_distribution_between_two_nodes].

init_per_suite(Config) ->
    Rel = case os:getenv("CELLRT_REL") of
              false -> filename:dirname(filename:dirname(cellrt_rel:bin()));
              Dir -> Dir
          end,
    Bin = filename:absname(filename:join([Rel, "bin", "cellrt"])),
    filelib:is_regular(Bin) orelse
        ct:fail("no release at ~s: build it with `rebar3 release` (make test does)", [Rel]),
    %% This node connects to the release's node as a stranger would.
    [{bin, Bin}, {started_dist, cellrt_rel:start_dist("dist_suite")} | Config].

end_per_suite(Config) ->
    cellrt_rel:stop_dist(?config(started_dist, Config)).

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    %% Unique per run: two checkouts may run this suite on one machine at once.
    Name = "cellrt_ct_" ++ atom_to_list(Case) ++ "_" ++ os:getpid(),
    Env = [{"CELLRT_ROOT", Root}, {"CELLRT_NODE", Name ++ "@localhost"},
           {"CELLRT_WEB_PORT", "0"}, {"CELLRT_SHDR_PORT", "0"}, {"CELLRT_HEART", "-noheart"},
           %% What the test's own environment may hold must not decide for the node.
           {"CELLRT_COOKIE", case Case of
                                 tls_distribution_between_two_nodes -> "cellrt_ct_tls";
                                 well_known_cookie_is_warned_of -> "cellrt";
                                 _ -> false
                             end},
           {"CELLRT_DIST_BIND", case Case of
                                    distribution_bind_opens_it -> "0.0.0.0";
                                    bad_distribution_bind_is_refused -> "all-of-them";
                                    _ -> false
                                end}],
    [{env, Env}, {root, Root}, {name, Name}, {node, list_to_atom(Name ++ "@localhost")}
     | Config].

end_per_testcase(_Case, Config) ->
    _ = cellrt(Config, ["stop"]),
    ok.

%% With no cookie given, the node makes a random one at its first start, keeps it in
%% the cell root's Distribution/cookie readable by its owner only, and refuses anyone
%% who comes with the cookie the release used to ship with; at the next start it uses
%% the same one again.
no_cookie_makes_one_in_the_root(Config) ->
    Node = ?config(node, Config),
    File = filename:join([?config(root, Config), "Distribution", "cookie"]),
    ok = start(Config),
    {ok, #file_info{mode = Mode}} = file:read_file_info(File),
    ?assertEqual(8#600, Mode band 8#777),
    {ok, Bin} = file:read_file(File),
    Cookie = binary_to_list(Bin),
    ?assertMatch({match, _}, re:run(Cookie, "^[0-9a-f]{64}$")),
    %% The vm.args the start script writes is kept beside the cookie, in a folder only
    %% the owner can open; the root stays as any folder.
    Dist = filename:dirname(File),
    {ok, #file_info{mode = DistMode}} = file:read_file_info(Dist),
    ?assertEqual(8#700, DistMode band 8#777),
    Usual = ?config(root, Config) ++ ".usual",
    ok = file:make_dir(Usual),
    {ok, #file_info{mode = UsualMode}} = file:read_file_info(Usual),
    {ok, #file_info{mode = RootMode}} = file:read_file_info(?config(root, Config)),
    ?assertEqual(UsualMode band 8#777, RootMode band 8#777),
    {ok, VmArgs} = file:read_file(filename:join(Dist, "vm.args")),
    ?assertNotEqual(nomatch, binary:match(VmArgs, <<"-sname ">>)),
    %% ps shows a command line to every user of the PC: the node reads its cookie from
    %% the file, so that it is on none.
    ?assertEqual(nomatch, binary:match(VmArgs, Bin)),
    Args = eval(Config, "os:cmd(\"ps -o args= -p \" ++ os:getpid())."),
    ?assertNotEqual(nomatch, string:find(Args, ?config(name, Config))),
    ?assertEqual(nomatch, string:find(Args, Cookie)),
    true = erlang:set_cookie(Node, cellrt),
    ?assertEqual(false, net_kernel:connect_node(Node)),
    true = erlang:set_cookie(Node, list_to_atom(Cookie)),
    ?assertEqual(true, net_kernel:connect_node(Node)),
    ?assertEqual(list_to_atom(Cookie), erpc:call(Node, erlang, get_cookie, [])),
    true = erlang:disconnect_node(Node),
    {0, _} = cellrt(Config, ["stop"]),
    ok = await_down(Config),
    ok = start(Config),
    ?assertEqual({ok, Bin}, file:read_file(File)),
    ?assertEqual(list_to_atom(Cookie), erpc:call(Node, erlang, get_cookie, [])),
    true = erlang:disconnect_node(Node).

%% Given the cookie older releases shipped with, a build other than the production one
%% starts and says in the log what to do (the production build refuses it:
%% cell_dist's unit tests).
well_known_cookie_is_warned_of(Config) ->
    ok = start(Config),
    {0, _} = cellrt(Config, ["eval", "cell_log:flush()."]),
    [Log] = filelib:wildcard(filename:join([?config(root, Config), "Logs", "log *.log"])),
    {ok, Bin} = file:read_file(Log),
    ?assertNotEqual(nomatch, binary:match(Bin, <<"WARNING cell_base: the node's distribution "
                                                 "cookie is the well-known `cellrt'">>)).

%% A cookie file other users can read is as good as no cookie: the start is refused
%% and says what to do.
cookie_others_can_read_is_refused(Config) ->
    File = filename:join([?config(root, Config), "Distribution", "cookie"]),
    ok = filelib:ensure_dir(File),
    ok = file:write_file(File, <<"a_cookie_everyone_can_read">>),
    ok = file:change_mode(File, 8#644),
    {Status, Out} = cellrt(Config, ["foreground"], 60000),
    ct:log("~s", [Out]),
    ?assertNotEqual(0, Status),
    ?assertNotEqual(nomatch, string:find(Out, "can be read by other users")),
    ?assertNotEqual(nomatch, string:find(Out, "chmod 600")),
    ?assertEqual(pang, net_adm:ping(?config(node, Config))).

%% Unless told otherwise, the distribution listens on loopback only, and an epmd the
%% node starts does too.
distribution_listens_on_loopback(Config) ->
    ok = start(Config),
    ?assertEqual([{127, 0, 0, 1}], dist_addresses(Config)),
    ?assertEqual("\"127.0.0.1\"", eval(Config, "os:getenv(\"ERL_EPMD_ADDRESS\").")),
    %% From another address of this PC, nobody gets in.
    Port = dist_port(Config),
    [?assertEqual({error, econnrefused},
                  gen_tcp:connect(Ip, Port, [], 5000), Ip) || Ip <- other_addresses()].

%% A cell's node connects to the nodes it dials and those that dial it, not to every
%% node they know; and a cut between two other nodes never makes it drop its own
%% connections (the line keeps one neighbour when it loses the other).
line_neighbours_only(Config) ->
    ok = start(Config),
    ?assertEqual({{ok, [["false"]]}, {ok, false}},
                 parse(eval(Config, "{init:get_argument(connect_all), application:get_env("
                                    "kernel, prevent_overlapping_partitions)}."))).

%% CELLRT_DIST_BIND opens the distribution to a line of cells on several PCs.
distribution_bind_opens_it(Config) ->
    ok = start(Config),
    ?assertEqual([{0, 0, 0, 0}], dist_addresses(Config)),
    ?assertEqual("false", eval(Config, "os:getenv(\"ERL_EPMD_ADDRESS\").")).

%% A malformed address is refused before the node starts, naming the setting.
bad_distribution_bind_is_refused(Config) ->
    {Status, Out} = cellrt(Config, ["foreground"], 60000),
    ct:log("~s", [Out]),
    ?assertNotEqual(0, Status),
    ?assertNotEqual(nomatch, string:find(Out, "CELLRT_DIST_BIND")).

%% With Distribution/ssl_dist.conf in the cell root, the node speaks the distribution
%% over TLS: the start script's own commands reach it, and so does another node over
%% TLS with a certificate of the same authority; a node without TLS, or with a
%% certificate of another authority, does not get in.
tls_distribution_between_two_nodes(Config) ->
    Node = ?config(node, Config),
    Dir = filename:join(?config(priv_dir, Config), "tls"),
    ok = filelib:ensure_dir(filename:join(Dir, ".")),
    ok = make_ca(Dir, "ca"),
    ok = make_cert(Dir, "ca", "cell1"),
    ok = make_cert(Dir, "ca", "cell2"),
    ok = make_ca(Dir, "other_ca"),
    ok = make_cert(Dir, "other_ca", "stranger"),
    Conf = filename:join([?config(root, Config), "Distribution", "ssl_dist.conf"]),
    ok = filelib:ensure_dir(Conf),
    ok = file:write_file(Conf, ssl_dist_conf(Dir, "ca", "cell1")),
    ok = file:write_file(filename:join(Dir, "cell2.conf"), ssl_dist_conf(Dir, "ca", "cell2")),
    ok = file:write_file(filename:join(Dir, "stranger.conf"),
                         ssl_dist_conf(Dir, "other_ca", "stranger")),
    ok = start(Config),
    ?assertEqual("tls", eval(Config, "{ok, [{_, I} | _]} = net_kernel:nodes_info(), "
                                  "element(4, proplists:get_value(address, I)).")),
    ?assertEqual([{127, 0, 0, 1}], dist_addresses(Config)),
    Peer = fun(Name, ConfFile) ->
                   peer(Name, ConfFile, "cellrt_ct_tls", Node)
           end,
    ?assertEqual({pong, Node}, Peer("cell2", filename:join(Dir, "cell2.conf"))),
    ?assertMatch({pang, _}, Peer("stranger", filename:join(Dir, "stranger.conf"))),
    true = erlang:set_cookie(Node, cellrt_ct_tls),
    ?assertEqual(false, net_kernel:connect_node(Node)).

%% Helpers

%% Another node, over TLS with the options of `ConfFile': its ping of `Node' and, when
%% it got in, the name of the node its call ran on.
peer(Name, ConfFile, Cookie, Node) ->
    Erl = os:find_executable("erl"),
    Self = Name ++ "_" ++ os:getpid() ++ "@localhost",
    Eval = lists:flatten(
             io_lib:format("P = net_adm:ping(~p), "
                           "R = case P of pong -> erpc:call(~p, erlang, node, [], 30000); "
                           "pang -> none end, "
                           "io:format(\"~~nresult: ~~p.~~n\", [{P, R}]), halt().", [Node, Node])),
    Port = open_port({spawn_executable, Erl},
                     [{args, ["-sname", Self, "-setcookie", Cookie, "-proto_dist", "inet_tls",
                              "-ssl_dist_optfile", ConfFile, "-noshell", "-eval", Eval]},
                      exit_status, stderr_to_stdout, binary]),
    {0, Out} = cellrt_rel:collect(Port, 60000),
    ct:log("~s: ~s", [Name, Out]),
    %% Its line of the output: the TLS handshake's own reports (an alert the refused
    %% side logs) may come before or after it.
    [Line] = [L || "result: " ++ L <- string:lexemes(Out, "\n")],
    {ok, Tokens, _} = erl_scan:string(Line),
    {ok, Term} = erl_parse:parse_term(Tokens),
    Term.

ssl_dist_conf(Dir, Ca, Name) ->
    F = fun(Ext) -> filename:join(Dir, Name ++ Ext) end,
    Common = [{certfile, F(".pem")}, {keyfile, F(".key")},
              {cacertfile, filename:join(Dir, Ca ++ ".pem")}, {verify, verify_peer}],
    io_lib:format("~p.~n", [[{server, [{fail_if_no_peer_cert, true} | Common]},
                             {client, Common}]]).

make_ca(Dir, Ca) ->
    openssl(Dir, ["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
                  "-keyout", Ca ++ ".key", "-out", Ca ++ ".pem", "-subj", "/CN=" ++ Ca]).

make_cert(Dir, Ca, Name) ->
    ok = openssl(Dir, ["req", "-newkey", "rsa:2048", "-nodes", "-keyout", Name ++ ".key",
                       "-out", Name ++ ".csr", "-subj", "/CN=localhost"]),
    ok = file:write_file(filename:join(Dir, Name ++ ".ext"),
                         "subjectAltName=DNS:localhost,IP:127.0.0.1\n"),
    openssl(Dir, ["x509", "-req", "-in", Name ++ ".csr", "-CA", Ca ++ ".pem",
                  "-CAkey", Ca ++ ".key", "-CAcreateserial", "-days", "2",
                  "-extfile", Name ++ ".ext", "-out", Name ++ ".pem"]).

openssl(Dir, Args) ->
    Port = open_port({spawn_executable, os:find_executable("openssl")},
                     [{args, Args}, {cd, Dir}, exit_status, stderr_to_stdout, binary]),
    case cellrt_rel:collect(Port, 60000) of
        {0, _} -> ok;
        {S, Out} -> ct:fail("openssl ~p: ~p~n~s", [Args, S, Out])
    end.

%% The addresses the node's distribution listens on.
dist_addresses(Config) ->
    Port = dist_port(Config),
    Out = eval(Config, lists:flatten(
                         io_lib:format("lists:usort([A || P <- erlang:ports(), "
                                       "erlang:port_info(P, name) =:= {name, \"tcp_inet\"}, "
                                       "{ok, {A, ~b}} <- [inet:sockname(P)], "
                                       %% The listening socket, not a connection to it.
                                       "{error, _} <- [inet:peername(P)]]).", [Port]))),
    parse(Out).

dist_port(Config) ->
    {port, Port, _} = erl_epmd:port_please(?config(name, Config), "localhost"),
    Port.

%% This PC's IPv4 addresses other than loopback (none on a PC without a network).
other_addresses() ->
    {ok, Ifs} = inet:getifaddrs(),
    [A || {_, Opts} <- Ifs, {addr, {B, _, _, _} = A} <- Opts, B =/= 127].

start(Config) ->
    {0, _} = cellrt(Config, ["daemon"]),
    ok = cellrt_rel:await_ping(?config(bin, Config), ?config(env, Config),
                               fun(Out) -> string:trim(Out) =:= "pong" end, 120000),
    ?assertEqual("ok", eval(Config, cellrt_rel:await_boot_expr())),
    ok.

await_down(Config) ->
    cellrt_rel:await_ping(?config(bin, Config), ?config(env, Config),
                          fun(Out) -> string:trim(Out) =/= "pong" end, 120000).

eval(Config, Expr) ->
    {0, Out} = cellrt(Config, ["eval", Expr], 120000),
    string:trim(Out).

parse(Out) ->
    {ok, Tokens, _} = erl_scan:string(Out ++ "."),
    {ok, Term} = erl_parse:parse_term(Tokens),
    Term.

cellrt(Config, Args) ->
    cellrt(Config, Args, 30000).

cellrt(Config, Args, Timeout) ->
    cellrt_rel:run(?config(bin, Config), Args, ?config(env, Config), Timeout).
