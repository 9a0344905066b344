%% A PropEr state-machine model of a HAL connection's worker (cell_hal_worker), written
%% from its contract (docs/architecture.md, HAL: the workers' table, Writes, Waiting,
%% Connectivity), never from its code: a simulated PLC (cell_hal_sim) whose inputs
%% change, whose outputs change on its own side, whose cable is pulled and plugged back
%% or that drops its connections for a moment; the HAL's writes, reads and watches.
%%
%% The model: whether the cable is in, whether the connection is up, the PLC's image,
%% what the HAL's outputs read, the watches placed and not fired, the next wait before
%% a connection attempt. Checked:
%% <ul>
%% <li>connecting / connected / disconnected: a cable pulled takes the connection down
%%   (subscribers told), a cable plugged back brings it up after the first complete
%%   read; a momentary loss does both;</li>
%% <li>backoff: the wait before each attempt is `reconnect_ms' after the connection was
%%   lost, twice as long after each failed attempt up to `max_reconnect_ms', and back to
%%   `reconnect_ms' only after a first complete read;</li>
%% <li>an input reads the PLC's value while up and `disconnected' while down; an output
%%   its last commanded value, and after a reconnect what the PLC holds;</li>
%% <li>a write while up is confirmed and the PLC holds it; a write while down is refused
%%   with `disconnected' and never reaches the PLC later (it is not queued);</li>
%% <li>a watch fires exactly once, as soon as its condition holds while up (at once if
%%   it holds when placed), never on an input while down, and is checked again after a
%%   reconnect.</li>
%% <li>the worker killed (its supervisor starts it again): in the moment it is gone the
%%   connection reads as down and its inputs as `disconnected', and a write is refused
%%   with `disconnected' and never reaches the PLC later; if it was up,
%%   connection subscribers are told of the loss and then of the connection again, the
%%   outputs read what the PLC holds and every watch is checked again; while the cable
%%   is out it stays down, its backoff not known to the model until the cable is back.
%%   The worker runs under a supervisor of the run's own with the product's child spec
%%   (cell_hal_test_worker_sup): a thousand runs kill it far more often than the
%%   product's ten restarts a minute allow.</li>
%% </ul>
%% Parallel runs race the PLC's side, the HAL's and the kills; at the end the cable is
%% in, the connection up, the inputs read the PLC's values and a reconnect reads its
%% outputs. Each command's answer is one the contract allows, and what the PLC took of
%% its outputs (the simulated PLC notes each value as it takes it, on the run's record
%% of marks that the writes also take before and after) agrees with how every write was
%% answered: a confirmed one was taken while it ran, once; one answered `disconnected'
%% was not taken, or, if a kill came while it ran (the worker killed with the write on
%% its way), taken while it ran and never after; a kill's own write never. To tell
%% whose write the PLC took, the HAL's writes of the integer output in a parallel run,
%% and the kills', write values no other command writes. The kills take turns (a lock
%% of the run's own): a kill that resumed the supervisor while another still held it
%% suspended let a successor start and confirm the other's write, which looked like a
%% write confirmed with no worker running; the model's error, not the worker's.
-module(prop_cell_hal_worker).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([set_input/2, plc_sets_output/2, write/2, read/1, watch/2, cable/1, drop/0,
         attempts/1, kill/3]).
-export([setup/0, cleanup/1, prop_sequential/0, prop_parallel/0, start_conn/1, stop_conn/1]).

-define(WAIT, 5000).
-define(TAB, prop_cell_hal_worker).
-define(INPUTS, [int16_in, bool_in]).
-define(OUTPUTS, [int16_out, bool_out]).
-define(RECONNECT_MS, 5).
-define(MAX_RECONNECT_MS, 20).

