%% @doc What every API handler of the panel does the same way: who is asking (the
%% session cookie), whether they may (roles), CSRF and origin checks on every
%% state-changing request, bodies read within limits, JSON answers and JSON errors,
%% and the audit trail of every state-changing request.
%%
%% A handler gives {@link run/2} a function of the request and the caller; the
%% function returns `{json, Status, Body}' (or `{json, Status, Body, Detail}', Detail
%% going to the audit trail), or `{done, Req}' when it replied itself. Anything wrong
%% is thrown with {@link fail/3} and answered as `{"error": Code, "message": Text}'
%% with a fitting status; nothing has changed when an error is answered.
-module(cell_web_req).

-export([run/2, caller/1, check_origin/1, fail/3, fail/4, require/2, read_json/1, read_body/3, qs/1,
         binding/2, peer/1, reply_json/3, reply_error/5, session_cookie/0, who_name/1,
         int_param/4, time_param/2, csv_param/3]).

-export_type([caller/0, result/0]).

-type caller() :: #{user := binary() | null, role := cell_web_users:role() | anonymous,
                    session := binary() | undefined, csrf := binary() | undefined}.
-type result() :: {json, cowboy:http_status(), term()}
                | {json, cowboy:http_status(), term(), binary()}
                | {done, cowboy_req:req()}
                | {done, cowboy_req:req(), binary()}.

-define(COOKIE, <<"cellrt_session">>).

%% @doc The session cookie's name.
-spec session_cookie() -> binary().
session_cookie() -> ?COOKIE.

%% @doc Runs a handler function: checks CSRF and origin on state-changing requests,
%% answers, records state-changing requests in the audit trail. An unexpected crash
%% of the function is answered 500 and logged with the request; the node stays up.
-spec run(cowboy_req:req(), fun((cowboy_req:req(), caller()) -> result())) ->
          cowboy_req:req().
