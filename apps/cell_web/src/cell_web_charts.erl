%% @doc What the panel's statistics charts show, as pure functions of what the
%% statistics keep: the production summaries of {@link cell_stats:summary/1} and the
%% times products left the cell.
%%
%% <ul>
%% <li>{@link selection/2} — the shifts a day or a time range covers.</li>
%% <li>{@link add/1} — several shifts' summaries added up: time per task and state,
%%     items in, out, good, failed, scrapped.</li>
%% <li>{@link hourly/3} — products out per hour of the clock.</li>
%% <li>{@link cycles/1} and {@link histogram/2} — the cell's cycle times (between two
%%     products out) and how they are spread.</li>
%% <li>{@link oee/2} — availability × performance × quality of one summary, by the
%%     definitions written on the panel's statistics page.</li>
%% </ul>
-module(cell_web_charts).

-export([selection/2, add/1, hourly/3, cycles/1, histogram/2, oee/2]).

-export_type([exit/0]).

%% A product that left the cell: when (ms since the epoch) and whether it was good.
-type exit() :: {integer(), good | failed}.

-define(HOUR_MS, 3600000).
-define(STATES, [executing, active, starved, blocked, setup, down, off]).

%% @doc Of the shifts recorded (each with its span in ms since the epoch), those a
%% selection covers: `{day, Date}' the shifts that start on that date, `{range, From,
%% To}' those whose span overlaps it. Kept in their order.
-spec selection({day, calendar:date()} | {range, integer(), integer()},
                [{cell_stats_shift:id(), integer(), integer()}]) ->
          [cell_stats_shift:id()].
selection({day, Date}, Shifts) ->
    [Id || {{D, _} = Id, _, _} <- Shifts, D =:= Date];
selection({range, From, To}, Shifts) ->
    [Id || {Id, S, E} <- Shifts, S < To, E > From].

%% @doc Summaries added up: per task the time in each state (ms) and the items; for
%% the cell in, out, good, failed, scrapped; the span from the first to the last.
-spec add([map()]) -> map().
add([]) ->
    #{from => null, to => null, tasks => #{},
      cell => #{in => 0, out => 0, good => 0, failed => 0, scrapped => 0}};
