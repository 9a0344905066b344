%% @doc The adapter's API: the `Devices.xml' an MTConnect agent needs, the port and
%% the clients, and a refresh of the recipe assets.
%%
%% `bin/cellrt devices_xml FILE' (a start-script extension) calls {@link
%% devices_xml/1} on the running node.
-module(cell_shdr).

-export([devices_xml/0, devices_xml/1, port/0, clients/0, refresh_assets/0]).

%% @doc The `Devices.xml' declaring every data item the adapter emits now.
-spec devices_xml() -> binary().
devices_xml() ->
    cell_shdr_devices:xml(cell_shdr_cache:items(), cell_shdr_cache:settings(),
                          os:system_time(millisecond)).

%% @doc Writes {@link devices_xml/0} to a file (durably: a reader never sees half).
-spec devices_xml(file:filename_all()) -> ok | {error, term()}.
devices_xml(File) when is_binary(File) ->
    devices_xml(unicode:characters_to_list(File));
devices_xml(File) ->
    cell_file:write(File, devices_xml()).

%% @doc The TCP port the adapter listens on, or `undefined' while it cannot.
-spec port() -> inet:port_number() | undefined.
port() ->
    cell_shdr_listener:port().

%% @doc The connected clients' processes.
-spec clients() -> [pid()].
clients() ->
    cell_shdr_cache:clients().

%% @doc Reads the recipes again and publishes the assets that changed (recipes are
%% otherwise read at every Start).
-spec refresh_assets() -> ok.
refresh_assets() ->
    cell_shdr_cache:refresh_assets().
