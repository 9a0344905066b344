%% @doc `/api/settings' — the cell's settings objects (seed 000 §3.1): read, edit with
%% validation, revisions, differences, restore.
%%
%% <ul>
%% <li>`GET /api/settings' — the objects, whether each has changes waiting for the
%%     next Start, and the role that may edit it.</li>
%% <li>`GET /api/settings/:name' — the saved values, the values in force (the
%%     snapshot of the last Start), and the fields with their types, ranges, defaults,
%%     units and docs, for a form.</li>
%% <li>`PUT /api/settings/:name' — some fields (a JSON object); refused whole with the
%%     field named when a value is wrong (422). Saved changes apply at the next Start.</li>
%% <li>`GET .../revisions', `GET .../revisions/:rev', `GET .../diff?from=A&amp;to=B',
%%     `POST .../restore' with `{"rev": N}'.</li>
%% </ul>
%%
%% Service edits the cell's objects; the panel's own `web' object needs admin. The
%% users object is not shown here (its hashes stay inside): see `/api/users'.
-module(cell_web_settings_h).
-behaviour(cowboy_handler).

-export([init/2, encode/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(list, Req, Caller) ->
    method(Req, <<"GET">>),
    _ = cell_web_req:require(Caller, view),
    Pending = cell_settings:pending(),
    {json, 200, [#{<<"name">> => atom_to_binary(N, utf8),
                   <<"pending">> => lists:member(N, Pending),
                   <<"edit_role">> => atom_to_binary(edit_role(N), utf8)}
                 || N <- shown()]};
handle(one, Req, Caller) ->
    case cowboy_req:method(Req) of
        <<"GET">> ->
            _ = cell_web_req:require(Caller, view),
            {json, 200, object(name(Req))};
        <<"PUT">> ->
            Name = name(Req),
            Who = cell_web_req:require(Caller, edit_role(Name)),
            {Changes, _} = cell_web_req:read_json(Req),
            saved(Name, cell_settings:put(Name, Changes, cell_web_req:who_name(Who)),
                  [atom_to_binary(Name, utf8), " changed"]);
        _ ->
            cell_web_req:fail(405, method_not_allowed, "use GET or PUT",
                              #{allow => <<"GET, PUT">>})
    end;
handle(revisions, Req, Caller) ->
    method(Req, <<"GET">>),
    _ = cell_web_req:require(Caller, view),
    {ok, Revs} = cell_settings:revisions(name(Req)),
    {json, 200, Revs};
handle(revision, Req, Caller) ->
    method(Req, <<"GET">>),
    _ = cell_web_req:require(Caller, view),
    Name = name(Req),
    Rev = rev(cell_web_req:binding(rev, Req)),
    case cell_settings:revision(Name, Rev) of
        {ok, #{settings := Obj} = R} ->
            {ok, Mod} = cell_settings:schema(Name),
            {json, 200, (maps:without([settings], R))#{values => encode(Mod, Obj)}};
        {error, Why} ->
            not_found(Why)
    end;
handle(diff, Req, Caller) ->
    method(Req, <<"GET">>),
    _ = cell_web_req:require(Caller, view),
    Name = name(Req),
    Qs = cell_web_req:qs(Req),
    From = cell_web_req:int_param(<<"from">>, Qs, 0, {1, 1 bsl 40}),
    To = cell_web_req:int_param(<<"to">>, Qs, 0, {1, 1 bsl 40}),
    From > 0 andalso To > 0
        orelse cell_web_req:fail(400, bad_query, "from and to must name two revisions"),
    case cell_settings:diff(Name, From, To) of
        {ok, Changes} ->
            {json, 200, [#{<<"path">> => cell_settings_schema:format_path(P),
                           <<"from">> => cell_web_json:term(A), <<"to">> => cell_web_json:term(B),
                           <<"text">> => cell_settings_schema:format_change(C)}
                         || #{path := P, from := A, to := B} = C <- Changes]};
        {error, Why} ->
            not_found(Why)
    end;
handle(restore, Req, Caller) ->
    method(Req, <<"POST">>),
    Name = name(Req),
    Who = cell_web_req:require(Caller, edit_role(Name)),
    {Body, _} = cell_web_req:read_json(Req),
    Rev = case maps:get(<<"rev">>, Body, undefined) of
              N when is_integer(N), N > 0 -> N;
              _ -> cell_web_req:fail(400, bad_request, "rev must be a revision number")
          end,
    case cell_settings:restore(Name, Rev, cell_web_req:who_name(Who)) of
        {error, {no_revision, _, _} = Why} -> not_found(Why);
        Result -> saved(Name, Result, [atom_to_binary(Name, utf8), " restored to revision ",
                                       integer_to_binary(Rev)])
    end.

method(Req, Method) ->
    cowboy_req:method(Req) =:= Method
        orelse cell_web_req:fail(405, method_not_allowed, ["use ", Method], #{allow => Method}).

saved(Name, ok, Detail) ->
    Name =:= web andalso cell_web_sessions:revalidate(),
    {json, 200, object(Name), iolist_to_binary(Detail)};
saved(_Name, {error, {invalid, Path, _} = Why}, _Detail) ->
    cell_web_req:fail(422, invalid, cell_web_words:settings_error(Why),
                      #{field => cell_settings_schema:format_path(Path)});
saved(_Name, {error, Why}, _Detail) ->
    cell_web_req:fail(422, invalid, cell_web_words:settings_error(Why)).

-spec not_found(term()) -> no_return().
not_found(Why) ->
    cell_web_req:fail(404, not_found, cell_web_words:settings_error(Why)).

rev(Bin) ->
    try binary_to_integer(Bin) of
        N when N > 0 -> N;
        _ -> cell_web_req:fail(404, not_found, "no such revision")
    catch error:badarg -> cell_web_req:fail(404, not_found, "no such revision")
    end.

%% The objects shown here: all but the users (their hashes stay inside).
shown() ->
    [N || N <- cell_settings:names(), N =/= cell_web_users:name()].

name(Req) ->
    Bin = cell_web_req:binding(name, Req),
    case [N || N <- shown(), atom_to_binary(N, utf8) =:= Bin] of
        [N] -> N;
        [] -> cell_web_req:fail(404, not_found, ["there are no settings ", Bin])
    end.

edit_role(web) -> admin;
edit_role(_) -> service.

object(Name) ->
    {ok, Mod} = cell_settings:schema(Name),
    InForce = case cell_settings:last_snapshot() of
                  #{Name := Obj} -> encode(Mod, Obj);
                  _ -> null
              end,
    #{<<"name">> => atom_to_binary(Name, utf8),
      <<"values">> => encode(Mod, cell_settings:get(Name)),
      <<"in_force">> => InForce,
      <<"pending">> => lists:member(Name, cell_settings:pending()),
      <<"edit_role">> => atom_to_binary(edit_role(Name), utf8),
      <<"fields">> => fields(Mod)}.

%% @doc An object as JSON values, by its schema.
-spec encode(module(), map()) -> map().
encode(Mod, Obj) ->
    maps:from_list([{atom_to_binary(N, utf8), value(T, maps:get(N, Obj))}
                    || #{name := N, type := T} <- Mod:fields()]).

value({object, Mod}, Obj) -> encode(Mod, Obj);
value({optional, _}, undefined) -> null;
value({optional, T}, V) -> value(T, V);
value({list, T}, L) -> [value(T, E) || E <- L];
value({list, T, _}, L) -> [value(T, E) || E <- L];
value({enum, _}, A) -> atom_to_binary(A, utf8);
value(_, V) -> V.

%% The fields of a schema, for a form: types with their ranges, defaults, units, docs.
fields(Mod) ->
    [maps:merge(#{<<"name">> => atom_to_binary(N, utf8),
                  <<"doc">> => maps:get(doc, F, <<>>),
                  <<"unit">> => maps:get(unit, F, <<>>),
                  <<"default">> => case F of
                                       #{default := D} -> value(T, D);
                                       _ -> null
                                   end},
                type(T))
     || #{name := N, type := T} = F <- Mod:fields()].

type(boolean) -> #{<<"type">> => <<"boolean">>};
type(integer) -> #{<<"type">> => <<"integer">>};
type(float) -> #{<<"type">> => <<"float">>};
type(string) -> #{<<"type">> => <<"string">>};
type({integer, Min, Max}) -> bounds(<<"integer">>, Min, Max);
type({float, Min, Max}) -> bounds(<<"float">>, Min, Max);
type({string, Max}) -> #{<<"type">> => <<"string">>, <<"max_length">> => Max};
type({enum, Values}) -> #{<<"type">> => <<"enum">>,
                          <<"values">> => [atom_to_binary(V, utf8) || V <- Values]};
type({list, T}) -> #{<<"type">> => <<"list">>, <<"of">> => type(T)};
type({list, T, Max}) -> #{<<"type">> => <<"list">>, <<"of">> => type(T), <<"max_length">> => Max};
type({object, Mod}) -> #{<<"type">> => <<"object">>, <<"fields">> => fields(Mod)};
type({optional, T}) -> maps:put(<<"optional">>, true, type(T)).

bounds(Type, Min, Max) ->
    #{<<"type">> => Type, <<"min">> => bound(Min), <<"max">> => bound(Max)}.

bound(unbounded) -> null;
bound(N) -> N.
