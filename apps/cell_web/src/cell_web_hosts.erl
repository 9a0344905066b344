%% @doc The names the panel answers to, and the middleware that refuses every request
%% naming another host.
%%
%% A page of another site can make a browser send requests to the panel under that
%% site's own name (DNS rebinding: `attacker.example' made to resolve to the cell PC).
%% Comparing Origin with the request's own Host header does not see it, since both
%% name the attacker; comparing both with the names the panel is known by does. The
%% names are the bind address, `localhost', `127.0.0.1', `::1', the PC's host name
%% (short and full), every address of the PC when the panel listens on all of them,
%% and the names of the `cell_web' setting `names' (a list, or text separated by
%% commas: the names a reverse proxy or a DNS entry gives the panel). A request whose
%% Host names anything else is answered 403 `unknown_host'; one whose Origin, when it
%% has one, names anything else 403 `bad_origin'.
-module(cell_web_hosts).
-behaviour(cowboy_middleware).

-export([execute/2, names/1, host_allowed/2, origin_allowed/2, normal/1]).

-spec execute(cowboy_req:req(), cowboy_middleware:env()) ->
          {ok, cowboy_req:req(), cowboy_middleware:env()} | {stop, cowboy_req:req()}.
execute(Req, #{hosts := Names} = Env) ->
    Host = cowboy_req:host(Req),
    Origin = cowboy_req:header(<<"origin">>, Req),
    case {host_allowed(Host, Names), Origin =:= undefined orelse origin_allowed(Origin, Names)} of
        {true, true} ->
            {ok, Req, Env};
        {false, _} ->
            {stop, refuse(unknown_host, ["this panel does not answer to the name ", printable(Host),
                           "; open it by one of its names, or add this one to the "
                           "panel's names setting"], Req)};
        {true, false} ->
            {stop, refuse(bad_origin, "this request comes from a page of another site", Req)}
    end.

refuse(Code, Message, Req) ->
    cell_web_req:reply_error(403, Code, unicode:characters_to_binary(Message), #{}, Req).

printable(Host) ->
    case byte_size(Host) =< 100 andalso unicode:characters_to_list(Host) of
        L when is_list(L) ->
            case io_lib:printable_unicode_list(L) of
                true -> Host;
                false -> <<"given">>
            end;
        _ -> <<"given">>
    end.

%% @doc The names of a panel bound to `Ip', with the configured ones (`names').
-spec names(inet:ip_address()) -> [binary()].
names(Ip) ->
    Bound = case Ip of
                {0, 0, 0, 0} -> all_addresses();
                {0, 0, 0, 0, 0, 0, 0, 0} -> all_addresses();
                _ -> [inet:ntoa(Ip)]
            end,
    {ok, Short} = inet:gethostname(),
    Full = net_adm:localhost(),
    Configured = case application:get_env(cell_web, names, []) of
                     Text when is_list(Text), Text =/= [], is_integer(hd(Text)) ->
                         string:lexemes(Text, ", ");
                     List when is_list(List) -> List
                 end,
    lists:usort([normal(unicode:characters_to_binary(N))
                 || N <- ["localhost", "127.0.0.1", "::1", Short, Full | Bound ++ Configured]]).

all_addresses() ->
    case inet:getifaddrs() of
        {ok, Ifs} -> [inet:ntoa(A) || {_, Opts} <- Ifs, {addr, A} <- Opts];
        {error, _} -> []
    end.

%% @doc A name as compared: lower case, without the brackets of an IPv6 address.
-spec normal(binary()) -> binary().
normal(Name) ->
    Lower = string:lowercase(Name),
    case Lower of
        <<"[", Rest/binary>> -> binary:part(Rest, 0, max(0, byte_size(Rest) - 1));
        _ -> Lower
    end.

%% @doc Whether a Host header's name (without the port) is one of `Names'. A request
%% with no Host at all (HTTP/1.0 by hand) names nothing and passes.
-spec host_allowed(binary(), [binary()]) -> boolean().
host_allowed(<<>>, _Names) -> true;
host_allowed(Host, Names) -> lists:member(normal(Host), Names).

%% @doc Whether an Origin header is `http://' or `https://' and one of `Names' (any
%% port).
-spec origin_allowed(binary(), [binary()]) -> boolean().
origin_allowed(Origin, Names) ->
    case uri_string:parse(Origin) of
        #{scheme := Scheme, host := Host} when Scheme =:= <<"http">>; Scheme =:= <<"https">> ->
            Host =/= <<>> andalso lists:member(normal(Host), Names);
        _ ->
            false
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

names() -> [<<"127.0.0.1">>, <<"::1">>, <<"cellpc">>, <<"localhost">>].

host_allowed_test_() ->
    [?_assert(host_allowed(<<"localhost">>, names())),
     ?_assert(host_allowed(<<"LocalHost">>, names())),
     ?_assert(host_allowed(<<"[::1]">>, names())),
     ?_assert(host_allowed(<<"cellpc">>, names())),
     ?_assert(host_allowed(<<>>, names())),
     ?_assertNot(host_allowed(<<"attacker.example">>, names())),
     ?_assertNot(host_allowed(<<"127.0.0.2">>, names())),
     ?_assertNot(host_allowed(<<"cellpc.attacker.example">>, names()))].

origin_allowed_test_() ->
    [?_assert(origin_allowed(<<"http://127.0.0.1:8080">>, names())),
     ?_assert(origin_allowed(<<"https://cellpc">>, names())),
     ?_assert(origin_allowed(<<"http://[::1]:8080">>, names())),
     ?_assertNot(origin_allowed(<<"http://attacker.example:8080">>, names())),
     ?_assertNot(origin_allowed(<<"null">>, names())),
     ?_assertNot(origin_allowed(<<"file://localhost">>, names())),
     ?_assertNot(origin_allowed(<<"http://">>, names())),
     ?_assertNot(origin_allowed(<<"%%%">>, names()))].

names_test() ->
    ok = application:set_env(cell_web, names, "Cell3.Plant.Local, other"),
    try
        Names = names({127, 0, 0, 1}),
        [?assert(lists:member(N, Names))
         || N <- [<<"cell3.plant.local">>, <<"other">>, <<"localhost">>, <<"127.0.0.1">>]]
    after
        application:unset_env(cell_web, names)
    end.
-endif.
