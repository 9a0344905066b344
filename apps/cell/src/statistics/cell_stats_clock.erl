%% @doc Shift accounting of the statistics, pure: the time each task spends in each
%% IPC-2541 state, split at shift boundaries, and the shift each count falls in.
%%
%% A clock knows each task's state and the moment it is counted up to, and the shift
%% last used. Each function answers the counter operations to apply (see {@link
%% cell_stats_db:merge/3}: `add', `min', `max', `set', `first') and the clock after
%% them; `cell_stats' applies them. The shift plan comes as a function giving the
%% shifts' start minutes, asked only when a moment falls outside the shift last used.
%% Times are wall-clock microseconds.
-module(cell_stats_clock).

-export([new/1, tasks/1, task_state/5, counting/4, account/6, seen/2, count/5, timing/5,
         shift_of/3, shift_ended/3, shift_at/2, shift_by_id/2, local/1, to_us/1,
         state_name/1]).

-export_type([clock/0, op/0, starts/0]).

-record(clock, {tasks = #{} :: #{atom() => {atom(), integer()}},   %% state, counted up to
                shift :: {cell_stats_shift:id(), integer(), integer()} | undefined,
                shift_end = 0 :: integer()}).

-opaque clock() :: #clock{}.
-type op() :: {term(), add | min | max | set | first, term()}.
-type starts() :: fun(() -> [0..1439, ...]).

%% @doc A clock counting each task in its state from the moment given.
-spec new(#{atom() => {atom(), integer()}}) -> clock().
new(Tasks) ->
    #clock{tasks = Tasks}.

%% @doc Each task's state and the moment it is counted up to.
-spec tasks(clock()) -> #{atom() => {atom(), integer()}}.
tasks(#clock{tasks = Tasks}) ->
    Tasks.

%% @doc A task entered `State' at `At': the time in the state before is counted (never
%% backwards: events of different tasks arrive in any order); a task seen for the
%% first time starts its time now.
-spec task_state(atom(), atom(), integer(), starts(), clock()) -> {[op()], clock()}.
task_state(T, State, At, Starts, #clock{tasks = Tasks} = C) ->
    {Ops, Upto, C1} = case maps:find(T, Tasks) of
                          {ok, {Was, Since}} ->
                              U = max(At, Since),
                              {O, C0} = account(T, Was, Since, U, Starts, C),
                              {O, U, C0};
                          error ->
                              {[seen(T, At)], At, C}
                      end,
    {Ops2, C2} = counting(T, State, Upto, C1),
    {Ops ++ Ops2, C2}.

%% @doc A task is in `State', counted up to `Upto': kept, and written with the
%% counters (queries add the time since; a restart counts it up to the last write).
-spec counting(atom(), atom(), integer(), clock()) -> {[op()], clock()}.
counting(T, State, Upto, #clock{tasks = Tasks} = C) ->
    {[{{meta, {open, T}}, set, {State, Upto}}], C#clock{tasks = Tasks#{T => {State, Upto}}}}.

%% @doc The first time a task was seen.
-spec seen(atom(), integer()) -> op().
seen(T, At) ->
    {{meta, {first, T}}, first, At}.

%% @doc A stretch of time in a state, added to the shift(s) it falls in and to the
%% total.
-spec account(atom(), atom(), integer(), integer(), starts(), clock()) -> {[op()], clock()}.
account(Scope, State, From, To, Starts, C) ->
    account(Scope, State, From, To, Starts, C, []).

account(_Scope, _State, From, To, _Starts, C, Acc) when To =< From ->
    {lists:append(lists:reverse(Acc)), C};
account(Scope, State, From, To, Starts, C, Acc) ->
    {Id, _Start, End, Ops, C1} = shift_of(From, Starts, C),
    Upto = min(To, End),
    D = Upto - From,
    Added = [{{Id, Scope, {time, State}}, add, D}, {{total, Scope, {time, State}}, add, D}],
    account(Scope, State, Upto, To, Starts, C1, [Ops ++ Added | Acc]).

%% @doc `N' more of each `{Scope, Metric}', in the shift of `At' and in the total.
-spec count([{atom(), term()}], integer(), integer(), starts(), clock()) -> {[op()], clock()}.
count(Keys, N, At, Starts, C) ->
    {Id, _, _, Ops, C1} = shift_of(At, Starts, C),
    {Ops ++ [{K, add, N} || {Scope, M} <- Keys, K <- [{Id, Scope, M}, {total, Scope, M}]],
     C1}.

%% @doc A duration ending at `At' since `From' (nothing when there is no start): its
%% count, sum, least and most, in the shift of `At' and in the total.
-spec timing({atom(), atom()}, integer() | undefined, integer(), starts(), clock()) ->
          {[op()], clock()}.
timing(_Key, undefined, _At, _Starts, C) ->
    {[], C};
timing({Scope, Kind}, From, At, Starts, C) ->
    D = max(At - From, 0),
    {Id, _, _, Ops, C1} = shift_of(At, Starts, C),
    {Ops ++ lists:append([[{{P, Scope, {Kind, n}}, add, 1}, {{P, Scope, {Kind, sum}}, add, D},
                           {{P, Scope, {Kind, min}}, min, D}, {{P, Scope, {Kind, max}}, max, D}]
                          || P <- [Id, total]]),
     C1}.

%% @doc The shift a moment falls in: the one last used if it still does. A shift's
%% span is recorded as the plan had it when the shift was first counted, so a report
%% of it stays right after the plan has changed.
-spec shift_of(integer(), starts(), clock()) ->
          {cell_stats_shift:id(), integer(), integer(), [op()], clock()}.
shift_of(Us, _Starts, #clock{shift = {Id, Start, End}} = C) when Us >= Start, Us < End ->
    {Id, Start, End, [], C};
shift_of(Us, Starts, C) ->
    {Id, Start, End} = shift_at(Us, Starts()),
    {Id, Start, End, [{{meta, {shift, Id}}, first, {Start, End}}],
     C#clock{shift = {Id, Start, End}}}.

%% @doc Once a shift has ended, every task's time in its state is closed at that
%% moment, so the shift's counters hold all of its time.
-spec shift_ended(integer(), starts(), clock()) -> {[op()], clock()}.
shift_ended(Now, _Starts, #clock{shift_end = End} = C) when Now < End ->
    {[], C};
shift_ended(Now, Starts, C0) ->
    {Ops1, C1} = maps:fold(fun(T, {State, Since}, {Acc, C}) ->
                                   Upto = max(Now, Since),
                                   {A, Ca} = account(T, State, Since, Upto, Starts, C),
                                   {O, Cb} = counting(T, State, Upto, Ca),
                                   {[A ++ O | Acc], Cb}
                           end, {[], C0}, C0#clock.tasks),
    {_, _, End, Ops2, C2} = shift_of(Now, Starts, C1),
    {lists:append(lists:reverse(Ops1)) ++ Ops2, C2#clock{shift_end = End}}.

%% @doc The shift of the plan `Starts' a moment falls in, as wall-clock microseconds;
%% its end is never before the moment.
-spec shift_at(integer(), [0..1439, ...]) -> {cell_stats_shift:id(), integer(), integer()}.
shift_at(Us, Starts) ->
    #{id := Id, start := S, 'end' := E} = cell_stats_shift:at(local(Us), Starts),
    {Id, to_us(S), max(to_us(E), Us + 1)}.

%% @doc A shift by its id, as the plan `Starts' has it.
-spec shift_by_id(cell_stats_shift:id(), [0..1439, ...]) -> cell_stats_shift:shift().
shift_by_id({Date, N} = Id, Starts) ->
    Minute = lists:nth(min(N, length(Starts)), Starts),
    #{id := Found} = Shift = cell_stats_shift:at({Date, {Minute div 60, Minute rem 60, 0}},
                                                 Starts),
    case Found of
        Id -> Shift;
        _ -> Shift#{id := Id}
    end.

%% @doc Wall-clock microseconds as local time.
-spec local(integer()) -> calendar:datetime().
local(Us) ->
    calendar:system_time_to_local_time(Us, microsecond).

%% @doc Local time as wall-clock microseconds (in a DST gap, as the clock would read).
-spec to_us(calendar:datetime()) -> integer().
to_us(Local) ->
    Utc = case calendar:local_time_to_universal_time_dst(Local) of
              [U | _] -> U;
              [] -> erlang:localtime_to_universaltime(Local)        %% a DST gap
          end,
    (calendar:datetime_to_gregorian_seconds(Utc) - 62167219200) * 1000000.

%% @doc The short name of a task's state in the counters.
-spec state_name(cell_ipc:state()) -> atom().
state_name(off) -> off;
state_name(down) -> down;
state_name(setup) -> setup;
state_name({ready, idle, blocked}) -> blocked;
state_name({ready, idle, starved}) -> starved;
state_name({ready, processing, active}) -> active;
state_name({ready, processing, executing}) -> executing.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% One shift a day starting at midnight, and two: 06:00 and 18:00.
day() -> fun() -> [0] end.
two() -> fun() -> [360, 1080] end.

us(Date, Time) -> to_us({Date, Time}).

ops_sum(Ops, Key) ->
    lists:sum([V || {K, add, V} <- Ops, K =:= Key]).

first_state_starts_the_time_test() ->
    At = us({2026, 3, 2}, {10, 0, 0}),
    {Ops, C} = task_state(t, active, At, day(), new(#{})),
    ?assertEqual([{{meta, {first, t}}, first, At}, {{meta, {open, t}}, set, {active, At}}], Ops),
    ?assertEqual(#{t => {active, At}}, tasks(C)).

time_split_at_the_shift_boundary_test() ->
    From = us({2026, 3, 2}, {17, 0, 0}),
    To = us({2026, 3, 2}, {19, 0, 0}),
    {Ops, _} = task_state(t, blocked, To, two(), new(#{t => {active, From}})),
    Hour = 3600 * 1000000,
    ?assertEqual(Hour, ops_sum(Ops, {{{2026, 3, 2}, 1}, t, {time, active}})),
    ?assertEqual(Hour, ops_sum(Ops, {{{2026, 3, 2}, 2}, t, {time, active}})),
    ?assertEqual(2 * Hour, ops_sum(Ops, {total, t, {time, active}})),
    %% Each shift's span recorded once, as the plan has it.
    ?assertMatch([_, _], [O || {{meta, {shift, _}}, first, _} = O <- Ops]).

never_backwards_test() ->
    Since = us({2026, 3, 2}, {10, 0, 0}),
    {Ops, C} = task_state(t, blocked, Since - 1000, day(), new(#{t => {active, Since}})),
    ?assertEqual(0, ops_sum(Ops, {total, t, {time, active}})),
    ?assertEqual(#{t => {blocked, Since}}, tasks(C)).

count_and_timing_in_shift_and_total_test() ->
    At = us({2026, 3, 2}, {10, 0, 0}),
    {Ops, C} = count([{t, in}], 1, At, day(), new(#{})),
    Id = {{2026, 3, 2}, 1},
    ?assertEqual([{{meta, {shift, Id}}, first, {us({2026, 3, 2}, {0, 0, 0}),
                                               us({2026, 3, 3}, {0, 0, 0})}},
                  {{Id, t, in}, add, 1}, {{total, t, in}, add, 1}], Ops),
    %% The shift is known now: no second span.
    {Ops2, _} = timing({t, lead}, At - 5, At, fun() -> error(asked) end, C),
    ?assertEqual([{{Id, t, {lead, n}}, add, 1}, {{Id, t, {lead, sum}}, add, 5},
                  {{Id, t, {lead, min}}, min, 5}, {{Id, t, {lead, max}}, max, 5},
                  {{total, t, {lead, n}}, add, 1}, {{total, t, {lead, sum}}, add, 5},
                  {{total, t, {lead, min}}, min, 5}, {{total, t, {lead, max}}, max, 5}], Ops2),
    ?assertEqual({[], C}, timing({t, lead}, undefined, At, day(), C)).

shift_end_closes_open_stretches_test() ->
    From = us({2026, 3, 2}, {17, 0, 0}),
    Now = us({2026, 3, 2}, {18, 30, 0}),
    {Ops, C} = shift_ended(Now, two(), new(#{t => {active, From}})),
    ?assertEqual(90 * 60 * 1000000, ops_sum(Ops, {total, t, {time, active}})),
    ?assertEqual(#{t => {active, Now}}, tasks(C)),
    %% Until the next shift ends, nothing more.
    ?assertEqual({[], C}, shift_ended(Now + 1000, two(), C)).

shift_by_id_test() ->
    ?assertMatch(#{id := {{2026, 3, 2}, 2}}, shift_by_id({{2026, 3, 2}, 2}, [360, 1080])).
-endif.
