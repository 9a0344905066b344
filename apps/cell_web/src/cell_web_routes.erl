%% @doc The panel's routes: the operator page, the REST API, the websocket, the routes
%% of the extensions (`cell_web_extension'). Anything else is a JSON 404.
-module(cell_web_routes).

-export([dispatch/0, routes/0]).

%% @doc The compiled dispatch for cowboy.
-spec dispatch() -> cowboy_router:dispatch_rules().
dispatch() ->
    cowboy_router:compile([{'_', routes()}]).

%% @doc The routes, in the order they are matched.
-spec routes() -> [{iodata(), module(), term()}].
routes() ->
    [{"/", cowboy_static, {priv_file, cell_web, "www/index.html"}},
     {"/app.js", cowboy_static, {priv_file, cell_web, "www/app.js",
                                 [{mimetypes, {<<"text">>, <<"javascript">>, []}}]}},
     {"/style.css", cowboy_static, {priv_file, cell_web, "www/style.css"}},
     {"/favicon.svg", cowboy_static, {priv_file, cell_web, "www/favicon.svg"}},
     {"/pages/[...]", cowboy_static, {priv_dir, cell_web, "www/pages",
                                      [{mimetypes, cow_mimetypes, all}]}},
     {"/api/session", cell_web_session_h, #{what => session}},
     {"/api/session/password", cell_web_session_h, #{what => password}},
     {"/api/cell", cell_web_cell_h, #{}},
     {"/api/cell/:command", cell_web_cell_h, #{}},
     {"/api/tasks", cell_web_tasks_h, #{}},
     {"/api/tasks/:id", cell_web_tasks_h, #{}},
     {"/api/tasks/:id/retained", cell_web_tasks_h, #{what => retained}},
     {"/api/alarms", cell_web_alarms_h, #{what => list}},
     {"/api/alarms/history", cell_web_alarms_h, #{what => history}},
     {"/api/alarms/:id/answer", cell_web_alarms_h, #{what => answer}},
     {"/api/log", cell_web_log_h, #{}},
     {"/api/products", cell_web_products_h, #{what => list}},
     {"/api/products/:serial", cell_web_products_h, #{what => one}},
     {"/api/products/:serial/history", cell_web_products_h, #{what => history}},
     {"/api/statistics", cell_web_stats_h, #{}},
     {"/api/statistics/charts", cell_web_stats_h, #{what => charts}},
     {"/api/settings", cell_web_settings_h, #{what => list}},
     {"/api/settings/:name", cell_web_settings_h, #{what => one}},
     {"/api/settings/:name/revisions", cell_web_settings_h, #{what => revisions}},
     {"/api/settings/:name/revisions/:rev", cell_web_settings_h, #{what => revision}},
     {"/api/settings/:name/diff", cell_web_settings_h, #{what => diff}},
     {"/api/settings/:name/restore", cell_web_settings_h, #{what => restore}},
     {"/api/recipes", cell_web_recipes_h, #{what => list}},
     {"/api/recipes/:name", cell_web_recipes_h, #{what => one}},
     {"/api/recipes/:name/file", cell_web_recipes_h, #{what => file}},
     {"/api/recipes/:name/drawing", cell_web_recipes_h, #{what => drawing}},
     {"/api/recipes/:name/dxf", cell_web_recipes_h, #{what => dxf}},
     {"/api/recipes/:name/rename", cell_web_recipes_h, #{what => rename}},
     {"/api/recipes/:name/copy", cell_web_recipes_h, #{what => copy}},
     {"/api/users", cell_web_users_h, #{}},
     {"/api/users/:name", cell_web_users_h, #{}},
     {"/api/audit", cell_web_audit_h, #{}},
     {"/api/layout", cell_web_layout_h, #{}},
     {"/api/io", cell_web_io_h, #{what => all}},
     {"/api/io/hardware/:id/image", cell_web_io_h, #{what => image}},
     {"/api/forces", cell_web_forces_h, #{what => all}},
     {"/api/forces/:group/:point", cell_web_forces_h, #{what => one}},
     {"/api/machine/actions", cell_web_machine_h, #{}},
     {"/api/ws", cell_web_ws_h, #{}}]
        ++ cell_web_extension:routes()
        ++ [{'_', cell_web_notfound_h, #{}}].
