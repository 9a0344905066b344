%% @doc Guards two promises of the runtime the tasks cannot keep alone:
%%
%% <ul>
%% <li><b>No product held twice.</b> The registry tells this process when a task takes a
%%     serial another task holds in a record as new as its own or newer
%%     ({@link held_twice/1}); at its own start it looks at every serial the tasks read
%%     back from their files. Once the holders have handled what they were sent (a stale
%%     copy is dropped by then), a serial still held by two tasks gets an error on each
%%     of them, naming both: Reset on one tells that task to forget the product. Both
%%     errors go as soon as one task no longer holds it, whoever made it so. While the
%%     errors stand, {@link cell_alarms:answer/3} refuses any answer that would let a
%%     holder go on with the product.</li>
%% <li><b>No silent deadlock.</b> A Started cell holding products that makes no progress
%%     for the no-progress time (machine setting `no_progress_ms') while no error waits
%%     raises a warning naming each task and what it waits for; the next progress
%%     clears it. The decisions are {@link cell_guard_core}'s. Progress is stamped by
%%     the registry when a product moves (a task takes or lets go of one) or work starts
%%     or ends (a task enters or leaves READY-PROCESSING-EXECUTING), with no message: the
%%     timer, when it fires, finds the deadline moved and is armed again for it; once
%%     the guard has warned (or the cell is empty) it asks the registry for one message
%%     at the next progress.</li>
%% </ul>
-module(cell_guard).
-behaviour(gen_server).

-export([start_link/0, held_twice/1, progress/0, waits/0, sync/0]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2]).

-define(ID, <<"no_progress">>).
-define(GLOBAL_ID, <<"cell:no_progress">>).
-define(DOUBLE, <<"held_twice">>).
-define(INFO_TIMEOUT, 2000).

-record(state, {core :: cell_guard_core:core(),
                timer :: reference() | undefined,
                %% serial => the errors raised for it: alarm id => holding task
                doubles = #{} :: #{binary() => #{binary() => atom()}},
                watching_saves = false :: boolean()}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc A task took `Serial' while another task holds it (called by the registry).
-spec held_twice(binary()) -> ok.
held_twice(Serial) ->
    gen_server:cast(?MODULE, {held_twice, Serial}).

%% @doc The progress the guard asked to be told of (called by the registry, once).
-spec progress() -> ok.
progress() ->
    gen_server:cast(?MODULE, progress).

%% @doc Every task's line: state, phase, product, what it waits for, its links.
-spec waits() -> [iolist()].
waits() ->
    [cell_guard_core:task_line(I) || I <- task_infos()].

%% @doc Returns once the guard has handled what was sent to it before.
-spec sync() -> ok.
sync() ->
    gen_server:call(?MODULE, sync).

-spec init([]) -> {ok, #state{}, {continue, boot}}.
init([]) ->
    {ok, #state{core = cell_guard_core:new(limit_ms())}, {continue, boot}}.

-spec handle_continue(boot, #state{}) -> {noreply, #state{}}.
handle_continue(boot, State) ->
    ok = cell_events:subscribe([request, estop, alarm_raised, alarm_cleared]),
    ok = cell_settings:subscribe(),
    %% The no-progress time read again now that a change of it is told: one saved
    %% between init/1 and the subscription would be missed otherwise.
    Limit = limit_ms(),
    State0 = core(fun(C) -> cell_guard_core:limit(Limit, now_ms(), C) end, State),
    %% A warning of an earlier incarnation would never be cleared by this one, which
    %% starts without it: it goes, and comes again if the cell is still stuck.
    ok = cell_alarms:reset_warning(cell, ?ID),
    %% The serials the tasks read back from their files before this process started.
    Serials = lists:usort([S || {S, _} <- held()]),
    State1 = lists:foldl(fun check_double/2, State0, Serials),
    {noreply, conditions(State1)}.

-spec handle_call(sync, gen_server:from(), #state{}) -> {reply, ok, #state{}}.
handle_call(sync, _From, State) ->
    {reply, ok, State}.

-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({held_twice, Serial}, State) ->
    {noreply, check_double(Serial, State)};
handle_cast(progress, State) ->
    {noreply, core(fun(C) -> cell_guard_core:progress(now_ms(), C) end, State)}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({timeout, Ref, deadline}, #state{timer = Ref} = State) ->
    %% Asked before the stamp is read: progress after this is either in the stamp
    %% or told (see cell_registry:wake_on_progress/0).
    ok = cell_registry:wake_on_progress(),
    Last = cell_registry:last_progress(),
    Products = cell_registry:product_count() > 0,
    Now = now_ms(),
    {noreply, core(fun(C) -> cell_guard_core:timeout(Now, Last, Products, C) end,
                   State#state{timer = undefined})};
handle_info({timeout, _Old, deadline}, State) ->
    {noreply, State};
handle_info({cell_event, #{type := product_saved}}, #state{doubles = Doubles} = State) ->
    {noreply, lists:foldl(fun check_double/2, State, maps:keys(Doubles))};
handle_info({cell_event, #{type := Type, alarm := #{id := ?GLOBAL_ID}}}, State)
  when Type =:= alarm_raised; Type =:= alarm_cleared ->
    %% Its own warning.
    {noreply, State};
handle_info({cell_event, _}, State) ->
    {noreply, conditions(State)};
handle_info({cell_settings, changed, machine}, State) ->
    Limit = limit_ms(),
    {noreply, core(fun(C) -> cell_guard_core:limit(Limit, now_ms(), C) end, State)};
handle_info({cell_settings, changed, _}, State) ->
    {noreply, State};
handle_info({cell_alarm, answer, Id, reset, Who}, State) ->
    {noreply, forget(Id, Who, State)}.

%% -------------------------------------------------------------------------------------
%% No progress
%% -------------------------------------------------------------------------------------

conditions(State) ->
    Started = cell_registry:control(request) =:= start andalso not cell_registry:estop_active(),
    Error = cell_alarms:has_error(),
    core(fun(C) -> cell_guard_core:conditions(#{started => Started, error => Error}, now_ms(), C) end,
         State).

core(Decide, #state{core = C0} = State) ->
    {C, Effects} = Decide(C0),
    lists:foldl(fun effect/2, State#state{core = C}, Effects).

effect({arm, Deadline}, State) ->
    ok = cell_registry:stay_asleep(),
    State1 = cancel(State),
    Ref = erlang:start_timer(max(0, Deadline - now_ms()), self(), deadline),
    State1#state{timer = Ref};
effect(disarm, State) ->
    ok = cell_registry:stay_asleep(),
    cancel(State);
effect(sleep, State) ->
    %% The registry tells of the next progress (asked for before the deadline's
    %% stamp was read).
    State;
effect(warn, State) ->
    Text = cell_guard_core:warning_text(limit_ms(), task_infos()),
    ok = cell_alarms:warning(cell, ?ID, "No progress, no error", Text),
    State;
effect(clear, State) ->
    ok = cell_alarms:reset_warning(cell, ?ID),
    State.

cancel(#state{timer = undefined} = State) ->
    State;
cancel(#state{timer = Ref} = State) ->
    _ = erlang:cancel_timer(Ref, [{async, true}, {info, false}]),
    State#state{timer = undefined}.

now_ms() ->
    erlang:monotonic_time(millisecond).

limit_ms() ->
    cell_settings:get(machine, no_progress_ms).

task_infos() ->
    [task_info(Row) || Row <- cell_registry:tasks()].

task_info(#{id := Id, state := State} = Row) ->
    Info = case maps:find(pid, Row) of
               {ok, Pid} ->
                   try cell_task_proc:info(Pid, ?INFO_TIMEOUT)
                   catch exit:_ -> #{}
                   end;
               error ->
                   #{}
           end,
    maps:merge(#{id => Id, state => State}, Info).

%% -------------------------------------------------------------------------------------
%% Held twice
%% -------------------------------------------------------------------------------------

held() ->
    [{S, Id} || #{id := Id, serial := S} <- cell_registry:tasks(), is_binary(S)].

check_double(Serial, State) ->
    %% A holder with a stale copy drops it when it handles the registry's word: wait
    %% for each to have handled what it was sent before deciding.
    _ = [sync_task(Id) || {Id, _} <- cell_registry:holders(Serial)],
    Holders = lists:usort([Id || {Id, _} <- cell_registry:holders(Serial)]),
    Raised = maps:get(Serial, State#state.doubles, #{}),
    State1 = case Holders of
                 [_, _ | _] -> raise_double(Serial, Holders, Raised, State);
                 _ -> withdraw_double(Serial, Raised, State)
             end,
    %% The one holder left may have held an offer back while the other held it too
    %% (cell_handshake): it offers it now, and the link says whose it is.
    _ = [Pid ! {cell_registry, sole_holder, Serial}
         || [Only] <- [Holders], Pid <- [cell_task_proc:whereis(Only)], is_pid(Pid)],
    watch_saves(State1).

sync_task(Id) ->
    case cell_task_proc:whereis(Id) of
        undefined -> ok;
        Pid -> try cell_task_proc:sync(Pid) catch exit:_ -> ok end
    end.

raise_double(Serial, Holders, Raised, State) ->
    New = lists:foldl(
            fun(Task, Acc) ->
                    case lists:member(Task, maps:values(Acc)) of
                        true ->
                            Acc;
                        false ->
                            [Other | _] = Holders -- [Task],
                            Spec = #{id => ?DOUBLE, caption => "Product held by two tasks",
                                     description => cell_guard_core:double_text(Serial, Task, Other),
                                     solutions => [reset]},
                            {ok, Id} = cell_alarms:raise_error(Task, Spec, self()),
                            maps:put(Id, Task, Acc)
                    end
            end, Raised, Holders),
    State#state{doubles = maps:put(Serial, New, State#state.doubles)}.

withdraw_double(Serial, Raised, State) ->
    _ = [cell_alarms:withdraw(Id) || Id <- maps:keys(Raised)],
    _ = map_size(Raised) > 0
        andalso cell_log:notice(cell, "product ~ts is held by one task again", [Serial]),
    State#state{doubles = maps:remove(Serial, State#state.doubles)}.

%% While a serial is held twice, every product saved may settle it.
watch_saves(#state{doubles = D, watching_saves = W} = State) ->
    case {map_size(D) > 0, W} of
        {Same, Same} -> State;
        {true, false} ->
            ok = cell_events:subscribe([request, estop, alarm_raised, alarm_cleared, product_saved]),
            State#state{watching_saves = true};
        {false, true} ->
            ok = cell_events:subscribe([request, estop, alarm_raised, alarm_cleared]),
            State#state{watching_saves = false}
    end.

%% Reset on one holder's error: that task forgets the product.
forget(Id, Who, #state{doubles = Doubles} = State) ->
    case [{S, T} || {S, Raised} <- maps:to_list(Doubles), {I, T} <- maps:to_list(Raised), I =:= Id] of
        [{Serial, Task}] ->
            Raised = maps:remove(Id, maps:get(Serial, Doubles)),
            State1 = State#state{doubles = maps:put(Serial, Raised, Doubles)},
            case cell_task_proc:whereis(Task) of
                undefined -> ok;
                Pid -> Pid ! {cell_registry, forget, Serial, Who}, ok
            end,
            check_double(Serial, State1);
        [] ->
            State
    end.
