%% Handshakes between device tasks (seed 000 §2.3.6) on a line of conveyor segments:
%% products pass; a Pause waits for a transfer under way; an emergency stop while a
%% product moves leaves it with one side and asks the operator; killed tasks and links
%% end transfers without deadlock; a master task switches between feeders; the
%% seed's race between TryAbortOffering and a commit is decided once. After each case
%% every product fed in is either out or owned by exactly one task, on disk and in
%% memory.
-module(cell_handshake_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([products_pass/1, pause_waits_for_transfer/1, estop_while_moving/1,
         kill_downstream_before_release/1, kill_upstream_after_release/1,
         kill_link_mid_transfer/1, try_abort_offering_race/1, dynamic_feeders/1,
         abort_after_release_gives_back/1, stop_waits_for_transfer_through_an_error/1,
         reset_of_interrupted_transfer_forgets/1]).

-define(SEGMENTS, [src, a, b, sink]).
-define(TIMEOUT, 10000).

all() ->
    [products_pass, pause_waits_for_transfer, estop_while_moving,
     kill_downstream_before_release, kill_upstream_after_release, kill_link_mid_transfer,
     try_abort_offering_race, dynamic_feeders, abort_after_release_gives_back,
     stop_waits_for_transfer_through_an_error, reset_of_interrupted_transfer_forgets].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Feed = ets:new(feed, [ordered_set, public]),
    Out = ets:new(out, [set, public]),
    Ref = make_ref(),
    Delay = case Case of
                products_pass -> 0;
                try_abort_offering_race -> 0;
                dynamic_feeders -> 0;
                _ -> 150
            end,
    Config1 = [{root, Root}, {feed, Feed}, {out, Out}, {ref, Ref}, {delay, Delay},
               {fed, 0} | Config],
    case Case of
        try_abort_offering_race -> Config1;
        dynamic_feeders -> Config1;
        abort_after_release_gives_back -> Config1;
        stop_waits_for_transfer_through_an_error ->
            #{tasks := Tasks} = Spec = line_spec(?SEGMENTS, Config1),
            Jam = fun(#{id := a, args := Args} = Task) -> Task#{args := Args#{jam => true}};
                     (Task) -> Task
                  end,
            start_cell(Root, Spec#{tasks := lists:map(Jam, Tasks)}),
            Config1;
        _ -> start_cell(Root, line_spec(?SEGMENTS, Config1)), Config1
    end.

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    ok.

%% -------------------------------------------------------------------------------------

products_pass(Config) ->
    ok = cell_events:subscribe([item_transfer_in, item_transfer_out]),
    Serials = feed(Config, 30),
    ok = cell_controller:start(),
    Out = await_outs(30),
    ?assertEqual(lists:sort(Serials), lists:sort(Out)),
    ok = cell_controller:stop(),
    ok = cell_controller:sync(),
    ?assertEqual([off, off, off, off], [cell_task_proc:state(T) || T <- ?SEGMENTS]),
    check_conservation(Config, Serials),
    %% Every hand-over raised ItemTransferOut upstream and ItemTransferIn downstream.
    Events = drain_events([]),
    [?assertEqual(30, length([E || #{type := item_transfer_out, task := T0} = E <- Events,
                                   T0 =:= Up]))
     || Up <- [src, a, b]],
    [?assertEqual(30, length([E || #{type := item_transfer_in, task := T0} = E <- Events,
                                   T0 =:= Down]))
     || Down <- [a, b, sink]].

%% Seed: once downstream has read Available, the handshake must be fully executed
%% before a stop is allowed. Pause while a takes the product from src: the transfer
%% finishes, then everything holds in DOWN.
pause_waits_for_transfer(Config) ->
    Serials = feed(Config, 3),
    ok = cell_controller:start(),
    await_phase(a, moving_in),
    ok = cell_controller:pause(),
    await_all_down(),
    %% a holds the product it was taking; it arrived before a paused.
    #{product := #{serial := S}} = cell_task_proc:info(a),
    ?assertEqual(hd(lists:sort(Serials)), S),
    check_conservation(Config, Serials),
    ok = cell_controller:start(),
    Out = await_outs(3),
    ?assertEqual(lists:sort(Serials), lists:sort(Out)),
    check_conservation(Config, Serials).

%% Stop while a takes the product from src, and the product sticks before it arrives:
%% a reports it after the Stop. Once the operator answers Retry the transfer finishes,
%% then the Stop it held back applies: every segment ends OFF, nothing is lost.
stop_waits_for_transfer_through_an_error(Config) ->
    Serials = feed(Config, 1),
    ok = cell_events:subscribe([alarm_raised, cell_state]),
    ok = cell_controller:start(),
    await_phase(a, arriving),
    ok = cell_controller:stop(),
    ok = cell_controller:sync(),
    Id = receive
             {cell_event, #{type := alarm_raised, alarm := #{task := a, id := AlarmId}}} ->
                 AlarmId
         after ?TIMEOUT -> ct:fail(no_jam)
         end,
    ?assertEqual(down, cell_task_proc:state(a)),
    ok = cell_alarms:answer(Id, retry, <<"op">>),
    receive
        {cell_event, #{type := cell_state, state := off}} -> ok
    after ?TIMEOUT ->
        ct:fail({not_off, [{T, cell_task_proc:state(T)} || T <- ?SEGMENTS]})
    end,
    #{product := #{serial := S}} = cell_task_proc:info(a),
    ?assertEqual(hd(Serials), S),
    check_conservation(Config, Serials).

%% An emergency stop while the product moves from src to a: a owns it, marked in
%% transit; at the next Start the operator is asked where it is.
estop_while_moving(Config) ->
    Serials = feed(Config, 1),
    ok = cell_controller:start(),
    await_phase(a, arriving),
    ok = cell_controller:estop(true),
    ok = cell_controller:sync(),
    ?assertEqual([off, off, off, off], [cell_task_proc:state(T) || T <- ?SEGMENTS]),
    check_conservation(Config, Serials),
    #{product := #{serial := S}, marker := #{phase := in_transit}} = cell_task_proc:info(a),
    ?assertEqual(hd(Serials), S),
    ok = cell_controller:estop(false),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ?assertEqual(down, cell_task_proc:state(a)),
    [#{id := Id, caption := <<"Product transfer interrupted">>, solutions := [ignore, reset]}] =
        [A || #{task := a} = A <- cell_alarms:list()],
    ok = cell_alarms:answer(Id, ignore, <<"op">>),
    Out = await_outs(1),
    ?assertEqual(Serials, Out),
    check_conservation(Config, Serials).

%% a is killed after committing but before src released: the product never left
%% src, which keeps it and offers it again to a's restarted incarnation.
kill_downstream_before_release(Config) ->
    ok = cell_events:subscribe([task_crashed]),
    Serials = feed(Config, 3),
    ok = cell_controller:start(),
    await_phase(src, leaving),
    exit(cell_task_proc:whereis(a), kill),
    receive {cell_event, #{type := task_crashed, task := a}} -> ok
    after ?TIMEOUT -> ct:fail(no_restart)
    end,
    %% a is asked about its crash; src, whose product was being moved out when a
    %% stopped, is asked where it is: here.
    Out = answer_until_out(Serials, ignore),
    ?assertEqual(lists:sort(Serials), lists:sort(Out)),
    check_conservation(Config, Serials).

%% As above, but the operator answers src's "Transfer interrupted" with Reset (the
%% product is not there): src forgets it and never sends it on.
reset_of_interrupted_transfer_forgets(Config) ->
    ok = cell_events:subscribe([task_crashed, alarm_raised]),
    [S] = feed(Config, 1),
    ok = cell_controller:start(),
    await_phase(src, leaving),
    %% The phases src went through so far are behind us: the next idle is the
    %% one after the Reset.
    ok = flush_phases(src),
    exit(cell_task_proc:whereis(a), kill),
    receive {cell_event, #{type := task_crashed, task := a}} -> ok
    after ?TIMEOUT -> ct:fail(no_restart)
    end,
    _ = [cell_alarms:answer(Id, answer_for(reset, Sols), <<"suite">>)
         || #{id := Id, kind := error, solutions := Sols} <- cell_alarms:list()],
    answer_until_forgotten(S),
    ok = cell_controller:sync(),
    ?assertMatch(#{product := undefined}, cell_task_proc:info(src)),
    ?assertEqual([], [T || T <- ?SEGMENTS,
                           #{product := #{serial := S1}} <- [cell_task_proc:info(T)], S1 =:= S]),
    ?assertEqual([], ets:tab2list(?config(out, Config))),
    Files = filelib:wildcard(filename:join([?config(root, Config), "Data", "*.product"])),
    ?assertEqual([], [F || F <- Files, {ok, #{product := #{serial := S1}}}
                                           <- [cell_product:load(F)], S1 =:= S]).

%% Answers src's "Transfer interrupted" with Reset and a's crash as asked, until src
%% forgot the product (idle after the Reset; without the Reset it went idle only after
%% handing the product on).
answer_until_forgotten(S) ->
    receive
        {cell_event, #{type := alarm_raised, alarm := #{id := <<"src:transfer">> = Id}}} ->
            ok = cell_alarms:answer(Id, reset, <<"suite">>),
            answer_until_forgotten(S);
        {cell_event, #{type := alarm_raised, alarm := #{id := Id, kind := error,
                                                         solutions := Sols}}} ->
            _ = cell_alarms:answer(Id, answer_for(reset, Sols), <<"suite">>),
            answer_until_forgotten(S);
        {line_phase, src, idle} ->
            ok
    after ?TIMEOUT ->
        ct:fail({src_not_idle, S, cell_alarms:list()})
    end.

flush_phases(Task) ->
    receive {line_phase, Task, _} -> flush_phases(Task)
    after 0 -> ok
    end.

%% src is killed after the product left it: a owns it and goes on.
kill_upstream_after_release(Config) ->
    ok = cell_events:subscribe([task_crashed]),
    Serials = feed(Config, 3),
    ok = cell_controller:start(),
    await_phase(a, arriving),
    exit(cell_task_proc:whereis(src), kill),
    receive {cell_event, #{type := task_crashed, task := src}} -> ok
    after ?TIMEOUT -> ct:fail(no_restart)
    end,
    Out = answer_until_out(Serials, ignore),
    ?assertEqual(lists:sort(Serials), lists:sort(Out)),
    check_conservation(Config, Serials).

%% The link process dies mid-transfer: both sides are told, the link comes back, the
%% line goes on.
kill_link_mid_transfer(Config) ->
    Serials = feed(Config, 4),
    ok = cell_controller:start(),
    await_phase(a, moving_in),
    exit(cell_handshake_link:whereis(l1), kill),
    answer_until_out(Serials, ignore),
    check_conservation(Config, Serials).

%% The seed's race, at the link: once downstream committed, TryAbortOffering fails and
%% the transfer goes on; before, it succeeds and the commit finds nothing. Every
%% answer carries the link's status, numbered in the order of the changes.
try_abort_offering_race(Config) ->
    start_cell(?config(root, Config), #{tasks => []}),
    {ok, _} = supervisor:start_child(cell_handshake_sup,
                                     cell_handshake_link:child_spec(#{id => race, from => u,
                                                                      to => d})),
    Up = partner(race, up, u),
    Down = partner(race, down, d),
    {ok, #{seq := S1, phase := offered}} =
        as_numbered(Up, race, {offer, Up, cell_product:new(<<"R1">>, <<"r">>), 1}),
    {{ok, _, 1}, #{seq := S2, phase := committed, available := true, not_busy := true}} =
        as_numbered(Down, race, {commit, Down}),
    ?assertEqual({false, S2}, seq(as_numbered(Up, race, {try_abort_offering, Up}))),
    ok = as(Up, race, {release, Up}),
    Down ! {cast, race, {owned, Down}},
    {ok, #{seq := S3, phase := idle}} = as_numbered(Down, race, {complete, Down}),
    ?assert(S1 < S2 andalso S2 + 1 < S3),
    ok = as(Up, race, {offer, Up, cell_product:new(<<"R2">>, <<"r">>), 1}),
    ?assertEqual(true, as(Up, race, {try_abort_offering, Up})),
    ?assertEqual({error, not_available}, as(Down, race, {commit, Down})),
    ?assertEqual(none, as(Down, race, {peek, Down})),
    %% Both partners were told of each step.
    ?assertMatch([_ | _], [M || {partner_got, P, {cell_handshake, race, owned} = M} <- flush([]),
                                P =:= Up]).

%% Seed: a master task connects its handshake to one of several feeders at run time.
dynamic_feeders(Config) ->
    %% Each feeder has its own supply of products, as separate conveyors do.
    Feed = ?config(feed, Config),
    Feed1 = ets:new(feed1, [ordered_set, public]),
    Out = ?config(out, Config),
    Spec = #{tasks => [#{id => feeder0, module => cell_line_task, zone => <<"Feeder">>,
                         lane => <<"0">>, args => #{next => f0, feed => Feed, out => Out,
                                                    ref => ?config(ref, Config)}},
                       #{id => master, module => cell_feeder_master, zone => <<"Master">>,
                         lane => <<"1">>, args => #{feeders => [f0, f1], out => Out,
                                                    notify => self()}},
                       #{id => feeder1, module => cell_line_task, zone => <<"Feeder">>,
                         lane => <<"1">>, args => #{next => f1, feed => Feed1, out => Out,
                                                    ref => ?config(ref, Config)}}],
             links => [#{id => f0, from => feeder0, to => undefined},
                       #{id => f1, from => feeder1, to => undefined}]},
    start_cell(?config(root, Config), Spec),
    Serials = feed(Config, 3) ++ feed(lists:keystore(feed, 1, Config, {feed, Feed1}), 3),
    [cell_task_proc:whereis(F) ! {?config(ref, Config), fed} || F <- [feeder0, feeder1]],
    ok = cell_controller:start(),
    Taken = [receive {master_took, F, S} -> {F, S} after ?TIMEOUT -> ct:fail(no_product) end
             || _ <- Serials],
    %% The master alternated between the feeders.
    ?assertEqual([f0, f1, f0, f1, f0, f1], [F || {F, _} <- Taken]),
    ?assertEqual(lists:sort(Serials), lists:sort([S || {_, S} <- Taken])).

%% Downstream aborts after the product left upstream: upstream takes it back with a
%% newer record before downstream forgets it.
abort_after_release_gives_back(Config) ->
    start_cell(?config(root, Config), #{tasks => []}),
    {ok, _} = supervisor:start_child(cell_handshake_sup,
                                     cell_handshake_link:child_spec(#{id => ab, from => u,
                                                                      to => d})),
    Up = partner(ab, up, u),
    Down = partner(ab, down, d),
    P = cell_product:new(<<"A1">>, <<"r">>),
    ok = as(Up, ab, {offer, Up, P, 3}),
    {ok, P, 3} = as(Down, ab, {commit, Down}),
    ok = as(Up, ab, {release, Up}),
    %% The step and the signals it leaves (Available off, NotBusy still on), together.
    receive {partner_got, Down, {cell_handshake, ab, {released, P, 3},
                                 #{phase := released, available := false,
                                   not_busy := true}}} -> ok
    after ?TIMEOUT -> ct:fail(no_released)
    end,
    %% Downstream's abort waits for upstream to take the product back.
    Down ! {do, ab, {abort, Down}, self()},
    receive {partner_got, Up, {cell_handshake, ab, {take_back, P, 3}}} -> ok
    after ?TIMEOUT -> ct:fail(no_take_back)
    end,
    ok = as(Up, ab, {taken_back, Up}),
    receive {done, Down, {given_back, #{phase := idle}}} -> ok
    after ?TIMEOUT -> ct:fail(no_abort_answer)
    end,
    _ = Config.

%% -------------------------------------------------------------------------------------

start_cell(Root, Spec) ->
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, Spec),
    {ok, _} = application:ensure_all_started(cell),
    ok.

line_spec(Ids, Config) ->
    N = length(Ids),
    Links = [#{id => link_id(I), from => lists:nth(I, Ids), to => lists:nth(I + 1, Ids)}
             || I <- lists:seq(1, N - 1)],
    Tasks = [#{id => Id, module => cell_line_task, zone => atom_to_binary(Id, utf8),
               lane => <<"Front">>,
               args => #{prev => case I of 1 -> undefined; _ -> link_id(I - 1) end,
                         next => case I of N -> undefined; _ -> link_id(I) end,
                         feed => ?config(feed, Config), out => ?config(out, Config),
                         ref => ?config(ref, Config), notify => self(),
                         delay => ?config(delay, Config)}}
             || {I, Id} <- lists:zip(lists:seq(1, N), Ids)],
    #{tasks => Tasks, links => Links}.

link_id(I) -> list_to_atom("l" ++ integer_to_list(I)).

feed(Config, N) ->
    Feed = ?config(feed, Config),
    Base = ets:info(Feed, size) + erlang:unique_integer([positive]) * 1000,
    Serials = [<<"P-", (integer_to_binary(Base + I))/binary>> || I <- lists:seq(1, N)],
    true = ets:insert(Feed, [{Base + I, S} || {I, S} <- lists:zip(lists:seq(1, N), Serials)]),
    case cell_task_proc:whereis(src) of
        undefined -> ok;
        Pid -> Pid ! {?config(ref, Config), fed}
    end,
    Serials.

await_phase(Task, Phase) ->
    receive
        {line_phase, Task, Phase} -> ok
    after ?TIMEOUT ->
        ct:fail({phase_not_reached, Task, Phase})
    end.

await_outs(N) ->
    [receive {line_out, sink, S} -> S after ?TIMEOUT -> ct:fail({outs_missing, N}) end
     || _ <- lists:seq(1, N)].

%% Answers every error the line raises until all products are out.
answer_until_out(Serials, Solution) ->
    ok = cell_events:subscribe([alarm_raised]),
    _ = [cell_alarms:answer(Id, answer_for(Solution, Sols), <<"suite">>)
         || #{id := Id, kind := error, solutions := Sols} <- cell_alarms:list()],
    answer_loop(length(Serials), [], Solution).

answer_for(Solution, Sols) ->
    case lists:member(Solution, Sols) of
        true -> Solution;
        false -> hd(Sols)
    end.

answer_loop(0, Acc, _Solution) ->
    lists:reverse(Acc);
answer_loop(N, Acc, Solution) ->
    receive
        {line_out, sink, S} ->
            answer_loop(N - 1, [S | Acc], Solution);
        {cell_event, #{type := alarm_raised, alarm := #{id := Id, kind := error,
                                                         solutions := Sols}}} ->
            _ = cell_alarms:answer(Id, answer_for(Solution, Sols), <<"suite">>),
            answer_loop(N, Acc, Solution)
    after ?TIMEOUT ->
        ct:fail({outs_missing, N, cell_alarms:list()})
    end.

await_all_down() ->
    ok = cell_events:subscribe([task_state]),
    await_all_down(erlang:monotonic_time(millisecond) + ?TIMEOUT).

await_all_down(Deadline) ->
    ok = cell_controller:sync(),
    States = [cell_task_proc:state(T) || T <- ?SEGMENTS],
    case lists:all(fun(S) -> S =:= down orelse S =:= off end, States) of
        true ->
            ok;
        false ->
            Left = Deadline - erlang:monotonic_time(millisecond),
            receive
                {cell_event, #{type := task_state}} -> await_all_down(Deadline)
            after max(0, Left) ->
                ct:fail({not_down, States})
            end
    end.

%% Every serial fed in is out, or owned by exactly one task: on disk (the highest
%% generation, never two files sharing it) and in memory.
check_conservation(Config, Serials) ->
    ok = cell_controller:sync(),
    Dir = filename:join(?config(root, Config), "Data"),
    Files = [F || F <- filelib:wildcard(filename:join(Dir, "*.product"))],
    Stored = [{S, G} || F <- Files, {ok, #{product := #{serial := S}, gen := G}}
                                        <- [cell_product:load(F)]],
    Owners = lists:usort([S || {S, _} <- Stored]),
    [begin
         Gens = [G || {S1, G} <- Stored, S1 =:= S],
         Top = lists:max(Gens),
         ?assertEqual(1, length([G || G <- Gens, G =:= Top]), {two_owners, S, Gens})
     end || S <- Owners],
    InMemory = [S || T <- ?SEGMENTS, cell_task_proc:whereis(T) =/= undefined,
                     #{product := #{serial := S}} <- [cell_task_proc:info(T)]],
    ?assertEqual(lists:usort(InMemory), lists:sort(InMemory), duplicate_in_memory),
    ?assertEqual(lists:usort(InMemory), Owners, memory_and_disk_differ),
    Out = [S || {S, _} <- ets:tab2list(?config(out, Config))],
    Waiting = [S || {_, S} <- ets:tab2list(?config(feed, Config))],
    ?assertEqual([], [S || S <- Owners, lists:member(S, Out)], out_and_owned),
    ?assertEqual(lists:sort(Serials), lists:sort(Out ++ Owners ++ Waiting), lost_or_extra).

drain_events(Acc) ->
    receive {cell_event, E} -> drain_events([E | Acc])
    after 0 -> lists:reverse(Acc)
    end.

%% A process standing in for a task at one end of a link: it makes the calls the test
%% asks for and passes on everything the link sends it.
partner(Link, Role, Task) ->
    Test = self(),
    Pid = spawn_link(fun() -> partner_loop(Test) end),
    {ok, _} = as(Pid, Link, {attach, Role, Task, Pid, none}),
    Pid.

partner_loop(Test) ->
    receive
        {do, Link, Req, From} ->
            From ! {done, self(), gen_server:call(cell_handshake_link:whereis(Link), Req)},
            partner_loop(Test);
        {cast, Link, Req} ->
            gen_server:cast(cell_handshake_link:whereis(Link), Req),
            partner_loop(Test);
        Msg ->
            Test ! {partner_got, self(), Msg},
            partner_loop(Test)
    end.

%% A partner's request to a link and the answer; the status a protocol step's answer
%% carries is dropped (see as_numbered/3).
as(Pid, Link, Req) when element(1, Req) =:= attach; element(1, Req) =:= detach ->
    as_numbered(Pid, Link, Req);
as(Pid, Link, Req) ->
    {Reply, #{seq := _}} = as_numbered(Pid, Link, Req),
    Reply.

as_numbered(Pid, Link, Req) ->
    Pid ! {do, Link, Req, self()},
    receive {done, Pid, R} -> R after ?TIMEOUT -> ct:fail({no_answer, Req}) end.

seq({Reply, #{seq := Seq}}) -> {Reply, Seq}.

flush(Acc) ->
    receive M -> flush([M | Acc]) after 0 -> lists:reverse(Acc) end.
