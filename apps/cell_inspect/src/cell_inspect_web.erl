%% @doc The inspection blocks on the operator panel, as an extension of the panel
%% (`cell_web_extension', declared in this application's environment): the REST
%% routes of `cell_inspect_web_h', and the messages waiting for an answer sent live to
%% every page (`{"type": "inspect_messages", "messages": [Message]}', the whole list,
%% at connect and at every change) while the page is a member of `cell_inspect_panel'.
%% It implements the callbacks of `cell_web_extension' without naming the behaviour:
%% this application builds and runs without the panel.
-module(cell_inspect_web).

-export([routes/0, feed_join/1, feed_resync/0, feed_info/1, message_json/1]).

%% @doc The panel's routes of the inspection blocks.
-spec routes() -> [{string(), module(), map()}].
routes() ->
    [{"/api/inspect", cell_inspect_web_h, #{what => blocks}},
     {"/api/inspect/messages", cell_inspect_web_h, #{what => messages}},
     {"/api/inspect/messages/answer", cell_inspect_web_h, #{what => answer}},
     {"/api/inspect/parts/:serial", cell_inspect_web_h, #{what => part}}].

%% @doc A page connects: it joins the panel as a message client, when the app runs.
-spec feed_join(pid()) -> {ok, atom(), [map()]} | not_running.
feed_join(Page) ->
    case cell_inspect_panel:join(Page) of
        {ok, Ms} -> {ok, cell_inspect_panel, [page_message(Ms)]};
        {error, not_running} -> not_running
    end.

%% @doc The messages waiting now, for a page's fresh snapshot.
-spec feed_resync() -> [map()].
feed_resync() ->
    [page_message(cell_inspect_panel:messages())].

%% @doc The panel's list of messages, changed, for the page.
-spec feed_info(term()) -> {ok, [map()]} | ignore.
feed_info({cell_inspect_panel, Ms}) -> {ok, [page_message(Ms)]};
feed_info(_) -> ignore.

%% @doc A message waiting on the panel, for the page.
-spec message_json(cell_inspect_panel:message()) -> map().
message_json(M) ->
    cell_web_json:term(M).

page_message(Ms) ->
    #{<<"type">> => <<"inspect_messages">>, <<"messages">> => [message_json(M) || M <- Ms]}.
