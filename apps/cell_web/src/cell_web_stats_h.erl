%% @doc `GET /api/statistics' — what the cell can count now (tasks by state, products
%% in the cell, active errors, alarms and warnings, answers given) and the production
%% statistics `cell_stats' keeps in `Databases/': per task the time in each IPC-2541
%% state and the items, for the cell items in, out, good, failed and scrapped, lead
%% and cycle times, throughput per hour.
%%
%% `?period=' chooses the production figures: `shift' (the shift running now, the
%% default) and `total', or one shift by its name, `2024-05-01/2'; the answer always
%% lists the `periods' recorded.
%%
%% `GET /api/statistics/charts' — what the panel's charts draw, for one period
%% (`?period=' as above), a day (`?day=2024-05-01': its shifts) or a range (`?from=',
%% `?to=', milliseconds or RFC 3339, at most 31 days: the shifts it overlaps): each
%% shift's summary as `/api/statistics' has it with its OEE (see
%% {@link cell_web_charts:oee/2}), their sum, products out per hour of the clock and
%% the spread of the cell's cycle times, from the products that left in that time (of
%% a longer span, its last 31 days, from `hourly_from').
-module(cell_web_stats_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts, summary), R, C) end),
     Opts}.

handle(What, Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, view),
    case What of
        summary -> summary(Req);
        charts -> charts(Req)
    end.

summary(Req) ->
    Period = period(maps:get(<<"period">>, cell_web_req:qs(Req), <<"shift">>)),
    Tasks = cell_controller:tasks(),
    ByState = lists:foldl(fun(#{state := S}, Acc) ->
                                  maps:update_with(cell_web_json:state(S), fun(N) -> N + 1 end,
                                                   1, Acc)
                          end, #{}, Tasks),
    Alarms = cell_alarms:list(),
    Count = fun(K) -> length([A || #{kind := Kind} = A <- Alarms, Kind =:= K]) end,
    {json, 200,
     #{<<"time">> => os:system_time(millisecond),
       <<"cell_state">> => cell_web_json:state(cell_controller:state()),
       <<"tasks">> => #{<<"total">> => length(Tasks), <<"by_state">> => ByState},
       <<"products_in_cell">> => length([T || #{serial := S} = T <- Tasks, is_binary(S)]),
       <<"active">> => #{<<"errors">> => Count(error), <<"alarms">> => Count(alarm),
                         <<"warnings">> => Count(warning)},
       <<"answers_recorded">> => length(cell_alarms:history()),
       <<"production">> => cell_web_json:term(cell_stats:summary(Period)),
       <<"periods">> => [label(P) || P <- cell_stats:periods()]}}.

period(<<"shift">>) ->
    cell_stats:shift_now();
period(<<"total">>) ->
    total;
period(Text) ->
    case [P || P <- cell_stats:periods(), label(P) =:= Text] of
        [P] -> P;
        [] -> cell_web_req:fail(404, not_found, ["no statistics for the period ", Text,
                                                 "; see periods"])
    end.

label(total) -> <<"total">>;
label(Shift) -> cell_stats_shift:label(Shift).

-define(DAY_MS, 86400000).
-define(BINS, 12).

charts(Req) ->
    Qs = cell_web_req:qs(Req),
    {Kind, Label, Periods} = selected(Qs),
    Summaries = [cell_stats:summary(P) || P <- Periods],
    Ideal = cell_web_oee_settings:ideal_cycle_ms(),
    Sum = cell_web_charts:add(Summaries),
    {From, To} = case Sum of
                     #{from := null} -> {0, -1};
                     #{from := F, to := T} -> {F, T}
                 end,
    %% Products out of at most the last 31 days: the total of a year would be thousands
    %% of hours and every product kept.
    Since = max(From, To - 31 * ?DAY_MS),
    Exits = cell_stats:products_out(Since, To),
    Cycles = cell_web_charts:cycles(Exits),
    {json, 200,
     cell_web_json:term(
       #{selection => #{kind => Kind, label => Label, from => maps:get(from, Sum),
                        to => maps:get(to, Sum)},
         periods => [label(P) || P <- cell_stats:periods()],
         ideal_cycle_ms => Ideal,
         shifts => [S#{oee => cell_web_charts:oee(S, Ideal)} || S <- Summaries],
         sum => Sum#{oee => cell_web_charts:oee(Sum, Ideal)},
         hourly_from => Since,
         hourly => cell_web_charts:hourly(Exits, Since, To),
         cycles => #{n => length(Cycles), histogram => cell_web_charts:histogram(Cycles, ?BINS)}})}.

%% What the query asks for: a period, a day or a range.
selected(Qs) ->
    case Qs of
        #{<<"day">> := Day} when is_binary(Day) ->
            Date = date_param(Day),
            {day, Day, cell_web_charts:selection({day, Date}, [{P, 0, 0} || P <- shifts()])};
        #{<<"from">> := _} ->
            From = cell_web_req:time_param(<<"from">>, Qs),
            To = case cell_web_req:time_param(<<"to">>, Qs) of
                     undefined -> os:system_time(millisecond);
                     T -> T
                 end,
            From < To orelse cell_web_req:fail(400, bad_query, "from must be before to"),
            To - From =< 31 * ?DAY_MS
                orelse cell_web_req:fail(400, bad_query, "ask for at most 31 days"),
            %% A shift overlapping the range starts on its first day, the day before
            %% (a night shift) or a day within it: only those are read.
            First = add_days(local_date(From), -1),
            Last = local_date(To),
            Near = [P || {D, _} = P <- shifts(), D >= First, D =< Last],
            {range, null, cell_web_charts:selection({range, From, To}, spans(Near))};
        _ ->
            P = period(maps:get(<<"period">>, Qs, <<"shift">>)),
            {period, label(P), [P]}
    end.

date_param(<<Y:4/binary, $-, M:2/binary, $-, D:2/binary>>) ->
    try {binary_to_integer(Y), binary_to_integer(M), binary_to_integer(D)} of
        Date -> case calendar:valid_date(Date) of
                    true -> Date;
                    false -> bad_day()
                end
    catch error:badarg -> bad_day()
    end;
date_param(_) ->
    bad_day().

-spec bad_day() -> no_return().
bad_day() ->
    cell_web_req:fail(400, bad_query, "day must be a date, 2024-05-01").

%% The shifts recorded.
shifts() ->
    [P || P <- cell_stats:periods(), P =/= total].

%% Shifts with their spans.
spans(Shifts) ->
    [{P, F, T} || P <- Shifts, #{from := F, to := T} <- [cell_stats:summary(P)]].

local_date(Ms) ->
    {Date, _} = calendar:system_time_to_local_time(Ms div 1000, second),
    Date.

add_days(Date, N) ->
    calendar:gregorian_days_to_date(calendar:date_to_gregorian_days(Date) + N).

