%% @doc The statistics' database: its tables, the reports read from them, the
%% counters' write and what the purge removes. Reads skip the statistics process (they
%% read the tables directly, in a transaction where parts must agree); while the
%% database is not open they find nothing. Writes of the histories are made by the
%% process's writer (`cell_stats_writer') with the functions here.
%%
%% Tables (mnesia): `cell_stats_counter' (ordered_set, disc_copies: key `{Period,
%% Scope, Metric}', Period `total' or a shift id, Scope a task or `cell', and the
%% `{meta, _}' keys: when the counters were last written, each task's first time seen
%% and its state at that write, each shift's span, the last journal record applied);
%% `cell_trace_open' (disc_copies: the products in the cell, the summary of each);
%% `cell_trace_product' (disc_only_copies: the summary of each product that left) and
%% `cell_trace_event' (disc_only_copies, bag: the history by serial).
-module(cell_stats_db).

-export([tables/0, summary/2, counters/2, time_check/0, periods/0, product/1, products_out/2,
         in_cell/0]).
-export([at_open/0, left_summary/1, product_summary/4]).
-export([write_counters/5, merge/3, sync_histories/0, write_history/4, delete_counter/1,
         forget/1, expired/3, over_limit/1, to_drop/4]).

-define(COUNTER, cell_stats_counter).
-define(OPEN, cell_trace_open).
-define(PRODUCT, cell_trace_product).
-define(EVENT, cell_trace_event).

-type starts() :: cell_stats_clock:starts().

%%====================================================================
%% Schema
%%====================================================================

%% @doc The tables, for {@link cell_db:ensure_tables/2}.
-spec tables() -> [cell_db:table()].
tables() ->
    [{?COUNTER, [{type, ordered_set}, {attributes, [key, value]}]},
     {?OPEN, [{attributes, [serial, info]}]},
     {?PRODUCT, [{storage, disc_only_copies}, {attributes, [serial, info]}]},
     {?EVENT, [{storage, disc_only_copies}, {type, bag},
               {attributes, [serial, time, seq, entry]}]}].

%%====================================================================
%% Reports
%%====================================================================

%% @doc What happened in one period, in words a report uses (see {@link
%% cell_stats:summary/1}); `Starts' is the shift plan, for a shift not counted yet.
-spec summary(cell_stats:period(), starts()) -> map().
summary(Period, Starts) ->
    %% The products in the cell read with the counters: the books add up in any read.
    {{{From, To}, Counters}, InCell} =
        view(fun() -> {counted(Period, Starts), length(mnesia:all_keys(?OPEN))} end,
             {{{now_us(), now_us()}, #{}}, 0}),
    Hours = max(To - From, 0) / 3600.0e6,
    Cell = maps:get(cell, Counters, #{}),
    Out = maps:get(out, Cell, 0),
    Tasks = maps:without([cell], Counters),
    #{period => period_label(Period), from => From div 1000, to => To div 1000,
      cell => #{in => maps:get(in, Cell, 0), out => Out, good => maps:get(good, Cell, 0),
                failed => maps:get(failed, Cell, 0),
                scrapped => maps:get(scrapped, Cell, 0),
                lead_ms => times(lead, Cell), cycle_ms => times(cycle, Cell),
                throughput_per_hour => case Hours > 0 of
                                           true -> round1(Out / Hours);
                                           false -> 0.0
                                       end},
      in_cell => InCell,
      tasks => maps:map(fun(_, C) -> task_summary(C) end, Tasks)}.

task_summary(C) ->
    Time = maps:from_list([{S, V div 1000} || {{time, S}, V} <- maps:to_list(C)]),
    Total = lists:sum(maps:values(Time)),
    #{time_ms => Time, total_ms => Total,
      share => maps:map(fun(_, V) when Total > 0 -> round1(100 * V / Total);
                           (_, _) -> 0.0
                        end, Time),
      in => maps:get(in, C, 0), out => maps:get(out, C, 0),
      completed => maps:get(completed, C, 0), aborted => maps:get(aborted, C, 0),
      scrapped => maps:get(scrapped, C, 0), errors => maps:get(errors, C, 0),
      warnings => maps:get(warnings, C, 0), crashes => maps:get(crashes, C, 0),
      cycle_ms => times(cycle, C), lead_ms => times(lead, C), work_ms => times(work, C)}.

times(Kind, C) ->
    case maps:get({Kind, n}, C, 0) of
        0 -> #{n => 0};
        N -> #{n => N, mean => round1(maps:get({Kind, sum}, C) / N / 1000),
               min => round1(maps:get({Kind, min}, C) / 1000),
               max => round1(maps:get({Kind, max}, C) / 1000)}
    end.

