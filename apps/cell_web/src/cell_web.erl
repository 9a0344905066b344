%% @doc The operator web panel of cellrt: a REST API (JSON), live updates over a
%% websocket, and the operator page, served by cowboy. See the routes in
%% {@link cell_web_routes} and the contract in docs/architecture.md.
-module(cell_web).

-export([port/0, url/0]).

%% @doc The port the panel listens on.
-spec port() -> inet:port_number().
port() ->
    case cell_web_listener:port() of
        {ok, Port} -> Port;
        {error, not_listening} -> erlang:error(not_listening)
    end.

%% @doc The panel's address, as a browser on this PC opens it.
-spec url() -> binary().
url() ->
    {ok, Ip} = cell_config:ip(cell_web, bind, {127, 0, 0, 1}),
    Host = case Ip of
               {0, 0, 0, 0} -> "127.0.0.1";
               _ -> inet:ntoa(Ip)
           end,
    Scheme = case cell_web_listener:https() of
                 true -> "https";
                 false -> "http"
             end,
    iolist_to_binary(io_lib:format("~s://~s:~p/", [Scheme, Host, port()])).
