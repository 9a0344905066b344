%% @doc The inspection blocks (seed 004) on the panel: `GET /api/inspect' — each block's
%% PLC link, InspectionStatus, ErrorCode, MessageStatus and what is under way;
%% `GET /api/inspect/messages' — the PLC messages waiting for an answer on the panel;
%% `POST /api/inspect/messages/answer' with `{"block", "ref", "answer": "yes" | "no" |
%% "text", "text"}' — an operator's answer; `GET /api/inspect/parts/:serial' — the
%% traceability of a part (its inspections and overrides).
%%
%% The panel is a message client of the blocks whose settings say so (see
%% `cell_inspect_panel'); the page gets the messages live over the websocket
%% (`cell_inspect_web'). When the inspection app does not run, the lists are empty and
%% an answer is 404.
%%
%% The panel (`cell_web') serves these routes as an extension (`cell_inspect_web'):
%% the handler runs in the panel's processes and uses its request helpers.
-module(cell_inspect_web_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(blocks, Req, Caller) ->
    get_only(Req),
    _ = cell_web_req:require(Caller, view),
    {json, 200, [block_json(B) || B <- running(fun cell_inspect:blocks/0, [])]};
handle(messages, Req, Caller) ->
    get_only(Req),
    _ = cell_web_req:require(Caller, view),
    {json, 200, [cell_inspect_web:message_json(M)
                 || M <- running(fun cell_inspect_panel:messages/0, [])]};
handle(part, Req, Caller) ->
    get_only(Req),
    _ = cell_web_req:require(Caller, view),
    Serial = cell_web_req:binding(serial, Req),
    case running(fun() -> cell_inspect:traceability(Serial) end, {error, not_running}) of
        {ok, #{inspections := Is, overrides := Os}} ->
            {json, 200, #{<<"serial">> => Serial, <<"inspections">> => Is,
                          <<"overrides">> => Os}};
        {error, _} ->
            cell_web_req:fail(503, not_available, "the inspection records cannot be read now")
    end;
handle(answer, Req0, Caller0) ->
    cowboy_req:method(Req0) =:= <<"POST">>
        orelse cell_web_req:fail(405, method_not_allowed, "use POST", #{allow => <<"POST">>}),
    Caller = cell_web_req:require(Caller0, operator),
    {Body, _Req} = cell_web_req:read_json(Req0),
    Block = text_field(<<"block">>, Body),
    Ref = text_field(<<"ref">>, Body),
    Answer = case maps:get(<<"answer">>, Body, undefined) of
                 <<"yes">> -> yes;
                 <<"no">> -> no;
                 <<"text">> -> {text, text_field(<<"text">>, Body)};
                 _ -> cell_web_req:fail(400, bad_request,
                                        "answer must be \"yes\", \"no\" or \"text\"")
             end,
    Detail = <<Block/binary, " ", Ref/binary, " ", (maps:get(<<"answer">>, Body))/binary>>,
    Who = cell_web_req:who_name(Caller),
    case running(fun() -> cell_inspect_panel:answer(Block, Ref, Answer, Who) end,
                 {error, not_running}) of
        ok ->
            {json, 200, #{<<"block">> => Block, <<"ref">> => Ref}, Detail};
        {error, no_such_message} ->
            cell_web_req:fail(404, not_found, "this message is no longer waiting for an answer",
                              #{detail => Detail});
        {error, not_running} ->
            cell_web_req:fail(404, not_found, "no inspection block runs", #{detail => Detail});
        {error, {bad_answer, Kind}} ->
            cell_web_req:fail(422, answer_not_offered,
                              ["this message does not offer that answer (it asks for ",
                               atom_to_binary(Kind), ")"], #{detail => Detail});
        {error, {too_long, Max}} ->
            cell_web_req:fail(422, text_too_long,
                              ["the PLC holds at most ", integer_to_binary(Max), " characters"],
                              #{detail => Detail});
        {error, not_latin1} ->
            cell_web_req:fail(422, text_not_writable,
                              "the PLC cannot hold some of these characters", #{detail => Detail});
        {error, Why} ->
            cell_web_req:fail(409, not_answered,
                              ["the answer was not taken: ", not_taken(Why)],
                              #{detail => Detail})
    end.

%% Words for the rest of the refusals (a block that went away, a call that timed
%% out); the reason itself goes to the trace log.
not_taken(not_shown_to_client) -> "this message was not shown on the panel";
not_taken({noproc, _}) -> "the inspection block stopped meanwhile";
not_taken({timeout, _}) -> "the inspection block did not answer in time";
not_taken(Why) ->
    cell_log:trace(web, "an answer to an inspection message was not taken: ~0tP", [Why, 30]),
    "the inspection block refused it; the trace log says why".

%% The inspection app is temporary and may not run: then its processes are absent.
running(Fun, Default) ->
    case whereis(cell_inspect_sup) of
        undefined -> Default;
        _ -> Fun()
    end.

get_only(Req) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}).

text_field(Key, Body) ->
    case maps:get(Key, Body, undefined) of
        V when is_binary(V) -> V;
        _ -> cell_web_req:fail(400, bad_request, [Key, " must be a string"])
    end.

block_json(B) ->
    cell_web_json:term(maps:update_with(message, fun(undefined) -> undefined;
                                                    (M) -> maps:without([ref], M)
                                                 end, B)).
