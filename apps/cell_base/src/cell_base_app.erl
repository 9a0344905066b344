%% @doc The foundation application: checks the node's distribution cookie, creates the
%% cell root folder, then starts the log server and installs the daily task log and
%% trace log. A production build (the `prod' profile) does not start with a cookie
%% anyone can guess (`cellrt', or none): the node stops at boot and says why.
-module(cell_base_app).
-behaviour(application).

-export([start/2, stop/1]).

-ifdef(CELLRT_PROD).
-define(PROD, true).
-else.
-define(PROD, false).
-endif.

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    Cookie = case node() of
                 nonode@nohost -> ok;
                 _ -> cell_dist:check_cookie(erlang:get_cookie(), ?PROD)
             end,
    case {Cookie, cell_config:ensure_root()} of
        {{error, Text}, _} ->
            cell_log:error(cell_base, "~ts", [Text]),
            {error, {distribution_cookie, Text}};
        {_, {error, Reason}} ->
            {error, {cell_root_folder, Reason}};
        {ok, ok} ->
            cell_base_sup:start_link();
        {{warning, Text}, ok} ->
            %% Once the log files are in place, so that the warning is in them too.
            Started = cell_base_sup:start_link(),
            cell_log:warning(cell_base, "~ts", [Text]),
            Started
    end.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.
