%% @doc The adapter's one door to the HAL (docs/architecture.md, "HAL"): reads a
%% point, subscribes to its changes (`{cell_hal, {Group, Point}, Value}'), to its
%% faults (`{cell_hal_fault, {Group, Point}, Why | cleared}') and to its connection's
%% status (`{cell_hal_conn, Conn, up | down}'), so that a point that cannot be read
%% is shown UNAVAILABLE as soon as the HAL knows; and names points from the settings
%% without making atoms; and watches and reads the cell's axes (hardware objects of
%% `cell_hal', whichever HAL module serves the points).
%%
%% The HAL module is the `cell_shdr' environment key `hal_module' (default
%% `cell_hal'), so the adapter's tests can stand a scripted HAL in its place. While no
%% HAL module is loaded, every configured point reads as unavailable.
-module(cell_shdr_hal).

-export([read/2, subscribe/2, same_point/3, watch_axis/1, axis_status/1, axis_moving/1]).

%% @doc Reads a point named in the settings.
-spec read(binary(), binary()) -> {ok, term()} | {error, term()}.
read(Group, Point) ->
    with_point(Group, Point, fun(Mod, G, P) -> Mod:read(G, P) end).

%% @doc Subscribes the caller to a point's changes and faults, and to the status of
%% its connection (a point is read again on each of them: see {@link read/2}).
-spec subscribe(binary(), binary()) -> ok | {error, term()}.
subscribe(Group, Point) ->
    with_point(Group, Point, fun(Mod, G, P) ->
                                     case Mod:subscribe(G, P) of
                                         ok -> subscribe_connection(Mod, G);
                                         {ok, _} -> subscribe_connection(Mod, G);
                                         {error, _} = E -> E
                                     end
                             end).

subscribe_connection(Mod, Group) ->
    case Mod:connection_of(Group) of
        {ok, Conn} ->
            case Mod:subscribe_connection(Conn) of
                {ok, _} -> ok;
                {error, _} = E -> E
            end;
        {error, _} = E ->
            E
    end.

%% @doc Watches an axis (`{cell_hal_hw_changed, Id}' when it may have changed): its
%% process, to monitor, or `not_present'.
-spec watch_axis(atom()) -> {ok, pid()} | {error, not_present}.
watch_axis(Id) ->
    cell_hal_hw:watch(Id).

%% @doc An axis's status as its NC has it now.
-spec axis_status(atom()) -> {ok, cell_hal_axis:status()} | {error, term()}.
axis_status(Id) ->
    cell_hal_axis:status(Id).

%% @doc Whether an axis whose status reads so may be moving (see cell_hal_axis:moving/1).
-spec axis_moving(map()) -> boolean().
axis_moving(Status) ->
    cell_hal_axis:moving(Status).

%% @doc Whether a configured point (names as binaries) is the HAL's `{Group, Point}'.
-spec same_point(#{group := binary(), point := binary(), atom() => term()}, atom(),
                 atom()) -> boolean().
same_point(#{group := G, point := P}, Group, Point) ->
    G =:= atom_to_binary(Group, utf8) andalso P =:= atom_to_binary(Point, utf8).

%% The HAL names groups and points by atoms it declared itself: a name from the
%% settings that is not an atom already cannot be one of them.
with_point(Group, Point, Fun) ->
    Mod = application:get_env(cell_shdr, hal_module, cell_hal),
    case code:ensure_loaded(Mod) of
        {module, Mod} ->
            try {binary_to_existing_atom(Group, utf8), binary_to_existing_atom(Point, utf8)} of
                {G, P} -> Fun(Mod, G, P)
            catch
                error:badarg -> {error, unknown_point}
            end;
        {error, _} ->
            {error, no_hal}
    end.
