%% The operator panel as a message client of an inspection block, through its REST
%% API: roles and CSRF as the panel has them, every refusal with its status, the
%% answer reaching the PLC (a simulated one here), and the audit trail naming who
%% answered. The page itself is tested in test/browser/inspect.test.mjs.
-module(cell_inspect_web_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([blocks_and_parts/1, answer_needs_an_operator_and_csrf/1, answers/1,
         texts_the_plc_cannot_hold/1]).

-define(WAIT, 15000).

all() ->
    [blocks_and_parts, answer_needs_an_operator_and_csrf, answers, texts_the_plc_cannot_hold].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    Root = filename:join(?config(priv_dir, Config), "root"),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    _ = [application:stop(A) || A <- [cell_inspect, cell_web, cell_shdr, cell, cell_hal,
                                      cell_base, mnesia]],
    _ = [application:load(A) || A <- [cell_base, cell, cell_web, cell_inspect]],
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, #{name => <<"inspect web">>, tasks => []}),
    ok = application:set_env(cell_web, port, 0),
    ok = application:set_env(cell_inspect, connections,
                             [#{id => plc, driver => cell_hal_sim, opts => #{poll_ms => 10}}]),
    ok = application:set_env(cell_inspect, blocks,
                             [#{id => line1, connection => plc, io => #{layout => s7}}]),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = cell_inspect_settings:register(),
    ok = cell_settings:put(inspect, #{blocks => [#{id => <<"line1">>, panel_messages => true,
                                                  messages => [#{id => 7, text => <<"OK?">>,
                                                                 kind => yes_no},
                                                               #{id => 8, text => <<"Lot">>,
                                                                 kind => text}]}]},
                           <<"suite">>),
    {ok, _} = application:ensure_all_started(cell_inspect),
    ok = cell_inspect:subscribe(),
    ok = await_view(fun(#{plc := Plc, status := S}) -> Plc =:= up andalso S =:= ready end,
                    erlang:monotonic_time(millisecond) + ?WAIT),
    [{port, cell_web:port()} | Config].

end_per_suite(_Config) ->
    _ = [application:stop(A) || A <- [cell_inspect, cell_web, cell, cell_hal, cell_base,
                                      mnesia]],
    ok = application:unset_env(cell, cell_spec),
    ok.

%%--------------------------------------------------------------------

blocks_and_parts(Config) ->
    {200, [B], _} = req(Config, anonymous, get, "/api/inspect", none),
    ?assertMatch(#{<<"id">> := <<"line1">>, <<"status">> := <<"ready">>,
                   <<"plc">> := <<"up">>, <<"layout">> := <<"s7">>,
                   <<"message_status">> := <<"ready">>}, B),
    {200, #{<<"serial">> := <<"SN 1">>, <<"inspections">> := [], <<"overrides">> := []}, _} =
        req(Config, anonymous, get, "/api/inspect/parts/SN%201", none),
    {405, _, _} = req(Config, anonymous, post, "/api/inspect", #{}).

answer_needs_an_operator_and_csrf(Config) ->
    Body = #{block => <<"line1">>, ref => <<"1.1">>, answer => <<"yes">>},
    {401, #{<<"error">> := <<"login_required">>}, _} =
        req(Config, anonymous, post, "/api/inspect/messages/answer", Body),
    Op = login(Config, "operator"),
    {403, #{<<"error">> := <<"bad_csrf_token">>}, _} =
        req(Config, Op#{csrf := undefined}, post, "/api/inspect/messages/answer", Body),
    {404, #{<<"error">> := <<"not_found">>}, _} =
        req(Config, Op, post, "/api/inspect/messages/answer", Body),
    {400, _, _} = req(Config, Op, post, "/api/inspect/messages/answer", Body#{answer => <<"maybe">>}).

%% The suite's process is a panel page: the panel is a connected client of line1.
answers(Config) ->
    Op = login(Config, "operator"),
    {ok, []} = cell_inspect_panel:join(self()),
    ok = await_clients([<<"panel">>]),
    ok = send_message(7),
    [#{ref := Ref, kind := yes_no, max_length := 48}] = panel_messages(),
    {200, [#{<<"ref">> := Ref, <<"text">> := <<"OK?">>}], _} =
        req(Config, anonymous, get, "/api/inspect/messages", none),
    Path = "/api/inspect/messages/answer",
    {422, #{<<"error">> := <<"answer_not_offered">>}, _} =
        req(Config, Op, post, Path, #{block => <<"line1">>, ref => Ref, answer => <<"text">>,
                                      text => <<"x">>}),
    {404, _, _} = req(Config, Op, post, Path, #{block => <<"line1">>, ref => <<"9.9">>,
                                                 answer => <<"yes">>}),
    {404, _, _} = req(Config, Op, post, Path, #{block => <<"line2">>, ref => Ref,
                                                 answer => <<"yes">>}),
    {200, _, _} = req(Config, Op, post, Path, #{block => <<"line1">>, ref => Ref,
                                                 answer => <<"yes">>}),
    ok = await(message_status, 5),
    [] = panel_messages(),
    Entries = cell_web_audit:query(#{action => <<"POST">>}),
    ?assert(lists:any(fun(#{who := <<"operator">>, target := <<"/api/inspect/messages/answer">>,
                            outcome := <<"200">>, detail := D}) ->
                              binary:match(D, Ref) =/= nomatch;
                         (_) -> false
                      end, Entries)).

texts_the_plc_cannot_hold(Config) ->
    Op = login(Config, "operator"),
    {ok, _} = cell_inspect_panel:join(self()),
    ok = await_clients([<<"panel">>]),
    ok = send_message(8),
    [#{ref := Ref}] = panel_messages(),
    Path = "/api/inspect/messages/answer",
    Answer = fun(T) -> req(Config, Op, post, Path, #{block => <<"line1">>, ref => Ref,
                                                      answer => <<"text">>, text => T}) end,
    {422, #{<<"error">> := <<"text_too_long">>}, _} = Answer(binary:copy(<<"x">>, 49)),
    {422, #{<<"error">> := <<"text_not_writable">>}, _} = Answer(<<"5 €"/utf8>>),
    {200, _, _} = Answer(<<"Grün 48"/utf8>>),
    ok = await(message_result, <<"Grün 48"/utf8>>),
    ok = await(message_status, 5).

%%--------------------------------------------------------------------

%% The simulated PLC sends a message with the echo handshake.
send_message(Id) ->
    ok = cell_hal_sim:set({line1, message_id}, Id),
    ok = await(message_id_echo, Id),
    ok = cell_hal_sim:set({line1, send_message}, true),
    ok = await(send_message_echo, true),
    ok = cell_hal_sim:set({line1, send_message}, false),
    await(send_message_echo, false).

%% The panel's list as the page gets it, once it holds the message just sent.
panel_messages() ->
    receive {cell_inspect_panel, Ms} -> flush_panel(Ms)
    after ?WAIT -> ct:fail(no_panel_message)
    end.

flush_panel(Last) ->
    receive {cell_inspect_panel, Ms} -> flush_panel(Ms)
    after 0 -> Last
    end.

io() ->
    {ok, Io} = cell_inspect_io:check_opts(#{layout => s7}),
    Io.

%% Waits until the block holds an output at a value (the HAL tells subscribers of an
%% output each commanded value).
await(Tag, Value) ->
    {ok, Points} = cell_hal:points(line1),
    Outputs = [N || #{name := N, dir := out} <- Points],
    _ = [ok = cell_hal:subscribe(line1, P) || P <- Outputs],
    Result = await(Tag, Value, erlang:monotonic_time(millisecond) + ?WAIT),
    _ = [ok = cell_hal:unsubscribe(line1, P) || P <- Outputs],
    Result.

await(Tag, Value, Deadline) ->
    case cell_inspect_io:read(io(), line1, Tag) of
        {ok, Value} -> ok;
        Other ->
            receive {cell_hal, {line1, _}, _} -> await(Tag, Value, Deadline)
            after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                    ct:fail({not_written, Tag, Value, Other})
            end
    end.

await_clients(Clients) ->
    ok = cell_inspect:subscribe(),
    await_view(fun(#{clients := Cs}) -> Clients -- Cs =:= [] end,
               erlang:monotonic_time(millisecond) + ?WAIT).

%% Waits for line1's view to satisfy `Cond' (the caller is subscribed to changes).
await_view(Cond, Deadline) ->
    Now = case cell_inspect:block(line1) of
              {ok, V} -> Cond(V);
              {error, _} -> false
          end,
    case Now of
        true -> ok;
        false ->
            receive {cell_inspect, view, _} -> await_view(Cond, Deadline)
            after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                    ct:fail({view_never, cell_inspect:block(line1)})
            end
    end.

login(Config, User) ->
    {200, #{<<"csrf">> := Csrf}, Headers} =
        req(Config, anonymous, post, "/api/session",
            #{user => list_to_binary(User), password => list_to_binary(User)}),
    [Cookie | _] = [hd(string:split(V, ";")) || {"set-cookie", V} <- Headers],
    #{cookie => Cookie, csrf => Csrf}.

req(Config, Who, Method, Path, Body) ->
    Url = "http://127.0.0.1:" ++ integer_to_list(?config(port, Config)) ++ Path,
    Headers = case Who of
                  anonymous -> [];
                  #{cookie := C, csrf := undefined} -> [{"cookie", C}];
                  #{cookie := C, csrf := T} -> [{"cookie", C}, {"x-csrf-token", binary_to_list(T)}]
              end,
    Request = case Body of
                  none -> {Url, Headers};
                  _ -> {Url, Headers, "application/json", jsx:encode(Body)}
              end,
    {ok, {{_, Status, _}, RespHeaders, RespBody}} =
        httpc:request(Method, Request, [{timeout, 30000}], [{body_format, binary}]),
    Decoded = case lists:keyfind("content-type", 1, RespHeaders) of
                  {_, "application/json" ++ _} -> jsx:decode(RespBody, [return_maps]);
                  _ -> RespBody
              end,
    {Status, Decoded, RespHeaders}.
