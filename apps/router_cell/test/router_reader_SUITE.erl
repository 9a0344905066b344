%% The code reader above the loading stopper: a hardware object wired through the
%% simulated router's PLC (cell_hal_code_reader_io), connected and watched by the
%% cell's monitor, read by the loading task without blocking it. Panels enter under
%% the serial their reader read; a no-read (forced from the shell as an operator
%% would, router_sim:no_read_next/0) is the operator's "Code not read" error, and each
%% of its answers does what its description says: RETRY reads again, IGNORE takes the
%% panel under a NOREAD serial marked as such, RESET after the panel was taken off
%% leaves it out of the records.
%%
%% Every wait is for an event or a message with a deadline.
-module(router_reader_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([monitor_connects_the_reader/1, panels_read/1, no_read_retry/1,
         no_read_ignore/1, no_read_reset/1, reader_lost_mid_read/1, plc_lost_mid_read/1]).

-define(DEADLINE_MS, 60000).
-define(EVENTS, [item_identifier_read, item_transfer_out, alarm_raised, alarm_cleared,
                 cell_state]).
-define(NO_CODE, <<"loading_front:no_code">>).

all() ->
    [monitor_connects_the_reader, panels_read, no_read_retry, no_read_ignore,
     no_read_reset, reader_lost_mid_read, plc_lost_mid_read].

init_per_testcase(Case, Config) ->
    ok = application:set_env(cell, shutdown_wait_ms, 10000),
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = router_test_settings:write(
           Root, #{machine => #{},
                   router_sim => #{time_scale => 0.02, arrival_ms => 0,
                                   product_lost_rate => 0.0, jam_rate => 0.0,
                                   no_read_rate => 0.0, magazine_low_s => 0},
                   router => #{hal_poll_ms => 5, transfer_timeout_ms => 3000,
                               motion_timeout_ms => 3000,
                               reader_deadline_ms => deadline(Case),
                               %% The inspection application is not started here.
                               inspection => false}}),
    ok = cell_testkit:start(Root, router_cell, router_cell),
    ok = cell_testkit:await_connection(router_plc, ?DEADLINE_MS),
    ok = router_sim:ready(?DEADLINE_MS),
    ok = await_reader_up(),
    [{root, Root} | Config].

%% Long enough for the reader's object to be killed with its read in flight.
deadline(reader_lost_mid_read) -> 5000;
deadline(_) -> 1000.

end_per_testcase(_Case, _Config) ->
    _ = application:unset_env(cell, shutdown_wait_ms),
    cell_testkit:stop(router_cell, [router_plc]).

%% -------------------------------------------------------------------------------------

