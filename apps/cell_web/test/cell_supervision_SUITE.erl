%% Supervision that degrades instead of dying: bursts of restarts of the cell's
%% services leave the node, the panel, the SHDR adapter and the inspection app running,
%% their subscribers attached again and delivering events; a node run that did not end
%% cleanly is told at the next start and counted.
-module(cell_supervision_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([burst_of_event_restarts/1, other_services_restart/1, stop_after_fault_on_the_panel/1,
         unclean_stop_is_told/1]).

-define(APPS, [cell, cell_web, cell_shdr, cell_inspect]).
-define(WAIT_MS, 20000).

all() ->
    %% The last stops and starts the cell application itself.
    [burst_of_event_restarts, other_services_restart, stop_after_fault_on_the_panel,
     unclean_stop_is_told].

init_per_suite(Config) ->
    {ok, _} = application:ensure_all_started(inets),
    Root = filename:join(?config(priv_dir, Config), "root"),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    _ = [application:stop(A) || A <- [cell_inspect, cell_shdr, cell_web, cell, mnesia,
                                       cell_base]],
    _ = [application:load(A) || A <- [cell_base, cell, cell_web, cell_shdr, cell_inspect]],
    ok = application:set_env(cell_base, root, Root),
    Specs = [cell_web_demo_task:spec(Id, <<"Z">>, Lane, self())
             || {Id, Lane} <- [{t1, <<"Front">>}, {t2, <<"Rear">>}]],
    ok = application:set_env(cell, cell_spec, #{name => <<"suite">>, tasks => Specs}),
    ok = application:set_env(cell_web, port, 0),
    ok = application:set_env(cell_shdr, port, 0),
    ok = application:set_env(cell_inspect, blocks, []),
    _ = [{ok, _} = application:ensure_all_started(A) || A <- ?APPS],
    [{root, Root}, {port, cell_web:port()} | Config].

end_per_suite(_Config) ->
    _ = [application:stop(A) || A <- [cell_inspect, cell_shdr, cell_web, cell, mnesia,
                                       cell_base]],
    ok = application:unset_env(cell, cell_spec),
    _ = [application:unset_env(A, port) || A <- [cell_web, cell_shdr]],
    ok.

%% Twenty kills of the event fan-out in a row restart it alone: the tasks and the
%% controller are the same processes. Then eleven kills of the registry (past the
%% controller's own intensity, so its tree is restarted whole once): the apps run on,
%% the panel's feed, its recent lines, the SHDR cache and the inspection app are the
%% same processes, the feed attached again after every kill, a page stays connected
%% and gets events again, and the controller answers.
burst_of_event_restarts(Config) ->
    Same = [cell_web_sup, cell_web_feed, cell_web_recent, cell_shdr_sup, cell_shdr_cache,
            cell_inspect_sup],
    Before = [{N, whereis(N)} || N <- Same],
    {ok, Ws0} = cell_web_client:ws_connect(cell_web_client:new(?config(port, Config)), none),
    {[#{<<"type">> := <<"snapshot">>} | _], Ws} = cell_web_client:ws_next(Ws0, ?WAIT_MS),
    ok = cell_web_feed:join(self()),
    Cell = [whereis(cell_controller_sup), whereis(cell_controller) | task_pids()],
    _ = [restart(cell_events) || _ <- lists:seq(1, 20)],
    ?assertEqual(Cell, [whereis(cell_controller_sup), whereis(cell_controller) | task_pids()]),
    _ = [restart(cell_registry) || _ <- lists:seq(1, 11)],
    ?assertEqual(Before, [{N, whereis(N)} || N <- Same]),
    ok = apps_running(),
    ?assertMatch(#{request := _}, cell_controller:flags()),
    Serial = <<"SUP-1">>,
    ok = cell_events:publish(cell_events:new(item_identifier_read, t1, #{item => Serial})),
    ok = await_feed(Serial),
    ok = await_ws(Serial, Ws),
    ok = cell_web_client:ws_close(Ws).

%% The registry, the alarms and the settings restarted in turn, five times each: the
%% same, and the settings the panel registered are back.
other_services_restart(_Config) ->
    Same = [cell_web_feed, cell_shdr_cache, cell_inspect_sup],
    Before = [{N, whereis(N)} || N <- Same],
    ok = cell_web_feed:join(self()),
    _ = [restart(N) || _ <- lists:seq(1, 5), N <- [cell_registry, cell_alarms, cell_settings]],
    ?assertEqual(Before, [{N, whereis(N)} || N <- Same]),
    ok = apps_running(),
    ?assert(is_boolean(cell_web_settings:get(anonymous_view))),
    %% The events were not restarted by the settings' restart: the feed still has them.
    ok = await_attached(),
    Serial = <<"SUP-2">>,
    ok = cell_events:publish(cell_events:new(item_identifier_read, t1, #{item => Serial})),
    ok = await_feed(Serial).

%% The cell Started, the keeper of the services' tables killed: the controller's tree
%% starts anew and the tasks come back OFF. A page, which stays connected, is shown the
%% alarm saying the cell stopped by itself and why; the operator's Start clears it.
stop_after_fault_on_the_panel(Config) ->
    {ok, Ws0} = cell_web_client:ws_connect(cell_web_client:new(?config(port, Config)), none),
    {[#{<<"type">> := <<"snapshot">>} | _], Ws} = cell_web_client:ws_next(Ws0, ?WAIT_MS),
    ok = cell_controller:start(<<"suite">>),
    ok = cell_web_feed:join(self()),
    ok = restart(cell_service_tables),
    ?assertMatch(#{request := stop, has_alarm := true}, cell_controller:flags()),
    ok = await_ws_text(<<"Cell stopped after an internal fault">>, Ws),
    ok = cell_controller:start(<<"suite">>),
    ?assertEqual({error, not_found}, cell_alarms:get(<<"cell:stopped">>)),
    ok = cell_controller:stop(<<"suite">>),
    ok = cell_web_client:ws_close(Ws).

%% A record left saying the node runs (as a kill leaves it) is told in the log at the
%% next start, counted as an unexpected restart, and shown as the alarm that the cell
%% stopped (by an unexpected restart) until the operator's Start; an orderly stop and
%% start counts a clean one and raises nothing.
unclean_stop_is_told(_Config) ->
    #{clean := C0, unexpected := U0} = cell_stats:node_restarts(),
    Path = filename:join(cell_config:dir(data), "cellrt.run"),
    {ok, Run} = cell_file:read_term(Path),
    ?assert(is_integer(maps:get(running, Run))),
    _ = [ok = application:stop(A) || A <- lists:reverse(?APPS)],
    %% Stopped in order: the record says so.
    ?assertMatch({ok, #{running := false}}, cell_file:read_term(Path)),
    %% As a killed node would leave it.
    ok = cell_file:write_term(Path, Run),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    ok = await_log(<<"the cell restarted after an unexpected stop of the node">>),
    ok = cell_log:unsubscribe(),
    ?assertEqual(#{clean => C0, unexpected => U0 + 1}, cell_stats:node_restarts()),
    {ok, #{caption := <<"Cell stopped by an unexpected restart">>, description := Text}} =
        cell_alarms:get(<<"cell:stopped">>),
    ?assertNotEqual(nomatch, string:find(Text, <<"power cut">>)),
    ok = cell_controller:start(<<"suite">>),
    ?assertEqual({error, not_found}, cell_alarms:get(<<"cell:stopped">>)),
    ok = cell_controller:stop(<<"suite">>),
    ok = application:stop(cell),
    {ok, _} = application:ensure_all_started(cell),
    ?assertEqual(#{clean => C0 + 1, unexpected => U0 + 1}, cell_stats:node_restarts()),
    ?assertEqual({error, not_found}, cell_alarms:get(<<"cell:stopped">>)),
    _ = [{ok, _} = application:ensure_all_started(A) || A <- ?APPS],
    ok.

%% Helpers

%% Kills a service of the controller and waits until its supervisor has started it
%% again; when the events were among those restarted, until the feed is attached again.
restart(Name) ->
    Old = whereis(Name),
    true = is_pid(Old),
    Ref = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', Ref, process, Old, _} -> ok
    after ?WAIT_MS -> ct:fail({not_stopped, Name})
    end,
    ok = supervisors_done(),
    New = whereis(Name),
    ?assert(is_pid(New) andalso New =/= Old, {not_restarted, Name}),
    ok = await_attached().

%% The controller's supervisor handles the exit (it reached it before this call) before
%% it answers: it has restarted the service, or it gave up and is gone, and then its own
%% exit reached cell_sup before this next call, which starts the tree anew first. The
%% services' supervisor, under the controller's, is asked first in the same way.
supervisors_done() ->
    try supervisor:which_children(cell_service_sup) of
        _ -> ok
    catch
        exit:{Gone, _} when Gone =:= shutdown; Gone =:= noproc -> ok
    end,
    try supervisor:which_children(cell_controller_sup) of
        _ -> ok
    catch
        exit:{Why, _} when Why =:= shutdown; Why =:= noproc ->
            _ = supervisor:which_children(cell_sup),
            ok
    end.

%% The feed is subscribed to the events running now: it says so to its pages with a
%% resync once attached; an earlier resync (a message it could not make while the
%% cell's tables came back) is passed over.
await_attached() ->
    case lists:member(whereis(cell_web_feed), subscribers()) of
        true ->
            ok;
        false ->
            receive cell_web_feed_resync -> await_attached()
            after ?WAIT_MS -> ct:fail(feed_not_attached)
            end
    end.

subscribers() ->
    try ets:lookup_element(cell_event_subscribers, item_identifier_read, 2)
    catch error:badarg -> []
    end.

task_pids() ->
    [cell_task_proc:whereis(T) || T <- [t1, t2]].

apps_running() ->
    Running = [A || {A, _, _} <- application:which_applications()],
    ?assertEqual([], ?APPS -- Running),
    ok.

await_feed(Serial) ->
    receive
        {cell_web_feed, Json} ->
            case binary:match(Json, Serial) of
                nomatch -> await_feed(Serial);
                _ -> ok
            end
    after ?WAIT_MS ->
        ct:fail({not_delivered, Serial})
    end.

%% Frames until the event's: snapshots (resyncs) and other changes in between.
await_ws(Serial, Ws) ->
    case cell_web_client:ws_next(Ws, ?WAIT_MS) of
        {Messages, Ws1} when is_list(Messages) ->
            case [E || #{<<"type">> := <<"event">>, <<"event">> := #{<<"item">> := I} = E}
                           <- Messages, I =:= Serial] of
                [] -> await_ws(Serial, Ws1);
                [_ | _] -> ok
            end;
        {Other, _} ->
            ct:fail({websocket, Other})
    end.

%% Frames until one shows the text (an alarm, or a snapshot listing it).
await_ws_text(Text, Ws) ->
    case cell_web_client:ws_next(Ws, ?WAIT_MS) of
        {Messages, Ws1} when is_list(Messages) ->
            case binary:match(jsx:encode(Messages), Text) of
                nomatch -> await_ws_text(Text, Ws1);
                _ -> ok
            end;
        {Other, _} ->
            ct:fail({websocket, Other})
    end.

await_log(Text) ->
    receive
        {cell_log, #{text := Line}} ->
            case binary:match(Line, Text) of
                nomatch -> await_log(Text);
                _ -> ok
            end
    after ?WAIT_MS ->
        ct:fail({not_logged, Text})
    end.
