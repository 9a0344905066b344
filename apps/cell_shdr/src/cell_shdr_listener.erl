%% @doc Owns the SHDR listener (ranch): listens on the configured address and port,
%% and, when it cannot (the port is taken), says so in the log and tries again with a
%% backoff (1 s doubling to 30 s) instead of crashing, so a port conflict never takes
%% the adapter, let alone the cell, down. A change of port or address in the
%% settings moves the listener (connected clients reconnect). How many clients may be
%% connected is the cache's to decide (see {@link cell_shdr_protocol}), not ranch's.
%%
%% The port is `CELLRT_SHDR_PORT' (the `cell_shdr' environment key `port') when set,
%% else the `port' field of the settings; the address likewise `CELLRT_SHDR_BIND'
%% (`bind'), else the `bind' field.
-module(cell_shdr_listener).
-behaviour(gen_server).

-export([start_link/0, restart/0, port/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-define(REF, cell_shdr).
-define(SOURCE, shdr).
-define(BACKOFF_MIN, 1000).
-define(BACKOFF_MAX, 30000).

-record(state, {listening = false :: boolean(),
                backoff = ?BACKOFF_MIN :: pos_integer(),
                retry :: reference() | undefined}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Listens again with the address and port now configured.
-spec restart() -> ok.
restart() ->
    gen_server:cast(?MODULE, restart).

%% @doc The port listened on, or `undefined' while not listening.
-spec port() -> inet:port_number() | undefined.
port() ->
    try ranch:get_port(?REF)
    catch error:badarg -> undefined
    end.

%% The first try is made here, not later: once the application has started, port/0
%% answers (a port taken is tried again on a timer, without holding up the start).
-spec init([]) -> {ok, #state{}}.
init([]) ->
    %% terminate/2 must run to stop the listener, which lives under ranch's supervisor.
    process_flag(trap_exit, true),
    {ok, listen(#state{})}.

-spec handle_call(term(), gen_server:from(), #state{}) -> no_return().
handle_call(Msg, _From, _State) ->
    error({unexpected_call, Msg}).

-spec handle_cast(restart, #state{}) -> {noreply, #state{}}.
handle_cast(restart, State) ->
    {noreply, listen(stop(State))}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}} | {stop, term(), #state{}}.
handle_info({timeout, TRef, listen}, #state{retry = TRef} = State) ->
    {noreply, listen(State#state{retry = undefined})};
handle_info({timeout, _, listen}, State) ->
    {noreply, State};
handle_info({'EXIT', _, Reason}, State) ->
    {stop, Reason, State}.

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, State) ->
    _ = stop(State),
    ok.

listen(#state{backoff = B} = State) ->
    case address() of
        {ok, Ip, Port} ->
            %% No limit in ranch: its limit holds connections beyond it in the kernel's
            %% queue, once per acceptor's connection supervisor. The cache admits
            %% `max_clients' exactly, and a client beyond is closed at once.
            Opts = #{socket_opts => [{ip, Ip}, {port, Port}],
                     max_connections => infinity,
                     num_acceptors => 2},
            case ranch:start_listener(?REF, ranch_tcp, Opts, cell_shdr_protocol, #{}) of
                {ok, _} ->
                    cell_log:notice(?SOURCE, "MTConnect SHDR adapter listening on ~ts:~p",
                                    [inet:ntoa(Ip), ranch:get_port(?REF)]),
                    State#state{listening = true, backoff = ?BACKOFF_MIN};
                {error, Reason} ->
                    cell_log:error(?SOURCE, "the MTConnect SHDR adapter cannot listen on "
                                   "~ts:~p (~ts); trying again in ~p s",
                                   [inet:ntoa(Ip), Port, why(Reason), B div 1000]),
                    later(State)
            end;
        {error, {bad_config, _, Key, Value}} ->
            cell_log:error(?SOURCE, "the MTConnect SHDR adapter's ~ts setting \"~ts\" is not "
                           "valid; trying again in ~p s", [Key, io_lib:format("~tp", [Value]),
                                                           B div 1000]),
            later(State)
    end.

later(#state{backoff = B} = State) ->
    State#state{listening = false, retry = erlang:start_timer(B, self(), listen),
                backoff = min(2 * B, ?BACKOFF_MAX)}.

stop(#state{listening = true} = State) ->
    _ = ranch:stop_listener(?REF),
    State#state{listening = false};
stop(#state{retry = TRef} = State) when TRef =/= undefined ->
    _ = erlang:cancel_timer(TRef),
    State#state{retry = undefined};
stop(State) ->
    State.

address() ->
    Settings = cell_shdr_cache:settings(),
    {ok, Default} = inet:parse_address(binary_to_list(maps:get(bind, Settings))),
    case {cell_config:port(cell_shdr, port, maps:get(port, Settings)),
          cell_config:ip(cell_shdr, bind, Default)} of
        {{ok, Port}, {ok, Ip}} -> {ok, Ip, Port};
        {{error, _} = E, _} -> E;
        {_, {error, _} = E} -> E
    end.

why({shutdown, {failed_to_start_child, _, {listen_error, _, Posix}}}) -> inet:format_error(Posix);
why({listen_error, _, Posix}) -> inet:format_error(Posix);
why(Posix) when is_atom(Posix) -> inet:format_error(Posix);
why(Other) -> io_lib:format("~0tp", [Other]).
