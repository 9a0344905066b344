%% @doc `/api/recipes' — the recipes of seed 000 §3.2, each a `.zprd' file.
%%
%% <ul>
%% <li>`GET /api/recipes' — every recipe with its description, author, date, size.</li>
%% <li>`GET /api/recipes/:name' — one; `GET /api/recipes/:name/file' — its file, to
%%     download.</li>
%% <li>`PUT /api/recipes/:name' — upload a recipe file (`application/zip' or
%%     `application/octet-stream'); checked in full as untrusted input before anything
%%     is written; `?replace=true' to overwrite. 201 new, 200 replaced.</li>
%% <li>`DELETE /api/recipes/:name'; `POST /api/recipes/:name/rename' and `/copy' with
%%     `{"to": "new name"}' (an existing recipe is never overwritten).</li>
%% <li>`GET /api/recipes/:name/drawing' — the recipe's drawing tree in drawing
%%     coordinates (every `Transform' applied, as {@link
%%     cell_recipe_drawing:apply_transform/2} does), in the JSON form of the recipe's
%%     `drawing.json', for the panel's preview.</li>
%% <li>`PUT /api/recipes/:name/dxf' — a DXF file (ASCII) made the recipe's drawing: a
%%     new recipe with it, or, with `?replace=true', the drawing of an existing one
%%     replaced and its settings kept. Answers the recipe and what was imported and
%%     left out.</li>
%% </ul>
%%
%% Reading needs `view'; changes need `service'. The recipe buffer is emptied at the
%% next Start, so changes reach the tasks then.
-module(cell_web_recipes_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(list, Req, Caller) ->
    _ = method(Req, [<<"GET">>]),
    _ = cell_web_req:require(Caller, view),
    {json, 200, [case cell_recipe:info(N) of
                     {ok, Info} -> Info;
                     {error, Why} -> #{name => N, error => cell_web_words:recipe_error(Why)}
                 end || N <- cell_recipe:list()]};
handle(one, Req, Caller) ->
    Name = name(Req),
    case method(Req, [<<"GET">>, <<"PUT">>, <<"DELETE">>]) of
        <<"GET">> ->
            _ = cell_web_req:require(Caller, view),
            {json, 200, ok(cell_recipe:info(Name))};
        <<"PUT">> ->
            _ = cell_web_req:require(Caller, service),
            upload(Name, Req);
        <<"DELETE">> ->
            _ = cell_web_req:require(Caller, service),
            ok = ok(cell_recipe:delete(Name)),
            {json, 200, #{<<"deleted">> => Name}, <<"recipe ", Name/binary, " deleted">>}
    end;
handle(file, Req, Caller) ->
    _ = method(Req, [<<"GET">>]),
    _ = cell_web_req:require(Caller, view),
    Name = name(Req),
    Bin = ok(cell_recipe:export(Name)),
    {done, cowboy_req:reply(200, #{<<"content-type">> => <<"application/zip">>,
                                   <<"content-disposition">> => disposition(Name),
                                   <<"cache-control">> => <<"no-store">>}, Bin, Req)};
handle(drawing, Req, Caller) ->
    _ = method(Req, [<<"GET">>]),
    _ = cell_web_req:require(Caller, view),
    #{drawing := Drawing} = ok(cell_recipe:load(name(Req))),
    Flat = cell_recipe_drawing:apply_transform(cell_recipe_drawing:identity(), Drawing),
    {json, 200, jsx:decode(iolist_to_binary(cell_recipe_drawing:to_json(Flat)),
                           [return_maps])};
handle(dxf, Req, Caller) ->
    _ = method(Req, [<<"PUT">>]),
    Who = cell_web_req:who_name(cell_web_req:require(Caller, service)),
    Name = name(Req),
    Replace = replace(Req),
    Existed = lists:member(Name, cell_recipe:list()),
    Existed andalso not Replace
        andalso cell_web_req:fail(409, exists, cell_web_words:recipe_error({exists, Name})),
    Max = application:get_env(cell_web, upload_body_max, 64 * 1024 * 1024),
    {Bin, _} = cell_web_req:read_body(Req, Max, [<<"application/dxf">>, <<"image/vnd.dxf">>,
                                                 <<"application/octet-stream">>,
                                                 <<"text/plain">>]),
    Bin =:= <<>> andalso cell_web_req:fail(400, bad_request, "the body must be a DXF file"),
    {Drawing, #{imported := N, skipped := Skipped}} =
        case cell_recipe_dxf:import(Bin) of
            {ok, D, Report} -> {D, Report};
            {error, Why} -> cell_web_req:fail(422, invalid_dxf, cell_recipe_dxf:format_error(Why))
        end,
    Recipe = case Existed of
                 true -> maps:with([description, settings, files], ok(cell_recipe:load(Name)));
                 false -> #{description => <<"imported from DXF">>}
             end,
    ok = ok(cell_recipe:save(Name, Recipe#{drawing => cell_recipe_drawing:new([Drawing])}, Who)),
    Status = case Existed of true -> 200; false -> 201 end,
    {json, Status, #{<<"recipe">> => ok(cell_recipe:info(Name)),
                     <<"imported">> => N, <<"skipped">> => Skipped},
     iolist_to_binary(["recipe ", Name, " drawing imported from DXF (", integer_to_binary(N),
                       " items)"])};
handle(Op, Req, Caller) when Op =:= rename; Op =:= copy ->
    _ = method(Req, [<<"POST">>]),
    _ = cell_web_req:require(Caller, service),
    Name = name(Req),
    {Body, _} = cell_web_req:read_json(Req),
    To = case maps:get(<<"to">>, Body, undefined) of
             T when is_binary(T) -> checked(T);
             _ -> cell_web_req:fail(400, bad_request, "to must name the new recipe")
         end,
    ok = ok(case Op of
                rename -> cell_recipe:rename(Name, To);
                copy -> cell_recipe:copy(Name, To)
            end),
    {json, 200, #{<<"name">> => To, <<"from">> => Name},
     iolist_to_binary(["recipe ", Name, " ", atom_to_binary(Op, utf8), " to ", To])}.

upload(Name, Req) ->
    Max = application:get_env(cell_web, upload_body_max, 64 * 1024 * 1024),
    Replace = replace(Req),
    Existed = lists:member(Name, cell_recipe:list()),
    {Bin, _} = cell_web_req:read_body(Req, Max, [<<"application/zip">>,
                                                 <<"application/octet-stream">>]),
    Bin =:= <<>> andalso cell_web_req:fail(400, bad_request, "the body must be a recipe file"),
    ok = ok(cell_recipe:import(Name, Bin, #{replace => Replace})),
    Status = case Existed of true -> 200; false -> 201 end,
    {json, Status, ok(cell_recipe:info(Name)),
     iolist_to_binary(["recipe ", Name, " uploaded (", integer_to_binary(byte_size(Bin)),
                       " bytes)"])}.

replace(Req) ->
    case maps:get(<<"replace">>, cell_web_req:qs(Req), <<"false">>) of
        <<"true">> -> true;
        <<"false">> -> false;
        _ -> cell_web_req:fail(400, bad_query, "replace must be true or false")
    end.

method(Req, Allowed) ->
    M = cowboy_req:method(Req),
    case lists:member(M, Allowed) of
        true -> M;
        false -> cell_web_req:fail(405, method_not_allowed, ["use ", lists:join(" or ", Allowed)],
                                   #{allow => iolist_to_binary(lists:join(", ", Allowed))})
    end.

name(Req) ->
    checked(cell_web_req:binding(name, Req)).

checked(Name) ->
    case cell_recipe:check_name(Name) of
        ok -> Name;
        {error, Why} -> cell_web_req:fail(400, bad_name, cell_web_words:recipe_error(Why))
    end.

%% A recipe result, or the error answered with a fitting status.
ok(ok) -> ok;
ok({ok, V}) -> V;
ok({error, Why}) ->
    {Status, Code} = case Why of
                         {no_recipe, _} -> {404, not_found};
                         {exists, _} -> {409, exists};
                         {bad_name, _, _} -> {400, bad_name};
                         {file, _, _} -> {500, file_error};
                         _ -> {422, invalid_recipe}
                     end,
    cell_web_req:fail(Status, Code, cell_web_words:recipe_error(Why)).

%% The file name for the browser: ASCII for old clients, UTF-8 (RFC 6266) for the rest.
disposition(Name) ->
    Ascii = << <<(case C >= 32 andalso C < 127 andalso C =/= $" andalso C =/= $\\ of
                      true -> C;
                      false -> $_
                  end)>> || <<C>> <= Name >>,
    iolist_to_binary(["attachment; filename=\"", Ascii, ".zprd\"; filename*=UTF-8''",
                      [pct(C) || <<C>> <= <<Name/binary, ".zprd">>]]).

pct(C) when C >= $a, C =< $z; C >= $A, C =< $Z; C >= $0, C =< $9 -> C;
pct(C) when C =:= $-; C =:= $.; C =:= $_; C =:= $~ -> C;
pct(C) -> io_lib:format("%~2.16.0B", [C]).
