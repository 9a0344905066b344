%% @doc `/api/machine/actions' — the operator's hand on the simulated machine (see
%% {@link cell_machine_actions}): `GET' lists the actions the cell's simulation offers
%% and where it runs (`local': in the cell's VM; `vplc': in the virtual PLC's process;
%% `none': a real PLC, no actions); `POST' `{"action", "choice"}' carries one out and
%% answers once the machine has taken it. Both need the role service or higher
%% ({@link cell_web_machine_rules}). The panel waits for the machine at most
%% `?DEADLINE_MS': a virtual PLC that is gone or hangs is answered with an error, and
%% the request's process is free again. Every action is in the audit trail and the
%% cell's log, in the operator's words.
-module(cell_web_machine_h).
-behaviour(cowboy_handler).

-export([init/2]).

-define(DEADLINE_MS, 5000).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, #{role := Role} = Caller) ->
    case cowboy_req:method(Req) of
        <<"GET">> ->
            ok = allowed(Role),
            case cell_machine_actions:list() of
                {ok, Where, Actions} ->
                    {json, 200, #{where => where(Where),
                                  actions => cell_machine_actions:json(Actions)}};
                {error, Why} ->
                    fail(Why)
            end;
        <<"POST">> ->
            ok = allowed(Role),
            {Body, _} = cell_web_req:read_json(Req),
            {Action, Choice} = body(Body),
            case cell_machine_actions:run(Action, Choice, ?DEADLINE_MS) of
                {ok, A, C} ->
                    Words = cell_web_machine_rules:words(A, C),
                    cell_log:notice(web, "~ts on the machine: ~ts", [cell_web_req:who_name(Caller), Words]),
                    {json, 200, #{action => Action, choice => Choice, done => Words}, Words};
                {error, Why} ->
                    cell_log:trace(web, "machine action ~ts ~ts not carried out: ~tp",
                                   [Action, Choice, Why]),
                    fail(Why)
            end;
        _ ->
            cell_web_req:fail(405, method_not_allowed, "use GET or POST",
                              #{allow => <<"GET, POST">>})
    end.

allowed(Role) ->
    case cell_web_machine_rules:may_act(Role) of
        ok -> ok;
        {error, S, Code, Words} -> cell_web_req:fail(S, Code, Words)
    end.

-spec fail(cell_machine_actions:failure()) -> no_return().
fail(Why) ->
    {S, Code, Words} = cell_web_machine_rules:refusal(Why),
    cell_web_req:fail(S, Code, Words).

body(#{<<"action">> := A, <<"choice">> := C}) when is_binary(A), is_binary(C) ->
    {A, C};
body(_) ->
    cell_web_req:fail(400, bad_request,
                      "give the action and its choice: {\"action\": ..., \"choice\": ...}").

where(local) -> #{kind => local};
where({vplc, Node, _Cookie}) -> #{kind => vplc, node => Node};
where(none) -> #{kind => none}.