-record(m, {cable = true :: boolean(),
            up = true :: boolean(),
            plc = #{} :: #{atom() => term()},
            hal_out = #{} :: #{atom() => term()},
            watches = [] :: [{term(), atom(), term()}],   %% placed, not fired
            fired = [] :: [term()],
            %% the next wait when down; unknown after a kill while down (the new
            %% worker's first attempt races the model's next command)
            wait = ?RECONNECT_MS :: pos_integer() | unknown,
            mode = sequential :: sequential | parallel}).

worker_test_() ->
    {setup, fun setup/0, fun cleanup/1,
     fun(_) ->
             [{timeout, 600, ?_assert(proper:quickcheck(prop_sequential(),
                                                        [{to_file, user}, {numtests, 1000}]))},
              {timeout, 600, ?_assert(proper:quickcheck(prop_parallel(),
                                                        [{to_file, user}, {numtests, 1000}]))}]
     end}.

prop_sequential() ->
    ?FORALL(Cmds, commands(?MODULE),
            begin
                Conn = start_conn(sequential),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                Final = unfired_as_modelled(State),
                stop_conn(Conn),
                ?WHENFAIL(io:format(user, "History: ~p~nState: ~p~nResult: ~p~nFinal: ~p~n",
                                    [History, State, Result, Final]),
                          aggregate(command_names(Cmds), Result =:= ok andalso Final =:= ok))
            end).