add(Summaries) ->
    Cell = lists:foldl(
             fun(#{cell := C}, Acc) ->
                     maps:map(fun(K, V) -> V + maps:get(K, C, 0) end, Acc)
             end, #{in => 0, out => 0, good => 0, failed => 0, scrapped => 0}, Summaries),
    Tasks = lists:foldl(
              fun(#{tasks := Ts}, Acc) ->
                      maps:fold(fun(Id, T, A) ->
                                        Old = maps:get(Id, A, #{}),
                                        A#{Id => add_task(Old, T)}
                                end, Acc, Ts)
              end, #{}, Summaries),
    #{from => lists:min([F || #{from := F} <- Summaries]),
      to => lists:max([T || #{to := T} <- Summaries]),
      tasks => Tasks, cell => Cell}.

add_task(Old, #{time_ms := Time} = T) ->
    OldTime = maps:get(time_ms, Old, #{}),
    NewTime = maps:fold(fun(S, V, Acc) -> maps:update_with(S, fun(X) -> X + V end, V, Acc) end,
                        OldTime, Time),
    #{time_ms => NewTime,
      out => maps:get(out, Old, 0) + maps:get(out, T, 0),
      in => maps:get(in, Old, 0) + maps:get(in, T, 0)}.

%% @doc Products out per hour of the clock from the hour `From' falls in to the hour
%% `To' falls in: `[#{start, out, good, failed}]', oldest first. Exits outside the
%% span are not counted.
-spec hourly([exit()], integer(), integer()) -> [map()].
hourly(_Exits, From, To) when To < From ->
    [];
hourly(Exits, From, To) ->
    First = From - floor_mod(From, ?HOUR_MS),
    Hours = (To - First) div ?HOUR_MS + 1,
    Empty = maps:from_list([{First + I * ?HOUR_MS, {0, 0}} || I <- lists:seq(0, Hours - 1)]),
    Counted = lists:foldl(
                fun({At, Quality}, Acc) when At >= From, At =< To ->
                        H = At - floor_mod(At, ?HOUR_MS),
                        {G, F} = maps:get(H, Acc),
                        case Quality of
                            good -> Acc#{H := {G + 1, F}};
                            failed -> Acc#{H := {G, F + 1}}
                        end;
                   (_, Acc) ->
                        Acc
                end, Empty, Exits),
    [#{start => H, out => G + F, good => G, failed => F}
     || {H, {G, F}} <- lists:sort(maps:to_list(Counted))].

floor_mod(X, M) ->
    ((X rem M) + M) rem M.

%% @doc The cell's cycle times (ms): the time between two products out, in the order
%% they left.
-spec cycles([exit()]) -> [non_neg_integer()].
cycles(Exits) ->
    Times = lists:sort([At || {At, _} <- Exits]),
    case Times of
        [] -> [];
        [_ | Rest] -> [B - A || {A, B} <- lists:zip(lists:droplast(Times), Rest)]
    end.

%% @doc How cycle times are spread: at most `Bins' bins of equal width (a whole
%% number of ms, at least 1) from the shortest to the longest, each with its count;
%% the last bin includes its upper end.
-spec histogram([non_neg_integer()], pos_integer()) -> [map()].
histogram([], _Bins) ->
    [];
histogram(Values, Bins) ->
    Min = lists:min(Values),
    Max = lists:max(Values),
    Width = max(1, ceil_div(Max - Min + 1, Bins)),
    N = (Max - Min) div Width + 1,
    Counts = lists:foldl(fun(V, Acc) ->
                                 I = min((V - Min) div Width, N - 1),
                                 maps:update_with(I, fun(C) -> C + 1 end, Acc)
                         end, maps:from_list([{I, 0} || I <- lists:seq(0, N - 1)]), Values),
    [#{from => Min + I * Width, to => Min + (I + 1) * Width, count => C}
     || {I, C} <- lists:sort(maps:to_list(Counts))].

ceil_div(A, B) -> (A + B - 1) div B.

%% @doc The OEE of one summary, with the ideal cycle time in ms:
%% <ul>
%% <li>planned time: each task's time not OFF, averaged over the tasks;</li>
%% <li>run time: the planned time less the time DOWN or in SETUP, averaged alike;</li>
%% <li>availability = run time / planned time;</li>
%% <li>performance = ideal cycle time × products out / run time;</li>
%% <li>quality = good / out.</li>
%% </ul>
%% A factor that cannot be known (no planned time, nothing out) is `null', and so is
%% the OEE then.
-spec oee(map(), number()) -> map().
oee(#{tasks := Tasks, cell := Cell}, IdealMs) ->
    N = map_size(Tasks),
    {Planned, Run} = maps:fold(
                       fun(_, #{time_ms := T}, {P, R}) ->
                               Get = fun(S) -> maps:get(S, T, 0) end,
                               Pl = lists:sum([Get(S) || S <- ?STATES]) - Get(off),
                               {P + Pl, R + Pl - Get(down) - Get(setup)}
                       end, {0, 0}, Tasks),
    PlannedMs = case N of 0 -> 0; _ -> Planned / N end,
    RunMs = case N of 0 -> 0; _ -> Run / N end,
    Out = maps:get(out, Cell, 0),
    Good = maps:get(good, Cell, 0),
    A = ratio(RunMs, PlannedMs),
    P = ratio(IdealMs * Out, RunMs),
    Q = ratio(Good, Out),
    #{planned_ms => round(PlannedMs), run_ms => round(RunMs), ideal_cycle_ms => IdealMs,
      out => Out, good => Good, availability => A, performance => P, quality => Q,
      oee => case lists:member(null, [A, P, Q]) of
                 true -> null;
                 false -> round4(A * P * Q)
             end}.

ratio(_, D) when D == 0 -> null;
ratio(N, D) -> round4(N / D).

round4(X) -> round(X * 10000) / 10000.
