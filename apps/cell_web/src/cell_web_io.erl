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
%% The axes and the interpolation channels are watched too ({@link
%% cell_hal_hw:watch/1}): when one may have changed (a move began or ended, it
%% published its position while moving, it faulted, its override changed) it is read
%% again at the next flush and sent as `{"type": "hardware", "hardware": [Object]}',
%% each as `GET /api/io' has it ({@link hardware_json/1}). An axis that may be moving
%% (cell_hal_axis:moving/1) or a channel following or halting a path is read again at
%% every flush until it rests, so the pages follow a move whether or not the axis
%% publishes its position; one at rest costs nothing.
%%
%% The subscriptions live in the HAL's tables, so a restart of a HAL process keeps
%% them; a restart of this process subscribes again at the next page. A hardware
%% object that restarts is watched again at the next page.
-module(cell_web_io).
-behaviour(gen_server).

-export([start_link/0, watch/0, connections/0, point_json/2, quality/1, hardware_json/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(FLUSH_MS, 50).

-record(state, {points = #{} :: #{{atom(), atom()} => true},
                conns = #{} :: #{atom() => #{status := up | down, reconnects := non_neg_integer(),
                                            seen_up := boolean()}},
                pending = #{} :: #{{atom(), atom()} => true},
                %% The axes and channels watched, by the monitor of their process.
                hw = #{} :: #{atom() => reference()},
                hw_pending = #{} :: #{atom() => true},
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

%% @doc A hardware object as the IO page shows it: id, kind, status (`up', `down',
%% `absent') and, for an axis or a channel, its motion as its NC has it now.
-spec hardware_json({atom(), cell_hal_hw:kind(), module()}) -> map().
hardware_json(Object) ->
    element(1, hardware(Object)).

%% The object as the page shows it, and whether it may be moving.
hardware({Id, Kind, _Mod}) ->
    Base = #{<<"id">> => atom_to_binary(Id, utf8), <<"kind">> => atom_to_binary(Kind, utf8),
             <<"status">> => case cell_hal_hw:status(Id) of
                                 S when is_atom(S) -> atom_to_binary(S, utf8);
                                 {error, _} -> <<"absent">>
                             end},
    {Motion, Moving} = motion(Kind, Id),
    {maps:merge(Base, Motion), Moving}.

%% An axis's or a channel's state as its NC has it now (PLCopen's state, position,
%% velocity, error code; a channel's progress along its path).
motion(axis, Id) ->
    case cell_hal_axis:status(Id) of
        {ok, St} -> {#{<<"axis">> => cell_web_json:term(maps:with([state, position, velocity,
                                                                   error, homed, powered,
                                                                   override], St))},
                     cell_hal_axis:moving(St)};
        {error, _} -> {#{}, false}
    end;
motion(channel, Id) ->
    case cell_hal_channel:status(Id) of
        {ok, #{state := State} = St} ->
            {#{<<"channel">> => cell_web_json:term(maps:with([state, along, length,
                                                              segment, segments], St))},
             State =/= idle};
        {error, _} ->
            {#{}, false}
    end;
motion(_Kind, _Id) ->
    {#{}, false}.

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
handle_info({cell_hal_hw_changed, Id}, #state{hw_pending = Pending} = State) ->
    {noreply, arm(State#state{hw_pending = Pending#{Id => true}})};
handle_info({'DOWN', MRef, process, _, _}, #state{hw = Hw, hw_pending = Pending} = State) ->
    %% The object went (or restarts): the pages see it so; the next page watches the
    %% new one.
    case [Id || {Id, R} <- maps:to_list(Hw), R =:= MRef] of
        [Id] -> {noreply, arm(State#state{hw = maps:remove(Id, Hw),
                                          hw_pending = Pending#{Id => true}})};
        [] -> {noreply, State}
    end;
handle_info({timeout, TRef, flush}, #state{timer = TRef, pending = Pending,
                                           hw_pending = HwPending} = State) ->
    Points = [point_json(G, P) || {G, P} <- maps:keys(Pending)],
    Objects = maps:from_list([{Id, O} || {Id, _, _} = O <- cell_hal_hw:list()]),
    Read = [{Id, case Objects of
                     #{Id := O} -> hardware(O);
                     #{} -> {#{<<"id">> => atom_to_binary(Id, utf8),
                               <<"status">> => <<"absent">>}, false}
                 end} || Id <- lists:sort(maps:keys(HwPending))],
    Hardware = [Json || {_, {Json, _}} <- Read],
    ok = cell_web_feed:publish([#{<<"type">> => <<"io">>, <<"points">> => Points}
                                || Points =/= []]
                               ++ [#{<<"type">> => <<"hardware">>, <<"hardware">> => Hardware}
                                   || Hardware =/= []]),
    %% What moves is read again at the next flush.
    Moving = maps:from_list([{Id, true} || {Id, {_, true}} <- Read]),
    {noreply, arm(State#state{timer = undefined, pending = #{}, hw_pending = Moving})}.

changed(Key, #state{pending = Pending} = State) ->
    arm(State#state{pending = Pending#{Key => true}}).

arm(#state{timer = undefined, pending = P, hw_pending = H} = State)
  when map_size(P) > 0; map_size(H) > 0 ->
    State#state{timer = erlang:start_timer(?FLUSH_MS, self(), flush)};
arm(State) ->
    State.

watch_new(#state{points = Points, conns = Conns} = State) ->
    New = [{G, P} || G <- cell_hal:groups(), {ok, Ps} <- [cell_hal:points(G)],
                     #{name := P} <- Ps, not is_map_key({G, P}, Points)],
    Subscribed = [K || {G, P} = K <- New, cell_hal:subscribe(G, P) =:= ok],
    NewConns = [C || C <- cell_hal:connections(), not is_map_key(C, Conns)],
    Watched = [{C, S} || C <- NewConns, {ok, S} <- [cell_hal:subscribe_connection(C)]],
    Hw = lists:foldl(fun({Id, Kind, _}, Acc) when (Kind =:= axis orelse Kind =:= channel),
                                                   not is_map_key(Id, Acc) ->
                             case cell_hal_hw:watch(Id) of
                                 {ok, Pid} -> Acc#{Id => erlang:monitor(process, Pid)};
                                 {error, _} -> Acc
                             end;
                        (_, Acc) ->
                             Acc
                     end, State#state.hw, cell_hal_hw:list()),
    State#state{hw = Hw,
                points = maps:merge(Points, maps:from_keys(Subscribed, true)),
                conns = maps:merge(Conns, maps:from_list(
                                            [{C, #{status => S, reconnects => 0,
                                                   seen_up => S =:= up}} || {C, S} <- Watched]))}.