prop_parallel() ->
    ?FORALL(Cmds, parallel_commands(?MODULE, #m{mode = parallel}),
            begin
                Conn = start_conn(parallel),
                {Seq, Par, Result} = run_parallel_commands(?MODULE, Cmds),
                Final = final_check(),
                Taken = taken_as_answered(Cmds, Seq, Par),
                stop_conn(Conn),
                ?WHENFAIL(io:format(user, "Seq: ~p~nPar: ~p~nResult: ~p~nFinal: ~p~n"
                                    "Taken: ~p~n", [Seq, Par, Result, Final, Taken]),
                          aggregate(command_names(Cmds),
                                    Result =:= ok andalso Final =:= ok andalso Taken =:= ok))
            end).

%% -------------------------------------------------------------------------------------
%% The model
%% -------------------------------------------------------------------------------------

initial_state() ->
    Zero = maps:from_list([{P, zero(P)} || P <- ?INPUTS ++ ?OUTPUTS]),
    #m{plc = Zero, hal_out = maps:with(?OUTPUTS, Zero)}.

zero(P) when P =:= bool_in; P =:= bool_out -> false;
zero(_) -> 0.

%% A small domain, so that watches fire and values repeat.
value(P) when P =:= bool_in; P =:= bool_out -> boolean();
value(_) -> integer(0, 3).

%% What the HAL writes. In a parallel run the integer output takes a value no other
%% command writes (`fresh', drawn as the command runs), so that the PLC's record of
%% what it took tells whose write it was (see taken_as_answered/3); the boolean output
%% keeps its two values, and with them writes that watches see.
written(parallel, int16_out) -> fresh;
written(_, P) -> value(P).

%% A parallel run's kill writes a fresh value, which nobody else writes, so that it is
%% seen never to reach the PLC.
kill_outputs(sequential) -> ?OUTPUTS;
kill_outputs(parallel) -> [int16_out].

command(#m{mode = Mode, cable = Cable, up = Up} = M) ->
    frequency([{4, ?LET(P, oneof(?INPUTS), {call, ?MODULE, set_input, [P, value(P)]})},
               {2, ?LET(P, oneof(?OUTPUTS), {call, ?MODULE, plc_sets_output, [P, value(P)]})},
               {4, ?LET(P, oneof(?OUTPUTS), {call, ?MODULE, write, [P, written(Mode, P)]})},
               {3, {call, ?MODULE, read, [oneof(?INPUTS ++ ?OUTPUTS)]}},
               {3, ?LET(P, oneof(?INPUTS ++ ?OUTPUTS), {call, ?MODULE, watch, [P, value(P)]})},
               {case Cable of true -> 2; false -> 4 end, {call, ?MODULE, cable, [not Cable]}},
               {1, {call, ?MODULE, drop, []}},
               {2, ?LET(P, oneof(kill_outputs(Mode)),
                        {call, ?MODULE, kill, [P, written(Mode, P), Cable]})}]
              ++ [{2, {call, ?MODULE, attempts, [range(1, 4)]}}
                  || Mode =:= sequential, not Cable, not Up, M#m.wait =/= unknown]).

precondition(#m{mode = parallel}, {call, _, attempts, _}) -> false;
precondition(#m{mode = parallel}, _) -> true;
precondition(M, {call, _, drop, []}) -> M#m.cable;
precondition(M, {call, _, attempts, _}) -> not M#m.cable andalso M#m.wait =/= unknown;
precondition(_, _) -> true.

next_state(#m{mode = parallel} = M, _, _) ->
    M;
next_state(M, _, {call, _, set_input, [P, V]}) ->
    fire(M#m{plc = (M#m.plc)#{P := V}});
next_state(M, _, {call, _, plc_sets_output, [P, V]}) ->
    %% The HAL does not poll outputs: it sees this only at its next connection.
    M#m{plc = (M#m.plc)#{P := V}};
next_state(#m{up = true} = M, _, {call, _, write, [P, V]}) ->
    fire(M#m{plc = (M#m.plc)#{P := V}, hal_out = (M#m.hal_out)#{P := V}});
next_state(M, _, {call, _, write, _}) ->
    %% Refused while down: not queued for later.
    M;
next_state(M, Ref, {call, _, watch, [P, V]}) ->
    fire(M#m{watches = M#m.watches ++ [{Ref, P, V}]});
next_state(#m{cable = false} = M, _, {call, _, cable, [true]}) ->
    reconnected(M);
next_state(#m{cable = true, up = true} = M, _, {call, _, cable, [false]}) ->
    %% Lost: the first wait is reconnect_ms, then twice as long after each attempt.
    M#m{cable = false, up = false, wait = ?RECONNECT_MS};
next_state(M, _, {call, _, cable, [Cable]}) ->
    M#m{cable = Cable};
next_state(M, _, {call, _, drop, []}) ->
    reconnected(M);
next_state(#m{cable = true} = M, _, {call, _, kill, _}) ->
    %% Killed while up (or coming up): down, then up again with a first complete read.
    reconnected(M#m{up = false});
next_state(M, _, {call, _, kill, _}) ->
    M#m{wait = unknown};
next_state(M, _, {call, _, attempts, [N]}) ->
    M#m{wait = lists:last(waits(M#m.wait, N + 1))};
next_state(M, _, _) ->
    M.

%% The first complete read after a connection: the outputs read what the PLC holds,
%% every watch is checked again, the backoff starts over.
reconnected(M) ->
    fire(M#m{cable = true, up = true, hal_out = maps:with(?OUTPUTS, M#m.plc),
             wait = ?RECONNECT_MS}).

%% Watches whose condition holds fire: an input's only while up, an output's (which
%% reads its last commanded value) also while down.
fire(#m{watches = Ws, up = Up} = M) ->
    {Fired, Left} = lists:partition(fun({_, P, V}) ->
                                            (Up orelse lists:member(P, ?OUTPUTS))
                                                andalso seen(P, M) =:= V
                                    end, Ws),
    M#m{watches = Left, fired = M#m.fired ++ [R || {R, _, _} <- Fired]}.

seen(P, M) ->
    case lists:member(P, ?INPUTS) of
        true -> maps:get(P, M#m.plc);
        false -> maps:get(P, M#m.hal_out)
    end.

%% The waits logged after each failed attempt: doubling, capped.
waits(W, N) ->
    lists:reverse(lists:foldl(fun(_, [Last | _] = Acc) ->
                                      [min(2 * Last, ?MAX_RECONNECT_MS) | Acc]
                              end, [W], lists:seq(2, N))).

postcondition(#m{mode = parallel}, {call, _, _, _} = Call, Res) ->
    allowed(Call, Res);
postcondition(M, {call, _, _, _} = Call, Res) ->
    M1 = next_state(M, Res, Call),
    Fired = M1#m.fired -- M#m.fired,
    case check(M, M1, Call, Res) andalso fired(Fired, M1) of
        true -> true;
        false -> io:format(user, "~nFailed ~p: ~p~n", [Call, Res]), false
    end.

check(M, _, {call, _, set_input, [P, V]}, Res) ->
    case M#m.up of
        true -> Res =:= {ok, V};
        false -> Res =:= {error, disconnected} andalso is_map_key(P, M#m.plc)
    end;
check(M, _, {call, _, plc_sets_output, [P, _]}, Res) ->
    Res =:= {ok, maps:get(P, M#m.hal_out)};
check(#m{up = true}, _, {call, _, write, [_, V]}, Res) ->
    Res =:= {ok, {ok, V}, {ok, V}};
check(M, _, {call, _, write, [P, _]}, Res) ->
    Res =:= {{error, disconnected}, {ok, maps:get(P, M#m.hal_out)},
             {ok, maps:get(P, M#m.plc)}};
check(M, _, {call, _, read, [P]}, Res) ->
    case lists:member(P, ?INPUTS) of
        true when M#m.up -> Res =:= {ok, maps:get(P, M#m.plc)};
        true -> Res =:= {error, disconnected};
        false -> Res =:= {ok, maps:get(P, M#m.hal_out)}
    end;
check(_, _, {call, _, watch, _}, Res) ->
    is_reference(Res);
check(_, M1, {call, _, cable, _}, Res) ->
    Res =:= ok andalso outputs_read(M1);
check(_, M1, {call, _, drop, []}, Res) ->
    Res =:= ok andalso outputs_read(M1);
check(M, M1, {call, _, kill, [P, _, _]}, {Write, Gone, Told, Plc, Reads}) ->
    %% The write in the moment the worker was gone: refused, and not replayed once up
    %% (the PLC holds what the model says, read after the reconnect).
    Write =:= {error, disconnected}
        andalso Gone =:= gone()
        andalso Plc =:= {ok, maps:get(P, M#m.plc)}
        andalso Told =:= case M#m.cable of
                             true -> [down, up];
                             false -> []
                         end
        andalso (not M#m.cable orelse Reads =:= expected_reads(M1));
check(M, _, {call, _, attempts, [N]}, Res) ->
    %% Every attempt failed: each logged the wait before the next, doubling.
    Res =:= waits(M#m.wait, N).

%% The watches the model says fired have fired, each with the value of its condition.
fired(Refs, M1) ->
    lists:all(fun(R) ->
                      receive {cell_hal_watch, R, _} -> true
                      after ?WAIT -> io:format(user, "~nwatch ~p not fired (~p)~n", [R, M1]), false
                      end
              end, Refs).

expected_reads(#m{hal_out = Out} = M) ->
    [{P, {ok, seen(P, M)}} || P <- ?INPUTS] ++ [{P, {ok, maps:get(P, Out)}} || P <- ?OUTPUTS].

outputs_read(#m{hal_out = Out}) ->
    lists:all(fun(P) -> cell_hal:read(io, P) =:= {ok, maps:get(P, Out)} end, ?OUTPUTS).

%% Those it says did not fire have not: cancelling them finds them unfired, and no
%% message of a watch came that the model did not expect.
unfired_as_modelled(#m{watches = Ws}) ->
    Unfired = [R || {R, _, _} <- Ws, not cell_hal:cancel_watch(R)],
    Stray = [R || {cell_hal_watch, R, _} <- drain()],
    case {Unfired, Stray} of
        {[], []} -> ok;
        _ -> {watches, fired_early, Unfired, stray, Stray}
    end.

allowed({call, _, set_input, _}, Res) -> element(1, Res) =:= ok orelse Res =:= {error, disconnected}
                                            orelse element(1, Res) =:= timeout;
allowed({call, _, write, _}, {ok, _, _, #{}}) -> true;
allowed({call, _, write, _}, {{error, disconnected}, _, _, #{}}) -> true;
allowed({call, _, read, _}, {ok, _}) -> true;
allowed({call, _, read, _}, {error, disconnected}) -> true;
allowed({call, _, watch, _}, Res) -> is_reference(Res);
allowed({call, _, kill, _}, #{write := Write, gone := Gone, down := Why}) ->
    %% The worker it killed was running (the kills take turns), and no other ran
    %% while it wrote and read.
    Write =:= {error, disconnected} andalso Gone =:= gone() andalso Why =:= killed;
allowed(_, Res) -> Res =:= ok orelse element(1, Res) =:= ok.

%% -------------------------------------------------------------------------------------
%% Commands, each waiting until the HAL has settled (never a fixed sleep)
%% -------------------------------------------------------------------------------------

%% Sets an input on the PLC; while up, waits for the HAL to read it.
set_input(P, V) ->
    ok = cell_hal_sim:set({io, P}, V),
    case {mode(), cell_hal:status(conn())} of
        {sequential, up} -> await(P, V);
        _ -> cell_hal:read(io, P)
    end.

plc_sets_output(P, V) ->
    ok = cell_hal_sim:set({io, P}, V),
    cell_hal:read(io, P).

%% A write confirmed by the PLC, or refused; then what the HAL and the PLC read. In a
%% parallel run also the value written and the span of the PLC's record it ran in (the
%% PLC's read is a call to it: what it took of the write is recorded before).
write(P, V) ->
    V1 = resolve(V),
    From = tick(),
    R = cell_hal:write_sync(io, P, V1, ?WAIT),
    Seen = {R, cell_hal:read(io, P), cell_hal_sim:get({io, P})},
    case mode() of
        sequential -> Seen;
        parallel -> erlang:append_element(Seen, #{value => V1, from => From, to => tick()})
    end.

read(P) ->
    cell_hal:read(io, P).

watch(P, V) ->
    {ok, Ref} = cell_hal:watch(io, P, {eq, V}),
    Ref.

%% The cable pulled (the connection goes down) or plugged back (it comes up).
cable(In) ->
    _ = In andalso forget_logs(),
    Was = cell_hal:status(conn()),
    ok = cell_hal_sim:link(conn(), case In of true -> up; false -> down end),
    case {mode(), Was, In} of
        {sequential, up, false} -> await_status(down);
        {sequential, down, true} -> up_and_quiet();
        _ -> ok
    end.

%% Up again: what was logged before coming up (its last failure) is the past.
up_and_quiet() ->
    Res = await_status(up),
    forget_logs(),
    Res.

drop() ->
    forget_logs(),
    ok = cell_hal_sim:drop(conn()),
    case mode() of
        sequential ->
            ok = await_status(down),
            up_and_quiet();
        parallel ->
            ok
    end.

%% Kills the worker and at once writes an output: a write the worker never confirmed
%% (it is gone, its successor not started); then asks the connection's status and
%% reads the inputs, in the same moment. Then, in a sequential run with the cable in
%% (as the model knows it), the connection's news until it is up again, what the PLC
%% holds of that output and what every point reads; in a parallel run how the worker
%% ended, the value written and the marks on the run's record the kill came between.
kill(P, V, CableIn) ->
    V1 = resolve(V),
    {Killed, Why, Write, Gone} = kill_and_write(P, V1),
    case mode() of
        sequential when CableIn ->
            Told = told_until_up([]),
            forget_logs(),
            Reads = [{Q, settled_read(Q, element(2, cell_hal_sim:get({io, Q})))}
                     || Q <- ?INPUTS] ++ [{Q, cell_hal:read(io, Q)} || Q <- ?OUTPUTS],
            {Write, Gone, Told, cell_hal_sim:get({io, P}), Reads};
        sequential ->
            {Write, Gone, [], cell_hal_sim:get({io, P}), []};
        parallel ->
            #{write => Write, gone => Gone, down => Why, value => V1, killed => Killed}
    end.

%% What the connection says while no worker runs, whatever the cable: down, and no
%% input read.
gone() ->
    {down, [{error, disconnected} || _ <- ?INPUTS]}.

%% The worker's supervisor is held back (suspended, it leaves the worker's exit in its
%% mailbox) from before the worker is looked up until after the write and the reads,
%% so they surely come while no worker runs. The kills of a parallel run take turns: one that
%% resumed the supervisor while another held it would let a successor start under the
%% other's write, and one could look up a worker the other had just killed.
kill_and_write(P, V) ->
    Sup = ets:lookup_element(?TAB, sup, 2),
    Lock = ets:lookup_element(?TAB, lock, 2),
    Lock ! {lock, self()},
    receive {locked, Lock} -> ok end,
    Old = cell_hal_test_worker_sup:worker(Sup),
    ok = sys:suspend(Sup),
    Ref = monitor(process, Old),
    Before = tick(),
    exit(Old, kill),
    Why = receive {'DOWN', Ref, process, Old, W} -> W end,
    Killed = {Before, tick()},
    Write = cell_hal:write_sync(io, P, V, ?WAIT),
    Gone = {cell_hal:status(conn()), [cell_hal:read(io, Q) || Q <- ?INPUTS]},
    ok = sys:resume(Sup),
    Lock ! {unlock, self()},
    {Killed, Why, Write, Gone}.

%% One process at a time holds it, until it unlocks or ends.
lock() ->
    receive
        {lock, Pid} ->
            Ref = monitor(process, Pid),
            Pid ! {locked, self()},
            receive
                {unlock, Pid} -> demonitor(Ref, [flush]);
                {'DOWN', Ref, process, Pid, _} -> ok
            end,
            lock();
        stop ->
            ok
    end.

%% A value of the run's own (see written/2).
resolve(fresh) -> 100 + ets:update_counter(?TAB, fresh, 1);
resolve(V) -> V.

%% The next mark on the run's record: every value the PLC takes on an output is noted
%% with one, as the PLC takes it.
tick() -> ets:update_counter(?TAB, tick, 1).

%% The connection's news in order, until it is up.
told_until_up(Acc) ->
    Conn = conn(),
    receive
        {cell_hal_conn, Conn, up} -> lists:reverse([up | Acc]);
        {cell_hal_conn, Conn, S} -> told_until_up([S | Acc])
    after ?WAIT -> lists:reverse([timeout | Acc])
    end.

%% The waits the worker logs after its next N failed attempts (it logs the wait before
%% each next attempt, "retrying in 10 ms").
attempts(N) ->
    Source = source(),
    [next_retry(Source) || _ <- lists:seq(1, N)].

%% Other lines of the connection (its coming up a moment after it was announced) say
%% no wait.
next_retry(Source) ->
    receive
        {cell_log, #{source := Source, text := Text}} ->
            case retry_ms(Text) of
                not_a_retry -> next_retry(Source);
                Ms -> Ms
            end
    after ?WAIT -> no_attempt
    end.

forget_logs() ->
    receive {cell_log, _} -> forget_logs() after 0 -> ok end.

retry_ms(Text) ->
    case re:run(Text, <<"retrying in ([0-9]+) ms">>, [{capture, all_but_first, binary}]) of
        {match, [Ms]} -> binary_to_integer(Ms);
        nomatch -> not_a_retry
    end.

await(P, V) ->
    {ok, Ref} = cell_hal:watch(io, P, {eq, V}),
    receive {cell_hal_watch, Ref, V} -> {ok, V}
    after ?WAIT -> {timeout, cell_hal:read(io, P)}
    end.

%% The connection's messages are taken in their order: one of another status before
%% the awaited one is past (a repeat of the status the subscription returned, say).
await_status(Status) ->
    Conn = conn(),
    receive
        {cell_hal_conn, Conn, Status} -> ok;
        {cell_hal_conn, Conn, _} -> await_status(Status)
    after ?WAIT -> {timeout, Status, cell_hal:status(Conn)}
    end.

%% -------------------------------------------------------------------------------------
%% After a parallel run: the cable in, the connection up; the inputs read the PLC's
%% values; after a momentary loss the outputs read what the PLC holds.
%% -------------------------------------------------------------------------------------

final_check() ->
    true = ets:insert(?TAB, {mode, sequential}),
    Conn = conn(),
    ok = cell_hal_sim:link(Conn, up),
    _ = drain(),
    {ok, _} = cell_hal:subscribe_connection(Conn),
    ok = cell_hal_sim:drop(Conn),
    Up = await_up(),
    Plc = maps:from_list([{P, V} || P <- ?INPUTS ++ ?OUTPUTS, {ok, V} <- [cell_hal_sim:get({io, P})]]),
    Wrong = [{P, maps:get(P, Plc), Got} || P <- ?INPUTS ++ ?OUTPUTS, is_map_key(P, Plc),
                                           Got <- [settled_read(P, maps:get(P, Plc))],
                                           Got =/= {ok, maps:get(P, Plc)}],
    case {Up, Wrong} of
        {ok, []} -> ok;
        _ -> {not_settled, Up, Wrong}
    end.

%% What the PLC took of the outputs in the run (each value recorded as it took it)
%% agrees with what every write was answered, as the HAL's contract has it:
%% <ul>
%% <li>a confirmed write was taken while it ran, once;</li>
%% <li>a write answered `disconnected' was never taken, unless the worker it was sent
%%   to was killed with it on its way (a kill while it ran): then it may have been
%%   taken while it ran, never after, as a real PLC takes what was on the wire when
%%   the sender died. (The simulated PLC answers at once and takes nothing on a
%%   connection it dropped, so no other answer can be lost);</li>
%% <li>a kill's own write, made while no worker runs, was never taken.</li>
%% </ul>
%% Only fresh values tell whose write the PLC took; of the boolean output, a confirmed
%% write is checked by its value alone.
taken_as_answered({SeqCmds, _ParCmds}, Seq, Par) ->
    Calls = [Call || {set, _, Call} <- SeqCmds],
    Answered = lists:zip(Calls, [Res || {_, Res} <- Seq])
        ++ [{Call, Res} || {{set, _, Call}, Res} <- lists:append(Par)],
    Took = [{T, P, V} || {{took, T}, P, V} <- ets:tab2list(?TAB)],
    Kills = [Killed || {{call, _, kill, _}, #{killed := Killed}} <- Answered],
    Wrong = [{Call, Res} || {Call, Res} <- Answered, not taken_as(Call, Res, Took, Kills)],
    case Wrong of
        [] -> ok;
        _ -> {not_as_answered, Wrong, lists:sort(Took)}
    end.

taken_as({call, _, write, [P, fresh]}, {R, _, _, #{value := V, from := From, to := To}},
         Took, Kills) ->
    KilledMeanwhile = lists:any(fun({K0, K1}) -> K0 < To andalso K1 > From end, Kills),
    case [T || {T, Q, W} <- Took, Q =:= P, W =:= V] of
        [] -> R =:= {error, disconnected};
        [T] -> T > From andalso T < To andalso (R =:= ok orelse KilledMeanwhile);
        _ -> false
    end;
taken_as({call, _, write, [P, _]}, {ok, _, _, #{value := V, from := From, to := To}}, Took,
         _Kills) ->
    lists:any(fun({T, Q, W}) -> Q =:= P andalso W =:= V andalso T > From andalso T < To end,
              Took);
taken_as({call, _, kill, [P, _, _]}, #{value := V}, Took, _Kills) ->
    not lists:any(fun({_, Q, W}) -> Q =:= P andalso W =:= V end, Took);
taken_as(_, _, _, _) ->
    true.

%% After the drop: down, then up (a status message may repeat the status in force).
await_up() ->
    case cell_hal:status(conn()) of
        up ->
            receive {cell_hal_conn, _, up} -> ok after ?WAIT -> no_up end;
        down ->
            await_status(up)
    end.

settled_read(P, V) ->
    case lists:member(P, ?INPUTS) of
        true -> await(P, V);
        false -> cell_hal:read(io, P)
    end.

%% -------------------------------------------------------------------------------------
%% A connection of its own for each run, on a HAL started once
%% -------------------------------------------------------------------------------------

setup() ->
    cell_hal_prop_env:start("prop_cell_hal_worker", ?TAB).

cleanup(Env) ->
    cell_hal_prop_env:stop(Env, ?TAB).

start_conn(Mode) ->
    N = ets:update_counter(?TAB, run, 1),
    Conn = list_to_atom("hw_" ++ integer_to_list(N)),
    Source = <<"hal/", (atom_to_binary(Conn))/binary>>,
    true = ets:insert(?TAB, [{mode, Mode}, {conn, Conn}, {source, Source}]),
    ok = cell_hal:add_connection(#{id => Conn, driver => cell_hal_sim,
                                   opts => #{poll_ms => 2, reconnect_ms => ?RECONNECT_MS,
                                             max_reconnect_ms => ?MAX_RECONNECT_MS,
                                             timeout_ms => 500}}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => Conn,
                              opts => #{only => ?INPUTS ++ ?OUTPUTS}}),
    true = ets:insert(?TAB, {sup, cell_hal_test_worker_sup:adopt(Conn)}),
    ok = cell_hal_sim:preset(Conn, maps:from_list([{{io, P}, zero(P)} || P <- ?INPUTS ++ ?OUTPUTS])),
    %% The run's record of what the PLC takes on its outputs, each noted as it takes it.
    _ = ets:match_delete(?TAB, {{took, '_'}, '_', '_'}),
    true = ets:insert(?TAB, [{tick, 0}, {fresh, 0}, {lock, spawn_link(fun lock/0)}]),
    [ok = cell_hal_sim:on_change({io, P}, fun(V) -> took(P, V) end) || P <- ?OUTPUTS],
    %% Up, and the outputs read back from the PLC's preset image.
    ok = case cell_hal:subscribe_connection(Conn) of
             {ok, up} -> ok;
             {ok, down} -> await_status(up)
         end,
    ok = cell_hal_sim:drop(Conn),
    ok = await_status(down),
    ok = await_status(up),
    [{ok, _} = await(P, zero(P)) || P <- ?INPUTS],
    ok = cell_log:set_level(Source, verbose),
    ok = cell_log:subscribe(),
    Conn.

took(P, V) ->
    true = ets:insert(?TAB, {{took, tick()}, P, V}),
    [].

stop_conn(Conn) ->
    ets:lookup_element(?TAB, lock, 2) ! stop,
    _ = cell_log:unsubscribe(),
    ok = cell_hal:unsubscribe_connection(Conn),
    ok = cell_hal_test_worker_sup:release(ets:lookup_element(?TAB, sup, 2)),
    ok = cell_hal_sim:stop_device(Conn),
    ok = cell_hal:remove_group(io),
    ok = cell_hal:remove_connection(Conn),
    _ = drain(),
    ok.

conn() -> ets:lookup_element(?TAB, conn, 2).
source() -> ets:lookup_element(?TAB, source, 2).
mode() -> ets:lookup_element(?TAB, mode, 2).

drain() ->
    receive M -> [M | drain()] after 0 -> [] end.
