%% @doc What the NC's hardware objects over ADS ({@link cell_hal_ads_axis}, {@link
%% cell_hal_ads_channel}) share about their own ADS clients: the connection options
%% and their check, a client started and watched, given up, and the poll timer.
%%
%% Options (as for {@link cell_hal_ads}): `host', `target_net_id' (both required),
%% `port' (48898), `source_net_id' (auto), `source_port' (32905), `timeout_ms' (1000,
%% each request's), `poll_ms' (20, while a job runs), `idle_poll_ms' (200, at rest),
%% `reconnect_ms' (1000) doubling up to `max_reconnect_ms' (10000) while connecting
%% fails.
-module(cell_hal_ads_nc_conn).

-export([check_opts/3, connect/2, disconnect/2, rearm_poll/3, cancel_poll/1]).

-define(CLIENT_KEYS, [host, target_net_id, port, source_net_id, source_port]).

%% @doc The options with their defaults, checked by the object's own `Known' (option
%% => {Default, Check}) beside the connection's, `Required' of them given; the ADS
%% client's own check of what it will be given.
-spec check_opts(map(), #{atom() => {term(), fun((term()) -> boolean())}}, [atom()]) ->
          {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts, Known, Required) ->
    Conn = #{host => {undefined, fun(H) -> is_list(H) orelse is_binary(H)
                                               orelse is_tuple(H) end},
             target_net_id => {undefined, fun(_) -> true end},
             port => {48898, fun port/1},
             source_net_id => {auto, fun(_) -> true end},
             source_port => {32905, fun port/1},
             timeout_ms => {1000, fun pos_int/1},
             poll_ms => {20, fun pos_int/1},
             idle_poll_ms => {200, fun pos_int/1},
             reconnect_ms => {1000, fun pos_int/1},
             max_reconnect_ms => {10000, fun pos_int/1}},
    case cell_hal_hw:check_opts(Opts, maps:merge(Conn, Known)) of
        {ok, Full} ->
            case [K || K <- [host, target_net_id | Required],
                       maps:get(K, Full) =:= undefined] of
                [] ->
                    case cell_hal_ads_client:check_opts(client_opts(Full, 500)) of
                        {ok, _} -> {ok, Full};
                        {error, _} = Error -> Error
                    end;
                [K | _] ->
                    {error, {bad_option, K}}
            end;
        {error, _} = Error ->
            Error
    end.

client_opts(#{timeout_ms := T} = Opts, TargetPort) ->
    (maps:with(?CLIENT_KEYS, Opts))#{target_port => TargetPort, request_timeout => T,
                                     connect_timeout => max(T, 1000),
                                     symbol_version => ignore}.

port(P) -> is_integer(P) andalso P >= 1 andalso P =< 65535.
pos_int(V) -> is_integer(V) andalso V > 0.

%% @doc A client of the calling process to the AMS port `TargetPort' of the target,
%% linked and monitored, its status told to the caller (`{cell_hal_ads, Client, up |
%% {down, Why}}'; down while it connects, and its end, if connecting fails, by the
%% monitor).
-spec connect(map(), 1..65535) -> {pid(), reference()}.
connect(Opts, TargetPort) ->
    {ok, Client} = cell_hal_ads_client:start_link(client_opts(Opts, TargetPort)),
    Mon = erlang:monitor(process, Client),
    try
        ok = cell_hal_ads_client:subscribe_status(Client)
    catch
        %% It could not connect and ended already: its monitor says so.
        exit:{_, {gen_statem, call, _}} -> ok
    end,
    {Client, Mon}.

%% @doc A client given up: no more word of it, and its parent's exit signal ends it,
%% alive or already ending, without waiting.
-spec disconnect(pid(), reference()) -> ok.
disconnect(Client, Mon) ->
    erlang:demonitor(Mon, [flush]),
    unlink(Client),
    exit(Client, shutdown),
    ok.

%% @doc The next poll, `{timeout, Ref, poll}' to the caller, the one armed before
%% cancelled: at once (`now'), or as the options say for a job running (`poll_ms') or
%% none (`idle_poll_ms').
-spec rearm_poll(reference() | undefined, now | running | idle, map()) -> reference().
rearm_poll(T, When, #{poll_ms := Fast, idle_poll_ms := Slow}) ->
    undefined = cancel_poll(T),
    Ms = case When of now -> 0; running -> Fast; idle -> Slow end,
    erlang:start_timer(Ms, self(), poll).

%% @doc The poll timer cancelled (a stale one that fires anyway has another ref).
-spec cancel_poll(reference() | undefined) -> undefined.
cancel_poll(undefined) ->
    undefined;
cancel_poll(T) ->
    _ = erlang:cancel_timer(T),
    undefined.
