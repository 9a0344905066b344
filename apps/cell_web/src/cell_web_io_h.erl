%% @doc `GET /api/io' — every IO group and point of the HAL (value, type, caption,
%% unit, address, quality, whether it is forced and whether it can be: an output, or
%% an input of a simulated PLC), grouped as the cell spec lists the
%% groups, the PLC connections (status, why down, reconnections) and the hardware
%% objects (an axis with its state, position, velocity and error code, a channel with
%% its progress, as they are at the request); the page then follows the websocket
%% (`io', `io_conn', `forces').
%% `GET /api/io/hardware/:id/image' — grabs an image from a camera (role service) and
%% answers it as PNG.
-module(cell_web_io_h).
-behaviour(cowboy_handler).

-export([init/2, lookup_point/2]).

-define(GRAB_TIMEOUT, 5000).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(What, Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    case What of
        all ->
            _ = cell_web_req:require(Caller, view),
            ok = cell_web_io:watch(),
            {json, 200, #{<<"connections">> => [cell_web_json:term(C)
                                                || C <- cell_web_io:connections()],
                          <<"groups">> => [group(G) || G <- ordered_groups()],
                          <<"hardware">> => [cell_web_io:hardware_json(H) || H <- cell_hal_hw:list()],
                          <<"forces">> => cell_web_forces:json()}};
        image ->
            _ = cell_web_req:require(Caller, service),
            grab(cell_web_req:binding(id, Req), Req)
    end.

%% The groups in the order of the spec's `hal' key, then any others.
ordered_groups() ->
    Spec = [Id || #{id := Id} <- maps:get(groups, maps:get(hal, cell_spec:running(), #{}), [])],
    All = cell_hal:groups(),
    [G || G <- Spec, lists:member(G, All)] ++ [G || G <- All, not lists:member(G, Spec)].

group(G) ->
    {ok, Conn} = cell_hal:connection_of(G),
    Driver = case cell_hal:info(Conn) of
                 {ok, #{driver := D}} -> D;
                 {error, _} -> undefined
             end,
    Points = case cell_hal:points(G) of
                 {ok, Ps} -> Ps;
                 {error, _} -> []
             end,
    #{<<"id">> => atom_to_binary(G, utf8), <<"connection">> => atom_to_binary(Conn, utf8),
      <<"points">> => [point(P, Driver) || P <- Points]}.

point(#{group := G, name := P, dir := Dir, type := Type, address := A, caption := Cap} = Info,
      Driver) ->
    (cell_web_io:point_json(G, P))#{
      <<"dir">> => atom_to_binary(Dir, utf8),
      <<"type">> => iolist_to_binary(cell_hal_type:name(Type)),
      <<"address">> => A, <<"caption">> => Cap, <<"unit">> => maps:get(unit, Info, <<>>),
      <<"forced">> => cell_hal_force:forced(G, P),
      <<"forceable">> => cell_hal_force:forceable(Dir, Driver) =:= ok}.

grab(Name, Req) ->
    case [Id || {Id, camera, _} <- cell_hal_hw:list(), atom_to_binary(Id, utf8) =:= Name] of
        [Id] ->
            case cell_hal_camera:grab(Id, ?GRAB_TIMEOUT) of
                {ok, Image} ->
                    case cell_web_png:encode(Image) of
                        {ok, Png} ->
                            {done, cowboy_req:reply(200, #{<<"content-type">> => <<"image/png">>,
                                                           <<"cache-control">> => <<"no-store">>},
                                                    Png, Req)};
                        {error, Why} ->
                            cell_web_req:fail(502, unsupported_image,
                                              io_lib:format("the camera's image cannot be shown "
                                                            "(~0tp)", [Why]))
                    end;
                {error, Why} ->
                    cell_web_req:fail(502, grab_failed,
                                      io_lib:format("the camera ~s did not give an image: ~0tp",
                                                    [Id, Why]))
            end;
        [] ->
            cell_web_req:fail(404, not_found, ["no camera ", Name])
    end.

%% @doc The point named by a group and a point name from a request, without making
%% atoms of them: `{ok, {Group, Point}}' or `error'.
-spec lookup_point(binary(), binary()) -> {ok, {atom(), atom()}} | error.
lookup_point(Group, Point) ->
    case [G || G <- cell_hal:groups(), atom_to_binary(G, utf8) =:= Group] of
        [G] ->
            {ok, Ps} = cell_hal:points(G),
            case [P || #{name := P} <- Ps, atom_to_binary(P, utf8) =:= Point] of
                [P] -> {ok, {G, P}};
                [] -> error
            end;
        [] ->
            error
    end.
