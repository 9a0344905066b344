%% @doc `GET /api/audit' — the audit trail (see {@link cell_web_audit}), oldest first:
%% `from', `to' (milliseconds or RFC 3339; default the last 24 hours), `who',
%% `action' (the method: POST, PUT, DELETE), `offset', `limit' (1 to 1000). Service
%% and admin read it.
-module(cell_web_audit_h).
-behaviour(cowboy_handler).

-export([init/2]).

-define(DAY_MS, 86400000).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, service),
    Qs = cell_web_req:qs(Req),
    Now = os:system_time(millisecond),
    To = case cell_web_req:time_param(<<"to">>, Qs) of undefined -> Now + 1; T -> T end,
    From = case cell_web_req:time_param(<<"from">>, Qs) of undefined -> To - ?DAY_MS; F -> F end,
    From < To orelse cell_web_req:fail(400, bad_query, "from must be before to"),
    To - From =< 31 * ?DAY_MS orelse cell_web_req:fail(400, bad_query, "ask for at most 31 days"),
    Limit = cell_web_req:int_param(<<"limit">>, Qs, 200, {1, 1000}),
    Offset = cell_web_req:int_param(<<"offset">>, Qs, 0, {0, 10000000}),
    Q = maps:merge(#{from => From, to => To, offset => Offset, limit => Limit + 1},
                   maps:from_list([{K, V} || {KB, K} <- [{<<"who">>, who}, {<<"action">>, action}],
                                             V <- [maps:get(KB, Qs, undefined)], is_binary(V)])),
    Entries = cell_web_audit:query(Q),
    {json, 200, #{<<"entries">> => lists:sublist(Entries, Limit), <<"offset">> => Offset,
                  <<"limit">> => Limit, <<"more">> => length(Entries) > Limit}}.
