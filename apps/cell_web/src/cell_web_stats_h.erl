%% @doc `GET /api/statistics' — what the cell can count now: tasks by state, products
%% in the cell, active errors, alarms and warnings, answers given.
%%
%% Production statistics (throughput, cycle times, yield, time per state over a
%% shift) need the statistics records of `Databases/', which the runtime does not
%% keep yet: `production' is null, and says so, until they exist.
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
       <<"production">> => null,
       <<"production_note">> => <<"production statistics (throughput, cycle times, yield) "
                                  "are not recorded yet">>}}.
