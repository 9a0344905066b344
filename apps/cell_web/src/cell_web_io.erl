%% @doc The IO points and PLC connections, live for the panel's pages.
%%
%% Subscribed to every point and connection of the HAL (when a page connects it looks
%% for points and connections added since: {@link watch/0}), this process gathers the
%% changes and sends them to the pages through {@link cell_web_feed} at most every
%% `?FLUSH_MS' ms, one message for all of them: `{"type": "io", "points": [{"group",
%% "point", "value", "quality"}]}', the latest value of each point changed (a point
%% changing faster than that is seen at that rate, never behind it). A connection's
%% change is sent at once: `{"type": "io_conn", "connection": Conn}'. It counts the
%% reconnections of each connection it has seen come up again.
%%
%% The subscriptions live in the HAL's tables, so a restart of a HAL process keeps
%% them; a restart of this process subscribes again at the next page.
-module(cell_web_io).
-behaviour(gen_server).

-export([start_link/0, watch/0, connections/0, point_json/2, quality/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(FLUSH_MS, 50).

-record(state, {points = #{} :: #{{atom(), atom()} => true},
                conns = #{} :: #{atom() => #{status := up | down, reconnects := non_neg_integer(),
                                            seen_up := boolean()}},
                pending = #{} :: #{{atom(), atom()} => true},
                timer :: reference() | undefined}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Subscribes to the points and connections not yet watched.
-spec watch() -> ok.
watch() ->
    gen_server:cast(?MODULE, watch).

%% @doc The connections as the IO page shows them: status, endpoint, why down, since
%% when, faulty points, and the reconnections seen since the panel started.
-spec connections() -> [map()].
connections() ->
    Counts = gen_server:call(?MODULE, reconnects),
    [begin
         Info = case cell_hal:info(C) of
                    {ok, I} -> (maps:with([status, endpoint, since, reason, groups], I))
                                   #{faults => length(maps:get(faults, I))};
                    {error, _} -> #{status => down}
                end,
         Info#{id => C, reconnects => maps:get(C, Counts, 0)}
     end || C <- cell_hal:connections()].

%% @doc A point's value and quality as the pages get them.
-spec point_json(atom(), atom()) -> map().
point_json(G, P) ->
    {Value, Quality} = quality(cell_hal:read(G, P)),
    #{<<"group">> => atom_to_binary(G, utf8), <<"point">> => atom_to_binary(P, utf8),
      <<"value">> => cell_web_json:term(Value), <<"quality">> => Quality}.

%% @doc A read as a value and its quality: `good', `disconnected', `not_yet_read',
%% `unavailable' (the driver cannot serve it), `unknown'.
-spec quality({ok, term()} | {error, term()}) -> {term(), binary()}.
quality({ok, V}) -> {V, <<"good">>};
quality({error, disconnected}) -> {null, <<"disconnected">>};
quality({error, not_yet_read}) -> {null, <<"not_yet_read">>};
quality({error, {unavailable, _}}) -> {null, <<"unavailable">>};
quality({error, _}) -> {null, <<"unknown">>}.

%%--------------------------------------------------------------------

-spec init([]) -> {ok, #state{}}.
init([]) ->
    process_flag(message_queue_data, off_heap),
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call(reconnects, _From, #state{conns = Cs} = State) ->
    {reply, maps:map(fun(_, #{reconnects := N}) -> N end, Cs), State}.

-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast(watch, State) ->
    {noreply, watch_new(State)}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_hal, Key, _Value}, State) ->
    {noreply, changed(Key, State)};
handle_info({cell_hal_fault, Key, _Why}, State) ->
    {noreply, changed(Key, State)};
handle_info({cell_hal_conn, C, Status}, #state{conns = Cs} = State) ->
    Old = maps:get(C, Cs, #{status => down, reconnects => 0, seen_up => false}),
    New = case {maps:get(status, Old), Status, maps:get(seen_up, Old)} of
              {down, up, true} -> Old#{status := up, reconnects := maps:get(reconnects, Old) + 1};
              {_, up, _} -> Old#{status := up, seen_up := true};
              {_, down, _} -> Old#{status := down}
          end,
    ok = cell_web_feed:publish([#{<<"type">> => <<"io_conn">>,
                                  <<"connection">> => cell_web_json:term(C),
                                  <<"status">> => cell_web_json:term(Status),
                                  <<"reconnects">> => maps:get(reconnects, New)}]),
    %% Its points' quality changed with it.
    Pending = lists:foldl(fun(K, Acc) -> Acc#{K => true} end, State#state.pending,
                          [K || {G, _} = K <- maps:keys(State#state.points),
                                cell_hal:connection_of(G) =:= {ok, C}]),
    {noreply, arm(State#state{conns = Cs#{C => New}, pending = Pending})};
handle_info({timeout, TRef, flush}, #state{timer = TRef, pending = Pending} = State) ->
    Points = [point_json(G, P) || {G, P} <- maps:keys(Pending)],
    ok = cell_web_feed:publish([#{<<"type">> => <<"io">>, <<"points">> => Points}]),
    {noreply, State#state{timer = undefined, pending = #{}}}.

changed(Key, #state{pending = Pending} = State) ->
    arm(State#state{pending = Pending#{Key => true}}).

arm(#state{timer = undefined, pending = P} = State) when map_size(P) > 0 ->
    State#state{timer = erlang:start_timer(?FLUSH_MS, self(), flush)};
arm(State) ->
    State.

watch_new(#state{points = Points, conns = Conns} = State) ->
    New = [{G, P} || G <- cell_hal:groups(), {ok, Ps} <- [cell_hal:points(G)],
                     #{name := P} <- Ps, not is_map_key({G, P}, Points)],
    Subscribed = [K || {G, P} = K <- New, cell_hal:subscribe(G, P) =:= ok],
    NewConns = [C || C <- cell_hal:connections(), not is_map_key(C, Conns)],
    Watched = [{C, S} || C <- NewConns, {ok, S} <- [cell_hal:subscribe_connection(C)]],
    State#state{points = maps:merge(Points, maps:from_keys(Subscribed, true)),
                conns = maps:merge(Conns, maps:from_list(
                                            [{C, #{status => S, reconnects => 0,
                                                   seen_up => S =:= up}} || {C, S} <- Watched]))}.
