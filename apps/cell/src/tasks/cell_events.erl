%% @doc The cell's event fan-out: every IPC-2541 event of seed 000 §2.3.4, task and
%% cell state changes, alarms, requests.
%%
%% A subscriber receives `{cell_event, Event}' for the event types it asked for; it is
%% monitored and dropped when it exits. Publishing does not go through this process:
%% the publisher reads the subscriber list from ETS and sends to each subscriber
%% itself, so a thousand tasks never queue behind one server, and the events of one
%% publisher arrive in the order they were published.
%%
%% An event is a map (see docs/architecture.md): `type', `task', `zone', `lane', `time'
%% (UTC wall clock, milliseconds), `mono' (monotonic microseconds) and the fields of its
%% type: `item', `scanner', `pause_id', `abort_id', `state', `from', `alarm' ...
-module(cell_events).
-behaviour(gen_server).

-export([start_link/0, subscribe/0, subscribe/1, subscribe/2, unsubscribe/0, unsubscribe/1,
         publish/1, publish/3, new/2, new/3, types/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([event/0, type/0]).

-type type() :: cell_ipc:event() | task_state | cell_state | alarm_raised
              | alarm_cleared | request | estop | service_mode | task_crashed
              | product_saved | link_phase.
-type event() :: #{type := type(), task := atom(), time := integer(), mono := integer(),
                   atom() => term()}.

%% One row per event type, the pids subscribed to it: a publication reads only its
%% own type's subscribers, already chosen. One row per subscriber too, `{{subscriber,
%% Pid}, Types}': the table outlives a restart of this process (see {@link
%% cell_service_tables}), and the process started again re-monitors every subscriber
%% found there, who never notices it went.
-define(TAB, cell_event_subscribers).

-record(state, {subs = #{} :: #{pid() => {reference(), all | [type()]}}}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Every event type there is.
-spec types() -> [type()].
types() ->
    [equipment_starved, equipment_unstarved, equipment_blocked, equipment_unblocked,
     item_identifier_read, item_transfer_in, item_work_start, item_work_pause,
     item_work_resume, item_work_complete, item_work_abort, item_transfer_out,
     task_state, cell_state, alarm_raised, alarm_cleared, request, estop, service_mode,
     task_crashed, product_saved, link_phase].

%% @doc Subscribes the caller to every event.
-spec subscribe() -> ok.
subscribe() ->
    gen_server:call(?MODULE, {subscribe, self(), all}).

%% @doc Subscribes the caller to some event types (subscribing again replaces them).
-spec subscribe([type()]) -> ok | {error, {unknown_types, [term()]}}.
subscribe(Types) when is_list(Types) ->
    case [T || T <- Types, not lists:member(T, types())] of
        [] -> gen_server:call(?MODULE, {subscribe, self(), lists:usort(Types)});
        Unknown -> {error, {unknown_types, Unknown}}
    end.

%% @doc Subscribes another process, such as one on another node watching this cell.
-spec subscribe(pid(), all | [type()]) -> ok | {error, {unknown_types, [term()]}}.
subscribe(Pid, all) when is_pid(Pid) ->
    gen_server:call(?MODULE, {subscribe, Pid, all});
subscribe(Pid, Types) when is_pid(Pid), is_list(Types) ->
    case [T || T <- Types, not lists:member(T, types())] of
        [] -> gen_server:call(?MODULE, {subscribe, Pid, lists:usort(Types)});
        Unknown -> {error, {unknown_types, Unknown}}
    end.

%% @doc Unsubscribes the caller from every event.
-spec unsubscribe() -> ok.
unsubscribe() ->
    gen_server:call(?MODULE, {unsubscribe, self()}).

%% @doc Unsubscribes another process (see {@link subscribe/2}).
-spec unsubscribe(pid()) -> ok.
unsubscribe(Pid) when is_pid(Pid) ->
    gen_server:call(?MODULE, {unsubscribe, Pid}).

%% @doc An event of a type for a source, stamped now.
-spec new(type(), atom()) -> event().
new(Type, Task) ->
    new(Type, Task, #{}).

-spec new(type(), atom(), map()) -> event().
new(Type, Task, Fields) ->
    Fields#{type => Type, task => Task, time => os:system_time(millisecond),
            mono => erlang:monotonic_time(microsecond)}.

%% @doc Sends an event to every subscriber of its type, from the calling process.
-spec publish(event()) -> ok.
publish(#{type := Type} = Event) ->
    send(subscribers(Type), {cell_event, Event}).

%% @doc As `publish(new(Type, Task, Fields))', but an event nobody subscribed to is not
%% even made: what a task publishes at every step costs nothing unwatched.
-spec publish(type(), atom(), map()) -> ok.
publish(Type, Task, Fields) ->
    case subscribers(Type) of
        [] -> ok;
        Pids -> send(Pids, {cell_event, new(Type, Task, Fields)})
    end.

subscribers(Type) ->
    try ets:lookup_element(?TAB, Type, 2)
    catch error:badarg -> []
    end.

send([], _Msg) ->
    ok;
send([Pid | Pids], Msg) ->
    Pid ! Msg,
    send(Pids, Msg).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    case cell_service_tables:claim(?TAB, [protected, {read_concurrency, true}]) of
        new -> {ok, store(#state{})};
        kept -> {ok, store(resubscribe(ets:match_object(?TAB, {{subscriber, '_'}, '_'})))}
    end.

%% The subscribers a predecessor left, monitored again: one that died meanwhile is
%% dropped at its 'DOWN', as always.
resubscribe(Rows) ->
    #state{subs = maps:from_list([{Pid, {monitor(process, Pid), Types}}
                                  || {{subscriber, Pid}, Types} <- Rows])}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, ok, #state{}}.
handle_call({subscribe, Pid, Types}, _From, #state{subs = Subs} = State) ->
    Ref = case maps:find(Pid, Subs) of
              {ok, {R, _}} -> R;
              error -> monitor(process, Pid)
          end,
    true = ets:insert(?TAB, {{subscriber, Pid}, Types}),
    {reply, ok, store(State#state{subs = maps:put(Pid, {Ref, Types}, Subs)})};
handle_call({unsubscribe, Pid}, _From, State) ->
    {reply, ok, drop(Pid, State)}.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'DOWN', _Ref, process, Pid, _Reason}, State) ->
    {noreply, drop(Pid, State)}.

drop(Pid, #state{subs = Subs} = State) ->
    case maps:take(Pid, Subs) of
        {{Ref, _}, Subs1} ->
            demonitor(Ref, [flush]),
            true = ets:delete(?TAB, {subscriber, Pid}),
            store(State#state{subs = Subs1});
        error ->
            State
    end.

store(#state{subs = Subs} = State) ->
    true = ets:insert(?TAB, [{Type, [Pid || {Pid, {_, Types}} <- maps:to_list(Subs),
                                            Types =:= all orelse lists:member(Type, Types)]}
                             || Type <- types()]),
    State.
