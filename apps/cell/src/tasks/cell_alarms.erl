%% @doc Errors, alarms and warnings of seed 000 §2.3.8 in one registry.
%%
%% <ul>
%% <li>An <b>error</b> is an unexpected situation an operator must answer. Its owner
%%     (a device task) waits in DOWN; the operator picks one of the error's allowed
%%     solutions (retry, ignore, reset, close) and the owner receives
%%     `{cell_alarm, answer, Id, Solution, Who}'.</li>
%% <li>An <b>alarm</b> is an unrecoverable dangerous condition (an open emergency
%%     circuit); code raises and clears it.</li>
%% <li>A <b>warning</b> does not block: setting it again with the same id updates its
%%     text; code can reset it, the operator can close it.</li>
%% </ul>
%%
%% Any of them may carry a qualifier, `high' or `low', when it is about a measured
%% value above or below its limit (MTConnect conditions pass it on).
%%
%% Ids are `<<"Task:LocalId">>', unique per task. Every answer and close records who,
%% what and when, in the history and in the task log. Errors of an owner that exits are
%% withdrawn (a restarted task raises its own).
-module(cell_alarms).
-behaviour(gen_server).

-export([start_link/0, raise_error/3, withdraw/1, answer/3, warning/4, warning/5,
         reset_warning/2, close/2, alarm/4, alarm/5, clear_alarm/2, list/0, list/1, get/1,
         history/0, has_error/0, has_error/1, has_alarm/0, has_alarm/1, has_warning/0,
         has_warning/1, solutions/0, sync/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([alarm/0, kind/0, solution/0, spec/0, answer_record/0, qualifier/0, options/0]).

-type kind() :: error | alarm | warning.
-type solution() :: retry | ignore | reset | close.
%% Which side of its limit a measured value is on, for a condition about a value out of
%% range (MTConnect's condition qualifier).
-type qualifier() :: high | low.
-type spec() :: #{id := binary(), caption := iodata(), description => iodata(),
                  solutions := [solution()], qualifier => qualifier()}.
-type options() :: #{qualifier => qualifier()}.
-type alarm() :: #{id := binary(), local_id := binary(), kind := kind(),
                   task := atom(), caption := binary(), description := binary(),
                   solutions := [solution()], raised := integer(),
                   qualifier => qualifier()}.
-type answer_record() :: #{id := binary(), task := atom(), caption := binary(),
                           what := solution() | reset | cleared | withdrawn,
                           who := binary(), time := integer()}.

-define(TAB, cell_alarm_table).
-define(HISTORY_MAX, 1000).

-record(state, {owners = #{} :: #{reference() => binary()},
                history = [] :: [answer_record()],
                history_len = 0 :: non_neg_integer()}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The solutions an error may offer, in the seed's order.
-spec solutions() -> [solution()].
solutions() -> [retry, ignore, reset, close].

%% @doc Raises an error owned by the calling process; answers its id.
-spec raise_error(atom(), spec(), pid()) -> {ok, binary()} | {error, {bad_spec, term()}}.
raise_error(Task, Spec, Owner) ->
    case check_spec(Spec) of
        ok -> call({raise_error, Task, Spec, Owner});
        Error -> Error
    end.

%% @doc The owner takes an unanswered error back (it stopped waiting for an answer).
-spec withdraw(binary()) -> ok.
withdraw(Id) ->
    call({withdraw, Id}).

%% @doc An operator's answer to an error: only one of its solutions is accepted. An
%% answer other than Reset (or Close) lets the error's task go on with the product it
%% holds; while another task holds the same serial that would be a product held twice,
%% and it is refused with `{double_holding, Serial, OtherTasks}' (see cell_guard): the
%% error stays. An answer is in the trace journal before the task hears it; one that
%% cannot be recorded is refused with `{not_recorded, Why}'.
-spec answer(binary(), solution(), binary()) ->
          ok | {error, not_found | {not_allowed, [solution()]}
                | {double_holding, binary(), [atom()]} | {not_recorded, term()}}.
answer(Id, Solution, Who) ->
    gen_server:call(?MODULE, {answer, Id, Solution, Who}).

%% @doc Sets a warning; setting it again with the same id updates caption and text.
-spec warning(atom(), binary(), iodata(), iodata()) -> ok.
warning(Task, LocalId, Caption, Description) ->
    warning(Task, LocalId, Caption, Description, #{}).

%% @doc As {@link warning/4}, with a qualifier (`high' or `low': a value above or
%% below its limit).
-spec warning(atom(), binary(), iodata(), iodata(), options()) -> ok.
warning(Task, LocalId, Caption, Description, Opts) ->
    set(warning, Task, LocalId, Caption, Description, Opts).

