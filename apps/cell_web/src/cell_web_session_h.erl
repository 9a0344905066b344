%% @doc `/api/session' — logging in and out.
%%
%% <ul>
%% <li>`GET' — who the caller is: `user' (null when nobody is logged in), `role', the
%%     session's `csrf' token for the header `x-csrf-token', whether anonymous viewing
%%     is on, whether the user still has a demo password.</li>
%% <li>`POST' with `{"user": Name, "password": P}' — log in: sets the session cookie
%%     (HttpOnly, SameSite=Strict) and answers as `GET'. Wrong name or password: 401,
%%     the same answer for both. Too many failures for that account from this
%%     address, or from this address for accounts not known there: 429 with
%%     `Retry-After', before the password is checked.</li>
%% <li>`DELETE' — log out (the IO points the user forced are released).</li>
%% <li>`POST /api/session/password' with `{"old": P, "new": Q}' — change one's own
%%     password; the session is renewed.</li>
%% </ul>
-module(cell_web_session_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(session, Req, Caller) ->
    case cowboy_req:method(Req) of
        <<"GET">> -> {json, 200, session(Caller)};
        <<"POST">> -> login(Req);
        <<"DELETE">> -> logout(Req, Caller);
        _ -> cell_web_req:fail(405, method_not_allowed, "use GET, POST or DELETE",
                               #{allow => <<"GET, POST, DELETE">>})
    end;
handle(password, Req, Caller0) ->
    cowboy_req:method(Req) =:= <<"POST">>
        orelse cell_web_req:fail(405, method_not_allowed, "use POST", #{allow => <<"POST">>}),
    #{user := Name} = cell_web_req:require(Caller0, operator),
    {Body, _} = cell_web_req:read_json(Req),
    {Old, New} = case Body of
                     #{<<"old">> := O, <<"new">> := N} when is_binary(O), is_binary(N) -> {O, N};
                     _ -> cell_web_req:fail(400, bad_request, "give old and new as text")
                 end,
    case cell_web_users:authenticate(Name, Old) of
        {ok, _} -> ok;
        {error, bad_login} -> cell_web_req:fail(403, bad_password, "the old password is wrong")
    end,
    case cell_web_users:set_password(Name, New, Name) of
        {ok, updated} -> ok;
        {error, {password, Why}} -> cell_web_req:fail(422, weak_password, password_text(Why));
        {error, Why} -> cell_web_req:fail(422, invalid, cell_web_words:settings_error(Why))
    end,
    {ok, User} = cell_web_users:find(Name),
    ok = cell_web_sessions:revalidate(),
    {Req1, Session} = new_session(User, false, Req),
    {done, cell_web_req:reply_json(200, Session, Req1), <<"password of ", Name/binary, " changed">>}.

login(Req) ->
    Addr = cell_web_req:peer(Req),
    {Body, _} = cell_web_req:read_json(Req),
    {Name, Password} =
        case Body of
            #{<<"user">> := U, <<"password">> := P} when is_binary(U), is_binary(P),
                                                         byte_size(U) =< 256,
                                                         byte_size(P) =< 1024 -> {U, P};
            _ -> cell_web_req:fail(400, bad_request, "give user and password as text")
        end,
    case cell_web_sessions:login_allowed(Addr, Name) of
        ok ->
            ok;
        {wait, Ms} ->
            Seconds = integer_to_binary((Ms + 999) div 1000),
            cell_web_req:fail(429, too_many_attempts,
                              ["too many failed logins; try again in ", Seconds, " s"],
                              #{retry_after => Seconds,
                                detail => <<"login braked for ", Name/binary>>})
    end,
    case cell_web_users:authenticate(Name, Password) of
        {ok, User} ->
            ok = cell_web_sessions:login_succeeded(Addr, Name),
            Demo = lists:member(Name, [<<"operator">>, <<"service">>, <<"admin">>])
                andalso Password =:= Name,
            {Req1, Session} = new_session(User, Demo, Req),
            {done, cell_web_req:reply_json(200, Session, Req1), <<"login as ", Name/binary>>};
        {error, bad_login} ->
            ok = cell_web_sessions:login_failed(Addr, Name),
            cell_web_req:fail(401, bad_login, "wrong user name or password",
                              #{detail => <<"login refused for ", Name/binary>>})
    end.

new_session(User, Demo, Req) ->
    {Id, #{user := U, role := R, csrf := Csrf}} =
        cell_web_sessions:create(User, #{addr => cell_web_req:peer(Req), demo_password => Demo}),
    Req1 = cowboy_req:set_resp_cookie(cell_web_req:session_cookie(), Id, Req,
                                      #{http_only => true, same_site => strict,
                                        secure => cell_web_listener:https(), path => <<"/">>}),
    {Req1, session(#{user => U, role => R, session => Id, csrf => Csrf})}.

logout(Req, #{session := Id, user := User}) ->
    _ = Id =/= undefined andalso cell_web_sessions:delete(Id),
    %% The IO points this user forced are released with the logout.
    ok = case User of
             null -> ok;
             _ -> cell_web_forces:user_left(User)
         end,
    Req1 = cowboy_req:set_resp_cookie(cell_web_req:session_cookie(), <<>>, Req,
                                      #{http_only => true, same_site => strict,
                                        secure => cell_web_listener:https(),
                                        path => <<"/">>, max_age => 0}),
    {done, cell_web_req:reply_json(200, session(#{user => null, role => anonymous,
                                                   session => undefined, csrf => undefined}),
                                   Req1)}.

session(#{user := User, role := Role, csrf := Csrf, session := Id}) ->
    Demo = case Id of
               undefined -> false;
               _ -> case cell_web_sessions:lookup(Id) of
                        {ok, #{demo_password := D}} -> D;
                        {error, _} -> false
                    end
           end,
    #{<<"user">> => User, <<"role">> => atom_to_binary(Role, utf8),
      <<"csrf">> => case Csrf of undefined -> null; _ -> Csrf end,
      <<"anonymous_view">> => cell_web_settings:get(anonymous_view),
      <<"demo_password">> => Demo}.

password_text(too_short) -> "the new password needs at least 8 characters";
password_text(too_long) -> "the new password is longer than 1024 bytes";
password_text(not_text) -> "the new password is not text".