%% The spec's reader is a hardware object the monitor added and watches, as are each
%% robot's axes and channel; the reader's IO is a group of its own on the PLC.
monitor_connects_the_reader(_Config) ->
    ?assertEqual([{lower_x, axis, cell_hal_axis_sim}, {lower_xy, channel, cell_hal_channel_sim},
                  {lower_y, axis, cell_hal_axis_sim},
                  {reader_front, code_reader, cell_hal_code_reader_io},
                  {upper_x, axis, cell_hal_axis_sim}, {upper_xy, channel, cell_hal_channel_sim},
                  {upper_y, axis, cell_hal_axis_sim}],
                 lists:sort(cell_hal_hw:list())),
    #{devices := Devices} = cell_monitor:info(),
    ?assertMatch(#{reader_front := up, lower_x := up, lower_y := up, lower_xy := up,
                   upper_x := up, upper_y := up, upper_xy := up, router_plc := up}, Devices),
    {ok, Points} = cell_hal:points(reader_front_io),
    ?assertEqual([done, no_read, result, read_count, trigger], [P || #{name := P} <- Points]),
    %% The physics answers a read asked by hand, with the serial of the panel at the
    %% stopper or, with none there, no code.
    ?assertEqual({error, no_read}, cell_hal_code_reader:read(reader_front, ?DEADLINE_MS)),
    ?assertEqual({error, no_such_lane}, router_sim:no_read_next(rear)).

%% Panels enter under the serials the physics gave them, read by the reader, and
%% leave under them.
panels_read(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Seen = cell_testkit:collect(8, fun(#{type := item_identifier_read, task := loading_front,
                                         item := S, scanner := <<"code reader">>}) ->
                                           {true, {read, S}};
                                      (#{type := item_transfer_out, task := unloading_front,
                                         item := S}) ->
                                           {true, {out, S}};
                                      (_) ->
                                           false
                                   end, fun never_answer/1, ?DEADLINE_MS),
    Read = [S || {read, S} <- Seen],
    Out = [S || {out, S} <- Seen],
    ?assertEqual(length(Read), length(lists:usort(Read))),
    [?assertMatch(<<"P", _/binary>>, S) || S <- Read],
    %% The line holds three panels at most: some have left, each one read, in order.
    ?assert(length(Out) >= 2),
    ?assertEqual(Out, lists:sublist(Read, length(Out))),
    #{reads := #{front := Reads}} = router_sim:world(),
    ?assert(Reads >= length(Read)),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% RETRY: the panel is read again, under its own serial.
no_read_retry(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = router_sim:no_read_next(),
    ok = cell_controller:start(<<"suite">>),
    A = await_no_code(),
    ?assertEqual([retry, ignore, reset], maps:get(solutions, A)),
    Serial = at_stopper(),
    ok = cell_alarms:answer(?NO_CODE, retry, <<"suite">>),
    await(fun(#{type := item_identifier_read, task := loading_front, item := S}) -> S =:= Serial;
             (_) -> false
          end),
    ?assertEqual([Serial], collect_out(1)),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% IGNORE: the panel enters under a serial the cell made, NOREAD-..., marked as not
%% read, and leaves as any other.
no_read_ignore(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = router_sim:no_read_next(),
    ok = cell_controller:start(<<"suite">>),
    _ = await_no_code(),
    ok = cell_alarms:answer(?NO_CODE, ignore, <<"suite">>),
    Serial = <<"NOREAD-loading_front-000001">>,
    await(fun(#{type := item_identifier_read, task := loading_front, item := S,
                scanner := <<"operator (no read)">>}) -> S =:= Serial;
             (_) -> false
          end),
    ?assertMatch([#{no_read := true}],
                 [P || #{product := #{serial := S} = P} <- cell_controller:tasks(), S =:= Serial]),
    ?assertEqual([Serial], collect_out(1)),
    %% The next no-read gets the next serial: the counter is the task's retained data.
    ok = router_sim:no_read_next(),
    _ = await_no_code(),
    ok = cell_alarms:answer(?NO_CODE, ignore, <<"suite">>),
    await(fun(#{type := item_identifier_read, task := loading_front, item := S}) ->
                  S =:= <<"NOREAD-loading_front-000002">>;
             (_) -> false
          end),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% RESET after the operator took the panel off: it never enters the records; the
%% machine's ledger has it as taken out, and the next panel is read.
no_read_reset(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = router_sim:no_read_next(),
    ok = cell_controller:start(<<"suite">>),
    _ = await_no_code(),
    {ok, Serial} = router_sim:take_out(loading, front),
    %% The operator answers once the stopper is seen empty.
    {ok, Empty} = cell_hal:watch(loading_front_io, panel_at_stop, {eq, false}),
    receive {cell_hal_watch, Empty, false} -> ok after ?DEADLINE_MS -> ct:fail(still_there) end,
    ok = cell_alarms:answer(?NO_CODE, reset, <<"suite">>),
    Next = cell_testkit:collect(1, fun(#{type := item_identifier_read, task := loading_front,
                                         item := S}) -> {true, S};
                                      (_) -> false
                                   end, fun never_answer/1, ?DEADLINE_MS),
    ?assertNotEqual([Serial], Next),
    Out = collect_out(1),
    ?assertEqual(Next, Out),
    #{ledger := Ledger} = router_sim:world(),
    ?assert(lists:member({Serial, removed}, Ledger)),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% The reader's object killed with its trigger on: the task hears nothing and, after
%% its own wait, reports the reader; the object the monitor has back clears the trigger
%% (the machine never answers it), and Retry reads the panel, which enters once under
%% its own serial.
reader_lost_mid_read(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    %% A slow read (1.2 s at the time scale): the trigger stays on long enough.
    ok = cell_settings:put(router_sim, #{read_ms => 60000}, <<"suite">>),
    {ok, Trigger} = cell_hal:watch(reader_front_io, trigger, {eq, true}),
    ok = cell_controller:start(<<"suite">>),
    receive {cell_hal_watch, Trigger, true} -> ok after ?DEADLINE_MS -> ct:fail(no_trigger) end,
    [{reader_front, Pid, _, _}] = ets:lookup(cell_hal_hw_objects, reader_front),
    MRef = erlang:monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', MRef, process, Pid, _} -> ok end,
    ok = cell_settings:put(router_sim, #{read_ms => 150}, <<"suite">>),
    A = await(fun(#{type := alarm_raised, alarm := #{id := Id}}) -> Id =:= <<"loading_front:reader">>;
                 (_) -> false
              end, alarm),
    ?assertEqual([retry], maps:get(solutions, A)),
    Serial = at_stopper(),
    %% The supervisor has started the object again (its children listed after the
    %% restart); the monitor attaches it.
    _ = supervisor:which_children(cell_hal_hw_sup),
    ok = await_reader_up(),
    ?assertEqual({ok, false}, cell_hal:read(reader_front_io, trigger)),
    ok = cell_alarms:answer(<<"loading_front:reader">>, retry, <<"suite">>),
    await(fun(#{type := item_identifier_read, task := loading_front, item := S}) -> S =:= Serial;
             (_) -> false
          end),
    ?assertEqual([Serial], collect_out(1)),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% The PLC's connection lost while the reader reads: the reader, on that connection,
%% answers `not_connected'; the operator is asked about the lost connection only (its
%% Retry once it is back), never about the reader, and the panel is read again and
%% enters once under its own serial.
plc_lost_mid_read(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_settings:put(router_sim, #{read_ms => 60000}, <<"suite">>),
    {ok, Trigger} = cell_hal:watch(reader_front_io, trigger, {eq, true}),
    ok = cell_controller:start(<<"suite">>),
    receive {cell_hal_watch, Trigger, true} -> ok after ?DEADLINE_MS -> ct:fail(no_trigger) end,
    {ok, up} = cell_hal:subscribe_connection(router_plc),
    ok = cell_hal_sim:link(router_plc, down),
    receive {cell_hal_conn, router_plc, down} -> ok after ?DEADLINE_MS -> ct:fail(still_up) end,
    ok = cell_settings:put(router_sim, #{read_ms => 150}, <<"suite">>),
    Serial = at_stopper(),
    ok = cell_hal_sim:link(router_plc, up),
    receive {cell_hal_conn, router_plc, up} -> ok after ?DEADLINE_MS -> ct:fail(still_down) end,
    ok = read_after_reconnect(Serial, erlang:monotonic_time(millisecond) + ?DEADLINE_MS),
    ?assertEqual([Serial], collect_out(1)),
    ok = cell_testkit:stop_cell(fun never_answer/1, ?DEADLINE_MS).

%% The serial read, the lost connection's errors answered Retry meanwhile (one the cell
%% withdrew by itself is no longer there to answer).
read_after_reconnect(Serial, Deadline) ->
    receive
        {cell_event, #{type := item_identifier_read, task := loading_front, item := Serial}} ->
            ok;
        {cell_event, #{type := alarm_raised, alarm := #{kind := error, id := Id} = A}} ->
            case binary:split(Id, <<":">>) of
                [_, <<"io">>] -> ok;
                [<<"cell">>, <<"connection.router_plc">>] -> ok;
                _ -> ct:fail({unexpected_error, A})
            end,
            _ = cell_alarms:answer(Id, retry, <<"suite">>),
            read_after_reconnect(Serial, Deadline);
        {cell_event, _} ->
            read_after_reconnect(Serial, Deadline)
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail({not_read, Serial, cell_alarms:list()})
    end.

%% -------------------------------------------------------------------------------------

%% The panel at the front loading stopper, as the machine has it.
at_stopper() ->
    #{loading := #{front := {Serial, stop}}} = router_sim:world(),
    Serial.

await_no_code() ->
    await(fun(#{type := alarm_raised, alarm := #{id := Id}}) -> Id =:= ?NO_CODE;
             (_) -> false
          end, alarm).

%% The reader connected: subscribed, its status now, then its changes as messages.
await_reader_up() ->
    case cell_hal_hw:subscribe(reader_front) of
        {ok, up} ->
            ok;
        {ok, down} ->
            receive {cell_hal_hw, reader_front, up} -> ok
            after ?DEADLINE_MS -> ct:fail(reader_down)
            end
    end.

collect_out(N) ->
    cell_testkit:collect(N, fun(#{type := item_transfer_out, task := unloading_front,
                                  item := S}) -> {true, S};
                               (_) -> false
                            end, fun never_answer/1, ?DEADLINE_MS).

never_answer(#{kind := error} = A) -> ct:fail({unexpected_error, A});
never_answer(_) -> ok.

await(Match) ->
    cell_testkit:await_event(Match, ?DEADLINE_MS).

%% The event's alarm.
await(Match, alarm) ->
    Self = self(),
    ok = cell_testkit:await_event(fun(#{alarm := A} = E) ->
                                          Match(E) andalso (Self ! {matched, A}) =/= x;
                                     (E) -> Match(E)
                                  end, ?DEADLINE_MS),
    receive {matched, A} -> A after 0 -> ct:fail(no_alarm) end.
