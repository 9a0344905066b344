%% System tests of the operator panel in the built releases: the default release
%% serves the panel on the port it is given, and a release built with the prod
%% profile refuses to start while a demo account keeps its demo password, until
%% `bin/cellrt set_password' changed them with the cell stopped.
-module(web_release_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([release_serves_the_panel/1, prod_release_refuses_demo_passwords/1]).

all() ->
    [release_serves_the_panel, prod_release_refuses_demo_passwords].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    Config.

end_per_suite(Config) ->
    Config.

release_serves_the_panel(Config) ->
    Bin = filename:join([cellrt_rel:top(), "_build", "default", "rel", "cellrt", "bin", "cellrt"]),
    filelib:is_regular(Bin) orelse ct:fail("no release: build it with `rebar3 release`"),
    Env = env(Config, "web_default"),
    try
        {0, _} = run(Bin, ["daemon"], Env, 30000),
        ok = await_pong(Bin, Env, 100),
        ok = await_boot(Bin, Env),
        {0, Out} = run(Bin, ["eval", "cell_web:port()."], Env, 30000),
        Port = list_to_integer(string:trim(Out)),
        ?assert(Port > 0),
        Url = "http://127.0.0.1:" ++ integer_to_list(Port),
        {ok, {{_, 200, _}, _, Cell}} = httpc:request(get, {Url ++ "/api/cell", []}, [], []),
        ?assertNotEqual(nomatch, string:find(Cell, "\"state\":\"OFF\"")),
        %% The default cell: the simulated router, waiting for Start.
        {ok, {{_, 200, _}, _, Tasks}} = httpc:request(get, {Url ++ "/api/tasks", []}, [], []),
        ?assertNotEqual(nomatch, string:find(Tasks, "\"id\":\"loading_front\"")),
        ?assertEqual(nomatch, string:find(Tasks, "READY")),
        {ok, {{_, 200, _}, _, Page}} = httpc:request(get, {Url ++ "/", []}, [], []),
        ?assertNotEqual(nomatch, string:find(Page, "Start"))
    after
        run(Bin, ["stop"], Env, 30000)
    end.

prod_release_refuses_demo_passwords(Config) ->
    %% Build the prod release (a few seconds; the suite runs where `make test' built).
    {0, _} = run(os:find_executable("rebar3"), ["as", "prod", "release"], [], 300000, cellrt_rel:top()),
    Bin = filename:join([cellrt_rel:top(), "_build", "prod", "rel", "cellrt", "bin", "cellrt"]),
    Env = env(Config, "web_prod"),
    {Status, Out} = run(Bin, ["foreground"], Env, 120000),
    ?assertEqual(1, Status),
    ?assertNotEqual(nomatch, string:find(Out, "the demo accounts operator, service, admin still "
                                              "have their demo passwords")),
    %% The passwords changed with the release's own command (a password on standard
    %% input): too short and unknown users are refused, nothing is changed for them.
    {1, Short} = run_input(Bin, ["set_password", "admin"], Env, 60000, "short\n"),
    ?assertNotEqual(nomatch, string:find(Short, "at least 8 characters")),
    {1, Nobody} = run_input(Bin, ["set_password", "nobody"], Env, 60000, "long enough\n"),
    ?assertNotEqual(nomatch, string:find(Nobody, "no such user")),
    {1, Still} = run(Bin, ["foreground"], Env, 120000),
    ?assertNotEqual(nomatch, string:find(Still, "operator, service, admin")),
    [{0, _} = run_input(Bin, ["set_password", U], Env, 60000, "changed-" ++ U ++ "\n")
     || U <- ["operator", "service", "admin"]],
    %% A revision with who, and no hash in the log.
    {_, Root} = lists:keyfind("CELLRT_ROOT", 1, Env),
    {ok, Log} = file:read_file(hd(filelib:wildcard(filename:join([Root, "Logs", "log *"])))),
    ?assertNotEqual(nomatch, binary:match(Log, <<"users[3].hash: \"(hidden)\"">>)),
    ?assertNotEqual(nomatch, binary:match(Log, <<"(shell)">>)),
    try
        {0, _} = run(Bin, ["daemon"], Env, 30000),
        ok = await_pong(Bin, Env, 100),
        ok = await_boot(Bin, Env),
        %% The new password logs in; the command refuses to touch a running cell.
        {0, Ok} = run(Bin, ["eval", "cell_web_users:authenticate(<<\"admin\">>, "
                                    "<<\"changed-admin\">>)."], Env, 30000),
        ?assertNotEqual(nomatch, string:find(Ok, "{ok,")),
        {1, Running} = run_input(Bin, ["set_password", "admin"], Env, 60000, "another-one\n"),
        ?assertNotEqual(nomatch, string:find(Running, "The cell is running"))
    after
        run(Bin, ["stop"], Env, 30000)
    end.

%% Helpers

env(Config, Name) ->
    Root = filename:join(?config(priv_dir, Config), Name),
    Node = "cellrt_ct_" ++ Name ++ "_" ++ os:getpid() ++ "@localhost",
    [{"CELLRT_ROOT", Root}, {"CELLRT_NODE", Node}, {"CELLRT_COOKIE", "cellrt_ct"},
     {"CELLRT_WEB_PORT", "0"}].

run(Bin, Args, Env, Timeout) ->
    run(Bin, Args, Env, Timeout, filename:dirname(filename:dirname(Bin))).

run(Bin, Args, Env, Timeout, Dir) ->
    Port = open(Bin, Args, Env, Dir),
    cellrt_rel:collect(Port, Timeout).

%% As run/4, with `Input' on the command's standard input.
run_input(Bin, Args, Env, Timeout, Input) ->
    Port = open(Bin, Args, Env, filename:dirname(filename:dirname(Bin))),
    true = port_command(Port, Input),
    cellrt_rel:collect(Port, Timeout).

open(Bin, Args, Env, Dir) ->
    open_port({spawn_executable, Bin},
              [{args, Args}, {env, Env}, {cd, Dir}, exit_status, stderr_to_stdout, binary]).

%% A node answers ping while its boot still starts the applications.
await_boot(Bin, Env) ->
    {0, Out} = run(Bin, ["eval", cellrt_rel:await_boot_expr()], Env, 120000),
    ?assertEqual("ok", string:trim(Out)),
    ok.

%% `ping' waits for its answer: each try is a round trip, not a sleep.
await_pong(_Bin, _Env, 0) ->
    {error, timeout};
await_pong(Bin, Env, N) ->
    case run(Bin, ["ping"], Env, 30000) of
        {_, Out} ->
            case string:trim(Out) of
                "pong" -> ok;
                _ -> await_pong(Bin, Env, N - 1)
            end
    end.
