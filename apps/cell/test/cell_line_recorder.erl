%% What a cell node of a line test saw, kept on that node: the phases and products out of
%% its `cell_line_task's (their `notify'), the link phases and the alarms raised there.
%% A test on another network than the node's own waits here, over the node's control
%% channel, for what it expects, with a deadline: nothing crosses the line's network,
%% which the test cuts.
%%
%% It owns the node's `line_feed' and `line_out' tables (see cell_line_task), feeds the
%% first segment, and answers the cell's errors as an operator would: Ignore when it is
%% offered (the product is here), else the first solution, or, with `answers =>
%% manual', not at all (the test answers).
-module(cell_line_recorder).
-behaviour(gen_server).

-export([start/1, subscribe/0, feed/3, take_feed/1, mark/0, await/3, events/0, timeline/0, now_ms/0, outs/0, answered/0, stop/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-type event() :: {phase, atom(), atom()} | {out, atom(), binary()}
               | {link_phase, atom(), atom(), term()} | {alarm, map()}
               | {answered, binary(), atom()} | {crashed, term()}
               | {in_transit, atom(), binary()}.
-type spec() :: {phase, atom(), atom()} | {outs, non_neg_integer()} | {link_phase, atom()}
              | alarm | {alarm, binary()} | {in_transit, atom()}.

-record(state, {events = [] :: [{pos_integer(), event()}],
                %% When each event came (monotonic ms), by its number.
                times = #{} :: #{pos_integer() => integer()},
                n = 0 :: non_neg_integer(),
                answers :: ignore | manual,
                waiters = [] :: [{gen_server:from(), spec(), non_neg_integer(), reference()}]}).

%% @doc Starts the recorder of this node, registered as `cell_line_recorder', outside
%% any caller's link (a peer call's process ends with the call).
-spec start(#{answers => ignore | manual}) -> {ok, pid()}.
start(Opts) ->
    gen_server:start({local, ?MODULE}, ?MODULE, Opts, []).

%% @doc Subscribes the recorder to the cell's link phases, alarms, task crashes and
%% products saved marked in transit (once the cell runs, before its tasks start).
-spec subscribe() -> ok.
subscribe() ->
    cell_events:subscribe(whereis(?MODULE), [link_phase, alarm_raised, task_crashed,
                                             product_saved]).

%% @doc Puts products in the feed and wakes the first segment `Task' (waiting on `Ref').
-spec feed([binary()], atom(), reference()) -> ok.
feed(Serials, Task, Ref) ->
    gen_server:call(?MODULE, {feed, Serials, Task, Ref}).

%% @doc Before the node is killed: stops the first segment `Task' (suspended, so it
%% takes nothing more) and gives the serials still in the feed, which a kill of the
%% node would lose with its memory, to be fed again to its successor. The products on
%% the infeed are the machine's, not the cell's: they outlive the node.
-spec take_feed(atom()) -> [binary()].
take_feed(Task) ->
    %% The task may be in a call across a cut: its deadline (8 s) comes first.
    gen_server:call(?MODULE, {take_feed, Task}, 30000).

%% @doc How many events so far: `await/3' after a mark looks at later events only.
-spec mark() -> non_neg_integer().
mark() ->
    gen_server:call(?MODULE, mark).

%% @doc Waits for an event matching `Spec' after the mark `Since'; `{outs, N}' waits
%% until N products are out in all (with repeats). `{ok, Event}' or `timeout'.
-spec await(spec(), non_neg_integer(), timeout()) -> {ok, term()} | timeout.
await(Spec, Since, Timeout) ->
    gen_server:call(?MODULE, {await, Spec, Since, Timeout}, infinity).

-spec events() -> [event()].
events() ->
    [E || {_, E} <- timeline()].

%% @doc The events with the time each came (erlang:monotonic_time in ms, of this node).
-spec timeline() -> [{integer(), event()}].
timeline() ->
    gen_server:call(?MODULE, timeline).

%% @doc This node's monotonic clock in ms, to measure against the timeline.
-spec now_ms() -> integer().
now_ms() ->
    erlang:monotonic_time(millisecond).

%% @doc Every product out so far, in order, a product out twice twice.
-spec outs() -> [binary()].
outs() ->
    [S || {out, _, S} <- events()].

%% @doc The errors answered so far: `{Id, Solution}'.
-spec answered() -> [{binary(), atom()}].
answered() ->
    [{Id, Sol} || {answered, Id, Sol} <- events()].

-spec stop() -> ok.
stop() ->
    gen_server:stop(?MODULE).

%% -------------------------------------------------------------------------------------

-spec init(map()) -> {ok, #state{}}.
init(Opts) ->
    _ = ets:new(line_feed, [named_table, public, ordered_set]),
    _ = ets:new(line_out, [named_table, public, set]),
    {ok, #state{answers = maps:get(answers, Opts, ignore)}}.

-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, term(), #state{}} | {noreply, #state{}}.
handle_call({feed, Serials, Task, Ref}, _From, State) ->
    Base = case ets:last(line_feed) of '$end_of_table' -> 0; L -> L end,
    true = ets:insert(line_feed, lists:zip(lists:seq(Base + 1, Base + length(Serials)),
                                           Serials)),
    _ = case cell_task_proc:whereis(Task) of
            undefined -> ok;
            Pid -> Pid ! {Ref, fed}
        end,
    {reply, ok, State};
handle_call({take_feed, Task}, _From, State) ->
    _ = case cell_task_proc:whereis(Task) of
            undefined -> ok;
            Pid -> sys:suspend(Pid, 25000)
        end,
    {reply, [S || {_, S} <- ets:tab2list(line_feed)], State};
handle_call(mark, _From, #state{n = N} = State) ->
    {reply, N, State};
handle_call(timeline, _From, #state{events = Es, times = Ts} = State) ->
    {reply, [{maps:get(I, Ts), E} || {I, E} <- lists:reverse(Es)], State};
handle_call({await, Spec, Since, Timeout}, From, #state{waiters = Ws} = State) ->
    case found(Spec, Since, State) of
        {ok, E} ->
            {reply, {ok, E}, State};
        none ->
            TRef = erlang:start_timer(Timeout, self(), {await, From}),
            {noreply, State#state{waiters = [{From, Spec, Since, TRef} | Ws]}}
    end.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({line_phase, Task, Phase}, State) ->
    {noreply, record({phase, Task, Phase}, State)};
handle_info({line_out, Task, Serial}, State) ->
    {noreply, record({out, Task, Serial}, State)};
handle_info({cell_event, #{type := link_phase} = E}, State) ->
    {noreply, record({link_phase, maps:get(link, E), maps:get(phase, E),
                      maps:get(serial, E, undefined)}, State)};
handle_info({cell_event, #{type := alarm_raised, alarm := A}}, State) ->
    {noreply, answer(A, record({alarm, A}, State))};
handle_info({cell_event, #{type := task_crashed} = E}, State) ->
    {noreply, record({crashed, E}, State)};
handle_info({cell_event, #{type := product_saved, task := T, item := S, in_transit := true}},
            State) ->
    %% On the disk, marked in transit: the task holds the product of a transfer cut
    %% short (or one it takes in).
    {noreply, record({in_transit, T, S}, State)};
handle_info({cell_event, _}, State) ->
    {noreply, State};
handle_info({timeout, TRef, {await, From}}, #state{waiters = Ws} = State) ->
    gen_server:reply(From, timeout),
    {noreply, State#state{waiters = lists:keydelete(TRef, 4, Ws)}}.

record(Event, #state{events = Es, n = N, waiters = Ws} = State) ->
    State1 = State#state{events = [{N + 1, Event} | Es], n = N + 1,
                         times = (State#state.times)#{N + 1 => now_ms()}},
    Left = lists:filter(fun({From, Spec, Since, TRef}) ->
                                case found(Spec, Since, State1) of
                                    {ok, E} ->
                                        _ = erlang:cancel_timer(TRef),
                                        gen_server:reply(From, {ok, E}),
                                        false;
                                    none ->
                                        true
                                end
                        end, Ws),
    State1#state{waiters = Left}.

found({outs, Want}, _Since, #state{events = Es}) ->
    case length([x || {_, {out, _, _}} <- Es]) of
        N when N >= Want -> {ok, N};
        _ -> none
    end;
found(Spec, Since, #state{events = Es}) ->
    case [E || {I, E} <- lists:reverse(Es), I > Since, matches(Spec, E)] of
        [E | _] -> {ok, E};
        [] -> none
    end.

matches({phase, T, P}, {phase, T, P}) -> true;
matches({link_phase, P}, {link_phase, _, P, _}) -> true;
matches(alarm, {alarm, _}) -> true;
matches({in_transit, T}, {in_transit, T, _}) -> true;
matches({alarm, Prefix}, {alarm, #{local_id := Id}}) ->
    binary:longest_common_prefix([Prefix, Id]) =:= byte_size(Prefix);
matches(_, _) -> false.

answer(_A, #state{answers = manual} = State) ->
    State;
answer(#{id := Id, kind := error, solutions := Sols}, State) ->
    Sol = case lists:member(ignore, Sols) of true -> ignore; false -> hd(Sols) end,
    _ = cell_alarms:answer(Id, Sol, <<"suite">>),
    record({answered, Id, Sol}, State);
answer(_A, State) ->
    State.
