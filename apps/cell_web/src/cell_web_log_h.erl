%% @doc `GET /api/log' — the task log (seed 000 §5.1) read back from the daily files,
%% oldest first: `level' (comma-separated: error, warning, silent, brief, verbose),
%% `task' (a source: a task id, `cell', `settings' ...), `from' and `to' (milliseconds
%% or RFC 3339; default the last 24 hours), `offset' and `limit' (1 to 1000, default
%% 200). The answer says whether more lines follow.
-module(cell_web_log_h).
-behaviour(cowboy_handler).

-export([init/2]).

-define(DAY_MS, 86400000).
%% Longest range one request reads: each day is a file to read.
-define(MAX_RANGE_MS, 31 * ?DAY_MS).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, view),
    Qs = cell_web_req:qs(Req),
    Now = os:system_time(millisecond),
    To = default(cell_web_req:time_param(<<"to">>, Qs), Now + 1),
    From = default(cell_web_req:time_param(<<"from">>, Qs), To - ?DAY_MS),
    From < To orelse cell_web_req:fail(400, bad_query, "from must be before to"),
    To - From =< ?MAX_RANGE_MS
        orelse cell_web_req:fail(400, bad_query, "ask for at most 31 days at a time"),
    Limit = cell_web_req:int_param(<<"limit">>, Qs, 200, {1, 1000}),
    Offset = cell_web_req:int_param(<<"offset">>, Qs, 0, {0, 10000000}),
    Q0 = #{from => From, to => To, offset => Offset, limit => Limit + 1},
    Q1 = case cell_web_req:csv_param(<<"level">>, Qs, [error, warning, silent, brief, verbose]) of
             all -> Q0;
             Levels -> Q0#{levels => Levels}
         end,
    Q = case maps:get(<<"task">>, Qs, undefined) of
            undefined -> Q1;
            Source when is_binary(Source), Source =/= <<>> -> Q1#{source => Source};
            _ -> cell_web_req:fail(400, bad_query, "task must name a task or source")
        end,
    Lines = cell_log:query(Q),
    {json, 200, #{<<"lines">> => [cell_web_json:line(L) || L <- lists:sublist(Lines, Limit)],
                  <<"offset">> => Offset, <<"limit">> => Limit, <<"from">> => From,
                  <<"to">> => To, <<"more">> => length(Lines) > Limit}}.

default(undefined, D) -> D;
default(V, _) -> V.