%% @doc Resets a warning from code; nothing happens if it is not set.
-spec reset_warning(atom(), binary()) -> ok.
reset_warning(Task, LocalId) ->
    cell_service_tables:cast(?MODULE, {reset, warning, Task, LocalId}).

%% @doc Raises a dangerous condition; cleared by code only.
-spec alarm(atom(), binary(), iodata(), iodata()) -> ok.
alarm(Task, LocalId, Caption, Description) ->
    alarm(Task, LocalId, Caption, Description, #{}).

%% @doc As {@link alarm/4}, with a qualifier.
-spec alarm(atom(), binary(), iodata(), iodata(), options()) -> ok.
alarm(Task, LocalId, Caption, Description, Opts) ->
    set(alarm, Task, LocalId, Caption, Description, Opts).

set(Kind, Task, LocalId, Caption, Description, Opts) ->
    case check_options(Opts) of
        ok -> cell_service_tables:cast(?MODULE, {set, Kind, Task, LocalId, Caption, Description, Opts});
        {error, Why} -> erlang:error({bad_options, Why}, [Task, LocalId, Caption, Description, Opts])
    end.

-spec clear_alarm(atom(), binary()) -> ok.
clear_alarm(Task, LocalId) ->
    cell_service_tables:cast(?MODULE, {reset, alarm, Task, LocalId}).

%% @doc An operator closes a warning (seed: warnings have only a Close button).
-spec close(binary(), binary()) -> ok | {error, not_found | {not_allowed, [solution()]}}.
close(Id, Who) ->
    gen_server:call(?MODULE, {close, Id, Who}).

%% @doc Returns once the registry has handled what the caller sent it before
%% (warnings and alarms are set without waiting).
-spec sync() -> ok.
sync() ->
    call(sync).

%% @doc Every active error, alarm and warning, oldest first.
-spec list() -> [alarm()].
list() ->
    lists:sort(fun(A, B) -> maps:get(raised, A) =< maps:get(raised, B) end,
               [public(A) || {_, A} <- ets:tab2list(?TAB)]).

%% @doc Those of one task.
-spec list(atom()) -> [alarm()].
list(Task) ->
    [A || #{task := T} = A <- list(), T =:= Task].

%% @doc One active error, alarm or warning by its id (`<<"Task:LocalId">>').
-spec get(binary()) -> {ok, alarm()} | {error, not_found}.
get(Id) ->
    case ets:lookup(?TAB, Id) of
        [{Id, A}] -> {ok, public(A)};
        [] -> {error, not_found}
    end.

%% @doc Recent answers, closes and clears, newest first: who, what, when.
-spec history() -> [answer_record()].
history() ->
    gen_server:call(?MODULE, history).

%% @doc Whether an error waits for the operator.
-spec has_error() -> boolean().
has_error() -> any(error, '_').
%% @doc Whether an error of `Task' waits for the operator.
-spec has_error(atom()) -> boolean().
has_error(Task) -> any(error, Task).
%% @doc Whether an alarm is raised.
-spec has_alarm() -> boolean().
has_alarm() -> any(alarm, '_').
%% @doc Whether an alarm of `Task' is raised.
-spec has_alarm(atom()) -> boolean().
has_alarm(Task) -> any(alarm, Task).
%% @doc Whether a warning is set.
-spec has_warning() -> boolean().
has_warning() -> any(warning, '_').
%% @doc Whether a warning of `Task' is set.
-spec has_warning(atom()) -> boolean().
has_warning(Task) -> any(warning, Task).

any(Kind, Task) ->
    ets:match(?TAB, {'_', #{kind => Kind, task => Task}}, 1) =/= '$end_of_table'.

check_spec(#{id := Id, caption := _, solutions := [_ | _] = Sols} = Spec)
  when is_binary(Id), Id =/= <<>> ->
    case {[S || S <- Sols, not lists:member(S, solutions())],
          check_options(maps:with([qualifier], Spec))} of
        {[], ok} -> ok;
        {[], {error, Why}} -> {error, {bad_spec, {Why, Spec}}};
        {Bad, _} -> {error, {bad_spec, {unknown_solutions, Bad, Spec}}}
    end;
check_spec(Spec) ->
    {error, {bad_spec, Spec}}.

check_options(Opts) when is_map(Opts) ->
    case {maps:keys(Opts) -- [qualifier], maps:find(qualifier, Opts)} of
        {[K | _], _} -> {error, {unknown_option, K}};
        {[], {ok, Q}} when Q =/= high, Q =/= low -> {error, {bad_qualifier, Q}};
        {[], _} -> ok
    end;
check_options(Opts) ->
    {error, {bad_options, Opts}}.

public(A) -> maps:without([owner, monitor], A).

%% The serial of the product the error's task holds, or `undefined'.
serial_of(Task) ->
    case cell_registry:task(Task) of
        {ok, #{serial := Serial}} when is_binary(Serial) -> Serial;
        _ -> undefined
    end.

%% Whether answering lets the error's task go on with a product another task holds.
held_twice(_Task, undefined, _Solution) ->
    none;
held_twice(_Task, _Serial, Solution) when Solution =:= reset; Solution =:= close ->
    none;
held_twice(Task, Serial, _Solution) ->
    Holders = [O || {O, _} <- cell_registry:holders(Serial)],
    case {lists:member(Task, Holders), [O || O <- Holders, O =/= Task]} of
        %% Its copy was found older than another task's record: it is no holder any
        %% more, and it drops the copy before it acts on the answer (cell_task_proc).
        {false, _} -> none;
        {true, []} -> none;
        {true, Others} -> {Serial, lists:usort(Others)}
    end.

%% What the tasks, the monitor and the controller ask wait through a restart of this
%% process instead of failing (see cell_service_tables).
call(Request) ->
    cell_service_tables:call(?MODULE, Request, 5000).

-spec init([]) -> {ok, #state{}}.
init([]) ->
    case cell_service_tables:claim(?TAB, [protected, {read_concurrency, true}]) of
        new -> {ok, #state{}};
        kept -> {ok, rewatch(ets:tab2list(?TAB))}
    end.

%% Restarted after a fault: the active errors, alarms and warnings are still in the
%% table (see cell_service_tables), and each error's owner, still waiting for its
%% answer, is watched again; one that died meanwhile withdraws its error at its 'DOWN'.
rewatch(Rows) ->
    Owners = [begin
                  Ref = monitor(process, Owner),
                  true = ets:insert(?TAB, {Id, A#{monitor => Ref}}),
                  {Ref, Id}
              end || {Id, #{owner := Owner} = A} <- Rows],
    #state{owners = maps:from_list(Owners)}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({raise_error, Task, Spec, Owner}, _From, State) ->
    #{id := Local, caption := Caption, solutions := Sols} = Spec,
    Id = global_id(Task, Local),
    Alarm0 = #{id => Id, local_id => Local, kind => error, task => Task,
               caption => text(Caption), description => text(maps:get(description, Spec, <<>>)),
               solutions => Sols, raised => os:system_time(millisecond), owner => Owner},
    Alarm = maps:merge(Alarm0, maps:with([qualifier], Spec)),
    State1 = case ets:lookup(?TAB, Id) of
                 [{Id, _}] -> remove(Id, withdrawn, <<"cell">>, State);
                 [] -> State
             end,
    Ref = monitor(process, Owner),
    true = ets:insert(?TAB, {Id, Alarm#{monitor => Ref}}),
    cell_log:error(Task, "~ts: ~ts", [maps:get(caption, Alarm), maps:get(description, Alarm)]),
    ok = publish(alarm_raised, Alarm),
    {reply, {ok, Id}, State1#state{owners = maps:put(Ref, Id, State1#state.owners)}};
handle_call({withdraw, Id}, _From, State) ->
    {reply, ok, remove(Id, withdrawn, <<"cell">>, State)};
handle_call({answer, Id, Solution, Who}, _From, State) ->
    case ets:lookup(?TAB, Id) of
        [{Id, #{kind := error, task := Task, solutions := Sols} = A}] ->
            Serial = serial_of(Task),
            case lists:member(Solution, Sols) andalso held_twice(Task, Serial, Solution) of
                {Serial, Others} ->
                    cell_log:warning(Task,
                                     "~ts answered \"~ts\" with ~ts: refused, product ~ts is "
                                     "held by ~ts too; settle that first",
                                     [Who, maps:get(caption, A), solution_name(Solution), Serial,
                                      lists:join(", ", [atom_to_list(O) || O <- Others])]),
                    {reply, {error, {double_holding, Serial, Others}}, State};
                none ->
                    answer(A, Serial, Solution, Who, State);
                false ->
                    {reply, {error, {not_allowed, Sols}}, State}
            end;
        [{Id, #{solutions := Sols}}] ->
            {reply, {error, {not_allowed, Sols}}, State};
        [] ->
            {reply, {error, not_found}, State}
    end;
handle_call({close, Id, Who}, _From, State) ->
    case ets:lookup(?TAB, Id) of
        [{Id, #{kind := warning} = A}] ->
            cell_log:notice(maps:get(task, A), "~ts closed the warning \"~ts\"",
                            [Who, maps:get(caption, A)]),
            {reply, ok, remove(Id, close, Who, State)};
        [{Id, #{solutions := Sols}}] ->
            {reply, {error, {not_allowed, Sols}}, State};
        [] ->
            {reply, {error, not_found}, State}
    end;
handle_call(history, _From, State) ->
    {reply, State#state.history, State};
handle_call(sync, _From, State) ->
    {reply, ok, State}.

%% An answer allowed: recorded in the trace journal before the task hears it.
answer(#{id := Id, owner := Owner} = A, Serial, Solution, Who, State) ->
    case journal_answer(A, Serial, Solution, Who) of
        {error, Why} ->
            {reply, {error, {not_recorded, Why}}, State};
        ok ->
            Owner ! {cell_alarm, answer, Id, Solution, Who},
            cell_log:notice(maps:get(task, A), "~ts answered \"~ts\" with ~ts",
                            [Who, maps:get(caption, A), solution_name(Solution)]),
            {reply, ok, remove(Id, Solution, Who, State)}
    end.

-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({set, Kind, Task, Local, Caption, Description, Opts}, State) ->
    Id = global_id(Task, Local),
    New = maps:merge(#{id => Id, local_id => Local, kind => Kind, task => Task,
                       caption => text(Caption), description => text(Description),
                       solutions => case Kind of warning -> [close]; alarm -> [] end},
                     maps:with([qualifier], Opts)),
    case ets:lookup(?TAB, Id) of
        [{Id, #{kind := Kind} = Old}] ->
            %% Caption, text and qualifier as now (a value back within its limit but
            %% still warned about has no qualifier any more).
            Updated = maps:merge(maps:remove(qualifier, Old),
                                 maps:with([caption, description, qualifier], New)),
            case Updated =:= Old of
                true -> ok;
                false ->
                    true = ets:insert(?TAB, {Id, Updated}),
                    ok = publish(alarm_raised, Updated)
            end,
            {noreply, State};
        _ ->
            Alarm = New#{raised => os:system_time(millisecond)},
            true = ets:insert(?TAB, {Id, Alarm}),
            Log = case Kind of warning -> warning; alarm -> error end,
            cell_log:log(Log, Task, "~ts: ~ts", [maps:get(caption, Alarm),
                                                 maps:get(description, Alarm)]),
            ok = publish(alarm_raised, Alarm),
            {noreply, State}
    end;
handle_cast({reset, Kind, Task, Local}, State) ->
    Id = global_id(Task, Local),
    case ets:lookup(?TAB, Id) of
        [{Id, #{kind := Kind}}] -> {noreply, remove(Id, cleared, <<"cell">>, State)};
        _ -> {noreply, State}
    end.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'DOWN', Ref, process, _Pid, _Reason}, #state{owners = Owners} = State) ->
    case maps:take(Ref, Owners) of
        {Id, Owners1} -> {noreply, remove(Id, withdrawn, <<"cell">>, State#state{owners = Owners1})};
        error -> {noreply, State}
    end.

remove(Id, What, Who, State) ->
    case ets:lookup(?TAB, Id) of
        [{Id, A}] ->
            true = ets:delete(?TAB, Id),
            Owners = case maps:find(monitor, A) of
                         {ok, Ref} ->
                             demonitor(Ref, [flush]),
                             maps:remove(Ref, State#state.owners);
                         error ->
                             State#state.owners
                     end,
            Now = os:system_time(millisecond),
            ok = publish(alarm_cleared, A#{cleared => What, who => Who}),
            Record = #{id => Id, task => maps:get(task, A), caption => maps:get(caption, A),
                       what => What, who => Who, time => Now},
            record(Record, State#state{owners = Owners});
        [] ->
            State
    end.

record(Record, #state{history = H, history_len = N} = State) when N >= ?HISTORY_MAX ->
    State#state{history = [Record | lists:sublist(H, ?HISTORY_MAX - 1)]};
record(Record, #state{history = H, history_len = N} = State) ->
    State#state{history = [Record | H], history_len = N + 1}.

publish(Type, Alarm) ->
    cell_events:publish(cell_events:new(Type, maps:get(task, Alarm),
                                        #{alarm => maps:without([owner, monitor], Alarm)})).

global_id(Task, Local) ->
    <<(atom_to_binary(Task, utf8))/binary, ":", Local/binary>>.

text(IoData) ->
    case unicode:characters_to_binary(IoData) of
        B when is_binary(B) -> B;
        _ -> iolist_to_binary(io_lib:format("~tp", [IoData]))
    end.

%% An answer is in the trace journal before its owner hears it: what an operator
%% decided about a product stays in its history after a crash (see cell_stats).
journal_answer(#{id := Id, task := Task, caption := Caption}, Serial, Solution, Who) ->
    Item = case Serial of
               undefined -> #{};
               _ -> #{item => Serial}
           end,
    case cell_trace_journal:append(Item#{type => alarm_answered, task => Task, alarm => Id,
                                         caption => Caption, solution => Solution,
                                         who => Who}) of
        {ok, _} -> ok;
        {error, not_running} -> ok;
        {error, _} = E -> E
    end.

solution_name(retry) -> "Retry";
solution_name(ignore) -> "Ignore";
solution_name(reset) -> "Reset";
solution_name(close) -> "Close".
