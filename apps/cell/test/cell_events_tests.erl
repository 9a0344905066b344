%% The event fan-out: who gets which events, and who no longer does.
-module(cell_events_tests).

-include_lib("eunit/include/eunit.hrl").

events_test_() ->
    {setup,
     fun() -> {ok, Pid} = cell_events:start_link(), unlink(Pid), Pid end,
     fun(Pid) -> MRef = monitor(process, Pid), exit(Pid, kill),
                 receive {'DOWN', MRef, _, _, _} -> ok end
     end,
     [fun types_are_filtered/0, fun another_process_subscribed_and_unsubscribed/0]}.

types_are_filtered() ->
    ok = cell_events:subscribe([item_transfer_in]),
    ?assertEqual({error, {unknown_types, [nonsense]}}, cell_events:subscribe([nonsense])),
    ok = cell_events:publish(item_transfer_out, t1, #{}),
    ok = cell_events:publish(item_transfer_in, t1, #{item => <<"S1">>}),
    receive {cell_event, Event} ->
            ?assertMatch(#{type := item_transfer_in, task := t1, item := <<"S1">>}, Event)
    end,
    ok = cell_events:unsubscribe(),
    ok = cell_events:publish(item_transfer_in, t1, #{}),
    ?assertEqual(nothing, next_event()).

%% A process subscribed by another (a watcher on another node, say) and unsubscribed
%% by it again.
another_process_subscribed_and_unsubscribed() ->
    Self = self(),
    Watcher = spawn_link(fun Loop() ->
                                 receive
                                     {cell_event, E} -> Self ! {watched, E}, Loop();
                                     stop -> Self ! stopped
                                 end
                         end),
    ok = cell_events:subscribe(Watcher, all),
    ok = cell_events:publish(item_transfer_out, t2, #{}),
    receive {watched, E1} -> ?assertMatch(#{type := item_transfer_out, task := t2}, E1) end,
    ok = cell_events:unsubscribe(Watcher),
    ok = cell_events:publish(item_transfer_out, t2, #{}),
    %% The watcher handles its messages in order: the event, had it come, would be
    %% reported before the stop is.
    Watcher ! stop,
    receive
        {watched, E2} -> ?assertEqual(no_event_after_unsubscribe, E2);
        stopped -> ok
    end,
    ?assertEqual(nothing, next_event()).

next_event() ->
    receive {cell_event, E} -> E
    after 0 -> nothing
    end.
