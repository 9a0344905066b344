%% The panel's REST API and websocket over real HTTP on 127.0.0.1: each endpoint, each
%% role, each kind of bad request (answered 4xx with a JSON error, nothing changed),
%% the audit trail, the live updates, and the refusal of demo passwords.
-module(cell_web_api_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-compile([export_all, nowarn_export_all]).

-define(TASKS, [{loader, <<"Loading">>}, {router, <<"Routing">>}]).

all() ->
    [pages_and_unknown_routes, session_login_logout, roles_are_enforced,
     csrf_and_origin_are_checked, foreign_host_names_are_refused, commands_change_the_cell, bad_requests_change_nothing,
     errors_are_answered, error_messages_carry_no_terms, warnings_are_closed, tasks_and_products, retained_data_is_read,
     log_is_queried,
     %% After log_is_queried: its errors are in the log that case reads.
     answer_refused_for_a_product_held_twice,
     settings_are_edited, recipes_up_and_down, recipe_drawing_and_dxf, users_are_managed,
     password_is_changed, statistics_and_history, statistics_charts, audit_trail_is_kept, audit_flood_is_bounded,
     audit_files_rotate_and_expire, websocket_snapshot_and_live,
     websocket_refusals, websocket_resyncs_when_behind, websocket_closes_when_session_ends,
     anonymous_view_can_be_switched_off, login_attempts_are_braked, login_brake_is_per_account,
     https_when_configured, demo_passwords_refused_when_configured,
     listener_waits_for_a_taken_port].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    Root = filename:join(?config(priv_dir, Config), "root"),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    %% Other suites of the same run may have left the cell running on their own root
    %% and spec: start afresh on ours.
    _ = [application:stop(A) || A <- [cell_web, cell, mnesia, cell_base]],
    _ = [application:load(A) || A <- [cell_base, cell, cell_web]],
    ok = application:set_env(cell_base, root, Root),
    %% The router runs on a snapshot of the machine settings, the loader on none.
    Specs = [with_settings(cell_web_demo_task:spec(Id, Z, <<"Front">>, self()))
             || {Id, Z} <- ?TASKS],
    ok = application:set_env(cell, cell_spec, #{name => <<"suite">>, tasks => Specs}),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    [{specs, Specs}, {root, Root} | Config].

with_settings(#{id := router} = Spec) -> Spec#{settings => machine};
with_settings(Spec) -> Spec.

end_per_suite(_Config) ->
    _ = [application:stop(A) || A <- [cell_web, cell, mnesia, cell_base]],
    ok = application:unset_env(cell, cell_spec),
    ok.

init_per_testcase(_Case, Config) ->
    [{port, cell_web:port()} | Config].

end_per_testcase(_Case, _Config) ->
    ok = cell_controller:stop(),
    ok = cell_controller:sync(),
    ok.

%% -------------------------------------------------------------------------------------
%% Helpers

anon(Config) -> cell_web_client:new(?config(port, Config)).

as(Role, Config) ->
    Name = atom_to_list(Role),
    {ok, C} = cell_web_client:login(anon(Config), Name, Name),
    C.

req(C, M, P) -> cell_web_client:req(C, M, P).
req(C, M, P, B) -> cell_web_client:req(C, M, P, B).

status(C, M, P) -> element(1, req(C, M, P)).
status(C, M, P, B) -> element(1, req(C, M, P, B)).

%% A 4xx with a JSON error: code and message.
assert_error(Status, Code, {Status, #{<<"error">> := Code, <<"message">> := M}, _}) ->
    ?assert(is_binary(M) andalso M =/= <<>>);
assert_error(Status, Code, Other) ->
    ct:fail("expected ~p ~s, got ~p", [Status, Code, Other]).

cmd(Config, Id, Command) ->
    [Spec] = [S || #{id := I} = S <- ?config(specs, Config), I =:= Id],
    ok = cell_web_demo_task:command(Spec, Id, Command),
    ok = cell_controller:sync(),
    ok = cell_alarms:sync().

started(Config) ->
    Op = as(operator, Config),
    {200, #{<<"request">> := <<"start">>}, _} = req(Op, post, "/api/cell/start"),
    ok = cell_controller:sync(),
    Op.

%% Waits for a message with a deadline.
await(Match, Timeout) ->
    receive
        M -> case Match(M) of
                 true -> M;
                 false -> await(Match, Timeout)
             end
    after Timeout -> ct:fail(timeout)
    end.

%% -------------------------------------------------------------------------------------

pages_and_unknown_routes(Config) ->
    A = anon(Config),
    {200, Html, H} = req(A, get, "/"),
    ?assertNotEqual(nomatch, binary:match(Html, <<"/app.js">>)),
    {_, Csp} = lists:keyfind("content-security-policy", 1, H),
    ?assertNotEqual(nomatch, string:find(Csp, "default-src 'none'")),
    {200, _, _} = req(A, get, "/app.js"),
    {200, _, _} = req(A, get, "/style.css"),
    assert_error(404, <<"not_found">>, req(A, get, "/api/nope")),
    assert_error(404, <<"not_found">>, req(A, get, "/etc/passwd")),
    assert_error(404, <<"not_found">>, req(A, post, "/api/cell/launch")),
    assert_error(405, <<"method_not_allowed">>, req(A, delete, "/api/cell")),
    {405, _, H405} = req(A, put, "/api/tasks"),
    ?assertEqual({"allow", "GET"}, lists:keyfind("allow", 1, H405)).

session_login_logout(Config) ->
    A = anon(Config),
    {200, #{<<"user">> := null, <<"role">> := <<"anonymous">>, <<"csrf">> := null}, _} =
        req(A, get, "/api/session"),
    assert_error(401, <<"bad_login">>, req(A, post, "/api/session",
                                           #{user => <<"operator">>, password => <<"x">>})),
    assert_error(401, <<"bad_login">>, req(A, post, "/api/session",
                                           #{user => <<"nobody">>, password => <<"x">>})),
    assert_error(400, <<"bad_request">>, req(A, post, "/api/session", #{user => 1})),
    {200, #{<<"user">> := <<"service">>, <<"role">> := <<"service">>,
            <<"demo_password">> := true}, H} =
        req(A, post, "/api/session", #{user => <<"service">>, password => <<"service">>}),
    [SetCookie] = [V || {"set-cookie", V} <- H],
    ?assertNotEqual(nomatch, string:find(SetCookie, "HttpOnly")),
    ?assertNotEqual(nomatch, string:find(SetCookie, "SameSite=Strict")),
    Sv = as(service, Config),
    {200, #{<<"user">> := <<"service">>}, _} = req(Sv, get, "/api/session"),
    {200, #{<<"user">> := null}, _} = req(Sv, delete, "/api/session"),
    %% The old cookie is worth nothing now.
    {200, #{<<"user">> := null}, _} = req(Sv, get, "/api/session"),
    assert_error(401, <<"login_required">>, req(Sv, post, "/api/cell/start")).

%% Every state-changing route refuses the roles below its own, and the cell is not
%% changed by a refused request.
roles_are_enforced(Config) ->
    Routes = [{post, "/api/cell/start", none, operator},
              {post, "/api/cell/stop", none, operator},
              {post, "/api/alarms/loader%3Ajam/answer", #{solution => retry}, operator},
              {put, "/api/settings/machine", #{speed_override => 60}, service},
              {post, "/api/settings/machine/restore", #{rev => 1}, service},
              {put, "/api/settings/web", #{idle_minutes => 5}, admin},
              {put, "/api/recipes/r1", {"application/zip", <<"PK">>}, service},
              {delete, "/api/recipes/r1", none, service},
              {post, "/api/recipes/r1/rename", #{to => <<"r2">>}, service},
              {put, "/api/recipes/r1/dxf", {"application/dxf", <<"0\nEOF\n">>}, service},
              {put, "/api/settings/oee", #{ideal_cycle_s => 5}, service},
              {get, "/api/users", none, admin},
              {put, "/api/users/x", #{role => <<"operator">>}, admin},
              {delete, "/api/users/operator", none, admin},
              {get, "/api/audit", none, service},
              {post, "/api/session/password", #{old => <<"a">>, new => <<"b">>}, operator}],
    Clients = [{anonymous, anon(Config)} | [{R, as(R, Config)} || R <- [operator, service]]],
    Before = {cell_controller:flags(), cell_settings:get(machine), cell_settings:get(web),
              cell_web_users:all(), cell_recipe:list()},
    [begin
         Rank = fun(anonymous) -> 0; (R) -> cell_web_users:rank(R) end,
         case Rank(Role) < Rank(Need) of
             true ->
                 Expected = case Role of anonymous -> 401; _ -> 403 end,
                 {S, #{<<"error">> := _}, _} = req(C, M, P, B),
                 ?assertEqual({M, P, Role, Expected}, {M, P, Role, S});
             false ->
                 ok
         end
     end || {M, P, B, Need} <- Routes, {Role, C} <- Clients],
    ?assertEqual(Before, {cell_controller:flags(), cell_settings:get(machine),
                          cell_settings:get(web), cell_web_users:all(), cell_recipe:list()}),
    %% Reading is open to anyone while anonymous viewing is on.
    [?assertEqual({P, 200}, {P, status(anon(Config), get, P)})
     || P <- ["/api/cell", "/api/tasks", "/api/alarms", "/api/alarms/history", "/api/log",
              "/api/products", "/api/statistics", "/api/statistics/charts", "/api/settings",
              "/api/settings/machine", "/api/recipes"]].

csrf_and_origin_are_checked(Config) ->
    Op = as(operator, Config),
    assert_error(403, <<"bad_csrf_token">>,
                 cell_web_client:req(Op, post, "/api/cell/start", none, [no_csrf])),
    assert_error(403, <<"bad_csrf_token">>,
                 cell_web_client:req(Op#{csrf := binary:copy(<<"0">>, 64)}, post,
                                     "/api/cell/start", none, [])),
    assert_error(403, <<"bad_origin">>,
                 cell_web_client:req(Op, post, "/api/cell/start", none,
                                     [{"origin", "http://evil.example"}])),
    ?assertEqual(stop, maps:get(request, cell_controller:flags())),
    Origin = "http://127.0.0.1:" ++ integer_to_list(?config(port, Config)),
    {200, _, _} = cell_web_client:req(Op, post, "/api/cell/start", none, [{"origin", Origin}]).

%% A page of another site whose name was made to resolve to this PC (DNS rebinding)
%% sends its own name in Host and Origin: refused, whatever it asks.
foreign_host_names_are_refused(Config) ->
    A = anon(Config),
    Op = as(operator, Config),
    Port = integer_to_list(?config(port, Config)),
    Rebound = [{"host", "attacker.example:" ++ Port}],
    assert_error(403, <<"unknown_host">>, cell_web_client:req(A, get, "/api/cell", none, Rebound)),
    {403, #{<<"message">> := M}, _} = cell_web_client:req(A, get, "/", none, Rebound),
    ?assertNotEqual(nomatch, binary:match(M, <<"attacker.example">>)),
    assert_error(403, <<"unknown_host">>,
                 cell_web_client:req(Op, post, "/api/cell/start", none,
                                     [{"origin", "http://attacker.example:" ++ Port} | Rebound])),
    assert_error(403, <<"bad_origin">>,
                 cell_web_client:req(Op, post, "/api/cell/start", none,
                                     [{"origin", "http://attacker.example:" ++ Port}])),
    assert_error(403, <<"bad_origin">>,
                 cell_web_client:req(A, get, "/api/cell", none,
                                     [{"origin", "http://attacker.example:" ++ Port}])),
    {error, 403} = cell_web_client:ws_connect(A, "http://attacker.example:" ++ Port),
    %% The panel's own names pass.
    {200, _, _} = cell_web_client:req(A, get, "/api/cell", none, [{"host", "localhost:" ++ Port}]),
    {200, _, _} = cell_web_client:req(A, get, "/api/cell", none, [{"host", "LOCALHOST"}]),
    {ok, Short} = inet:gethostname(),
    {200, _, _} = cell_web_client:req(A, get, "/api/cell", none, [{"host", Short}]).

commands_change_the_cell(Config) ->
    Op = started(Config),
    ?assertEqual({ready, idle, starved}, cell_controller:state()),
    {200, #{<<"request">> := <<"pause">>}, _} = req(Op, post, "/api/cell/pause"),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_controller:state()),
    {200, #{<<"state">> := <<"DOWN">>}, _} = req(Op, get, "/api/cell"),
    {200, _, _} = req(Op, post, "/api/cell/stop", #{}),
    ok = cell_controller:sync(),
    ?assertEqual(off, cell_controller:state()),
    %% Start during an emergency stop: refused, and said why.
    ok = cell_controller:estop(true),
    assert_error(409, <<"estop_active">>, req(Op, post, "/api/cell/start")),
    ok = cell_controller:estop(false).

bad_requests_change_nothing(Config) ->
    Sv = as(service, Config),
    Flags = cell_controller:flags(),
    Machine = cell_settings:get(machine),
    Raw = fun(M, P, Type, Body) -> cell_web_client:req(Sv, M, P, {Type, Body}) end,
    assert_error(400, <<"bad_json">>, Raw(post, "/api/cell/start", "application/json", <<"{bad">>)),
    assert_error(400, <<"bad_json">>, Raw(put, "/api/settings/machine", "application/json", <<"[1,2]">>)),
    assert_error(400, <<"bad_json">>, Raw(put, "/api/settings/machine", "application/json",
                                          <<"{\"a\":1,\"a\":2}">>)),
    assert_error(415, <<"unsupported_media_type">>,
                 Raw(put, "/api/settings/machine", "text/plain", <<"{}">>)),
    assert_error(422, <<"invalid">>, req(Sv, put, "/api/settings/machine",
                                         #{speed_override => <<"fast">>})),
    {422, #{<<"field">> := <<"speed_override">>}, _} =
        req(Sv, put, "/api/settings/machine", #{speed_override => 500}),
    {422, #{<<"field">> := <<"colour">>}, _} =
        req(Sv, put, "/api/settings/machine", #{colour => <<"red">>}),
    Big = jsx:encode(#{cell_name => binary:copy(<<"x">>, 70000)}),
    assert_error(413, <<"body_too_large">>, Raw(put, "/api/settings/machine", "application/json", Big)),
    assert_error(404, <<"not_found">>, req(Sv, get, "/api/settings/nothing")),
    assert_error(404, <<"not_found">>, req(Sv, get, "/api/settings/web_users")),
    assert_error(404, <<"not_found">>, req(Sv, get, "/api/tasks/nothing")),
    assert_error(404, <<"not_found">>, req(Sv, post, "/api/alarms/nothing%3Ahere/answer",
                                           #{solution => <<"retry">>})),
    assert_error(400, <<"bad_request">>, req(Sv, post, "/api/alarms/x/answer",
                                             #{solution => <<"explode">>})),
    assert_error(400, <<"bad_request">>, req(Sv, post, "/api/alarms/x/answer", #{solution => 1})),
    assert_error(400, <<"bad_query">>, req(Sv, get, "/api/log?limit=0")),
    assert_error(400, <<"bad_query">>, req(Sv, get, "/api/log?limit=abc")),
    assert_error(400, <<"bad_query">>, req(Sv, get, "/api/log?level=loud")),
    assert_error(400, <<"bad_query">>, req(Sv, get, "/api/log?from=yesterday")),
    assert_error(400, <<"bad_query">>, req(Sv, get, "/api/log?from=10&to=5")),
    assert_error(400, <<"bad_name">>, req(Sv, get, "/api/recipes/..%2Fetc")),
    ?assertEqual(Flags, cell_controller:flags()),
    ?assertEqual(Machine, cell_settings:get(machine)),
    ?assert(lists:keymember(cell_web, 1, application:which_applications())),
    {200, _, _} = req(Sv, get, "/api/cell").

errors_are_answered(Config) ->
    Op = started(Config),
    cmd(Config, loader, {error, [retry, reset]}),
    {200, [#{<<"id">> := Id, <<"kind">> := <<"error">>, <<"solutions">> := [<<"retry">>, <<"reset">>],
             <<"caption">> := <<"Board jammed">>}], _} = req(Op, get, "/api/alarms"),
    Path = "/api/alarms/" ++ uri_string:quote(binary_to_list(Id)) ++ "/answer",
    %% Not one of its solutions: refused, the error stays.
    {422, #{<<"allowed">> := [<<"retry">>, <<"reset">>]}, _} = req(Op, post, Path, #{solution => <<"ignore">>}),
    ?assertMatch({ok, _}, cell_alarms:get(Id)),
    {200, #{<<"solution">> := <<"retry">>}, _} = req(Op, post, Path, #{solution => <<"retry">>}),
    ok = cell_controller:sync(),
    ?assertEqual({ready, idle, starved}, cell_task_proc:state(loader)),
    assert_error(404, <<"not_found">>, req(Op, post, Path, #{solution => <<"retry">>})),
    {200, [#{<<"id">> := Id, <<"what">> := <<"retry">>, <<"who">> := <<"operator">>} | _], _} =
        req(Op, get, "/api/alarms/history").

%% Two tasks hold one serial: an answer that would let one go on with it is refused
%% (409, naming the serial and the other holder) and the error stays; Reset on the
%% double-holding error of the task where it is not settles it.
answer_refused_for_a_product_held_twice(Config) ->
    Op = started(Config),
    ok = cell_events:subscribe([alarm_raised, alarm_cleared]),
    Raised = fun(Id) -> fun({cell_event, #{type := alarm_raised, alarm := #{id := I}}}) -> I =:= Id;
                           (_) -> false
                        end
             end,
    cmd(Config, router, {product, <<"TWICE-1">>}),
    cmd(Config, loader, {product, <<"TWICE-1">>}),
    _ = await(Raised(<<"loader:held_twice">>), 10000),
    cmd(Config, loader, {error, [retry, reset]}),
    _ = await(Raised(<<"loader:jam">>), 10000),
    {409, #{<<"error">> := <<"double_holding">>, <<"serial">> := <<"TWICE-1">>,
            <<"held_by">> := [<<"router">>], <<"message">> := Message}, _} =
        req(Op, post, "/api/alarms/loader%3Ajam/answer", #{solution => <<"retry">>}),
    ?assertNotEqual(nomatch, string:find(Message, <<"held by router">>)),
    ?assertMatch({ok, _}, cell_alarms:get(<<"loader:jam">>)),
    {200, _, _} = req(Op, post, "/api/alarms/loader%3Aheld_twice/answer", #{solution => <<"reset">>}),
    _ = await(fun({cell_event, #{type := alarm_cleared, alarm := #{id := <<"router:held_twice">>}}}) -> true;
                 (_) -> false
              end, 10000),
    %% The loader forgot the product, and with it the error it waited on.
    ?assertEqual({error, not_found}, cell_alarms:get(<<"loader:jam">>)),
    cmd(Config, router, {product, undefined}),
    ok = cell_events:unsubscribe().

%% Every refusal is said in words: no answer carries an Erlang term (a tuple opening
%% with an atom, a binary, a map, a pid), however odd the request.
error_messages_carry_no_terms(Config) ->
    Sv = as(service, Config),
    Ad = as(admin, Config),
    Huge = 1000000000000000000000000000000,
    Deep = #{speed_override => #{<<"a">> => [<<"b">>, #{<<"c">> => 1}]}},
    Requests =
        [{Sv, post, "/api/settings/machine/restore", #{rev => Huge}},
         {Sv, post, "/api/settings/machine/restore", #{rev => 999}},
         {Sv, post, "/api/settings/machine/restore", #{rev => <<"x">>}},
         {Sv, get, "/api/settings/machine/revisions/" ++ integer_to_list(Huge), none},
         {Sv, get, "/api/settings/machine/diff?from=1&to=" ++ integer_to_list(Huge), none},
         {Sv, get, "/api/settings/nothing", none},
         {Sv, put, "/api/settings/machine", Deep},
         {Sv, put, "/api/settings/machine", #{speed_override => [1, <<"x">>]}},
         {Sv, put, "/api/settings/machine", #{speed_override => <<"fast">>}},
         {Sv, put, "/api/settings/machine", {"application/json", <<"[1,2]">>}},
         {Sv, put, "/api/settings/machine", {"application/json", <<"{\"a\":">>}},
         {Sv, put, "/api/settings/machine", {"text/plain", <<"x">>}},
         {Ad, put, "/api/users/admin", #{role => <<"service">>}},
         {Ad, put, "/api/users/x%20y", #{role => <<"operator">>, password => <<"s3cret-pass">>}},
         {Ad, put, "/api/users/newbie", #{role => #{<<"a">> => 1}, password => [1]}},
         {Ad, put, "/api/users/newbie", #{role => <<"king">>, password => <<"s3cret-pass">>}},
         {Sv, get, "/api/recipes/CON", none},
         {Sv, get, "/api/recipes/a%3Ab", none},
         {Sv, get, "/api/recipes/nothing-here", none},
         {Sv, post, "/api/recipes/nothing-here/copy", #{to => <<"a%3Ab">>}},
         {Sv, post, "/api/recipes/nothing-here/rename", #{to => #{}}},
         {Sv, put, "/api/recipes/x/file", {"application/zip", <<"PK not a zip">>}},
         {Sv, post, "/api/alarms/nothing/answer", #{solution => <<"retry">>}},
         {Sv, post, "/api/alarms/x/answer", #{solution => #{}}},
         {Sv, post, "/api/inspect/messages/answer",
          #{block => <<"b">>, ref => <<"r">>, answer => <<"yes">>}},
         {Sv, get, "/api/products/nothing", none},
         {Sv, get, "/api/log?from=yesterday&limit=" ++ integer_to_list(Huge), none},
         {Sv, get, "/api/audit?from=x", none},
         {Sv, post, "/api/session/password", #{old => <<"service">>, new => [<<"x">>]}},
         {Sv, post, "/api/cell/launch", none},
         {Sv, get, "/api/tasks/nothing/retained", none}],
    lists:foreach(
      fun({C, M, P, B}) ->
              {Status, Body, _} = req(C, M, P, B),
              Text = case is_map(Body) of
                         true -> jsx:encode(Body);
                         false -> Body
                     end,
              ?assertEqual({M, P, true}, {M, P, Status >= 400 orelse Status}),
              ?assertEqual({M, P, false}, {M, P, cell_web_words:has_terms(Text)})
      end, Requests),
    %% The restore of a revision that cannot exist says so.
    {404, #{<<"message">> := Words}, _} =
        req(Sv, post, "/api/settings/machine/restore", #{rev => Huge}),
    ?assertNotEqual(nomatch, binary:match(Words, <<"there is no revision">>)).

warnings_are_closed(Config) ->
    Op = started(Config),
    cmd(Config, router, {warning, <<"low">>, <<"Low on boxes">>}),
    Path = "/api/alarms/router%3Alow/answer",
    {422, #{<<"allowed">> := [<<"close">>]}, _} = req(Op, post, Path, #{solution => <<"retry">>}),
    {200, _, _} = req(Op, post, Path, #{solution => <<"close">>}),
    ?assertEqual([], cell_alarms:list()),
    %% An alarm has no solution an operator could give.
    ok = cell_controller:estop(true),
    {422, #{<<"allowed">> := []}, _} = req(Op, post, "/api/alarms/cell%3Aestop/answer",
                                           #{solution => <<"close">>}),
    ok = cell_controller:estop(false).

tasks_and_products(Config) ->
    Op = started(Config),
    cmd(Config, router, {product, <<"P-7">>}),
    cmd(Config, router, {event, unstarved}),
    {200, [#{<<"id">> := <<"loader">>, <<"state">> := <<"READY-IDLE-STARVED">>, <<"serial">> := null},
           #{<<"id">> := <<"router">>, <<"state">> := <<"READY-PROCESSING-ACTIVE">>,
             <<"serial">> := <<"P-7">>, <<"zone">> := <<"Routing">>}], _} = req(Op, get, "/api/tasks"),
    {200, #{<<"id">> := <<"router">>, <<"request">> := <<"start">>, <<"down">> := null,
            <<"product">> := #{<<"serial">> := <<"P-7">>, <<"recipe">> := <<"demo">>},
            <<"settings">> := #{<<"name">> := <<"machine">>, <<"pending">> := false,
                                <<"in_force">> := #{<<"speed_override">> := Speed}}}, _} =
        req(Op, get, "/api/tasks/router"),
    ?assertEqual(Speed, cell_settings:get(machine, speed_override)),
    {200, #{<<"settings">> := null}, _} = req(Op, get, "/api/tasks/loader"),
    {200, [#{<<"serial">> := <<"P-7">>, <<"task">> := <<"router">>}], _} = req(Op, get, "/api/products"),
    {200, #{<<"in_cell">> := [#{<<"task">> := <<"router">>}]}, _} = req(Op, get, "/api/products/P-7"),
    assert_error(404, <<"not_found">>, req(Op, get, "/api/products/P-8")),
    %% The statistics record the product as it happens; a flush waits for them.
    ok = cell_stats:flush(),
    {200, #{<<"serial">> := <<"P-7">>, <<"status">> := <<"in_cell">>, <<"recipe">> := <<"demo">>,
            <<"events">> := [#{<<"event">> := <<"entered">>, <<"task">> := <<"router">>} | _],
            <<"in_cell">> := [#{<<"task">> := <<"router">>}]}, _} =
        req(Op, get, "/api/products/P-7/history"),
    assert_error(404, <<"not_found">>, req(Op, get, "/api/products/P-8/history")),
    cmd(Config, router, {product, undefined}),
    {200, [], _} = req(Op, get, "/api/products"),
    ok = cell_controller:pause(),
    ok = cell_controller:sync(),
    {200, #{<<"state">> := <<"DOWN">>, <<"down">> := #{<<"why">> := <<"paused">>}}, _} =
        req(Op, get, "/api/tasks/router").

%% A task's retained data, read-only, for anyone who may view: as the task last made it
%% durable, plain values as JSON.
retained_data_is_read(Config) ->
    _ = started(Config),
    A = anon(Config),
    cmd(Config, router, {retain, serial, 41}),
    cmd(Config, router, {retain, <<"tool">>, #{wear => 0.25, changed => <<"2026-11-27">>}}),
    {200, #{<<"task">> := <<"router">>, <<"zone">> := <<"Routing">>, <<"lane">> := <<"Front">>,
            <<"retained">> := #{<<"serial">> := 41,
                                <<"tool">> := #{<<"wear">> := 0.25,
                                                <<"changed">> := <<"2026-11-27">>}},
            <<"error">> := null}, _} = req(A, get, "/api/tasks/router/retained"),
    cmd(Config, router, {retain, serial, 42}),
    {200, #{<<"retained">> := #{<<"serial">> := 42}}, _} =
        req(A, get, "/api/tasks/router/retained"),
    {200, #{<<"task">> := <<"loader">>, <<"retained">> := Empty, <<"error">> := null}, _} =
        req(A, get, "/api/tasks/loader/retained"),
    ?assertEqual(#{}, Empty),
    assert_error(404, <<"not_found">>, req(A, get, "/api/tasks/nothing/retained")),
    {405, _, H} = req(as(admin, Config), put, "/api/tasks/router/retained", #{serial => 1}),
    ?assertEqual({"allow", "GET"}, lists:keyfind("allow", 1, H)),
    cmd(Config, router, {forget_retained, <<"tool">>}),
    {200, #{<<"retained">> := Left}, _} = req(A, get, "/api/tasks/router/retained"),
    ?assertEqual(#{<<"serial">> => 42}, Left).

log_is_queried(Config) ->
    A = anon(Config),
    _ = started(Config),
    cmd(Config, router, {log, <<"cut 1 of 3">>}),
    cmd(Config, router, {log, <<"cut 2 of 3">>}),
    cmd(Config, router, {log, <<"cut 3 of 3">>}),
    %% The task sent its lines to the log's event manager before it answered the sync
    %% above; a call to the manager returns after it has written them.
    _ = gen_event:which_handlers(lager_event),
    {200, #{<<"lines">> := Lines}, _} = req(A, get, "/api/log?task=router&level=brief"),
    Cuts = [T || #{<<"text">> := <<"cut", _/binary>> = T} <- Lines],
    ?assertEqual([<<"cut 1 of 3">>, <<"cut 2 of 3">>, <<"cut 3 of 3">>], Cuts),
    ?assert(lists:all(fun(#{<<"source">> := S, <<"level">> := L}) ->
                              S =:= <<"router">> andalso L =:= <<"brief">> end, Lines)),
    N = length(Lines),
    {200, #{<<"lines">> := Page1, <<"more">> := true}, _} =
        req(A, get, "/api/log?task=router&level=brief&limit=" ++ integer_to_list(N - 1)),
    {200, #{<<"lines">> := Page2, <<"more">> := false}, _} =
        req(A, get, "/api/log?task=router&level=brief&offset=" ++ integer_to_list(N - 1)),
    ?assertEqual(Lines, Page1 ++ Page2),
    {200, #{<<"lines">> := []}, _} = req(A, get, "/api/log?task=router&level=error"),
    Future = os:system_time(millisecond) + 3600000,
    {200, #{<<"lines">> := []}, _} =
        req(A, get, io_lib:format("/api/log?from=~p&to=~p", [Future, Future + 1000])),
    %% A time range gives the lines from its start up to, not including, its end.
    [T1, _, T3] = [T || #{<<"text">> := <<"cut", _/binary>>, <<"time">> := T} <- Lines],
    {200, #{<<"lines">> := First}, _} =
        req(A, get, io_lib:format("/api/log?task=router&from=~p&to=~p", [T1, T1 + 1])),
    ?assert(lists:member(<<"cut 1 of 3">>, [T || #{<<"text">> := T} <- First])),
    ?assertEqual([T1], lists:usort([T || #{<<"time">> := T} <- First])),
    {200, #{<<"lines">> := After}, _} =
        req(A, get, io_lib:format("/api/log?task=router&from=~p", [T3 + 1])),
    ?assertEqual([], [L || #{<<"time">> := T} = L <- After, T =< T3]),
    {200, #{<<"lines">> := Before}, _} =
        req(A, get, io_lib:format("/api/log?task=router&to=~p", [T1])),
    ?assertEqual([], [L || #{<<"time">> := T} = L <- Before, T >= T1]).

settings_are_edited(Config) ->
    Sv = as(service, Config),
    {200, Names, _} = req(Sv, get, "/api/settings"),
    ?assertEqual([<<"machine">>, <<"oee">>, <<"statistics">>, <<"web">>],
                 lists:sort([N || #{<<"name">> := N} <- Names])),
    {200, #{<<"values">> := #{<<"speed_override">> := Old}, <<"fields">> := Fields}, _} =
        req(Sv, get, "/api/settings/machine"),
    [#{<<"type">> := <<"integer">>, <<"min">> := 1, <<"max">> := 100, <<"unit">> := <<"%">>,
       <<"default">> := 50}] =
        [F || #{<<"name">> := <<"speed_override">>} = F <- Fields],
    %% A refused value names its field, for the form to show it there.
    {422, #{<<"error">> := <<"invalid">>, <<"field">> := <<"speed_override">>}, _} =
        req(Sv, put, "/api/settings/machine", #{speed_override => 101}),
    ok = cell_controller:start(), ok = cell_controller:sync(),
    New = Old rem 100 + 1,
    {200, #{<<"values">> := #{<<"speed_override">> := New}, <<"pending">> := true,
            <<"in_force">> := #{<<"speed_override">> := Old}}, _} =
        req(Sv, put, "/api/settings/machine", #{speed_override => New}),
    ?assertEqual(New, cell_settings:get(machine, speed_override)),
    %% The task runs on what was in force at Start until the next one.
    {200, #{<<"settings">> := #{<<"pending">> := true,
                                <<"in_force">> := #{<<"speed_override">> := Old}}}, _} =
        req(Sv, get, "/api/tasks/router"),
    {200, [#{<<"rev">> := Rev, <<"who">> := <<"service">>}, #{<<"rev">> := Prev} | _], _} =
        req(Sv, get, "/api/settings/machine/revisions"),
    {200, #{<<"values">> := #{<<"speed_override">> := Old}}, _} =
        req(Sv, get, "/api/settings/machine/revisions/" ++ integer_to_list(Prev)),
    {200, [#{<<"path">> := <<"speed_override">>, <<"from">> := Old, <<"to">> := New}], _} =
        req(Sv, get, io_lib:format("/api/settings/machine/diff?from=~p&to=~p", [Prev, Rev])),
    assert_error(404, <<"not_found">>, req(Sv, get, "/api/settings/machine/revisions/999")),
    {200, #{<<"values">> := #{<<"speed_override">> := Old}}, _} =
        req(Sv, post, "/api/settings/machine/restore", #{rev => Prev}),
    assert_error(404, <<"not_found">>, req(Sv, post, "/api/settings/machine/restore", #{rev => 999})),
    %% The panel's own settings need an admin.
    Ad = as(admin, Config),
    {200, #{<<"values">> := #{<<"idle_minutes">> := 45}}, _} =
        req(Ad, put, "/api/settings/web", #{idle_minutes => 45}),
    {200, _, _} = req(Ad, put, "/api/settings/web", #{idle_minutes => 30}).

recipes_up_and_down(Config) ->
    Sv = as(service, Config),
    {ok, Zip} = cell_recipe:encode(#{description => <<"two boards">>, author => <<"t">>,
                                     modified => 0}, #{}),
    Up = fun(Name, Bin) -> req(Sv, put, "/api/recipes/" ++ Name, {"application/zip", Bin}) end,
    {201, #{<<"name">> := <<"Board A">>, <<"description">> := <<"two boards">>}, _} =
        Up("Board%20A", Zip),
    assert_error(409, <<"exists">>, Up("Board%20A", Zip)),
    {200, _, _} = req(Sv, put, "/api/recipes/Board%20A?replace=true", {"application/zip", Zip}),
    assert_error(422, <<"invalid_recipe">>, Up("Broken", <<"PK not a zip at all">>)),
    assert_error(400, <<"bad_request">>, Up("Empty", <<>>)),
    assert_error(415, <<"unsupported_media_type">>,
                 req(Sv, put, "/api/recipes/X", {"text/plain", Zip})),
    ?assertEqual([<<"Board A">>], cell_recipe:list()),
    {200, [#{<<"name">> := <<"Board A">>}], _} = req(Sv, get, "/api/recipes"),
    {200, Bin, H} = req(Sv, get, "/api/recipes/Board%20A/file"),
    ?assertEqual({ok, Bin}, cell_recipe:export(<<"Board A">>)),
    {_, Disposition} = lists:keyfind("content-disposition", 1, H),
    ?assertNotEqual(nomatch, string:find(Disposition, "Board%20A.zprd")),
    {200, _, _} = req(Sv, post, "/api/recipes/Board%20A/copy", #{to => <<"Board B">>}),
    assert_error(409, <<"exists">>, req(Sv, post, "/api/recipes/Board%20A/rename", #{to => <<"Board B">>})),
    {200, _, _} = req(Sv, post, "/api/recipes/Board%20B/rename", #{to => <<"Board C">>}),
    ?assertEqual([<<"Board A">>, <<"Board C">>], cell_recipe:list()),
    {200, _, _} = req(Sv, delete, "/api/recipes/Board%20C"),
    assert_error(404, <<"not_found">>, req(Sv, delete, "/api/recipes/Board%20C")),
    assert_error(404, <<"not_found">>, req(Sv, get, "/api/recipes/Nothing")),
    {200, _, _} = req(Sv, delete, "/api/recipes/Board%20A").

recipe_drawing_and_dxf(Config) ->
    Sv = as(service, Config),
    %% A drawing whose cut sits in a moved container: the tree comes in drawing
    %% coordinates, the move applied.
    D = cell_recipe_drawing,
    Cut = D:container(#{<<"ItemType">> => <<"Cut">>, <<"ExecOrder">> => <<"1">>,
                        <<"Transform">> => D:matrix_to_text(D:translation(100, 0, 0))},
                      [D:line({0, 0}, {0, 10})]),
    ok = cell_recipe:save(<<"Drawn">>, #{drawing => D:new([Cut])}, <<"t">>),
    {200, #{<<"kind">> := <<"container">>,
            <<"children">> := [#{<<"attributes">> := Attrs,
                                 <<"children">> := [#{<<"kind">> := <<"line">>,
                                                      <<"from">> := [100.0, 0.0, 0.0],
                                                      <<"to">> := [100.0, 10.0, 0.0]}]}]}, _} =
        req(Sv, get, "/api/recipes/Drawn/drawing"),
    ?assertEqual(#{<<"ItemType">> => <<"Cut">>, <<"ExecOrder">> => <<"1">>}, Attrs),
    assert_error(404, <<"not_found">>, req(Sv, get, "/api/recipes/Nothing/drawing")),
    %% A DXF made a recipe; what it cannot hold is counted.
    Dxf = <<"0\nSECTION\n2\nENTITIES\n0\nLINE\n8\nA\n10\n0\n20\n0\n30\n0\n11\n5\n21\n0\n31\n0\n"
            "0\nTEXT\n8\nA\n10\n0\n20\n0\n30\n0\n40\n1\n1\nx\n0\nENDSEC\n0\nEOF\n">>,
    {201, #{<<"imported">> := 1, <<"skipped">> := #{<<"TEXT">> := 1},
            <<"recipe">> := #{<<"name">> := <<"From CAD">>, <<"author">> := <<"service">>}}, _} =
        req(Sv, put, "/api/recipes/From%20CAD/dxf", {"application/dxf", Dxf}),
    {ok, #{drawing := Drawn}} = cell_recipe:load(<<"From CAD">>),
    ?assertEqual(1, D:count(Drawn)),
    %% Not over an existing recipe unless asked; then its settings are kept.
    assert_error(409, <<"exists">>, req(Sv, put, "/api/recipes/Drawn/dxf", {"application/dxf", Dxf})),
    {ok, #{settings := Settings}} = cell_recipe:load(<<"Drawn">>),
    {200, #{<<"imported">> := 1}, _} =
        req(Sv, put, "/api/recipes/Drawn/dxf?replace=true", {"text/plain", Dxf}),
    ?assertMatch({ok, #{settings := Settings}}, cell_recipe:load(<<"Drawn">>)),
    %% A file that is no DXF: refused with its line, nothing written.
    assert_error(422, <<"invalid_dxf">>,
                 req(Sv, put, "/api/recipes/Bad/dxf", {"application/dxf", <<"0\nSECTION\n2\nENTITIES\n">>})),
    assert_error(415, <<"unsupported_media_type">>,
                 req(Sv, put, "/api/recipes/Bad/dxf", {"application/json", Dxf})),
    ?assertEqual([<<"Drawn">>, <<"From CAD">>], cell_recipe:list()),
    [ok = cell_recipe:delete(N) || N <- cell_recipe:list()].

users_are_managed(Config) ->
    Ad = as(admin, Config),
    {200, Users, _} = req(Ad, get, "/api/users"),
    ?assertEqual([<<"operator">>, <<"service">>, <<"admin">>], [N || #{<<"name">> := N} <- Users]),
    ?assert(lists:all(fun(U) -> lists:sort(maps:keys(U)) =:= [<<"name">>, <<"role">>] end, Users)),
    {201, _, _} = req(Ad, put, "/api/users/jdoe", #{role => <<"operator">>, password => <<"s3cret-pass">>}),
    assert_error(422, <<"weak_password">>, req(Ad, put, "/api/users/kim",
                                               #{role => <<"operator">>, password => <<"short">>})),
    assert_error(422, <<"invalid">>, req(Ad, put, "/api/users/kim", #{role => <<"operator">>})),
    assert_error(400, <<"bad_request">>, req(Ad, put, "/api/users/kim", #{role => <<"root">>})),
    assert_error(400, <<"bad_request">>, req(Ad, put, "/api/users/kim", #{hash => <<"x">>})),
    assert_error(400, <<"bad_name">>, req(Ad, put, "/api/users/a%20b",
                                          #{role => <<"operator">>, password => <<"s3cret-pass">>})),
    {ok, J} = cell_web_client:login(anon(Config), "jdoe", "s3cret-pass"),
    {200, #{<<"role">> := <<"operator">>}, _} = req(J, get, "/api/session"),
    %% A changed role ends the user's sessions at once.
    {200, _, _} = req(Ad, put, "/api/users/jdoe", #{role => <<"service">>}),
    {200, #{<<"user">> := null}, _} = req(J, get, "/api/session"),
    {200, _, _} = req(Ad, delete, "/api/users/jdoe"),
    {error, 401, _} = cell_web_client:login(anon(Config), "jdoe", "s3cret-pass"),
    assert_error(409, <<"last_admin">>, req(Ad, delete, "/api/users/admin")),
    assert_error(409, <<"last_admin">>, req(Ad, put, "/api/users/admin", #{role => <<"service">>})),
    assert_error(404, <<"not_found">>, req(Ad, delete, "/api/users/nobody")).

password_is_changed(Config) ->
    Op = as(operator, Config),
    assert_error(403, <<"bad_password">>, req(Op, post, "/api/session/password",
                                              #{old => <<"wrong">>, new => <<"new-secret-1">>})),
    assert_error(422, <<"weak_password">>, req(Op, post, "/api/session/password",
                                               #{old => <<"operator">>, new => <<"short">>})),
    {200, #{<<"user">> := <<"operator">>, <<"demo_password">> := false}, H} =
        req(Op, post, "/api/session/password", #{old => <<"operator">>, new => <<"new-secret-1">>}),
    ?assertNot(lists:member(<<"operator">>, cell_web_users:demo_accounts())),
    %% The old session ended; the answer carries the new one.
    {200, #{<<"user">> := null}, _} = req(Op, get, "/api/session"),
    [Cookie] = [hd(string:split(V, ";")) || {"set-cookie", V} <- H],
    {200, #{<<"user">> := <<"operator">>}, _} = req(Op#{cookie := Cookie}, get, "/api/session"),
    %% Back to the demo password for the cases that follow ("operator" has 8 characters).
    {ok, updated} = cell_web_users:set_password(<<"operator">>, <<"operator">>, <<"suite">>).

statistics_and_history(Config) ->
    A = anon(Config),
    _ = started(Config),
    ok = cell_stats:flush(),
    {200, #{<<"tasks">> := #{<<"total">> := 2, <<"by_state">> := #{<<"READY-IDLE-STARVED">> := 2}},
            <<"production">> := #{<<"cell">> := #{<<"in">> := In0},
                                  <<"tasks">> := #{<<"router">> := #{<<"time_ms">> := _}}},
            <<"periods">> := [<<"total">> | _], <<"active">> := #{<<"errors">> := 0}}, _} =
        req(A, get, "/api/statistics?period=total"),
    %% A product enters the cell: the production figures count it.
    cmd(Config, router, {product, <<"P-9">>}),
    ok = cell_stats:flush(),
    {200, #{<<"production">> := #{<<"period">> := <<"total">>, <<"cell">> := #{<<"in">> := In1},
                                  <<"in_cell">> := InCell}}, _} =
        req(A, get, "/api/statistics?period=total"),
    ?assertEqual(In0 + 1, In1),
    ?assert(InCell >= 1),
    cmd(Config, router, {product, undefined}),
    {200, #{<<"production">> := #{<<"cell">> := #{<<"in">> := _}}}, _} =
        req(A, get, "/api/statistics"),
    assert_error(404, <<"not_found">>, req(A, get, "/api/statistics?period=1999-01-01/1")).

statistics_charts(Config) ->
    A = anon(Config),
    Op = started(Config),
    %% Two products through the cell.
    [begin cmd(Config, router, {product, S}), cmd(Config, router, {product, undefined}) end
     || S <- [<<"C-1">>, <<"C-2">>]],
    {200, _, _} = req(Op, post, "/api/cell/stop"),
    ok = cell_controller:sync(),
    ok = cell_stats:flush(),
    {200, #{<<"production">> := Prod}, _} = req(A, get, "/api/statistics?period=shift"),
    {200, #{<<"selection">> := #{<<"kind">> := <<"period">>, <<"label">> := Label},
            <<"shifts">> := [Shift], <<"sum">> := Sum, <<"hourly">> := Hours,
            <<"cycles">> := #{<<"n">> := N, <<"histogram">> := Bins},
            <<"hourly_from">> := HourlyFrom, <<"ideal_cycle_ms">> := Ideal}, _} =
        req(A, get, "/api/statistics/charts"),
    %% A shift is shorter than 31 days: its products out are counted from its start.
    ?assertMatch(#{<<"from">> := HourlyFrom}, Sum),
    ?assertEqual(maps:get(<<"period">>, Prod), Label),
    %% The shift is /api/statistics's with its OEE. The tasks are all OFF: that time,
    %% and the span with it, grows with every write (once a second) and may have grown
    %% between the two reads; the rest was written before them.
    ?assertEqual(steady(Prod), steady(maps:remove(<<"oee">>, Shift))),
    #{<<"cell">> := #{<<"out">> := Out, <<"good">> := Good}} = Prod,
    ?assert(Out >= 2),
    ?assertEqual(Out, lists:sum([O || #{<<"out">> := O} <- Hours])),
    ?assertEqual(N, lists:sum([C || #{<<"count">> := C} <- Bins])),
    ?assertEqual(Out - 1, N),
    ?assertMatch(#{<<"quality">> := Q} when Q == Good / Out, maps:get(<<"oee">>, Shift)),
    ?assertMatch(#{<<"cell">> := #{<<"out">> := Out}}, Sum),
    %% The ideal cycle time is a setting.
    Sv = as(service, Config),
    {200, _, _} = req(Sv, put, "/api/settings/oee", #{ideal_cycle_s => 2.5}),
    {200, #{<<"ideal_cycle_ms">> := 2500.0}, _} = req(A, get, "/api/statistics/charts"),
    ?assert(Ideal =/= 2500.0),
    %% A day and a range hold the shift. The day is the one the shift is named for (the
    %% day it began: just after midnight that is yesterday's).
    [Day | _] = string:split(binary_to_list(Label), "/"),
    {200, #{<<"selection">> := #{<<"kind">> := <<"day">>}, <<"shifts">> := Days}, _} =
        req(A, get, "/api/statistics/charts?day=" ++ Day),
    ?assert(lists:any(fun(#{<<"period">> := P}) -> P =:= Label end, Days)),
    Now = os:system_time(millisecond),
    {200, #{<<"selection">> := #{<<"kind">> := <<"range">>}, <<"shifts">> := Ranged}, _} =
        req(A, get, io_lib:format("/api/statistics/charts?from=~b&to=~b", [Now - 60000, Now])),
    ?assert(lists:any(fun(#{<<"period">> := P}) -> P =:= Label end, Ranged)),
    %% Bad choices are refused.
    assert_error(400, <<"bad_query">>, req(A, get, "/api/statistics/charts?day=2024-02-30")),
    assert_error(400, <<"bad_query">>, req(A, get, "/api/statistics/charts?day=yesterday")),
    assert_error(400, <<"bad_query">>,
                 req(A, get, io_lib:format("/api/statistics/charts?from=~b&to=~b", [Now, Now - 1]))),
    assert_error(400, <<"bad_query">>,
                 req(A, get, io_lib:format("/api/statistics/charts?from=~b&to=~b",
                                           [Now - 32 * 86400000, Now]))),
    assert_error(404, <<"not_found">>, req(A, get, "/api/statistics/charts?period=1999-01-01/1")),
    {200, _, _} = req(Sv, put, "/api/settings/oee", #{ideal_cycle_s => 60}).

%% A summary without what grows while nothing happens.
steady(#{<<"cell">> := Cell, <<"tasks">> := Tasks} = S) ->
    (maps:without([<<"to">>], S))#{
      <<"cell">> := maps:remove(<<"throughput_per_hour">>, Cell),
      <<"tasks">> := maps:map(fun(_, #{<<"time_ms">> := T} = Task) ->
                                      (maps:without([<<"total_ms">>, <<"share">>], Task))#{
                                        <<"time_ms">> := maps:remove(<<"off">>, T)}
                              end, Tasks)}.

audit_trail_is_kept(Config) ->
    Op = as(operator, Config),
    T0 = os:system_time(millisecond),
    {200, _, _} = req(Op, post, "/api/cell/start"),
    {403, _, _} = req(Op, put, "/api/settings/machine", #{speed_override => 10}),
    assert_error(403, <<"forbidden">>, req(Op, get, "/api/audit")),
    Sv = as(service, Config),
    {200, #{<<"entries">> := Entries}, _} =
        req(Sv, get, "/api/audit?who=operator&from=" ++ integer_to_list(T0)),
    ?assertMatch([#{<<"who">> := <<"operator">>, <<"role">> := <<"operator">>,
                    <<"address">> := <<"127.0.0.1">>, <<"action">> := <<"POST">>,
                    <<"target">> := <<"/api/cell/start">>, <<"outcome">> := <<"200">>},
                  #{<<"action">> := <<"PUT">>, <<"outcome">> := <<"403">>}], Entries),
    %% On disk, one line each, in the day's file.
    {ok, Files} = file:list_dir(filename:join(?config(root, Config), "Logs")),
    ?assert(lists:any(fun(F) -> lists:prefix("audit ", F) end, Files)).

audit_flood_is_bounded(Config) ->
    Dir = filename:join(?config(root, Config), "Logs"),
    %% The refusals of the cases before are written: the flood begins a minute.
    ok = cell_web_audit:flush(),
    Before = audit_files(Dir),
    A = anon(Config),
    Long = "/api/cell/" ++ lists:duplicate(2048, $x),
    [{404, _, _} = req(A, post, Long) || _ <- lists:seq(1, 300)],
    %% At most one line (the first of the address in its minute), the path cut short;
    %% the rest counted.
    Added = added_lines(Before, audit_files(Dir)),
    ?assert(length(Added) =< 1),
    ?assert(iolist_size(Added) < 1024),
    ok = cell_web_audit:flush(),
    Count = lists:last(added_lines(Before, audit_files(Dir))),
    #{<<"address">> := <<"127.0.0.1">>, <<"detail">> := Detail, <<"target">> := Target} =
        jsx:decode(Count, [return_maps]),
    [N | _] = binary:split(Detail, <<" ">>),
    ?assert(binary_to_integer(N) >= 299),
    ?assertNotEqual(nomatch, binary:match(Detail, <<"more refused requests from this address">>)),
    ?assert(byte_size(Target) =< 256),
    %% A logged-in caller's refusals are each written.
    Op = as(operator, Config),
    Mid = audit_files(Dir),
    {403, _, _} = req(Op, put, "/api/settings/machine", #{speed_override => 10}),
    {403, _, _} = req(Op, put, "/api/settings/machine", #{speed_override => 10}),
    ?assertEqual(2, length(added_lines(Mid, audit_files(Dir)))).

audit_files_rotate_and_expire(Config) ->
    Dir = filename:join(?config(root, Config), "Logs"),
    Old = filename:join(Dir, "audit 2001-01-01.jsonl"),
    ok = file:write_file(Old, <<"{}\n">>),
    ok = application:stop(cell_web),
    ok = application:set_env(cell_web, audit_file_max_bytes, 2000),
    try
        ok = application:start(cell_web),
        Op = as(operator, [{port, cell_web:port()} | Config]),
        T0 = os:system_time(millisecond),
        [{403, _, _} = req(Op, put, "/api/settings/machine", #{speed_override => I})
         || I <- lists:seq(1, 30)],
        %% The file of 2001 went when the trail opened today's.
        ?assertNot(filelib:is_regular(Old)),
        {ok, Names} = file:list_dir(Dir),
        Parts = [N || N <- Names, {ok, _, P} <- [cell_web_audit_rules:parse_name(N)], P > 1],
        ?assertNotEqual([], Parts),
        [?assert(filelib:file_size(filename:join(Dir, N)) < 2000 + 1024) || N <- Parts],
        %% Read back across the parts, in order.
        Entries = cell_web_audit:query(#{from => T0, who => <<"operator">>, limit => 1000}),
        ?assertEqual(30, length([E || #{outcome := <<"403">>} = E <- Entries]))
    after
        ok = application:stop(cell_web),
        ok = application:unset_env(cell_web, audit_file_max_bytes),
        ok = application:start(cell_web)
    end.

audit_files(Dir) ->
    {ok, Names} = file:list_dir(Dir),
    maps:from_list([{N, Bin} || N <- Names, lists:prefix("audit ", N),
                                {ok, Bin} <- [file:read_file(filename:join(Dir, N))]]).

%% The lines added to the audit files since `Before'.
added_lines(Before, After) ->
    lists:append(
      [begin
           Old = maps:get(N, Before, <<>>),
           New = binary:part(Bin, byte_size(Old), byte_size(Bin) - byte_size(Old)),
           binary:split(New, <<"\n">>, [global, trim_all])
       end || {N, Bin} <- lists:sort(maps:to_list(After))]).

websocket_snapshot_and_live(Config) ->
    Op = as(operator, Config),
    Origin = "http://127.0.0.1:" ++ integer_to_list(?config(port, Config)),
    {ok, Ws0} = cell_web_client:ws_connect(Op, Origin),
    {[#{<<"type">> := <<"snapshot">>, <<"resync">> := false, <<"cell">> := #{<<"state">> := <<"OFF">>},
        <<"tasks">> := [_, _], <<"alarms">> := [], <<"log">> := _,
        <<"session">> := #{<<"user">> := <<"operator">>}}], Ws1} = cell_web_client:ws_next(Ws0, 10000),
    ok = cell_controller:start(),
    Ws2 = until(Ws1, fun(#{<<"type">> := <<"task">>, <<"task">> := #{<<"id">> := <<"router">>,
                                                                     <<"state">> := <<"READY-IDLE-STARVED">>}}) -> true;
                        (_) -> false end),
    %% Every other event of the cell reaches the page as it is, with its task and time.
    Before = os:system_time(millisecond),
    cmd(Config, router, {event, unstarved}),
    Ws2b = until(Ws2, fun(#{<<"type">> := <<"event">>,
                            <<"event">> := #{<<"type">> := <<"equipment_unstarved">>,
                                             <<"task">> := <<"router">>, <<"time">> := T} = E}) ->
                              ?assertNot(maps:is_key(<<"mono">>, E)),
                              T >= Before;
                         (_) -> false end),
    cmd(Config, router, {error, [retry]}),
    Ws3 = until(Ws2b, fun(#{<<"type">> := <<"alarm">>, <<"alarm">> := #{<<"kind">> := <<"error">>}}) -> true;
                        (_) -> false end),
    ok = cell_alarms:answer(<<"router:jam">>, retry, <<"suite">>),
    Ws4 = until(Ws3, fun(#{<<"type">> := <<"alarm_cleared">>, <<"alarm">> := #{<<"cleared">> := <<"retry">>,
                                                                             <<"who">> := <<"suite">>}}) -> true;
                        (_) -> false end),
    cmd(Config, router, {log, <<"hello over the socket">>}),
    Ws5 = until(Ws4, fun(#{<<"type">> := <<"log">>, <<"line">> := #{<<"text">> := <<"hello over the socket">>}}) -> true;
                        (_) -> false end),
    ok = cell_web_client:ws_send(Ws5, <<"resync">>),
    Ws6 = until(Ws5, fun(#{<<"type">> := <<"snapshot">>, <<"resync">> := true}) -> true; (_) -> false end),
    ok = cell_web_client:ws_send(Ws6, <<"hello">>),
    {{close, 1003}, _} = skip_to_close(Ws6),
    cell_web_client:ws_close(Ws6).

%% Reads frames until one holds a message the predicate accepts (10 s deadline each).
until(Ws, Pred) ->
    case cell_web_client:ws_next(Ws, 10000) of
        {Msgs, Ws1} when is_list(Msgs) ->
            case lists:any(Pred, Msgs) of
                true -> Ws1;
                false -> until(Ws1, Pred)
            end;
        {Other, _} ->
            ct:fail({no_such_message, Other})
    end.

skip_to_close(Ws) ->
    case cell_web_client:ws_next(Ws, 10000) of
        {Msgs, Ws1} when is_list(Msgs) -> skip_to_close(Ws1);
        Other -> Other
    end.

websocket_refusals(Config) ->
    Op = as(operator, Config),
    ?assertEqual({error, 403}, cell_web_client:ws_connect(Op, "http://evil.example")),
    {ok, Ws} = cell_web_client:ws_connect(anon(Config), none),
    {[#{<<"type">> := <<"snapshot">>, <<"session">> := #{<<"user">> := null}}], _} =
        cell_web_client:ws_next(Ws, 10000),
    cell_web_client:ws_close(Ws),
    {426, #{<<"error">> := <<"upgrade_required">>}, _} = req(Op, get, "/api/ws").

websocket_resyncs_when_behind(Config) ->
    {ok, Ws0} = cell_web_client:ws_connect(anon(Config), none),
    {[#{<<"type">> := <<"snapshot">>}], Ws1} = cell_web_client:ws_next(Ws0, 10000),
    #{} = Socks = element(2, sys:get_state(cell_web_sessions)),
    [Pid] = [P || {P, {_, anonymous}} <- maps:to_list(Socks)],
    %% The browser's process falls behind: more events wait than it may keep.
    true = erlang:suspend_process(Pid),
    Event = cell_events:new(item_transfer_in, loader, #{item => <<"X">>}),
    _ = [cell_events:publish(Event) || _ <- lists:seq(1, 3000)],
    %% The feed has passed them all on (it answers after its queue).
    _ = sys:get_state(cell_web_feed),
    true = erlang:resume_process(Pid),
    %% What it sends next is a fresh snapshot, not 3000 events.
    {[#{<<"type">> := <<"snapshot">>, <<"resync">> := true}], Ws2} = cell_web_client:ws_next(Ws1, 10000),
    {message_queue_len, Left} = process_info(Pid, message_queue_len),
    ?assert(Left < 100),
    cell_web_client:ws_close(Ws2).

websocket_closes_when_session_ends(Config) ->
    Op = as(operator, Config),
    {ok, Ws0} = cell_web_client:ws_connect(Op, none),
    {[#{<<"type">> := <<"snapshot">>}], Ws1} = cell_web_client:ws_next(Ws0, 10000),
    {200, _, _} = req(Op, delete, "/api/session"),
    {{close, 4001}, _} = skip_to_close(Ws1).

anonymous_view_can_be_switched_off(Config) ->
    Ad = as(admin, Config),
    {ok, Ws0} = cell_web_client:ws_connect(anon(Config), none),
    {[#{<<"type">> := <<"snapshot">>}], Ws1} = cell_web_client:ws_next(Ws0, 10000),
    {200, _, _} = req(Ad, put, "/api/settings/web", #{anonymous_view => false}),
    {{close, 4001}, _} = skip_to_close(Ws1),
    assert_error(401, <<"login_required">>, req(anon(Config), get, "/api/cell")),
    ?assertEqual({error, 401}, cell_web_client:ws_connect(anon(Config), none)),
    {200, #{<<"anonymous_view">> := false}, _} = req(anon(Config), get, "/api/session"),
    {200, _, _} = req(Ad, get, "/api/cell"),
    {200, _, _} = req(Ad, put, "/api/settings/web", #{anonymous_view => true}),
    {200, _, _} = req(anon(Config), get, "/api/cell").

login_attempts_are_braked(Config) ->
    A = anon(Config),
    Wrong = #{user => <<"admin">>, password => <<"guess">>},
    [{401, _, _} = req(A, post, "/api/session", Wrong) || _ <- lists:seq(1, 10)],
    assert_error(429, <<"too_many_attempts">>, req(A, post, "/api/session", Wrong)),
    %% Even the right password waits out the brake.
    assert_error(429, <<"too_many_attempts">>,
                 req(A, post, "/api/session", #{user => <<"admin">>, password => <<"admin">>})),
    ok = cell_web_sessions:login_succeeded(<<"127.0.0.1">>, <<"admin">>),
    {ok, _} = cell_web_client:login(A, "admin", "admin").

%% Guesses at one account are braked whatever other users of the same address do, and
%% the brake holds back only the guessed account: the users who work from that address
%% get in all along.
login_brake_is_per_account(Config) ->
    A = anon(Config),
    {ok, _} = cell_web_client:login(A, "operator", "operator"),
    {ok, _} = cell_web_client:login(A, "service", "service"),
    Wrong = #{user => <<"admin">>, password => <<"guess">>},
    Results = lists:append(
                [begin
                     Guesses = [element(1, req(A, post, "/api/session", Wrong))
                                || _ <- lists:seq(1, 9)],
                     {ok, _} = cell_web_client:login(A, "operator", "operator"),
                     Guesses
                 end || _ <- lists:seq(1, 4)]),
    %% Ten free failures, then every guess refused before its password is checked.
    ?assertEqual(lists:duplicate(10, 401) ++ lists:duplicate(26, 429), Results),
    {429, #{<<"error">> := <<"too_many_attempts">>}, H} =
        req(A, post, "/api/session", #{user => <<"admin">>, password => <<"admin">>}),
    {_, Retry} = lists:keyfind("retry-after", 1, H),
    ?assert(list_to_integer(Retry) > 0),
    %% Another account of the same address is not held back.
    {ok, _} = cell_web_client:login(A, "service", "service"),
    ok = cell_web_sessions:login_succeeded(<<"127.0.0.1">>, <<"admin">>),
    {ok, _} = cell_web_client:login(A, "admin", "admin").

demo_passwords_refused_when_configured(_Config) ->
    ok = application:stop(cell_web),
    ok = application:set_env(cell_web, refuse_demo_accounts, true),
    try
        {error, {{demo_accounts, Text}, _}} = application:start(cell_web),
        ?assertNotEqual(nomatch, binary:match(Text, <<"operator, service, admin">>)),
        [{ok, updated} = cell_web_users:set_password(N, <<"changed-", N/binary>>, <<"suite">>)
         || N <- [<<"operator">>, <<"service">>]],
        {error, {{demo_accounts, Text2}, _}} = application:start(cell_web),
        ?assertNotEqual(nomatch, binary:match(Text2, <<"the demo accounts admin still">>)),
        {ok, updated} = cell_web_users:set_password(<<"admin">>, <<"changed-admin">>, <<"suite">>),
        ok = application:start(cell_web)
    after
        ok = application:set_env(cell_web, refuse_demo_accounts, false),
        {ok, _} = application:ensure_all_started(cell_web)
    end.

listener_waits_for_a_taken_port(_Config) ->
    ok = application:stop(cell_web),
    {ok, Taken} = gen_tcp:listen(0, [{ip, {127, 0, 0, 1}}, {reuseaddr, false}]),
    {ok, Port} = inet:port(Taken),
    ok = application:set_env(cell_web, port, Port),
    ok = cell_log:subscribe(),
    try
        %% The panel starts all the same, and says what is wrong.
        ok = application:start(cell_web),
        ?assertEqual({error, not_listening}, cell_web_listener:port()),
        await(fun({cell_log, #{source := <<"web">>, text := T}}) ->
                      binary:match(T, <<"cannot listen">>) =/= nomatch;
                 (_) -> false end, 10000),
        ok = gen_tcp:close(Taken),
        await(fun({cell_log, #{source := <<"web">>, text := T}}) ->
                      binary:match(T, <<"operator panel on">>) =/= nomatch;
                 (_) -> false end, 15000),
        ?assertEqual({ok, Port}, cell_web_listener:port())
    after
        ok = cell_log:unsubscribe(),
        ok = application:stop(cell_web),
        ok = application:set_env(cell_web, port, 0),
        ok = application:start(cell_web)
    end.

%% HTTPS with a certificate and key in the root folder: the API answers a client that
%% checks the certificate (issued here by a throwaway authority, since OTP refuses a
%% self-signed server certificate), the session cookie is Secure; plain HTTP gets no
%% answer; a client trusting another authority is refused; a missing key is said in
%% the log.
https_when_configured(Config) ->
    Root = ?config(root, Config),
    Priv = ?config(priv_dir, Config),
    Cert = filename:join(Root, "panel.crt"),
    Key = filename:join(Root, "panel.key"),
    Ca = filename:join(Priv, "ca.crt"),
    ok = certificates(Priv, "ca", Cert, Key),
    Other = filename:join(Priv, "other.crt"),
    ok = certificates(Priv, "other", filename:join(Priv, "other-panel.crt"),
                      filename:join(Priv, "other-panel.key")),
    ok = application:stop(cell_web),
    ok = application:set_env(cell_web, https, true),
    {ok, _} = application:ensure_all_started(ssl),
    try
        ok = application:start(cell_web),
        Url = "https://127.0.0.1:" ++ integer_to_list(cell_web:port()),
        ?assertEqual(list_to_binary(Url ++ "/"), cell_web:url()),
        Ssl = [{ssl, [{verify, verify_peer}, {cacertfile, Ca},
                      {server_name_indication, "localhost"}]},
               {timeout, 30000}],
        {ok, {{_, 200, _}, _, Body}} =
            httpc:request(get, {Url ++ "/api/session", []}, Ssl, [{body_format, binary}]),
        #{<<"user">> := null} = jsx:decode(Body, [return_maps]),
        {ok, {{_, 200, _}, H, _}} =
            httpc:request(post, {Url ++ "/api/session", [], "application/json",
                                 jsx:encode(#{user => <<"operator">>, password => <<"operator">>})},
                          Ssl, [{body_format, binary}]),
        [SetCookie] = [V || {"set-cookie", V} <- H],
        ?assertNotEqual(nomatch, string:find(SetCookie, "; Secure")),
        %% A client that does not trust the certificate is refused by its own check
        %% (a client of its own, which has no connection open yet).
        {ok, _} = inets:start(httpc, [{profile, cell_web_untrusted}]),
        try
            {error, _} = httpc:request(get, {Url ++ "/api/session", []},
                                       [{ssl, [{verify, verify_peer}, {cacertfile, Other},
                                               {server_name_indication, "localhost"}]}],
                                       [], cell_web_untrusted)
        after
            ok = inets:stop(httpc, cell_web_untrusted)
        end,
        %% Plain HTTP on the same port gets no HTTP answer.
        ?assertMatch({error, _}, httpc:request(get, {"http://127.0.0.1:" ++
                                                         integer_to_list(cell_web:port()) ++
                                                         "/api/session", []},
                                               [{timeout, 10000}], [])),
        %% Without its key the panel says so and waits; the cell runs on.
        ok = application:stop(cell_web),
        ok = file:delete(Key),
        ok = cell_log:subscribe(),
        ok = application:start(cell_web),
        await(fun({cell_log, #{source := <<"web">>, text := T}}) ->
                      binary:match(T, <<"cannot serve HTTPS">>) =/= nomatch
                          andalso binary:match(T, <<"panel.key">>) =/= nomatch;
                 (_) -> false end, 10000),
        ?assertEqual({error, not_listening}, cell_web_listener:port())
    after
        _ = cell_log:unsubscribe(),
        ok = application:stop(cell_web),
        ok = application:unset_env(cell_web, https),
        ok = application:start(cell_web)
    end.

%% An authority `<Dir>/<Name>.crt' and a server certificate it issued for 127.0.0.1
%% and localhost.
certificates(Dir, Name, Cert, Key) ->
    CaCrt = filename:join(Dir, Name ++ ".crt"),
    CaKey = filename:join(Dir, Name ++ ".key"),
    Csr = filename:join(Dir, Name ++ ".csr"),
    Ext = filename:join(Dir, Name ++ ".ext"),
    ok = file:write_file(Ext, "subjectAltName=IP:127.0.0.1,DNS:localhost\n"),
    ok = openssl(["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
                  "-subj", "/CN=" ++ Name, "-keyout", CaKey, "-out", CaCrt]),
    ok = openssl(["req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1",
                  "-keyout", Key, "-out", Csr]),
    ok = openssl(["x509", "-req", "-in", Csr, "-CA", CaCrt, "-CAkey", CaKey,
                  "-CAcreateserial", "-days", "2", "-extfile", Ext, "-out", Cert]).

openssl(Args) ->
    Port = open_port({spawn_executable, os:find_executable("openssl")},
                     [exit_status, stderr_to_stdout, {args, Args}]),
    0 = await_exit(Port),
    ok.

await_exit(Port) ->
    receive
        {Port, {exit_status, S}} -> S;
        {Port, {data, _}} -> await_exit(Port)
    after 60000 -> ct:fail(openssl_timeout)
    end.
