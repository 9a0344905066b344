%% System tests of the built release: the start script's commands, the cell root
%% folder, a restart after the VM was killed with SIGKILL (by heart, and by a start
%% by hand as a service manager would), the systemd unit it ships. The release is the one
%% `make test' builds (`_build/default/rel/cellrt', or `$CELLRT_REL').
-module(release_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([daemon_ping_eval_stop/1, root_folder_from_environment/1,
         restart_after_sigkill/1, heart_restarts_after_sigkill/1, sigterm_stops_cleanly/1,
         bad_root_folder_is_refused/1, ships_a_systemd_unit/1, make_run_first_screen/1,
         make_run_shows_errors/1]).

all() ->
    [daemon_ping_eval_stop, root_folder_from_environment, restart_after_sigkill,
     heart_restarts_after_sigkill, sigterm_stops_cleanly, bad_root_folder_is_refused,
     ships_a_systemd_unit, make_run_first_screen, make_run_shows_errors].

init_per_suite(Config) ->
    Rel = case os:getenv("CELLRT_REL") of
              false -> filename:join([cellrt_rel:top(), "_build", "default", "rel", "cellrt"]);
              Dir -> Dir
          end,
    Bin = filename:join([Rel, "bin", "cellrt"]),
    case filelib:is_regular(Bin) of
        true -> [{bin, filename:absname(Bin)} | Config];
        false -> ct:fail("no release at ~s: build it with `rebar3 release` (make test does)",
                         [Rel])
    end.

end_per_suite(Config) ->
    Config.

init_per_testcase(Case, Config) ->
    %% A root per case: a cell's database belongs to the node name that made it.
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    %% Unique per run: two checkouts may run this suite on one machine at once.
    Node = "cellrt_ct_" ++ atom_to_list(Case) ++ "_" ++ os:getpid() ++ "@localhost",
    Env = [{"CELLRT_ROOT", Root}, {"CELLRT_NODE", Node}, {"CELLRT_COOKIE", "cellrt_ct"},
           {"CELLRT_WEB_PORT", "0"}]
          %% Started again by hand after the kill, as a service manager would: heart,
          %% which would start it at the same moment, is left out.
          ++ [{"CELLRT_HEART", "-noheart"} || Case =:= restart_after_sigkill]
          %% Every command of the start script writes the release's sys.config from its
          %% own environment, the pings that wait for the boot included.
          ++ [{"CELLRT_SHDR_PORT", "0"} || Case =:= make_run_first_screen],
    [{env, Env}, {root, Root}, {node, list_to_atom(Node)} | Config].

end_per_testcase(_Case, Config) ->
    _ = cellrt(Config, ["stop"]),
    ok.

%% bin/cellrt daemon | ping | eval | stop.
daemon_ping_eval_stop(Config) ->
    {0, _} = cellrt(Config, ["daemon"]),
    ok = await_up(Config),
    {0, Apps} = cellrt(Config, ["eval", "[A || {A, _, _} <- application:which_applications()]."]),
    [?assertNotEqual(nomatch, string:find(Apps, atom_to_list(A)), A)
     || A <- [cell, cell_base, lager, cowboy, ranch, jsx, mnesia, cell_inspect]],
    {0, _} = cellrt(Config, ["stop"]),
    ok = await_down(Config).

%% The root folder and its sub-folders are created where $CELLRT_ROOT says, and the
%% task log is written there.
root_folder_from_environment(Config) ->
    Root = ?config(root, Config),
    {0, _} = cellrt(Config, ["daemon"]),
    ok = await_up(Config),
    [?assert(filelib:is_dir(filename:join(Root, D)), D)
     || D <- ["Settings", "Products", "Data", "Logs", "Databases"]],
    {0, _} = cellrt(Config, ["eval", "cell_log:notice(release_suite, \"hello from the test\", [])."]),
    {0, _} = cellrt(Config, ["stop"]),
    ok = await_down(Config),
    [Log] = filelib:wildcard(filename:join([Root, "Logs", "log *.log"])),
    {ok, Bin} = file:read_file(Log),
    ?assertNotEqual(nomatch, binary:match(Bin, <<"SILENT release_suite: hello from the test">>)).

%% A VM killed with SIGKILL starts again without manual clean-up.
restart_after_sigkill(Config) ->
    {0, _} = cellrt(Config, ["daemon"]),
    ok = await_up(Config),
    {0, Pid} = cellrt(Config, ["eval", "os:getpid()."]),
    OsPid = string:trim(Pid, both, "\"\n "),
    _ = os:cmd("kill -9 " ++ OsPid),
    ok = await_down(Config),
    {0, _} = cellrt(Config, ["daemon"]),
    ok = await_up(Config),
    {0, Pid2} = cellrt(Config, ["eval", "os:getpid()."]),
    ?assertNotEqual(Pid, Pid2).

%% Under heart (the release's default), a VM killed with SIGKILL comes back by itself,
%% says at its start that the node stopped unexpectedly, and counts it; an orderly stop
%% afterwards is not undone by heart.
heart_restarts_after_sigkill(Config) ->
    Root = ?config(root, Config),
    {0, _} = cellrt(Config, ["daemon"]),
    ok = await_up(Config),
    {0, Pid} = cellrt(Config, ["eval", "os:getpid()."]),
    _ = os:cmd("kill -9 " ++ string:trim(Pid, both, "\"\n ")),
    %% Each try is a round trip of the start script: the node answering with another
    %% OS process is heart's restart.
    ok = await(Config, fun(_) -> other_pid(Config, Pid) end),
    ok = await_up(Config),
    {0, Counts} = cellrt(Config, ["eval", "cell_stats:node_restarts()."]),
    ?assertEqual({ok, #{clean => 0, unexpected => 1}}, parse(Counts)),
    [Log] = filelib:wildcard(filename:join([Root, "Logs", "log *.log"])),
    {ok, Bin} = file:read_file(Log),
    ?assertNotEqual(nomatch,
                    binary:match(Bin, <<"the cell restarted after an unexpected stop of the node">>)),
    {0, _} = cellrt(Config, ["stop"]),
    ok = await_down(Config).

%% SIGTERM (what `make run' turns Ctrl-C into) stops the applications in order.
sigterm_stops_cleanly(Config) ->
    Root = ?config(root, Config),
    {0, _} = cellrt(Config, ["daemon"]),
    ok = await_up(Config),
    {0, Pid} = cellrt(Config, ["eval", "os:getpid()."]),
    _ = os:cmd("kill -TERM " ++ string:trim(Pid, both, "\"\n ")),
    ok = await_down(Config),
    [Log] = filelib:wildcard(filename:join([Root, "Logs", "log *.log"])),
    {ok, Bin} = file:read_file(Log),
    ?assertNotEqual(nomatch, binary:match(Bin, <<"cellrt stopped">>)).

%% A malformed root folder setting is refused with a message naming it; the node
%% does not come up half-configured.
bad_root_folder_is_refused(Config) ->
    Env = lists:keystore("CELLRT_ROOT", 1, ?config(env, Config),
                         {"CELLRT_ROOT", "/proc/cellrt-cannot-create-this"}),
    {_, Out} = cellrt([{env, Env} | Config], ["foreground"], 60000),
    ?assertNotEqual(nomatch, string:find(Out, "cell_root_folder")).

%% The release carries its systemd unit, which restarts the node whatever the way it
%% ended and runs it in the foreground (so the VM is the service's process).
ships_a_systemd_unit(Config) ->
    Unit = filename:join(filename:dirname(filename:dirname(?config(bin, Config))),
                         "cellrt.service"),
    {ok, Bin} = file:read_file(Unit),
    [?assertNotEqual(nomatch, binary:match(Bin, Line), Line)
     || Line <- [<<"\nRestart=always\n">>, <<"\nExecStart=/opt/cellrt/bin/cellrt foreground\n">>,
                 <<"\nWantedBy=multi-user.target\n">>]].

%% `make run' (scripts/run) shows the cell's own lines, not the start script's and
%% heart's (the erlexec command line, the release folder, heart's pid); Ctrl-C (SIGINT
%% to the script) stops the cell in order and its last lines still show.
make_run_first_screen(Config) ->
    Bin = ?config(bin, Config),
    Rel = filename:dirname(filename:dirname(Bin)),
    Script = filename:join([cellrt_rel:top(), "scripts", "run"]),
    Env = [{"CELLRT_REL", Rel} | ?config(env, Config)],
    %% Started as from a terminal, where Ctrl-C is not ignored: a shell cannot trap a
    %% signal ignored when it started, and a test run in the background (nohup, CI
    %% runners) hands its children SIGINT ignored.
    Port = open_port({spawn_executable, os:find_executable("env")},
                     [{args, ["--default-signal=INT", Script]},
                      {env, Env}, exit_status, stderr_to_stdout, binary, {line, 4096}]),
    {os_pid, OsPid} = erlang:port_info(Port, os_pid),
    ok = await_up(Config),
    _ = os:cmd("kill -INT " ++ integer_to_list(OsPid)),
    {Status, Lines} = lines(Port, [], erlang:monotonic_time(millisecond) + 120000),
    Text = [string:trim(re:replace(L, "\\e\\[[0-9;]*m", "", [global, {return, list}]))
            || L <- Lines],
    ct:log("~s", [lists:join("\n", Text)]),
    ?assertEqual(0, Status),
    [?assertEqual([], [L || L <- Text, lists:prefix(Noise, L)], Noise)
     || Noise <- ["Exec: ", "Root: ", "heart_beat_kill_pid", Rel]],
    [?assert(lists:member(Line, Text), Line)
     || Line <- ["cellrt: Ctrl-C stops the cell", "cellrt: stopped"]],
    ?assertMatch([_], [L || L <- Text, lists:suffix("[notice] cellrt stopped", L)]),
    ?assertEqual("cellrt: stopped", lists:last(Text)).

%% What `make run' leaves out is only that chatter: a node that cannot boot says why
%% on its screen, and the script ends with the VM's failure.
make_run_shows_errors(Config) ->
    Rel = filename:dirname(filename:dirname(?config(bin, Config))),
    Script = filename:join([cellrt_rel:top(), "scripts", "run"]),
    Env = lists:keystore("CELLRT_ROOT", 1, [{"CELLRT_REL", Rel} | ?config(env, Config)],
                         {"CELLRT_ROOT", "/proc/cellrt-cannot-create-this"}),
    Port = open_port({spawn_executable, Script},
                     [{env, Env}, exit_status, stderr_to_stdout, binary, {line, 4096}]),
    {Status, Lines} = lines(Port, [], erlang:monotonic_time(millisecond) + 120000),
    ct:log("~s", [lists:join("\n", Lines)]),
    ?assertNotEqual(0, Status),
    ?assertNotEqual([], [L || L <- Lines, string:find(L, "cell_root_folder") =/= nomatch]),
    ?assertEqual("cellrt: stopped", lists:last(Lines)).

%% Helpers

%% A port's output lines and its exit status, by the deadline.
lines(Port, Acc, Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {Port, {data, {eol, L}}} -> lines(Port, [binary_to_list(L) | Acc], Deadline);
        {Port, {data, {noeol, L}}} -> lines(Port, [binary_to_list(L) | Acc], Deadline);
        {Port, {exit_status, S}} -> {S, lists:reverse(Acc)}
    after Left ->
        %% Which of the scripts and VMs still run, for whoever reads the failure.
        Ps = os:cmd("ps -eo pid,ppid,pgid,stat,args | grep -E 'scripts/run|priv/run|vplc|beam|foreground|heart' "
                    "| grep -v grep"),
        catch port_close(Port),
        ct:fail("timed out; output so far: ~p~nprocesses: ~s", [lists:reverse(Acc), Ps])
    end.

other_pid(Config, Pid) ->
    case cellrt(Config, ["eval", "os:getpid()."]) of
        {0, Pid2} -> string:trim(Pid2) =/= string:trim(Pid) andalso string:trim(Pid2) =/= "";
        _ -> false
    end.

parse(Out) ->
    {ok, Tokens, _} = erl_scan:string(string:trim(Out) ++ "."),
    {ok, Term} = erl_parse:parse_term(Tokens),
    {ok, Term}.

cellrt(Config, Args) ->
    cellrt(Config, Args, 30000).

cellrt(Config, Args, Timeout) ->
    cellrt_rel:run(?config(bin, Config), Args, ?config(env, Config), Timeout).

%% Up: answering ping, and its boot done (a node answers ping while its boot still
%% starts the applications).
await_up(Config) ->
    ok = await(Config, fun(Out) -> string:trim(Out) =:= "pong" end),
    {0, Out} = cellrt(Config, ["eval", cellrt_rel:await_boot_expr()], 120000),
    ?assertEqual("ok", string:trim(Out)),
    ok.

await_down(Config) ->
    await(Config, fun(Out) -> string:trim(Out) =/= "pong" end).

%% Two minutes: a node (and, for `make run', its virtual PLC before it) boots within
%% that on a busy machine.
await(Config, Done) ->
    cellrt_rel:await_ping(?config(bin, Config), ?config(env, Config), Done, 120000).
