%% The tables a service keeps across its restarts: made once, given back to the keeper
%% when the service dies, claimed again by the next one; and what the events and the
%% alarms read back from them.
-module(cell_service_tables_tests).

-include_lib("eunit/include/eunit.hrl").

-define(TAB, cell_service_tables_test).

tables_test_() ->
    {foreach, fun start_keeper/0, fun stop/1,
     [fun made_once_then_kept/0, fun claim_waits_for_the_dying_owner/0,
      fun subscribers_kept/0, fun waiting_error_kept/0, fun await_until_claimed/0,
      fun call_waits_for_the_service/0]}.

%% Without a keeper (a service started alone) the service makes its own table.
alone_test() ->
    Owner = spawn_owner(?TAB),
    ?assertEqual({claimed, new}, receive_claim(Owner)),
    ?assertEqual(Owner, ets:info(?TAB, owner)),
    ok = stop(Owner),
    ?assertEqual(undefined, ets:info(?TAB)).

made_once_then_kept() ->
    Keeper = whereis(cell_service_tables),
    First = spawn_owner(?TAB),
    ?assertEqual({claimed, new}, receive_claim(First)),
    ?assertEqual(First, ets:info(?TAB, owner)),
    ?assertEqual(Keeper, ets:info(?TAB, heir)),
    true = ets:insert(?TAB, {k, 1}),
    ok = stop(First),
    Second = spawn_owner(?TAB),
    ?assertEqual({claimed, kept}, receive_claim(Second)),
    ?assertEqual(Second, ets:info(?TAB, owner)),
    ?assertEqual([{k, 1}], ets:lookup(?TAB, k)),
    ok = stop(Second).

%% A claim while the old owner still holds the table (its exit not complete) is
%% answered when the table is back. The claim is sent as claim/2 sends it, so that the
%% keeper has it, waiting, before the owner goes.
claim_waits_for_the_dying_owner() ->
    Keeper = whereis(cell_service_tables),
    First = spawn_owner(?TAB),
    {claimed, new} = receive_claim(First),
    Req = gen_server:send_request(Keeper, {claim, ?TAB, [public], self()}),
    _ = sys:get_state(Keeper),
    ?assertEqual(no_reply, gen_server:check_response({no_reply_yet, Req}, Req)),
    ?assertEqual(First, ets:info(?TAB, owner)),
    ok = stop(First),
    ?assertEqual({reply, kept}, gen_server:wait_response(Req, 5000)),
    receive {'ETS-TRANSFER', ?TAB, Keeper, ?TAB} -> ok after 5000 -> error(no_transfer) end,
    ?assertEqual(self(), ets:info(?TAB, owner)),
    true = ets:delete(?TAB).

%% A subscriber of the events gets them from the next fan-out without subscribing
%% again; one that died meanwhile is dropped.
subscribers_kept() ->
    {ok, E1} = cell_events:start_link(),
    ok = cell_events:subscribe([item_transfer_out]),
    Gone = spawn(fun() -> receive stop -> ok end end),
    ok = cell_events:subscribe(Gone, all),
    ok = stop(E1),
    ok = stop(Gone),
    {ok, E2} = cell_events:start_link(),
    _ = sys:get_state(E2),
    ?assertEqual([self()], ets:lookup_element(cell_event_subscribers, item_transfer_out, 2)),
    ok = cell_events:publish(item_transfer_out, t1, #{item => <<"S1">>}),
    receive {cell_event, Event} -> ?assertMatch(#{item := <<"S1">>}, Event)
    after 5000 -> error(no_event)
    end,
    ok = stop(E2).

%% An error raised before the alarms restarted is still listed and its answer still
%% reaches its owner. The registry runs, as it does before the services in the cell:
%% the alarms look up the product of the error's task before they pass an answer on.
waiting_error_kept() ->
    {ok, Registry} = cell_registry:start_link(),
    unlink(Registry),
    {ok, A1} = cell_alarms:start_link(),
    {ok, Id} = cell_alarms:raise_error(t1, #{id => <<"e">>, caption => "Jam",
                                             solutions => [retry]}, self()),
    ok = stop(A1),
    {ok, A2} = cell_alarms:start_link(),
    ?assertMatch({ok, #{id := Id, kind := error}}, cell_alarms:get(Id)),
    ?assertEqual(ok, cell_alarms:answer(Id, retry, <<"test">>)),
    receive {cell_alarm, answer, Id, retry, <<"test">>} -> ok
    after 5000 -> error(no_answer)
    end,
    ?assertEqual({error, not_found}, cell_alarms:get(Id)),
    ok = stop(A2),
    ok = stop(Registry).

%% Waiting for a service by name ends when a process of that name claims its table;
%% one registered already is not waited for.
await_until_claimed() ->
    Keeper = whereis(cell_service_tables),
    Req = gen_server:send_request(Keeper, {await, cell_service_tables_test_service}),
    _ = sys:get_state(Keeper),
    ?assertEqual(no_reply, gen_server:check_response({no_reply_yet, Req}, Req)),
    Self = self(),
    Service = spawn(fun() ->
                            true = register(cell_service_tables_test_service, self()),
                            Self ! {claimed, self(), cell_service_tables:claim(?TAB, [])},
                            receive stop -> ok end
                    end),
    ?assertEqual({reply, ok}, gen_server:wait_response(Req, 5000)),
    ?assertEqual({claimed, new}, receive_claim(Service)),
    ?assertEqual(ok, cell_service_tables:await(cell_service_tables_test_service, 0)),
    ok = stop(Service),
    ?assertEqual(timeout, cell_service_tables:await(cell_service_tables_test_service, 0)).

%% A call made while the alarms are away is answered once they are back, not an exit.
call_waits_for_the_service() ->
    {ok, A1} = cell_alarms:start_link(),
    ok = stop(A1),
    Self = self(),
    Caller = spawn(fun() -> Self ! {synced, self(), catch cell_alarms:sync()} end),
    {ok, A2} = cell_alarms:start_link(),
    receive {synced, Caller, R} -> ?assertEqual(ok, R)
    after 10000 -> error(no_reply)
    end,
    ok = stop(A2).

%% -------------------------------------------------------------------------------------

start_keeper() ->
    {ok, Pid} = cell_service_tables:start_link(),
    unlink(Pid),
    Pid.

%% A process that claims a table, says so, and holds it until stopped.
spawn_owner(Name) ->
    Self = self(),
    spawn(fun() ->
                  R = cell_service_tables:claim(Name, [public]),
                  Self ! {claimed, self(), R},
                  receive stop -> ok end
          end).

receive_claim(Pid) ->
    receive {claimed, Pid, R} -> {claimed, R}
    after 5000 -> error(no_claim)
    end.

stop(Pid) ->
    unlink(Pid),
    Ref = monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', Ref, process, Pid, _} -> ok end.
