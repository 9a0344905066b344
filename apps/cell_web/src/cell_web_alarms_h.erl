%% @doc `/api/alarms' — the active errors, alarms and warnings (seed 000 §2.3.8);
%% `/api/alarms/history' — recent answers, closes and clears; `POST
%% /api/alarms/:id/answer' with `{"solution": "retry"}' — an operator's answer, only
%% one of the error's own solutions (a warning's only solution is `close'). An answer
%% that would let a task go on with a product another task holds too is refused with
%% 409 `double_holding', naming the serial and the other tasks; the error stays. One
%% that cannot be recorded in the product trace is refused with 503 `not_recorded'.
-module(cell_web_alarms_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(list, Req, Caller) ->
    get_only(Req),
    _ = cell_web_req:require(Caller, view),
    {json, 200, [cell_web_json:alarm(A) || A <- cell_alarms:list()]};
handle(history, Req, Caller) ->
    get_only(Req),
    _ = cell_web_req:require(Caller, view),
    {json, 200, [cell_web_json:alarm_record(R) || R <- cell_alarms:history()]};
handle(answer, Req0, Caller0) ->
    cowboy_req:method(Req0) =:= <<"POST">>
        orelse cell_web_req:fail(405, method_not_allowed, "use POST", #{allow => <<"POST">>}),
    Caller = cell_web_req:require(Caller0, operator),
    Id = cell_web_req:binding(id, Req0),
    {Body, _Req} = cell_web_req:read_json(Req0),
    Solution = solution(maps:get(<<"solution">>, Body, undefined)),
    Alarm = case cell_alarms:get(Id) of
                {ok, A} -> A;
                {error, not_found} -> cell_web_req:fail(404, not_found, ["there is no active error ", Id])
            end,
    Who = cell_web_req:who_name(Caller),
    Result = case {maps:get(kind, Alarm), Solution} of
                 {warning, close} -> cell_alarms:close(Id, Who);
                 {warning, _} -> {error, {not_allowed, [close]}};
                 {error, _} -> cell_alarms:answer(Id, Solution, Who);
                 {alarm, _} -> {error, {not_allowed, []}}
             end,
    Detail = <<Id/binary, " ", (atom_to_binary(Solution, utf8))/binary>>,
    case Result of
        ok ->
            {json, 200, #{<<"id">> => Id, <<"solution">> => atom_to_binary(Solution, utf8)},
             Detail};
        {error, not_found} ->
            cell_web_req:fail(404, not_found, ["the error ", Id, " was answered already"]);
        {error, {double_holding, Serial, Others}} ->
            Names = [atom_to_binary(O, utf8) || O <- Others],
            cell_web_req:fail(409, double_holding,
                              [Id, " not answered with ", atom_to_binary(Solution, utf8),
                               ": product ", Serial, " is held by ", lists:join(", ", Names),
                               " too. Check where it is and select RESET on the error of the "
                               "task where it is not"],
                              #{serial => Serial, held_by => Names, detail => Detail});
        {error, {not_recorded, Why}} ->
            cell_web_req:fail(503, not_recorded,
                              [Id, " not answered: the answer could not be recorded in the "
                               "product trace (", recorded_why(Why), "). Check the "
                               "disc of the cell PC, then answer again"],
                              #{detail => Detail});
        {error, {not_allowed, Allowed}} ->
            cell_web_req:fail(422, solution_not_allowed,
                              [Id, " does not offer ", atom_to_binary(Solution, utf8)],
                              #{allowed => Allowed, detail => Detail})
    end.

recorded_why({file, _, R}) when is_atom(R) -> file:format_error(R);
recorded_why(R) when is_atom(R) -> file:format_error(R);
recorded_why(Why) ->
    cell_log:trace(web, "an answer could not be recorded in the product trace: ~0tP", [Why, 30]),
    "the trace log says why".

get_only(Req) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}).

solution(Bin) when is_binary(Bin) ->
    case [S || S <- cell_alarms:solutions(), atom_to_binary(S, utf8) =:= Bin] of
        [S] -> S;
        [] -> bad_solution()
    end;
solution(_) ->
    bad_solution().

-spec bad_solution() -> no_return().
bad_solution() ->
    cell_web_req:fail(400, bad_request,
                      "solution must be one of \"retry\", \"ignore\", \"reset\", \"close\"").