run(Req0, Fun) ->
    Caller = caller(Req0),
    Method = cowboy_req:method(Req0),
    Changes = lists:member(Method, [<<"POST">>, <<"PUT">>, <<"DELETE">>, <<"PATCH">>]),
    {Status, Detail, Req} =
        try
            Changes andalso check_origin(Req0),
            Changes andalso check_csrf(Req0, Caller),
            case Fun(Req0, Caller) of
                {json, S, Body} -> {S, <<>>, reply_json(S, Body, Req0)};
                {json, S, Body, D} -> {S, D, reply_json(S, Body, Req0)};
                {done, R} -> {200, <<>>, R};
                {done, R, D} -> {200, D, R}
            end
        catch
            throw:{cell_web_error, S1, Code, Message, Extra} ->
                {S1, maps:get(detail, Extra, Message),
                 reply_error(S1, Code, Message, maps:remove(detail, Extra), Req0)};
            Class:Reason:Stack ->
                cell_log:error(web, "~ts ~ts failed; answered 500", [Method, cowboy_req:path(Req0)]),
                cell_log:trace(web, "~ts ~ts: ~tp:~tp ~tp",
                               [Method, cowboy_req:path(Req0), Class, Reason, Stack]),
                {500, <<"internal error">>,
                 reply_error(500, internal, <<"the panel could not do this; see the trace log">>,
                             #{}, Req0)}
        end,
    _ = Changes andalso audit(Req0, Caller, Status, Detail),
    Req.

audit(Req, #{user := User, role := Role}, Status, Detail) ->
    Entry = #{who => case User of null -> <<"-">>; _ -> User end,
              role => atom_to_binary(Role, utf8),
              address => peer(Req),
              action => cowboy_req:method(Req),
              target => cowboy_req:path(Req),
              outcome => integer_to_binary(Status),
              detail => Detail},
    %% A refusal of a caller not logged in costs the caller nothing: counted, not
    %% each written (see cell_web_audit).
    Written = case Role =:= anonymous andalso Status >= 400 of
                  true -> cell_web_audit:refused(Entry);
                  false -> cell_web_audit:record(Entry)
              end,
    case Written of
        ok -> ok;
        {error, _} -> ok      %% logged by the audit process; the answer is sent
    end.

%% @doc Answers an error: `fail(404, not_found, "there is no task x")'.
-spec fail(cowboy:http_status(), atom(), iodata()) -> no_return().
fail(Status, Code, Message) ->
    fail(Status, Code, Message, #{}).

%% @doc As {@link fail/3} with more fields for the answer (`detail' goes to the audit
%% trail only).
-spec fail(cowboy:http_status(), atom(), iodata(), map()) -> no_return().
fail(Status, Code, Message, Extra) ->
    throw({cell_web_error, Status, Code, cell_web_words:no_terms(Message), Extra}).

%% @doc Checks that the caller may do something: `view' (anyone when anonymous
%% viewing is on, else any user) or a role (that role or a higher one).
-spec require(caller(), view | cell_web_users:role()) -> caller().
require(#{role := anonymous} = C, view) ->
    case cell_web_settings:get(anonymous_view) of
        true -> C;
        false -> fail(401, login_required, "log in to see the panel")
    end;
require(C, view) ->
    C;
require(#{role := anonymous}, _Role) ->
    fail(401, login_required, "log in first");
require(#{role := Has} = C, Role) ->
    case cell_web_users:rank(Has) >= cell_web_users:rank(Role) of
        true -> C;
        false -> fail(403, forbidden, ["this needs the role ", atom_to_binary(Role, utf8),
                                       " or higher; you are ", atom_to_binary(Has, utf8)])
    end.

%% @doc Who sends a request: the user of its session cookie, or nobody.
-spec caller(cowboy_req:req()) -> caller().
caller(Req) ->
    Anonymous = #{user => null, role => anonymous, session => undefined, csrf => undefined},
    case lists:keyfind(?COOKIE, 1, cookies(Req)) of
        {_, Id} ->
            case cell_web_sessions:lookup(Id) of
                {ok, #{user := U, role := R, csrf := Csrf}} ->
                    #{user => U, role => R, session => Id, csrf => Csrf};
                {error, no_session} ->
                    Anonymous
            end;
        false ->
            Anonymous
    end.

cookies(Req) ->
    try cowboy_req:parse_cookies(Req)
    catch _:_ -> []          %% a malformed Cookie header counts as none
    end.

%% @doc A request that changes something must come from a page of this panel: the
%% Origin, when the browser sends one, names this host.
-spec check_origin(cowboy_req:req()) -> ok.
check_origin(Req) ->
    case cowboy_req:header(<<"origin">>, Req) of
        undefined -> ok;
        Origin ->
            Host = cowboy_req:header(<<"host">>, Req, <<>>),
            case lists:member(Origin, [<<"http://", Host/binary>>, <<"https://", Host/binary>>]) of
                true -> ok;
                false -> fail(403, bad_origin, "this request comes from another site")
            end
    end.

%% Every state-changing request of a logged-in caller carries the session's CSRF
%% token in a header, which another site's page cannot read or set.
check_csrf(_Req, #{session := undefined}) ->
    ok;
check_csrf(Req, #{csrf := Csrf}) ->
    case cowboy_req:header(<<"x-csrf-token">>, Req) of
        Token when is_binary(Token), byte_size(Token) =:= byte_size(Csrf) ->
            case crypto:hash_equals(Token, Csrf) of
                true -> ok;
                false -> fail(403, bad_csrf_token, "the request's CSRF token is wrong; reload the page")
            end;
        _ ->
            fail(403, bad_csrf_token, "the request has no valid CSRF token; reload the page")
    end.

%% @doc The caller's name for the cell's records (who answered, who started).
-spec who_name(caller()) -> binary().
who_name(#{user := null}) -> <<"anonymous">>;
who_name(#{user := U}) -> U.

%% @doc Reads a JSON object body (`Content-Type: application/json', at most the
%% `json_body_max' bytes); an empty body is an empty object.
-spec read_json(cowboy_req:req()) -> {map(), cowboy_req:req()}.
read_json(Req0) ->
    Max = application:get_env(cell_web, json_body_max, 65536),
    {Body, Req} = read_body(Req0, Max, [<<"application/json">>]),
    case Body of
        <<>> -> {#{}, Req};
        _ ->
            case cell_settings_schema:json_decode(Body) of
                {ok, Map} when is_map(Map) -> {Map, Req};
                {ok, _} -> fail(400, bad_json, "the body must be a JSON object");
                {error, not_json} -> fail(400, bad_json, "the body is not valid JSON");
                {error, Why} -> fail(400, bad_json, ["the body is refused: ",
                                                     cell_web_words:settings_error(Why)])
            end
    end.

%% @doc Reads a body of one of the given media types, at most `Max' bytes: longer is
%% answered 413 without reading it all.
-spec read_body(cowboy_req:req(), pos_integer(), [binary()]) -> {binary(), cowboy_req:req()}.
read_body(Req, Max, Types) ->
    case cowboy_req:has_body(Req) of
        false ->
            {<<>>, Req};
        true ->
            check_type(Req, Types),
            case cowboy_req:body_length(Req) of
                N when is_integer(N), N > Max -> too_large(Max);
                _ -> read_loop(Req, Max, [])
            end
    end.

read_loop(Req0, Max, Acc) ->
    {More, Data, Req} = cowboy_req:read_body(Req0, #{length => Max + 1, period => 15000}),
    Acc1 = [Acc, Data],
    case iolist_size(Acc1) > Max of
        true -> too_large(Max);
        false when More =:= ok -> {iolist_to_binary(Acc1), Req};
        false -> read_loop(Req, Max, Acc1)
    end.

%% The rest of the body is not read: the connection closes after the answer.
-spec too_large(pos_integer()) -> no_return().
too_large(Max) ->
    fail(413, body_too_large, ["the body is larger than ", integer_to_binary(Max), " bytes"],
         #{close => true}).

check_type(Req, Types) ->
    Type = try cowboy_req:parse_header(<<"content-type">>, Req) of
               {T, S, _} -> <<T/binary, "/", S/binary>>;
               undefined -> undefined
           catch _:_ -> undefined
           end,
    case lists:member(Type, Types) of
        true -> ok;
        false -> fail(415, unsupported_media_type,
                      ["the body must be ", lists:join(" or ", Types)])
    end.

%% @doc The query string as a map of binaries; a malformed one is answered 400.
-spec qs(cowboy_req:req()) -> #{binary() => binary() | true}.
qs(Req) ->
    try maps:from_list(cowboy_req:parse_qs(Req))
    catch _:_ -> fail(400, bad_query, "the query string is malformed")
    end.

%% @doc A path binding (percent-decoded by the router).
-spec binding(atom(), cowboy_req:req()) -> binary().
binding(Name, Req) ->
    case cowboy_req:binding(Name, Req) of
        B when is_binary(B) -> B;
        _ -> fail(404, not_found, "no such resource")
    end.

%% @doc An integer parameter of the query within bounds, or the default.
-spec int_param(binary(), map(), integer(), {integer(), integer()}) -> integer().
int_param(Key, Qs, Default, {Min, Max}) ->
    case maps:get(Key, Qs, undefined) of
        undefined -> Default;
        V when is_binary(V) ->
            try binary_to_integer(V) of
                N when N >= Min, N =< Max -> N;
                _ -> bad_param(Key, ["a whole number from ", integer_to_binary(Min), " to ",
                                     integer_to_binary(Max)])
            catch error:badarg -> bad_param(Key, "a whole number")
            end;
        true -> bad_param(Key, "a value")
    end.

%% @doc A time parameter: milliseconds since the epoch, or RFC 3339 text
%% (`2026-11-21T08:00:00Z'); `undefined' when absent.
-spec time_param(binary(), map()) -> integer() | undefined.
time_param(Key, Qs) ->
    case maps:get(Key, Qs, undefined) of
        undefined -> undefined;
        V when is_binary(V) ->
            try binary_to_integer(V)
            catch error:badarg ->
                    try calendar:rfc3339_to_system_time(binary_to_list(V), [{unit, millisecond}])
                    catch error:_ -> bad_param(Key, "a time (milliseconds or RFC 3339)")
                    end
            end;
        true -> bad_param(Key, "a time")
    end.

%% @doc A comma-separated list of names, each one of `Allowed' (atoms, matched by
%% name, never made from the input); `all' when absent.
-spec csv_param(binary(), map(), [atom()]) -> all | [atom()].
csv_param(Key, Qs, Allowed) ->
    case maps:get(Key, Qs, undefined) of
        undefined -> all;
        V when is_binary(V) ->
            [case [A || A <- Allowed, atom_to_binary(A, utf8) =:= P] of
                 [A] -> A;
                 [] -> bad_param(Key, ["names among ",
                                       lists:join(", ", [atom_to_binary(A, utf8) || A <- Allowed])])
             end || P <- binary:split(V, <<",">>, [global, trim_all])];
        true -> bad_param(Key, "a value")
    end.

-spec bad_param(binary(), iodata()) -> no_return().
bad_param(Key, Expected) ->
    fail(400, bad_query, [Key, " must be ", Expected]).

%% @doc The caller's address, as text.
-spec peer(cowboy_req:req()) -> binary().
peer(Req) ->
    {Ip, _Port} = cowboy_req:peer(Req),
    list_to_binary(inet:ntoa(Ip)).

%% @doc A JSON answer.
-spec reply_json(cowboy:http_status(), term(), cowboy_req:req()) -> cowboy_req:req().
reply_json(Status, Body, Req) ->
    cowboy_req:reply(Status, #{<<"content-type">> => <<"application/json; charset=utf-8">>,
                               <<"cache-control">> => <<"no-store">>},
                     cell_web_json:encode(Body), Req).

%% @doc A JSON error answer.
-spec reply_error(cowboy:http_status(), atom(), binary(), map(), cowboy_req:req()) ->
          cowboy_req:req().
reply_error(Status, Code, Message, Extra, Req) ->
    Req1 = case Status of
               405 -> cowboy_req:set_resp_header(<<"allow">>, maps:get(allow, Extra, <<>>), Req);
               413 -> cowboy_req:set_resp_header(<<"connection">>, <<"close">>, Req);
               429 -> cowboy_req:set_resp_header(<<"retry-after">>,
                                                 maps:get(retry_after, Extra, <<"1">>), Req);
               _ -> Req
           end,
    reply_json(Status, maps:merge(cell_web_json:term(maps:remove(close, Extra)),
                                  #{<<"error">> => atom_to_binary(Code, utf8),
                                    <<"message">> => Message}), Req1).
