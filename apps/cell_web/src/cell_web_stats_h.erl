%% @doc `GET /api/statistics' — what the cell can count now (tasks by state, products
%% in the cell, active errors, alarms and warnings, answers given) and the production
%% statistics `cell_stats' keeps in `Databases/': per task the time in each IPC-2541
%% state and the items, for the cell items in, out, good, failed and scrapped, lead
%% and cycle times, throughput per hour.
%%
%% `?period=' chooses the production figures: `shift' (the shift running now, the
%% default) and `total', or one shift by its name, `2024-05-01/2'; the answer always
%% lists the `periods' recorded.
-module(cell_web_stats_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, view),
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
