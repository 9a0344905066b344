%% @doc The adapter's settings object, `Settings/shdr.json': who the device is for an
%% MTConnect agent (name, uuid, manufacturer, station, serial number, description),
%% the heartbeat period, the listener, the limits per client, relative time, recipes
%% as assets, and the HAL points published as samples, events or time series.
%%
%% An empty `uuid' is replaced by a new random one the first time the adapter starts,
%% and saved, so the device keeps its identity across restarts. `port' and `bind' are
%% overridden by `CELLRT_SHDR_PORT' and `CELLRT_SHDR_BIND' when those are set.
-module(cell_shdr_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

-spec name() -> shdr.
name() -> shdr.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => device_name, type => {string, 64}, default => <<"cell">>,
       doc => <<"The device's name in the MTConnect agent (letters, digits, _ . -).">>},
     #{name => uuid, type => {string, 64}, default => <<>>,
       doc => <<"The device's uuid; a new one is made and saved when empty.">>},
     #{name => manufacturer, type => {string, 128}, default => <<>>,
       doc => <<"Announced to the agent as * manufacturer.">>},
     #{name => station, type => {string, 128}, default => <<>>,
       doc => <<"Announced to the agent as * station.">>},
     #{name => serial_number, type => {string, 128}, default => <<>>,
       doc => <<"Announced to the agent as * serialNumber.">>},
     #{name => description, type => {string, 512}, default => <<>>,
       doc => <<"Announced to the agent as * description.">>},
     #{name => ping_period, type => {integer, 1000, 600000}, default => 10000,
       unit => <<"ms">>,
       doc => <<"The heartbeat period answered to * PING; an agent silent for two "
                "periods after its first PING is disconnected.">>},
     #{name => port, type => {integer, 0, 65535}, default => 7878,
       doc => <<"TCP port of the SHDR listener (CELLRT_SHDR_PORT overrides it).">>},
     #{name => bind, type => {string, 45}, default => <<"127.0.0.1">>,
       doc => <<"Address the listener binds to; 0.0.0.0 for every interface "
                "(CELLRT_SHDR_BIND overrides it).">>},
     #{name => max_clients, type => {integer, 1, 1000}, default => 64,
       doc => <<"Agents connected at once; more are refused at once, unless one "
                "connected has not yet sent a PING: the newcomer takes its place.">>},
     #{name => life_timeout, type => {integer, 1000, 600000}, default => 10000,
       unit => <<"ms">>,
       doc => <<"A client that sends no * PING within this time after its connect is "
                "disconnected.">>},
     #{name => max_client_buffer, type => {integer, 4096, 67108864}, default => 1048576,
       unit => <<"bytes">>,
       doc => <<"How far a client may fall behind before it is dropped.">>},
     #{name => relative_time, type => boolean, default => false,
       doc => <<"Stamp lines with a millisecond clock tick instead of UTC time.">>},
     #{name => recipes_as_assets, type => boolean, default => true,
       doc => <<"Publish each recipe as an MTConnect File asset.">>},
     #{name => points, type => {list, {object, cell_shdr_point_settings}, 256},
       doc => <<"HAL points published as samples, events or time series.">>}].

%% @doc The bind address parses; point names are unique and valid data item names.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{bind := Bind, points := Points, device_name := Name}) ->
    case inet:parse_address(binary_to_list(Bind)) of
        {ok, _} ->
            case cell_shdr_items:valid_name(Name) of
                true -> check_points(Points, 1, #{});
                false -> {error, [device_name], {not_a_name, Name}}
            end;
        {error, _} ->
            {error, [bind], {not_an_ip_address, Bind}}
    end.

check_points([], _, _) ->
    ok;
check_points([#{name := Name} | Rest], I, Seen) ->
    case {cell_shdr_items:valid_name(Name), Seen} of
        {false, _} -> {error, [points, I, name], {not_a_name, Name}};
        {true, #{Name := _}} -> {error, [points, I, name], {duplicate, Name}};
        {true, _} -> check_points(Rest, I + 1, Seen#{Name => true})
    end.
