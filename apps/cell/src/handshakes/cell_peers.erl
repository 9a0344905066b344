%% @doc Keeps this cell connected to the nodes of the cells it hands products to or
%% takes them from (a line of cells, one node each: the ends `{Task, Node}' of the cell
%% spec's links). It connects at start and after every loss, with a backoff, never
%% blocking anyone; when a node comes (back) it tells the local tasks whose links reach
%% it, and they attach to their links again.
%%
%% A neighbour that goes (its node down, or silent: no distribution tick for longer
%% than the line's tick time) is a warning on the panel until it is back. A silent
%% neighbour is noticed by the distribution's ticks: a cell with remote links runs
%% them at a tick time of 5 s (unless the release sets `net_ticktime' itself), so it
%% is told within 0.75 to 1.25 times that, where Erlang's default of 60 s would
%% leave it waiting a minute or more.
-module(cell_peers).
-behaviour(gen_server).

-export([start_link/1, child_spec/1, nodes_of/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(BACKOFF_MIN, 500).
-define(BACKOFF_MAX, 30000).
%% Seconds: a silent neighbour is noticed within 3.75 to 6.25 s. Ticks go every
%% ?LINE_TICKTIME/4 s; four missed in a row on a LAN is a broken link, not a busy one.
-define(LINE_TICKTIME, 5).

-record(state, {peers = #{} :: #{node() => #{links := [{atom(), atom()}],
                                            backoff := pos_integer(),
                                            up := boolean()}}}).

-spec start_link(cell_spec:spec()) -> {ok, pid()} | ignore | {error, term()}.
start_link(Spec) ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, Spec, []).

-spec child_spec(cell_spec:spec()) -> supervisor:child_spec().
child_spec(Spec) ->
    #{id => ?MODULE, start => {?MODULE, start_link, [Spec]}}.

%% @doc The remote nodes of a spec's links, each with the local task and link that
%% reach it.
-spec nodes_of(cell_spec:spec()) -> #{node() => [{atom(), atom()}]}.
nodes_of(#{links := Links}) ->
    lists:foldl(fun(#{id := L, from := From, to := To}, Acc) ->
                        case {From, To} of
                            {{_, N}, Local} when is_atom(Local), N =/= node() ->
                                add(N, {Local, L}, Acc);
                            {Local, {_, N}} when is_atom(Local), N =/= node() ->
                                add(N, {Local, L}, Acc);
                            _ ->
                                Acc
                        end
                end, #{}, Links).

add(Node, Entry, Acc) ->
    maps:update_with(Node, fun(L) -> [Entry | L] end, [Entry], Acc).

-spec init(cell_spec:spec()) -> {ok, #state{}}.
init(Spec) ->
    Peers = maps:map(fun(_, Links) -> #{links => Links, backoff => ?BACKOFF_MIN, up => false} end,
                     nodes_of(Spec)),
    case maps:size(Peers) of
        0 -> ok;
        _ -> ok = net_kernel:monitor_nodes(true), line_ticks()
    end,
    case cell_dist:unreachable_peers(cell_dist:listen_interface(), node(), maps:keys(Peers)) of
        [] ->
            ok;
        Away ->
            cell_log:error(cell, "the cells on ~ts are on other PCs, but this node's "
                           "distribution listens on this PC only: set CELLRT_DIST_BIND to "
                           "the address of the line's network on every PC of the line, and "
                           "run the line's distribution over TLS (README, \"Security\")",
                           [lists:join(", ", [atom_to_list(N) || N <- Away])])
    end,
    _ = [self() ! {connect, N} || N <- maps:keys(Peers)],
    {ok, #state{peers = Peers}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> no_return().
handle_call(Request, _From, _State) ->
    error({unexpected_call, Request}).

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({connect, Node}, State) ->
    %% Connecting may take seconds when the node is away: a process of its own does it.
    Self = self(),
    _ = spawn_link(fun() -> Self ! {connected, Node, net_kernel:connect_node(Node)} end),
    {noreply, State};
handle_info({connected, Node, true}, State) ->
    {noreply, node_up(Node, State)};
handle_info({connected, Node, _False}, State) ->
    {noreply, retry(Node, State)};
handle_info({nodeup, Node}, State) ->
    {noreply, node_up(Node, State)};
handle_info({nodedown, Node}, #state{peers = Peers} = State) ->
    case maps:find(Node, Peers) of
        {ok, #{up := true} = P} ->
            cell_log:warning(cell, "the cell on node ~ts is out of reach; reconnecting", [Node]),
            ok = cell_alarms:warning(cell, warning_id(Node), "Neighbour cell out of reach",
                                     io_lib:format("The cell on node ~ts does not answer (its "
                                                   "PC, its node or the network between is "
                                                   "down). Products are not handed to it or "
                                                   "taken from it until it is back; this "
                                                   "cell keeps trying.", [Node])),
            {noreply, retry(Node, State#state{peers = Peers#{Node => P#{up => false}}})};
        _ ->
            {noreply, State}
    end;
handle_info({'EXIT', _Pid, normal}, State) ->
    {noreply, State}.

node_up(Node, #state{peers = Peers} = State) ->
    case maps:find(Node, Peers) of
        {ok, #{up := false, links := Links} = P} ->
            cell_log:info(cell, "connected to the cell on node ~ts", [Node]),
            ok = cell_alarms:reset_warning(cell, warning_id(Node)),
            %% The tasks attach to their links again (a link on this node greets
            %% its remote partner when that partner's node comes back: its task does
            %% the same from there).
            _ = [cell_handshake:hello(Task, Link) || {Task, Link} <- Links],
            State#state{peers = Peers#{Node => P#{up => true, backoff => ?BACKOFF_MIN}}};
        _ ->
            State
    end.

%% The distribution's ticks at the line's pace, unless the release chose a tick time of
%% its own (anything but OTP's default, 60 s: `-kernel net_ticktime' in vm.args).
line_ticks() ->
    case net_kernel:get_net_ticktime() of
        60 ->
            %% At once: no transition period, the line's nodes all tick alike (a remote
            %% console asks the node for its tick time when it connects).
            _ = net_kernel:set_net_ticktime(?LINE_TICKTIME, 0),
            cell_log:info(cell, "distribution ticks every ~w ms: a silent neighbour is "
                          "noticed within ~w s", [?LINE_TICKTIME * 250,
                                                   ?LINE_TICKTIME * 5 div 4]);
        _Chosen ->
            %% Chosen by the release, changing, or not distributed (`ignored': no
            %% peer will be reached, and cell_dist says why).
            ok
    end.

warning_id(Node) ->
    <<"peer:", (atom_to_binary(Node, utf8))/binary>>.

retry(Node, #state{peers = Peers} = State) ->
    case maps:find(Node, Peers) of
        {ok, #{backoff := B} = P} ->
            _ = erlang:send_after(B, self(), {connect, Node}),
            State#state{peers = Peers#{Node => P#{backoff => min(2 * B, ?BACKOFF_MAX)}}};
        error ->
            State
    end.
