%% @doc The options of an ADS connection ({@link cell_hal_ads_client}): their defaults
%% and their check. Pure.
%%
%% `reconnect' and `backoff' are refused like any unknown option: a client is one
%% connection and ends when it is lost; connecting again, with a back-off, is its
%% owner's job (the HAL's worker, whose `reconnect_ms' and `max_reconnect_ms' set it).
-module(cell_hal_ads_opts).

-include("cell_hal_ads.hrl").

-export([defaults/0, check/1]).

-define(DEFAULTS, #{port => ?ADS_TCP_PORT, target_port => 851, source_net_id => auto,
                    source_port => 32905, request_timeout => 5000, connect_timeout => 5000,
                    sum_commands => true, max_sum => 500,
                    max_in_flight => 64, access => handle, symbol_version => watch,
                    handle_idle => 5000, link_check => 5000, max_frame => 16#1000000,
                    log_variables => true}).

%% @doc Every option that has a default, with it.
-spec defaults() -> map().
defaults() ->
    ?DEFAULTS.

%% @doc The options with their defaults, or the first bad one: missing, unknown or
%% malformed. Host names given as binaries come back as strings, names as binaries.
-spec check(term()) -> {ok, map()} | {error, {bad_option, atom()}}.
check(Opts) when is_map(Opts) ->
    Full = maps:merge(?DEFAULTS, Opts),
    Keys = [host, target_net_id | maps:keys(?DEFAULTS)] ++ [name],
    case [K || K <- maps:keys(Opts), not lists:member(K, Keys)] ++
             [K || K <- [host, target_net_id], not maps:is_key(K, Opts)] of
        [Bad | _] -> {error, {bad_option, Bad}};
        [] -> check_each(lists:sort(maps:to_list(Full)), #{})
    end;
check(_) ->
    {error, {bad_option, opts}}.

check_each([], Acc) ->
    {ok, Acc};
check_each([{K, V} | Rest], Acc) ->
    case check_opt(K, V) of
        {ok, V1} -> check_each(Rest, Acc#{K => V1});
        error -> {error, {bad_option, K}}
    end.

check_opt(host, H) when is_binary(H), byte_size(H) > 0 -> {ok, binary_to_list(H)};
check_opt(host, H) when is_list(H), H =/= [] ->
    case io_lib:printable_latin1_list(H) of
        true -> {ok, H};
        false -> error
    end;
check_opt(host, H) when is_tuple(H) ->
    case inet:ntoa(H) of
        {error, _} -> error;
        _ -> {ok, H}
    end;
check_opt(K, P) when K =:= port; K =:= target_port; K =:= source_port ->
    ok_if(is_integer(P) andalso P >= 1 andalso P =< 65535, P);
check_opt(target_net_id, Id) -> net_id(Id);
check_opt(source_net_id, auto) -> {ok, auto};
check_opt(source_net_id, Id) -> net_id(Id);
check_opt(name, N) when is_atom(N) -> {ok, atom_to_binary(N, utf8)};
check_opt(name, N) when is_binary(N), byte_size(N) > 0 -> {ok, N};
check_opt(K, T) when K =:= request_timeout; K =:= connect_timeout; K =:= max_sum;
                     K =:= max_in_flight ->
    ok_if(is_integer(T) andalso T >= 1, T);
check_opt(K, B) when K =:= sum_commands; K =:= log_variables ->
    ok_if(is_boolean(B), B);
check_opt(access, A) -> ok_if(A =:= handle orelse A =:= address, A);
check_opt(symbol_version, S) -> ok_if(lists:member(S, [watch, read, ignore]), S);
check_opt(handle_idle, T) -> ok_if(is_integer(T) andalso T >= 0, T);
check_opt(link_check, infinity) -> {ok, infinity};
check_opt(link_check, T) -> ok_if(is_integer(T) andalso T >= 1, T);
check_opt(max_frame, N) -> ok_if(is_integer(N) andalso N >= 1024, N);
check_opt(_, _) -> error.

ok_if(true, V) -> {ok, V};
ok_if(false, _) -> error.

net_id(Id) ->
    case cell_hal_ads_codec:parse_net_id(Id) of
        {ok, NetId} -> {ok, NetId};
        error -> error
    end.
