%% @doc The operator web panel application: registers its settings objects (the
%% panel's settings and its users), checks the demo accounts, starts the panel.
%%
%% A new cell has the demo accounts operator/operator, service/service and
%% admin/admin. A production build (the `prod' profile, or the `refuse_demo_accounts'
%% setting of this application) refuses to start while any of them still has its demo
%% password: at boot the node stops with status 1 and says why; other builds start and
%% say in the log which ones are still open.
-module(cell_web_app).
-behaviour(application).

-export([start/2, stop/1, refuse_demo_accounts/0]).

-ifdef(CELLRT_PROD).
-define(PROD, true).
-else.
-define(PROD, false).
-endif.

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    case check_config() of
        ok ->
            case cell_web_settings:register() of
                ok -> check_demo_accounts();
                {error, Why} -> {error, {web_settings, cell_settings_schema:format_error(Why)}}
            end;
        {error, _} = E ->
            E
    end.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.

%% @doc Whether this build refuses demo passwords (always in a production build).
-spec refuse_demo_accounts() -> boolean().
refuse_demo_accounts() ->
    ?PROD orelse application:get_env(cell_web, refuse_demo_accounts, false) =:= true.

%% The release starts this application as temporary (so a failing panel never stops
%% the cell); a refusal must stop the release's node all the same (its sys.config sets
%% `refusal_stops_node'). Started from a shell or a test, the start just fails.
refuse_boot() ->
    case application:get_env(cell_web, refusal_stops_node, false) of
        true -> init:stop(1);
        false -> ok
    end.

check_config() ->
    case {cell_config:port(cell_web, port, 8080), cell_config:ip(cell_web, bind, {127, 0, 0, 1})} of
        {{ok, _}, {ok, _}} -> ok;
        {{error, {bad_config, _, _, V}}, _} ->
            {error, {bad_config, "CELLRT_WEB_PORT (cell_web port) must be a port number", V}};
        {_, {error, {bad_config, _, _, V}}} ->
            {error, {bad_config, "CELLRT_WEB_BIND (cell_web bind) must be an IP address", V}}
    end.

check_demo_accounts() ->
    case {cell_web_users:demo_accounts(), refuse_demo_accounts()} of
        {[], _} ->
            cell_web_sup:start_link();
        {Open, true} ->
            Text = iolist_to_binary(
                     ["the demo accounts ", lists:join(", ", Open), " still have their demo "
                      "passwords; a production build does not start with them. Set each "
                      "one's password with the cell stopped: bin/cellrt set_password ",
                      hd(Open), " (it asks for the new password)."]),
            cell_log:error(web, "~ts", [Text]),
            refuse_boot(),
            {error, {demo_accounts, Text}};
        {Open, false} ->
            cell_log:warning(web, "demo accounts open on the operator panel: ~ts (each with "
                             "its name as password); change each one's password on the panel "
                             "(its name, top right) before production",
                             [lists:join(", ", [[N, "/", N] || N <- Open])]),
            cell_web_sup:start_link()
    end.
