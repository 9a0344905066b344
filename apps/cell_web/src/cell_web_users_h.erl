%% @doc `/api/users' — the panel's users, for admins.
%%
%% <ul>
%% <li>`GET /api/users' — names and roles (never the hashes).</li>
%% <li>`PUT /api/users/:name' with `{"role": R, "password": P}' — create a user (both
%%     needed) or change one (either); 201 created, 200 changed.</li>
%% <li>`DELETE /api/users/:name' — remove a user; the last admin stays.</li>
%% </ul>
%%
%% A user whose role or password changes, or who is removed, is logged out at once.
-module(cell_web_users_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, Caller0) ->
    Caller = cell_web_req:require(Caller0, admin),
    Who = cell_web_req:who_name(Caller),
    case {cowboy_req:method(Req), cowboy_req:binding(name, Req)} of
        {<<"GET">>, undefined} ->
            {json, 200, list()};
        {<<"PUT">>, Name} when is_binary(Name) ->
            {Body, _} = cell_web_req:read_json(Req),
            Changes = changes(Body),
            case cell_web_users:put_user(Name, Changes, Who) of
                {ok, What} ->
                    ok = cell_web_sessions:revalidate(),
                    {json, case What of created -> 201; updated -> 200 end, list(),
                     iolist_to_binary(["user ", Name, " ", atom_to_binary(What, utf8),
                                       [[" as ", atom_to_binary(R, utf8)]
                                        || #{role := R} <- [Changes]]])};
                {error, Why} ->
                    refused(Why)
            end;
        {<<"DELETE">>, Name} when is_binary(Name) ->
            case cell_web_users:delete_user(Name, Who) of
                ok ->
                    ok = cell_web_sessions:revalidate(),
                    {json, 200, list(), <<"user ", Name/binary, " removed">>};
                {error, Why} ->
                    refused(Why)
            end;
        {_, undefined} ->
            cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>});
        {_, _} ->
            cell_web_req:fail(405, method_not_allowed, "use PUT or DELETE",
                              #{allow => <<"PUT, DELETE">>})
    end.

list() ->
    [#{<<"name">> => N, <<"role">> => atom_to_binary(R, utf8)}
     || #{name := N, role := R} <- cell_web_users:all()].

changes(Body) ->
    maps:fold(fun(<<"role">>, R, Acc) when is_binary(R) ->
                      case [X || X <- cell_web_users:roles(), atom_to_binary(X, utf8) =:= R] of
                          [X] -> Acc#{role => X};
                          [] -> cell_web_req:fail(400, bad_request,
                                                  "role must be operator, service or admin")
                      end;
                 (<<"password">>, P, Acc) when is_binary(P) ->
                      Acc#{password => P};
                 (K, _, _) ->
                      cell_web_req:fail(400, bad_request,
                                        [K, " is not a field of a user (role, password, as text)"])
              end, #{}, Body).

-spec refused(term()) -> no_return().
refused(bad_user_name) ->
    cell_web_req:fail(400, bad_name, "a user name is 1 to 64 letters, digits and . _ - @");
refused({password, too_short}) ->
    cell_web_req:fail(422, weak_password, "a password needs at least 8 characters");
refused({password, _}) ->
    cell_web_req:fail(422, weak_password, "a password is text of at most 1024 bytes");
refused(new_user_needs_role_and_password) ->
    cell_web_req:fail(422, invalid, "a new user needs a role and a password");
refused(not_found) ->
    cell_web_req:fail(404, not_found, "there is no such user");
refused(last_admin) ->
    cell_web_req:fail(409, last_admin, "the last admin cannot be removed or demoted");
refused(Other) ->
    cell_web_req:fail(422, invalid, cell_web_words:settings_error(Other)).