round1(X) -> round(X * 10) / 10.

period_label(total) -> <<"total">>;
period_label(Id) -> cell_stats_shift:label(Id).

%% @doc The counters of a period up to the last write: `#{Scope => #{Metric =>
%% Value}}', times in microseconds, the time of tasks still in their state included;
%% `Starts' gives the shift plan, for a shift not counted yet.
-spec counters(cell_stats:period(), starts()) -> #{atom() => map()}.
counters(Period, Starts) ->
    {_Span, Counters} = view(fun() -> counted(Period, Starts) end, {undefined, #{}}),
    Counters.

%% @doc For every task seen, the time counted in its states and the time from when it
%% was first seen to the last write, in microseconds, read together.
-spec time_check() -> #{atom() => {non_neg_integer(), non_neg_integer()}}.
time_check() ->
    view(fun() ->
                 {_Span, Counters} = counted(total, fun() -> [0] end),
                 case meta(flushed, undefined) of
                     undefined ->
                         #{};
                     Flushed ->
                         maps:from_list(
                           [{T, {lists:sum([V || {{time, _}, V} <- maps:to_list(
                                                                      maps:get(T, Counters, #{}))]),
                                 Flushed - First}} || {T, First} <- firsts()])
                 end
         end, #{}).

%% @doc The periods recorded: `total' and the shifts, oldest first.
-spec periods() -> [cell_stats:period()].
periods() ->
    Keys = safe(fun() -> mnesia:dirty_all_keys(?COUNTER) end, []),
    [total | lists:usort([P || {{_, _} = P, _, _} <- Keys])].

%% @doc A product's history (see {@link cell_stats:product/1}).
-spec product(binary()) -> {ok, map()} | {error, not_found}.
product(Serial) ->
    %% The row in the cell first: a product leaving has its summary written in the
    %% transaction that deletes that row, so one of the two is found.
    Summary = case safe(fun() -> mnesia:dirty_read(?OPEN, Serial) end, []) of
                  [{?OPEN, _, Row}] ->
                      product_summary(Serial, Row, in_cell, undefined);
                  [] ->
                      case safe(fun() -> mnesia:dirty_read(?PRODUCT, Serial) end, []) of
                          [{?PRODUCT, _, Left}] -> Left;
                          [] -> undefined
                      end
              end,
    Events = safe(fun() -> mnesia:dirty_read(?EVENT, Serial) end, []),
    case {Summary, Events} of
        {undefined, []} ->
            {error, not_found};
        _ ->
            Sorted = lists:sort([{T, Seq, E} || {?EVENT, _, T, Seq, E} <- Events]),
            History = [E#{time => T} || {T, _, E} <- Sorted],
            %% Its summary is written with the counters, up to a second after its
            %% history: until then it is read from the history.
            Info = case Summary of
                       undefined -> cell_stats_trace:from_history(Serial, History);
                       I -> I
                   end,
            {ok, Info#{events => History}}
    end.

%% @doc How many products are in the cell.
-spec in_cell() -> non_neg_integer().
in_cell() ->
    case safe(fun() -> mnesia:table_info(?OPEN, size) end, 0) of
        N when is_integer(N) -> N;
        _ -> 0
    end.

%% Reads the counters in one transaction: a report never sees part of a write, nor a
%% write that came between two of its reads (the span of one and the counters of the
%% next would not add up).
view(Fun, Default) ->
    case mnesia:transaction(Fun) of
        {atomic, Result} -> Result;
        {aborted, _} -> Default
    end.

%% In a transaction: the period's span and its counters.
counted(Period, Starts) ->
    {From, To} = span(Period, Starts),
    {{From, To}, with_open(From, To, written(Period))}.

%% The counters as written.
written(Period) ->
    Rows = mnesia:select(?COUNTER, [{{?COUNTER, {Period, '$1', '$2'}, '$3'},
                                     [], [{{'$1', '$2', '$3'}}]}]),
    lists:foldl(fun({Scope, Metric, V}, Acc) ->
                        maps:update_with(Scope, fun(M) -> M#{Metric => V} end,
                                         #{Metric => V}, Acc)
                end, #{}, Rows).

%% The counters with the time of every task in the state it was in at the last write,
%% as much of it as falls in the period's span.
with_open(From, To, Counters) ->
    lists:foldl(fun({T, {State, Since}}, Acc) when is_integer(Since) ->
                        case To - max(From, Since) of
                            D when D > 0 ->
                                maps:update_with(T, fun(C) -> maps:update_with({time, State},
                                                                               fun(V) -> V + D end,
                                                                               D, C)
                                                    end, #{{time, State} => D}, Acc);
                            _ ->
                                Acc
                        end;
                   (_, Acc) ->
                        Acc
                end, Counters, open_rows()).

%% Each task's state and since when it is counted there, as last written.
open_rows() ->
    mnesia:select(?COUNTER, [{{?COUNTER, {meta, {open, '$1'}}, '$2'}, [], [{{'$1', '$2'}}]}]).

%% The time a period covers: a shift from its start to its end or to the last write;
%% the total from the first task seen to the last write.
%% Both begin no earlier than the first task was seen.
span(total, _Starts) ->
    Flushed = meta(flushed, now_us()),
    {first_seen(Flushed), Flushed};
span({_, _} = Id, Starts) ->
    {Start, End} = case meta({shift, Id}, undefined) of
                       {_, _} = Recorded ->
                           Recorded;
                       undefined ->
                           #{start := S, 'end' := E} =
                               cell_stats_clock:shift_by_id(Id, Starts()),
                           {cell_stats_clock:to_us(S), cell_stats_clock:to_us(E)}
                   end,
    Flushed = meta(flushed, now_us()),
    {max(Start, first_seen(Flushed)), min(End, Flushed)}.

first_seen(Default) ->
    lists:min([Default | [First || {_, First} <- firsts()]]).

%% Each task's first time seen.
firsts() ->
    mnesia:select(?COUNTER, [{{?COUNTER, {meta, {first, '$1'}}, '$2'}, [], [{{'$1', '$2'}}]}]).

meta(Key, Default) ->
    case mnesia:read(?COUNTER, {meta, Key}) of
        [{?COUNTER, _, V}] -> V;
        [] -> Default
    end.

%%====================================================================
%% What the statistics process reads back
%%====================================================================

%% @doc What the statistics read back when they open the database, in one transaction:
%% when the counters were last written (`flushed'), each task's state then and since
%% when (`open'), each task's first time seen (`firsts'), the products in the cell with
%% their rows (`products') and the id of the last journal record whose effects the
%% counters hold (`mark'). All or nothing: a read that fails is an error, never taken
%% for an empty database (the statistics would count products in the cell again, and
%% count with no mark, so that the journal's records are counted again after a crash).
-spec at_open() -> {ok, #{flushed := integer() | undefined,
                          open := [{atom(), {atom(), integer()}}],
                          firsts := #{atom() => integer()},
                          products := [{binary(), map()}],
                          mark := cell_trace_journal:id() | undefined}}
                 | {error, term()}.
at_open() ->
    Read = fun() ->
                   #{flushed => meta(flushed, undefined), open => open_rows(),
                     firsts => maps:from_list(firsts()),
                     products => [{Serial, Row} || {?OPEN, Serial, Row}
                                                       <- mnesia:select(?OPEN, [{'_', [], ['$_']}])],
                     mark => meta(journal, undefined)}
           end,
    %% mnesia stopping in the middle of a transaction exits rather than answers.
    try mnesia:transaction(Read) of
        {atomic, Books} -> {ok, Books};
        {aborted, Why} -> {error, Why}
    catch exit:{aborted, Why} -> {error, Why}
    end.

%% @doc How a product that left did, as written.
-spec left_summary(binary()) -> map() | undefined.
left_summary(Serial) ->
    case safe(fun() -> mnesia:dirty_read(?PRODUCT, Serial) end, []) of
        [{?PRODUCT, _, Info}] -> Info;
        [] -> undefined
    end.

%% @doc A product's summary (times in ms) from its row in the cell (`entered' in µs,
%% `recipe', `failed', `entry'): where it is, or how it left (`{Task, At}', At in µs).
-spec product_summary(binary(), map(), atom(), {atom(), integer()} | undefined) -> map().
product_summary(Serial, Row, Status, Left) ->
    {ExitTask, LeftAt} = case Left of
                             undefined -> {undefined, undefined};
                             {T, At} -> {T, At div 1000}
                         end,
    #{serial => Serial, status => Status, recipe => maps:get(recipe, Row, <<>>),
      failed => maps:get(failed, Row, false), entered => maps:get(entered, Row, 0) div 1000,
      entry_task => maps:get(entry, Row, undefined), left => LeftAt, exit_task => ExitTask}.

%%====================================================================
%% Writes
%%====================================================================

%% @doc One transaction: every pending counter operation (`{Key, Op, Value}' in the
%% ETS table `Pending'), the books (rows of the products in the cell to write or
%% delete, summaries of the products that left), the id of the last journal record
%% whose effects they hold, and the time of the write; then the log is synced.
-spec write_counters(ets:tid(), #{binary() => map() | delete}, #{binary() => map()},
                     cell_trace_journal:id() | undefined, integer()) -> ok | {error, term()}.
write_counters(Pending, Open, Gone, Mark, Now) ->
    F = fun() ->
                %% One lock for all: a thousand tasks starting change thousands of
                %% counters, and a lock request each would cost more than the writes.
                ok = mnesia:write_lock_table(?COUNTER),
                ets:foldl(fun({K, Op, V}, ok) ->
                                  New = case mnesia:read(?COUNTER, K, write) of
                                            [{?COUNTER, _, Old}] when Op =/= set ->
                                                merge(Op, Old, V);
                                            _ ->
                                                V
                                        end,
                                  mnesia:write({?COUNTER, K, New})
                          end, ok, Pending),
                ok = books(Open, Gone),
                _ = Mark =:= undefined orelse
                    mnesia:write({?COUNTER, {meta, journal}, Mark}),
                mnesia:write({?COUNTER, {meta, flushed}, Now})
        end,
    case mnesia:transaction(F) of
        {atomic, ok} ->
            _ = mnesia:sync_log(),
            ok;
        {aborted, Why} ->
            {error, Why}
    end.

%% In the counters' transaction: the books as the counters count them.
books(Open, Gone) ->
    %% A lock for each table, as for the counters: a line makes thousands of rows a
    %% second, and a lock request for each row waited on mnesia's lock manager every
    %% time (three waits a product).
    _ = map_size(Gone) =:= 0 orelse mnesia:write_lock_table(?PRODUCT),
    _ = map_size(Open) =:= 0 orelse mnesia:write_lock_table(?OPEN),
    ok = maps:fold(fun(Serial, Info, ok) -> mnesia:write({?PRODUCT, Serial, Info}) end,
                   ok, Gone),
    maps:fold(fun(Serial, delete, ok) -> mnesia:delete({?OPEN, Serial});
                 (Serial, Row, ok) -> mnesia:write({?OPEN, Serial, Row})
              end, ok, Open).

%% @doc Two operations on one counter as one.
-spec merge(add | min | max | set | first, term(), term()) -> term().
merge(add, Old, V) -> Old + V;
merge(min, Old, V) -> min(Old, V);
merge(max, Old, V) -> max(Old, V);
merge(set, _Old, V) -> V;
merge(first, Old, _V) -> Old.

%% @doc The history tables flushed to the disk (a table on disc only keeps writes in
%% memory for seconds).
-spec sync_histories() -> ok | {error, term()}.
sync_histories() ->
    case {sync_table(?EVENT), sync_table(?PRODUCT)} of
        {ok, ok} -> ok;
        {{error, Why}, _} -> {error, Why};
        {_, {error, Why}} -> {error, Why}
    end.

%% mnesia keeps a table on disc only in a dets file of the table's name.
sync_table(Tab) ->
    try dets:sync(Tab)
    catch error:badarg -> {error, {no_table, Tab}}
    end.

%% @doc An entry of a product's history, at `At' (µs), ordered among the entries of
%% its millisecond by `Seq'. The history keeps one copy of an entry written twice.
-spec write_history(binary(), integer(), term(), map()) -> ok.
write_history(Serial, At, Seq, Entry) ->
    mnesia:dirty_write({?EVENT, Serial, At div 1000, {At, Seq}, Entry}).

%% @doc A counter removed.
-spec delete_counter(term()) -> ok.
delete_counter(Key) ->
    mnesia:dirty_delete(?COUNTER, Key).

%% @doc A product's history and summary removed.
-spec forget(binary()) -> ok.
forget(Serial) ->
    ok = mnesia:dirty_delete(?EVENT, Serial),
    mnesia:dirty_delete(?PRODUCT, Serial).

%%====================================================================
%% Purge
%%====================================================================

%% @doc What the purge at `Now' removes: the counters (and spans) of the shifts that
%% began before the `shift_days' kept, and the products that left before the
%% `trace_days' kept.
-spec expired(integer(), pos_integer(), pos_integer()) -> {[term()], [binary()]}.
expired(Now, ShiftDays, TraceDays) ->
    {CutDate, _} = cell_stats_clock:local(Now - ShiftDays * 86400 * 1000000),
    %% A shift's counters, and its span, by the date the shift began.
    Before = fun(Key) ->
                     safe(fun() ->
                                  mnesia:dirty_select(?COUNTER, [{{?COUNTER, Key, '_'},
                                                                  [{'<', '$1', {const, CutDate}}],
                                                                  [{element, 2, '$_'}]}])
                          end, [])
             end,
    Keys = Before({{'$1', '_'}, '_', '_'}) ++ Before({meta, {shift, {'$1', '_'}}}),
    Cut = (Now div 1000) - TraceDays * 86400 * 1000,
    Old = safe(fun() ->
                       mnesia:dirty_select(?PRODUCT, [{{?PRODUCT, '$1', #{left => '$2'}},
                                                       [{is_integer, '$2'}, {'<', '$2', Cut}],
                                                       ['$1']}])
               end, []),
    {Keys, Old}.

%% @doc Past `Max' history records, the products whose histories go (those that left
%% longest ago, down to nine tenths of it), each as `{LeftMs, Serial}', oldest first.
-spec over_limit(pos_integer()) -> [{integer(), binary()}].
over_limit(Max) ->
    case safe(fun() -> mnesia:table_info(?EVENT, size) end, 0) of
        N when is_integer(N), N > Max ->
            Left = safe(fun() ->
                                mnesia:dirty_select(?PRODUCT, [{{?PRODUCT, '$1', #{left => '$2'}},
                                                                [{is_integer, '$2'}],
                                                                [{{'$2', '$1'}}]}])
                        end, []),
            Products = safe(fun() -> mnesia:table_info(?PRODUCT, size) end, 1),
            to_drop(N, Max, Products, Left);
        _ ->
            []
    end.

%% @doc Of `N' history records over `Max', held by `Products' products of which `Left'
%% (`{LeftMs, Serial}') left: those to drop, as many as hold about the records past
%% nine tenths of `Max', oldest first.
-spec to_drop(non_neg_integer(), pos_integer(), term(), [{integer(), binary()}]) ->
          [{integer(), binary()}].
to_drop(N, Max, _Products, _Left) when N =< Max ->
    [];
to_drop(N, Max, Products, Left) ->
    P = case Products of
            P0 when is_integer(P0) -> max(1, P0);
            _ -> 1
        end,
    lists:sublist(lists:sort(Left), ceil((N - Max * 0.9) * P / N)).

%% Reads skip the process; while the database is not open they find nothing.
%% The products that left between two times, from their summaries, chosen in the table.
-spec products_out(integer(), integer()) -> [{integer(), good | failed}].
products_out(From, To) when To < From ->
    [];
products_out(From, To) ->
    Spec = [{{?PRODUCT, '_', #{status => out, left => '$1', failed => '$2'}},
             [{is_integer, '$1'}, {'>=', '$1', From}, {'=<', '$1', To}],
             [{{'$1', '$2'}}]}],
    [{At, case Failed of true -> failed; false -> good end}
     || {At, Failed} <- safe(fun() -> mnesia:dirty_select(?PRODUCT, Spec) end, [])].

safe(Fun, Default) ->
    try Fun()
    catch exit:{aborted, _} -> Default
    end.

now_us() ->
    erlang:system_time(microsecond).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

merge_test() ->
    ?assertEqual(5, merge(add, 2, 3)),
    ?assertEqual(2, merge(min, 2, 3)),
    ?assertEqual(3, merge(max, 2, 3)),
    ?assertEqual(3, merge(set, 2, 3)),
    ?assertEqual(2, merge(first, 2, 3)).

to_drop_test() ->
    Left = [{30, <<"c">>}, {10, <<"a">>}, {20, <<"b">>}],
    ?assertEqual([], to_drop(100, 100, 3, Left)),
    %% 101 records of 3 products over 100: down to 90, one product's worth.
    ?assertEqual([{10, <<"a">>}], to_drop(101, 100, 3, Left)),
    ?assertEqual([{10, <<"a">>}, {20, <<"b">>}, {30, <<"c">>}], to_drop(1000, 100, 3, Left)),
    ?assertEqual([], to_drop(101, 100, 3, [])).

product_summary_test() ->
    Row = #{entered => 5000000, recipe => <<"r">>, failed => true, entry => load},
    ?assertEqual(#{serial => <<"s">>, status => out, recipe => <<"r">>, failed => true,
                   entered => 5000, entry_task => load, left => 7, exit_task => unload},
                 product_summary(<<"s">>, Row, out, {unload, 7000})),
    ?assertMatch(#{recipe := <<>>, failed := false, entered := 0, entry_task := undefined,
                   left := undefined}, product_summary(<<"s">>, #{}, in_cell, undefined)).
-endif.
