%% @doc Owns the panel's HTTP listener (cowboy over ranch), or its HTTPS listener when
%% the `cell_web' setting `https' is true: the certificate and key are PEM files in the
%% cell root folder (`https_certfile', `https_keyfile'; `panel.crt' and `panel.key'),
%% read when the listener starts, and the session cookie is then `Secure'.
%%
%% The panel must never keep the cell from running: when the port cannot be opened
%% (taken by another program, an address the PC does not have), this process says so
%% in the task log and tries again after 1, 2, 4 ... 30 s, while the cell runs on.
-module(cell_web_listener).
-behaviour(gen_server).

-export([start_link/0, port/0, listening/0, https/0]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-define(REF, cell_web_http).
-define(MAX_BACKOFF_MS, 30000).
%% How long a question waits for the first try to listen (the routes are read then).
-define(FIRST_TRY_MS, 60000).

-record(state, {ip :: inet:ip_address(), port :: inet:port_number(),
                backoff = 1000 :: pos_integer(), listening = false :: boolean()}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The port the panel listens on (the one the OS picked when configured as 0);
%% asked after the first try to listen is over, which may take seconds on a busy
%% machine.
-spec port() -> {ok, inet:port_number()} | {error, not_listening}.
port() ->
    gen_server:call(?MODULE, port, ?FIRST_TRY_MS).

%% @doc Whether the panel is configured to serve HTTPS.
-spec https() -> boolean().
https() ->
    lists:member(application:get_env(cell_web, https, false), [true, "true", <<"true">>]).

%% @doc Whether the listener is up.
-spec listening() -> boolean().
listening() ->
    gen_server:call(?MODULE, listening, ?FIRST_TRY_MS).

-spec init([]) -> {ok, #state{}, {continue, listen}} | {stop, term()}.
init([]) ->
    process_flag(trap_exit, true),
    case {cell_config:port(cell_web, port, 8080), cell_config:ip(cell_web, bind, {127, 0, 0, 1})} of
        {{ok, Port}, {ok, Ip}} -> {ok, #state{ip = Ip, port = Port}, {continue, listen}};
        {{error, _} = E, _} -> {stop, E};
        {_, {error, _} = E} -> {stop, E}
    end.

-spec handle_continue(listen, #state{}) -> {noreply, #state{}}.
handle_continue(listen, State) ->
    {noreply, listen(State)}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call(listening, _From, State) ->
    {reply, State#state.listening, State};
handle_call(port, _From, #state{listening = true} = State) ->
    {reply, {ok, ranch:get_port(?REF)}, State};
handle_call(port, _From, State) ->
    {reply, {error, not_listening}, State}.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({timeout, _, retry}, State) ->
    {noreply, listen(State)}.

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, #state{listening = true}) ->
    _ = cowboy:stop_listener(?REF),
    ok;
terminate(_Reason, _State) ->
    ok.

listen(#state{ip = Ip, port = Port, backoff = Backoff} = State) ->
    Transport = #{socket_opts => [{ip, Ip}, {port, Port},
                                  %% A browser that stops reading is dropped after 10 s
                                  %% instead of holding its connection's process.
                                  {send_timeout, 10000}, {send_timeout_close, true}],
                  num_acceptors => 4, max_connections => 1024},
    Protocol = #{env => #{dispatch => cell_web_routes:dispatch(),
                          hosts => cell_web_hosts:names(Ip)},
                 middlewares => [cell_web_headers, cell_web_hosts, cowboy_router,
                                 cowboy_handler],
                 idle_timeout => 120000, request_timeout => 30000},
    Started = case https() of
                  false -> {"http", cowboy:start_clear(?REF, Transport, Protocol)};
                  true -> {"https", start_tls(Transport, Protocol)}
              end,
    case Started of
        {Scheme, {ok, _}} ->
            cell_log:notice(web, "operator panel on ~ts://~ts:~p",
                            [Scheme, address(Ip), ranch:get_port(?REF)]),
            State#state{listening = true, backoff = 1000};
        {_, {error, {tls_file, Path, Why}}} ->
            cell_log:error(web, "the operator panel cannot serve HTTPS: ~ts ~ts; trying again "
                           "in ~p s", [Path, Why, Backoff div 1000]),
            retry(State);
        {_, {error, Reason}} ->
            cell_log:error(web, "the operator panel cannot listen on ~ts:~p (~ts); trying again "
                           "in ~p s", [address(Ip), Port, reason(Reason), Backoff div 1000]),
            retry(State)
    end.

retry(#state{backoff = Backoff} = State) ->
    _ = erlang:start_timer(Backoff, self(), retry),
    State#state{backoff = min(2 * Backoff, ?MAX_BACKOFF_MS)}.

%% The certificate and key are checked here, so that a missing or unreadable file is
%% said at once, not at the first browser's handshake.
start_tls(#{socket_opts := Opts} = Transport, Protocol) ->
    Root = cell_config:root(),
    Cert = filename:join(Root, application:get_env(cell_web, https_certfile, "panel.crt")),
    Key = filename:join(Root, application:get_env(cell_web, https_keyfile, "panel.key")),
    case {pem(Cert, 'Certificate'), pem(Key, key)} of
        {ok, ok} ->
            cowboy:start_tls(?REF, Transport#{socket_opts := [{certfile, Cert}, {keyfile, Key},
                                                              {versions, ['tlsv1.3', 'tlsv1.2']}
                                                              | Opts]},
                             Protocol);
        {{error, Why}, _} -> {error, {tls_file, Cert, Why}};
        {ok, {error, Why}} -> {error, {tls_file, Key, Why}}
    end.

pem(Path, Kind) ->
    case file:read_file(Path) of
        {ok, Bin} ->
            Entries = try public_key:pem_decode(Bin) catch _:_ -> [] end,
            Wanted = [E || {Type, _, _} = E <- Entries,
                           Kind =:= 'Certificate' andalso Type =:= 'Certificate'
                               orelse Kind =:= key andalso Type =/= 'Certificate'],
            case Wanted of
                [_ | _] -> ok;
                [] when Kind =:= key -> {error, "holds no private key in PEM"};
                [] -> {error, "holds no certificate in PEM"}
            end;
        {error, R} ->
            {error, ["cannot be read: ", file:format_error(R)]}
    end.

address(Ip) -> inet:ntoa(Ip).

%% ranch wraps the socket's error deep in supervisor reports; dig out the words.
reason(Reason) ->
    case lists:filter(fun(R) -> lists:member(R, [eaddrinuse, eaddrnotavail, eacces]) end,
                      flatten(Reason)) of
        [Posix | _] -> inet:format_error(Posix);
        [] -> io_lib:format("~0tP", [Reason, 8])
    end.

flatten(T) when is_tuple(T) -> lists:append([flatten(E) || E <- tuple_to_list(T)]);
flatten([H | T]) -> flatten(H) ++ flatten(T);
flatten(A) when is_atom(A) -> [A];
flatten(_) -> [].
