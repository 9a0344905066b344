%% @doc `/api/forces' — the IO points forced from the panel. `GET': the forces;
%% `POST' `{"group", "point", "value"}': forces a point (role service or higher, the
%% cell in service mode, no emergency stop; an output, or an input of a simulated
%% PLC); `DELETE': releases them all; `DELETE /api/forces/:group/:point': releases one.
%% Every force and release is in the audit trail. See {@link cell_web_forces}.
-module(cell_web_forces_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(What, Req, Caller) ->
    case {cowboy_req:method(Req), What} of
        {<<"GET">>, all} ->
            _ = cell_web_req:require(Caller, view),
            {json, 200, cell_web_forces:json()};
        {<<"POST">>, all} ->
            {Body, _} = cell_web_req:read_json(Req),
            {Key, Value} = force_body(Body),
            case cell_web_forces:force(Caller, Key, Value) of
                ok -> {json, 200, cell_web_forces:json(), detail("forced", Key, Value)};
                {error, S, Code, Words} -> cell_web_req:fail(S, Code, Words)
            end;
        {<<"DELETE">>, all} ->
            case cell_web_forces:release_all(Caller) of
                {ok, N} -> {json, 200, #{<<"released">> => N},
                            iolist_to_binary(io_lib:format("released ~b forced point(s)", [N]))};
                {error, S, Code, Words} -> cell_web_req:fail(S, Code, Words)
            end;
        {<<"DELETE">>, one} ->
            Key = point(cell_web_req:binding(group, Req), cell_web_req:binding(point, Req)),
            case cell_web_forces:release(Caller, Key) of
                ok -> {json, 200, cell_web_forces:json(), detail("released", Key, undefined)};
                {error, S, Code, Words} -> cell_web_req:fail(S, Code, Words)
            end;
        {_, all} ->
            cell_web_req:fail(405, method_not_allowed, "use GET, POST or DELETE",
                              #{allow => <<"GET, POST, DELETE">>});
        {_, one} ->
            cell_web_req:fail(405, method_not_allowed, "use DELETE", #{allow => <<"DELETE">>})
    end.

force_body(#{<<"group">> := G, <<"point">> := P, <<"value">> := V})
  when is_binary(G), is_binary(P) ->
    {Key, Type} = typed(point(G, P)),
    {Key, value(Type, V)};
force_body(_) ->
    cell_web_req:fail(400, bad_request,
                      "give the point and the value: {\"group\": ..., \"point\": ..., \"value\": ...}").

point(G, P) ->
    case cell_web_io_h:lookup_point(G, P) of
        {ok, Key} -> Key;
        error -> cell_web_req:fail(404, not_found, ["no IO point ", G, ".", P])
    end.

typed({G, P} = Key) ->
    {ok, #{type := Type}} = cell_hal:describe(G, P),
    {Key, Type}.

%% JSON has no dates: a DATE is [Y, M, D]; anything else is checked by the HAL.
value(date, [Y, M, D]) -> {Y, M, D};
value(_Type, V) -> V.

detail(What, {G, P}, Value) ->
    iolist_to_binary([What, " ", atom_to_binary(G, utf8), ".", atom_to_binary(P, utf8),
                      case Value of
                          undefined -> [];
                          _ -> [" = ", cell_web_json:encode(Value)]
                      end]).
