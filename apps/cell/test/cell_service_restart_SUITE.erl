%% A restart of a service of the controller (the events, the alarms, the settings) does
%% not stop the cell. A line of four segments runs products and a side line holds an
%% error waiting for the operator; each service is killed three times, then in a burst
%% of ten: the tasks, the handshake links, the monitor and the controller are the same
%% processes, the cell is still Started, products keep leaving, the subscribers still
%% get events, the error is still listed and the operator's answer still reaches its
%% task.
%%
%% A fault below the controller that restarts the tasks with it (the keeper of the
%% services' tables, the product journal, the registry) stops the cell: it says so, with
%% a request event and the alarm `cell:stopped' naming the cause and what to do, until
%% the operator's Start clears it and the line goes on.
-module(cell_service_restart_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([events_restart/1, alarms_restart/1, settings_restart/1, all_services_restart/1,
         tables_keeper_killed_is_told/1, journal_killed_is_told/1,
         registry_killed_is_told/1]).

-define(TASKS, [src, a, b, sink, jsrc, jam]).
-define(LINKS, [l1, l2, l3, lj]).
-define(JAM, <<"jam:jam">>).
-define(TIMEOUT, 20000).
-define(STOPPED, <<"cell:stopped">>).

all() ->
    [events_restart, alarms_restart, settings_restart, all_services_restart,
     tables_keeper_killed_is_told, journal_killed_is_told, registry_killed_is_told].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Feed = ets:new(feed, [ordered_set, public]),
    JamFeed = ets:new(jam_feed, [ordered_set, public]),
    Out = ets:new(out, [set, public]),
    Ref = make_ref(),
    true = ets:insert(JamFeed, {1, <<"J-1">>}),
    Config1 = [{feed, Feed}, {ref, Ref} | Config],
    %% The jam sticks a product on its way in: it needs a move that takes time.
    Segment = fun(Id, Prev, Next, F, R, Extra) ->
                      #{id => Id, module => cell_line_task, zone => atom_to_binary(Id, utf8),
                        lane => <<"Front">>,
                        args => maps:merge(#{prev => Prev, next => Next, feed => F,
                                             out => Out, ref => R, notify => self(),
                                             delay => 0, phases => false}, Extra)}
              end,
    Tasks = [Segment(src, undefined, l1, Feed, Ref, #{}),
             Segment(a, l1, l2, Feed, Ref, #{}),
             Segment(b, l2, l3, Feed, Ref, #{}),
             Segment(sink, l3, undefined, Feed, Ref, #{}),
             Segment(jsrc, undefined, lj, JamFeed, make_ref(), #{}),
             Segment(jam, lj, undefined, JamFeed, make_ref(), #{jam => true, delay => 10})],
    Links = [#{id => l1, from => src, to => a}, #{id => l2, from => a, to => b},
             #{id => l3, from => b, to => sink}, #{id => lj, from => jsrc, to => jam}],
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, #{tasks => Tasks, links => Links}),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe([item_transfer_out, alarm_raised]),
    ok = cell_controller:start(),
    ok = await_alarm(?JAM),
    ok = flowing(Config1),
    Config1.

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok.

%% -------------------------------------------------------------------------------------

events_restart(Config) ->
    survives([cell_events], 10, Config).

alarms_restart(Config) ->
    survives([cell_alarms], 10, Config).

settings_restart(Config) ->
    survives([cell_settings], 10, Config).

%% The three in turn, and the recipe buffer and the peers with them: fifteen restarts,
%% within the services' supervisor's intensity (twenty a minute).
all_services_restart(Config) ->
    survives([cell_events, cell_alarms, cell_settings, cell_recipe_buffer, cell_peers], 0,
             Config).

%% The keeper of the services' tables dies with the cell Started and products in it:
%% the services start from empty tables, and the tasks again, OFF.
tables_keeper_killed_is_told(Config) ->
    stopped_and_told(cell_service_tables, <<"services">>, Config).

%% The product journal dies: the services restart with their tables (a subscriber
%% keeps its subscription), so the request event reaches it too.
journal_killed_is_told(Config) ->
    ok = cell_events:subscribe([item_transfer_out, alarm_raised, alarm_cleared, request]),
    stopped_and_told(cell_trace_journal, <<"services">>, Config),
    %% The event was sent as the controller came back, before the checks above.
    receive
        {cell_event, #{type := request, request := stop, who := <<"cell">>, cause := _}} -> ok
    after 0 -> ct:fail(no_request_event)
    end.

%% The registry dies: the whole controller's tree starts anew from a fresh registry,
%% which still knows the cell ran.
registry_killed_is_told(Config) ->
    stopped_and_told(cell_registry, <<"task registry">>, Config).

stopped_and_told(Name, Cause, Config) ->
    %% The controller's tree has been started again by then, the controller too.
    _ = kill_under(Name, cell_controller_sup),
    ?assertMatch(#{request := stop, has_alarm := true}, cell_controller:flags()),
    ?assert(lists:all(fun(S) -> S =:= off end, task_states()), task_states()),
    {ok, #{kind := alarm, task := cell, caption := <<"Cell stopped after an internal fault">>,
           description := Text}} = cell_alarms:get(?STOPPED),
    [?assertNotEqual(nomatch, binary:match(Text, Words), {Words, Text})
     || Words <- [Cause, <<"press Start">>, <<"Check the machine">>]],
    %% The products are where their files say: the jammed one still at its task.
    ?assertMatch(#{product := #{serial := <<"J-1">>}}, cell_task_proc:info(jam)),
    %% A second restart of the controller (not of the tasks) before Start: still told.
    restart_controller(),
    ?assertMatch({ok, #{kind := alarm}}, cell_alarms:get(?STOPPED)),
    %% Start clears it, and the line goes on.
    ok = cell_events:subscribe([item_transfer_out, alarm_raised, alarm_cleared, request]),
    ok = cell_controller:start(<<"suite">>),
    receive
        {cell_event, #{type := alarm_cleared, alarm := #{id := ?STOPPED}}} -> ok
    after ?TIMEOUT -> ct:fail({not_cleared, cell_alarms:list()})
    end,
    ?assertEqual({error, not_found}, cell_alarms:get(?STOPPED)),
    ?assertEqual(undefined, cell_registry:stopped()),
    ok = flowing(Config).

restart_controller() ->
    _ = kill_under(cell_controller, cell_controller_sup),
    ?assert(is_pid(whereis(cell_controller))),
    ?assertMatch(#{request := stop}, cell_controller:flags()).

%% -------------------------------------------------------------------------------------

%% Three rounds of one kill of each service, checked after each; then a burst of
%% `Burst' kills of each in a row.
survives(Services, Burst, Config) ->
    Cell = cell(),
    Settings = cell_settings:names(),
    _ = [begin restart(S), ok = check(Cell, Settings, Config) end
         || _ <- lists:seq(1, 3), S <- Services],
    _ = [restart(S) || S <- Services, _ <- lists:seq(1, Burst)],
    ok = check(Cell, Settings, Config),
    %% The error waited through it all, and its answer reaches the task: the jammed
    %% product arrives and leaves.
    ok = cell_alarms:answer(?JAM, retry, <<"suite">>),
    receive {line_out, jam, <<"J-1">>} -> ok
    after ?TIMEOUT -> ct:fail(answer_not_delivered)
    end,
    ?assertEqual({error, not_found}, cell_alarms:get(?JAM)),
    ?assertEqual(Cell, cell()).

%% The processes that must not notice a service's restart.
cell() ->
    #{tasks => [cell_task_proc:whereis(T) || T <- ?TASKS],
      links => [cell_handshake_link:whereis(L) || L <- ?LINKS],
      others => [whereis(N) || N <- [cell_monitor, cell_controller, cell_task_sup,
                                     cell_handshake_sup, cell_stats]]}.

