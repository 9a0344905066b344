%% @doc The two keys of the cell spec ({@link cell_spec}) the monitor ({@link
%% cell_monitor}) works from, checked at the door: `hal', what the monitor connects,
%% and `monitor', what it watches and drives.
%%
%% ```
%% hal => #{connections => [#{id => plc1, driver => cell_hal_modbus,
%%                            opts => #{host => "10.0.0.5"}}],
%%          groups => [#{id => general, module => router_general_io, connection => plc1},
%%                     #{id => axes, module => router_axes_io, connection => plc1}],
%%          hardware => [#{id => camera, kind => camera, type => sim}]},
%% monitor => #{io => #{estop_ok => {general, estop_voltage},
%%                      service_key => {general, service_key},
%%                      door_locked => {general, door_locked},
%%                      air_ok => {general, air_pressure_ok},
%%                      beacon_red => {general, beacon_red},
%%                      beacon_yellow => {general, beacon_yellow},
%%                      beacon_green => {general, beacon_green},
%%                      beacon_blue => {general, beacon_blue}},
%%              drives => [#{id => x_axis, caption => <<"X axis">>,
%%                           error => {axes, x_error}, warning => {axes, x_warning},
%%                           code => {axes, x_error_code}, reset => {axes, x_reset},
%%                           override => {axes, x_override}, override_scale => 0.01}],
%%              severity => #{camera => error}}
%% '''
%%
%% `hal': connections and groups as {@link cell_hal:add_connection/1} and {@link
%% cell_hal:add_group/1} take them, hardware objects as {@link cell_hal_hw:add/1}
%% takes them; a group names a connection of the spec. Ids are unique, and a
%% connection and a hardware object never share one (each is a device the operator
%% sees by its id). The driver's own options are checked when the monitor adds the
%% connection.
%%
%% `monitor': every key is optional. `io' maps a role to a point `{Group, Point}' of a
%% group of the spec: the inputs `estop_ok' (true while the emergency-stop circuit has
%% voltage), `service_key' (true in the service position), `door_locked',
%% `air_ok'; the outputs `beacon_red', `beacon_yellow', `beacon_green',
%% `beacon_blue'. All are BOOL points. A drive has an `id' and any of: `error' and
%% `warning' (BOOL inputs: the drive's status bits), `code' (an integer input: the
%% drive's error code, shown with the error), `reset' (a BOOL output pulsed to reset
%% the drive), `override' (a number output: the speed override, written as percent
%% times `override_scale', default 1 — 0.01 for a factor 0..1), `caption' (how the
%% operator knows the drive; default its id). `severity' says, per connection or
%% hardware id, whether its loss is an `error' (the operator is needed; the default
%% for connections) or a `warning' (the default for hardware objects).
%%
%% Errors name what is wrong: `{bad_connection, Id, Why}', `{bad_group, Id, Why}',
%% `{bad_hardware, Id, Why}', `{bad_monitor, Where, Why}' with `Where' one of `io',
%% `{io, Role}', `{drive, Id}', `drives', `severity', and `Why' as
%% `{unknown_point, Point}', `{not_an_input, Point}', `{not_an_output, Point}',
%% `{wrong_type, Point, Type}', `{bad_option, Key}', `{unknown_keys, Keys}',
%% `duplicate_id'.
-module(cell_monitor_spec).

-export([validate/1, empty_hal/0, empty_monitor/0, roles/0, inputs/0, outputs/0,
         points/2, devices/1, is_empty/2, override_value/3]).

-export_type([hal/0, monitor/0, point/0, role/0, drive/0, device/0, severity/0,
              point_info/0]).

-type point() :: {atom(), atom()}.
-type role() :: estop_ok | service_key | door_locked | air_ok
              | beacon_red | beacon_yellow | beacon_green | beacon_blue.
-type drive() :: #{id := atom(), caption := binary(), override_scale := number(),
                   error => point(), warning => point(), code => point(),
                   reset => point(), override => point()}.
-type device() :: {connection, atom()} | {hardware, atom()}.
-type severity() :: error | warning.
-type hal() :: #{connections := [cell_hal:connection_spec()],
                 groups := [cell_hal:group_spec()],
                 hardware := [cell_hal_hw:spec()]}.
-type monitor() :: #{io := #{role() => point()}, drives := [drive()],
                     severity := #{atom() => severity()}}.
-type point_info() :: #{dir := in | out, type := cell_hal_type:type(),
                        connection := atom(), caption := binary()}.

-define(INTEGER_TYPES, [byte, sbyte, char, int16, uint16, int32, uint32, int64, uint64]).

%% @doc The HAL of a cell that has none.
-spec empty_hal() -> hal().
empty_hal() -> #{connections => [], groups => [], hardware => []}.

%% @doc A monitor with nothing to watch.
-spec empty_monitor() -> monitor().
empty_monitor() -> #{io => #{}, drives => [], severity => #{}}.

%% @doc Whether there is nothing for the monitor to do.
-spec is_empty(hal(), monitor()) -> boolean().
is_empty(Hal, Monitor) ->
    Hal =:= empty_hal() andalso Monitor =:= empty_monitor().

%% @doc The roles of the general IO, inputs first.
-spec roles() -> [role()].
roles() -> inputs() ++ outputs().

-spec inputs() -> [role()].
inputs() -> [estop_ok, service_key, door_locked, air_ok].

-spec outputs() -> [role()].
outputs() -> [beacon_red, beacon_yellow, beacon_green, beacon_blue].

%% @doc Checks the `hal' and `monitor' keys of a cell spec (both optional) and fills
%% in the defaults.
-spec validate(map()) -> {ok, #{hal := hal(), monitor := monitor()}} | {error, term()}.
validate(Spec) ->
    case hal(maps:get(hal, Spec, #{})) of
        {ok, Hal} ->
            case monitor_key(maps:get(monitor, Spec, #{}), Hal) of
                {ok, Monitor} -> {ok, #{hal => Hal, monitor => Monitor}};
                Error -> Error
            end;
        Error ->
            Error
    end.

%% @doc Every point the monitor uses, with its direction, type, connection and caption.
-spec points(hal(), monitor()) -> #{point() => point_info()}.
points(#{groups := Groups}, #{io := Io, drives := Drives}) ->
    Used = maps:values(Io) ++ lists:append([drive_points(D) || D <- Drives]),
    Defs = group_defs(Groups),
    maps:from_list([{P, maps:get(P, Defs)} || P <- lists:usort(Used)]).

%% @doc Every device the monitor watches: connections, then hardware objects (those
%% of type `none' are absent), each with the severity of its loss.
-spec devices(#{hal := hal(), monitor := monitor()}) -> [{device(), severity()}].
devices(#{hal := #{connections := Conns, hardware := Hw}, monitor := #{severity := Sev}}) ->
    [{{connection, Id}, maps:get(Id, Sev, error)} || #{id := Id} <- Conns]
        ++ [{{hardware, Id}, maps:get(Id, Sev, warning)}
            || #{id := Id, type := Type} <- Hw, Type =/= none].

drive_points(D) ->
    [P || {K, P} <- maps:to_list(D), lists:member(K, [error, warning, code, reset, override])].

%%====================================================================
%% hal
%%====================================================================

hal(Hal) when is_map(Hal) ->
    case maps:keys(Hal) -- [connections, groups, hardware] of
        [] ->
            Conns = maps:get(connections, Hal, []),
            Groups = maps:get(groups, Hal, []),
            Hw = maps:get(hardware, Hal, []),
            first([fun() -> each(Conns, connections, fun connection/2, bad_connection) end,
                   fun() -> each(Groups, groups, group_check(ids(Conns)), bad_group) end,
                   fun() -> each(Hw, hardware, fun hardware/2, bad_hardware) end,
                   fun() -> shared_ids(ids(Conns), ids(Hw)) end],
                  {ok, #{connections => [with_opts(C) || C <- Conns],
                         groups => [with_opts(G) || G <- Groups],
                         hardware => [with_opts(H) || H <- Hw]}});
        Unknown ->
            {error, {bad_cell_spec, hal, {unknown_keys, Unknown}}}
    end;
hal(Other) ->
    {error, {bad_cell_spec, hal, Other}}.

with_opts(M) -> maps:merge(#{opts => #{}}, M).

ids(L) -> [Id || #{id := Id} <- L].

%% Each element of a list passes its check; ids are atoms, unique.
each(L, Key, Check, Tag) when is_list(L) ->
    each(L, Check, Tag, #{}, Key);
each(Other, Key, _Check, _Tag) ->
    {error, {bad_cell_spec, hal, {Key, Other}}}.

each([], _Check, _Tag, _Seen, _Key) ->
    ok;
each([#{id := Id} = E | Rest], Check, Tag, Seen, Key) when is_atom(Id) ->
    case maps:is_key(Id, Seen) of
        true -> {error, {Tag, Id, duplicate_id}};
        false ->
            case Check(Id, E) of
                ok -> each(Rest, Check, Tag, Seen#{Id => true}, Key);
                {error, Why} -> {error, {Tag, Id, Why}}
            end
    end;
each([Other | _], _Check, _Tag, _Seen, Key) ->
    {error, {bad_cell_spec, hal, {Key, Other, "each needs an atom id"}}}.

connection(_Id, C) ->
    keys(C, [id, driver], [opts],
         [{driver, fun(D) -> exports(D, [{check_opts, 1}, {init, 2}, {connect, 1}]) end},
          {opts, fun is_map/1}]).

group_check(ConnIds) ->
    fun(_Id, G) ->
            case keys(G, [id, module, connection], [opts],
                      [{module, fun(M) -> exports(M, [{points, 1}]) end},
                       {connection, fun(C) -> lists:member(C, ConnIds) end},
                       {opts, fun is_map/1}]) of
                ok -> group_points(G);
                Error -> Error
            end
    end.

%% The group module lists its points for these options, and they are well formed.
group_points(#{module := M} = G) ->
    try cell_hal_group:check_points(M:points(maps:get(opts, G, #{}))) of
        ok -> ok;
        {error, Why} -> {error, Why}
    catch
        Class:Reason -> {error, {points_failed, M, {Class, Reason}}}
    end.

hardware(_Id, H) ->
    keys(H, [id, kind, type], [opts],
         [{kind, fun(K) -> lists:member(K, [camera, code_reader, laser_marker, axis,
                                            channel]) end},
          {type, fun is_atom/1},
          {opts, fun is_map/1}]).

shared_ids(Conns, Hw) ->
    case [Id || Id <- Conns, lists:member(Id, Hw)] of
        [] -> ok;
        [Id | _] -> {error, {bad_hardware, Id, {id_of_a_connection, Id}}}
    end.

%% Required and optional keys present, each passing its check, no others.
keys(M, Required, Optional, Checks) ->
    case {[K || K <- Required, not maps:is_key(K, M)],
          maps:keys(M) -- (Required ++ Optional)} of
        {[K | _], _} -> {error, {bad_option, K}};
        {[], [_ | _] = Unknown} -> {error, {unknown_keys, Unknown}};
        {[], []} ->
            case [K || {K, Ok} <- Checks, maps:is_key(K, M), not Ok(maps:get(K, M))] of
                [] -> ok;
                [K | _] -> {error, {bad_option, K}}
            end
    end.

exports(M, Funs) when is_atom(M) ->
    code:ensure_loaded(M) =:= {module, M}
        andalso lists:all(fun({F, A}) -> erlang:function_exported(M, F, A) end, Funs);
exports(_, _) ->
    false.

%%====================================================================
%% monitor
%%====================================================================

monitor_key(M, #{groups := Groups} = Hal) when is_map(M) ->
    case maps:keys(M) -- [io, drives, severity] of
        [] ->
            Defs = group_defs(Groups),
            Io = maps:get(io, M, #{}),
            Drives = maps:get(drives, M, []),
            Sev = maps:get(severity, M, #{}),
            case first([fun() -> io(Io, Defs) end,
                        fun() -> drives(Drives, Defs) end,
                        fun() -> severity(Sev, Hal) end],
                       ok) of
                ok ->
                    {ok, #{io => Io, drives => [drive_defaults(D) || D <- Drives],
                           severity => Sev}};
                Error ->
                    Error
            end;
        Unknown ->
            {error, {bad_cell_spec, monitor, {unknown_keys, Unknown}}}
    end;
monitor_key(Other, _Hal) ->
    {error, {bad_cell_spec, monitor, Other}}.

group_defs(Groups) ->
    maps:from_list(
      [{{G, N}, #{dir => Dir, type => T, connection => C, caption => Cap}}
       || #{id := G, module := Mod, connection := C} = Spec <- Groups,
          #{name := N, dir := Dir, type := T, caption := Cap}
              <- Mod:points(maps:get(opts, Spec, #{}))]).

io(Io, Defs) when is_map(Io) ->
    case maps:keys(Io) -- roles() of
        [] ->
            first([fun() -> point({io, Role}, P, role_kind(Role), Defs) end
                   || {Role, P} <- lists:sort(maps:to_list(Io))], ok);
        Unknown ->
            {error, {bad_monitor, io, {unknown_keys, Unknown}}}
    end;
io(Other, _Defs) ->
    {error, {bad_monitor, io, Other}}.

%% Each key names a connection or a hardware object of the spec.
severity(Sev, #{connections := Conns, hardware := Hw}) when is_map(Sev) ->
    Devices = ids(Conns) ++ ids(Hw),
    case [{Id, S} || {Id, S} <- lists:sort(maps:to_list(Sev)),
                     not lists:member(Id, Devices) orelse not lists:member(S, [error, warning])] of
        [] -> ok;
        [{Id, S} | _] ->
            case lists:member(Id, Devices) of
                false -> {error, {bad_monitor, severity, {unknown_device, Id}}};
                true -> {error, {bad_monitor, severity, {bad_severity, Id, S}}}
            end
    end;
severity(Other, _Hal) ->
    {error, {bad_monitor, severity, Other}}.

role_kind(Role) ->
    case lists:member(Role, inputs()) of
        true -> {in, bool};
        false -> {out, bool}
    end.

drives(Drives, Defs) when is_list(Drives) ->
    drives(Drives, Defs, #{});
drives(Other, _Defs) ->
    {error, {bad_monitor, drives, Other}}.

drives([], _Defs, _Seen) ->
    ok;
drives([#{id := Id} = D | Rest], Defs, Seen) when is_atom(Id) ->
    Where = {drive, Id},
    Points = [{error, {in, bool}}, {warning, {in, bool}}, {code, {in, integer}},
              {reset, {out, bool}}, {override, {out, number}}],
    Checks = [fun() ->
                      case maps:is_key(Id, Seen) of
                          true -> {error, {bad_monitor, Where, duplicate_id}};
                          false -> ok
                      end
              end,
              fun() ->
                      case keys(D, [id], [caption, override_scale | [K || {K, _} <- Points]],
                                [{caption, fun(C) -> is_binary(C) andalso C =/= <<>> end},
                                 {override_scale, fun(S) -> is_number(S) andalso S > 0 end}]) of
                          ok -> ok;
                          {error, Why} -> {error, {bad_monitor, Where, Why}}
                      end
              end,
              fun() ->
                      case [K || {K, _} <- Points, maps:is_key(K, D)] of
                          [] -> {error, {bad_monitor, Where, no_points}};
                          _ -> ok
                      end
              end
              | [fun() -> point(Where, maps:get(K, D), Kind, Defs) end
                 || {K, Kind} <- Points, maps:is_key(K, D)]]
        ++ [fun() -> override_fits(Where, D, Defs) end],
    case first(Checks, ok) of
        ok -> drives(Rest, Defs, Seen#{Id => true});
        Error -> Error
    end;
drives([Other | _], _Defs, _Seen) ->
    {error, {bad_monitor, drives, {bad_drive, Other, "a drive needs an atom id"}}}.

drive_defaults(#{id := Id} = D) ->
    maps:merge(#{caption => atom_to_binary(Id, utf8), override_scale => 1}, D).

%% The full speed, scaled, fits the override point's type.
override_fits(Where, #{override := P} = D, Defs) ->
    #{type := T} = maps:get(P, Defs),
    case cell_hal_type:check(T, override_value(T, 100, maps:get(override_scale, D, 1))) of
        {ok, _} -> ok;
        error -> {error, {bad_monitor, Where, {override_out_of_range, P, T}}}
    end;
override_fits(_Where, _D, _Defs) ->
    ok.

%% @doc The value an override point of type `Type' is written for a speed of
%% `Percent' % with its scale.
-spec override_value(cell_hal_type:type(), number(), number()) -> number().
override_value(T, Percent, Scale) when T =:= real; T =:= lreal -> float(Percent * Scale);
override_value(_, Percent, Scale) -> round(Percent * Scale).

point(Where, {G, N} = P, {Dir, Kind}, Defs) when is_atom(G), is_atom(N) ->
    case maps:find(P, Defs) of
        error ->
            {error, {bad_monitor, Where, {unknown_point, P}}};
        {ok, #{dir := D}} when D =/= Dir ->
            {error, {bad_monitor, Where, case Dir of in -> {not_an_input, P};
                                                    out -> {not_an_output, P} end}};
        {ok, #{type := T}} ->
            case kind_of(T, Kind) of
                true -> ok;
                false -> {error, {bad_monitor, Where, {wrong_type, P, T}}}
            end
    end;
point(Where, Other, _, _) ->
    {error, {bad_monitor, Where, {bad_point, Other}}}.

kind_of(bool, bool) -> true;
kind_of(T, integer) -> lists:member(T, ?INTEGER_TYPES);
kind_of(T, number) -> lists:member(T, [real, lreal | ?INTEGER_TYPES]);
kind_of(_, _) -> false.

%% The first check that fails, or Ok.
first([], Ok) -> Ok;
first([Check | Rest], Ok) ->
    case Check() of
        ok -> first(Rest, Ok);
        Error -> Error
    end.