check(Cell, Settings, Config) ->
    ?assertEqual(Cell, cell()),
    ?assertMatch(#{request := start, has_error := true}, cell_controller:flags()),
    ?assertMatch({ok, #{kind := error, task := jam, solutions := [retry]}},
                 cell_alarms:get(?JAM)),
    ?assertEqual(down, cell_task_proc:state(jam)),
    ?assertEqual(Settings, cell_settings:names()),
    flowing(Config).

task_states() ->
    [cell_task_proc:state(T) || T <- ?TASKS].

%% Products fed now leave the line, and the suite, a subscriber since before the
%% restarts, gets the events of their hand-overs.
flowing(Config) ->
    Feed = ?config(feed, Config),
    Base = erlang:unique_integer([positive]) * 100,
    Serials = [<<"P-", (integer_to_binary(Base + I))/binary>> || I <- lists:seq(1, 3)],
    true = ets:insert(Feed, [{Base + I, S} || {I, S} <- lists:zip(lists:seq(1, 3), Serials)]),
    cell_task_proc:whereis(src) ! {?config(ref, Config), fed},
    Deadline = erlang:monotonic_time(millisecond) + ?TIMEOUT,
    _ = [await_out(S, Deadline) || S <- Serials],
    ok.

%% A serial out of the line, and its hand-over from b to the sink told as an event.
await_out(Serial, Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {line_out, sink, Serial} ->
            receive
                {cell_event, #{type := item_transfer_out, task := b, item := Serial}} -> ok
            after Left -> ct:fail({no_event, Serial})
            end
    after Left ->
        ct:fail({not_out, Serial, task_states()})
    end.

await_alarm(Id) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := #{id := Id}}} -> ok
    after ?TIMEOUT ->
        ct:fail({no_alarm, Id, cell_alarms:list()})
    end.

%% Kills a service and waits until its supervisor has started it again.
restart(Name) ->
    Old = kill_under(Name, cell_service_sup),
    New = whereis(Name),
    ?assert(is_pid(New) andalso New =/= Old, {not_restarted, Name}),
    ok.

%% Kills a process and returns once `Sup' has handled its exit: the exit reached the
%% supervisor before this call, so the supervisor answers after it restarted what it
%% restarts.
kill_under(Name, Sup) ->
    Old = whereis(Name),
    true = is_pid(Old),
    Ref = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', Ref, process, Old, _} -> ok
    after ?TIMEOUT -> ct:fail({not_stopped, Name})
    end,
    _ = supervisor:which_children(Sup),
    Old.
