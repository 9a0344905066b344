%% A PropEr state-machine property of handshakes (seed 000 §2.3.6) on a line of 3 to 5
%% conveyor segments (cell_line_task) that moves products on its own between commands:
%% products are fed in, the cell is started, paused, stopped, emergency-stopped,
%% segments and links are killed, the line is drained (the operator answering what it
%% asks). Pause, Stop and the emergency stop race the transfers under way, and with
%% them the seed's TryAbortOffering against a commit.
%%
%% Checked: every pause and stop settles within a bound (no deadlock); whenever the
%% line is still, every product fed in is out or owned by exactly one segment, on
%% disk and in memory (none lost, none duplicated); a drain gets every product out.
%%
%% The harness (commands, setup, checks) serves prop_cell_handover too, whose line is
%% written with the framework's hand-over patterns (cell_handover_task) and whose
%% operator also answers Reset: a product the operator said is not there (forgotten)
%% is accounted for as such.
-module(prop_cell_line).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([feed/1, start/0, pause/0, stop/0, estop/1, kill_task/1, kill_link/1, drain/0]).
-export([setup/1, setup/2, setup/3, teardown/0, final_check/0, model/1, tab/0, size/0, task/1,
         info/1]).

-define(BOUND, 15000).

-record(m, {size = 3 :: 3..5, running = false :: boolean(), estop = false :: boolean(),
            fed = 0 :: non_neg_integer(), mode = sequential :: sequential | parallel}).

sequential_test_() ->
    {timeout, 900, ?_assert(proper:quickcheck(prop_sequential(),
                                              [{to_file, user}, {numtests, 40}]))}.

parallel_test_() ->
    {timeout, 900, ?_assert(proper:quickcheck(prop_parallel(),
                                              [{to_file, user}, {numtests, 25}]))}.

prop_sequential() ->
    ?FORALL(Size, range(3, 5),
            ?FORALL(Cmds, commands(?MODULE, #m{size = Size}),
                    begin
                        setup(Size),
                        {History, State, Result} = run_commands(?MODULE, Cmds),
                        Final = final_check(),
                        teardown(),
                        ?WHENFAIL(io:format(user, "Size ~p~nHistory: ~p~nState: ~p~n"
                                            "Result: ~p~nFinal: ~p~n",
                                            [Size, History, State, Result, Final]),
                                  aggregate(command_names(Cmds),
                                            Result =:= ok andalso Final =:= ok))
                    end)).

%% Commands race each other. A check while another branch moves the line would see
%% no still line, so here the commands only act, and the final check — drain, stop
%% within the bound, every product accounted for — judges whatever the interleaving.
prop_parallel() ->
    ?FORALL(Size, range(3, 5),
            ?FORALL(Cmds, parallel_commands(?MODULE, #m{size = Size, mode = parallel}),
                    begin
                        setup(Size),
                        true = ets:insert(tab(), {mode, parallel}),
                        {Seq, Par, Result} = run_parallel_commands(?MODULE, Cmds),
                        Final = final_check(),
                        teardown(),
                        ?WHENFAIL(io:format(user, "Size ~p~nSeq: ~p~nPar: ~p~nResult: ~p~n"
                                            "Final: ~p~n", [Size, Seq, Par, Result, Final]),
                                  Result =:= ok andalso Final =:= ok)
                    end)).

%% -------------------------------------------------------------------------------------
%% Model: what the controller was told; the line's own motion is checked, not predicted.
%% -------------------------------------------------------------------------------------

initial_state() -> #m{}.

%% The model of a line of `Size' segments, before any command.
-spec model(3..5) -> #m{}.
model(Size) -> #m{size = Size}.

command(#m{size = Size} = M) ->
    Tasks = tasks(Size),
    Links = links(Size),
    frequency([{4, {call, ?MODULE, feed, [range(1, 3)]}},
               {4, {call, ?MODULE, start, []}},
               {2, {call, ?MODULE, pause, []}},
               {2, {call, ?MODULE, stop, []}},
               {1, {call, ?MODULE, estop, [not M#m.estop]}},
               {2, {call, ?MODULE, kill_task, [elements(Tasks)]}},
               {2, {call, ?MODULE, kill_link, [elements(Links)]}},
               {3, {call, ?MODULE, drain, []}}]).

precondition(#m{running = Running, estop = Estop, mode = Mode}, {call, _, drain, []}) ->
    Running andalso not Estop andalso Mode =:= sequential;
precondition(_M, _Call) ->
    true.

next_state(M, _Res, {call, _, feed, [N]}) -> M#m{fed = M#m.fed + N};
next_state(#m{estop = true} = M, _Res, {call, _, start, []}) -> M;
next_state(M, _Res, {call, _, start, []}) -> M#m{running = true};
next_state(M, _Res, {call, _, pause, []}) -> M#m{running = false};
next_state(M, _Res, {call, _, stop, []}) -> M#m{running = false};
next_state(M, _Res, {call, _, estop, [true]}) -> M#m{running = false, estop = true};
next_state(M, _Res, {call, _, estop, [false]}) -> M#m{estop = false};
next_state(M, _Res, _Call) -> M.

postcondition(#m{estop = true}, {call, _, start, []}, Res) ->
    Res =:= {error, estop_active};
postcondition(#m{mode = Mode}, {call, _, _, _}, Res) ->
    case Res of
        ok ->
            true;
        Other ->
            %% In parallel runs PropEr tries interleavings that do not fit: no noise.
            Mode =:= sequential andalso io:format(user, "~nFailed: ~p~n", [Other]),
            false
    end.

tasks(Size) -> [task(I) || I <- lists:seq(1, Size)].
links(Size) -> [hs_link(I) || I <- lists:seq(1, Size - 1)].
task(I) -> list_to_atom("seg" ++ integer_to_list(I)).
hs_link(I) -> list_to_atom("hs" ++ integer_to_list(I)).

%% -------------------------------------------------------------------------------------
%% Commands
%% -------------------------------------------------------------------------------------

feed(N) ->
    #{feed := Feed, ref := Ref} = config(),
    Base = erlang:unique_integer([positive]) * 10,
    Items = [{Base + I, <<"S-", (integer_to_binary(Base + I))/binary>>} || I <- lists:seq(1, N)],
    true = ets:insert(Feed, Items),
    true = ets:insert(tab(), [{{fed, S}, true} || {_, S} <- Items]),
    case cell_task_proc:whereis(task(1)) of
        undefined -> ok;
        Pid -> Pid ! {Ref, fed}, ok
    end.

start() ->
    cell_controller:start().

%% Pause settles within the bound: no task left READY (a transfer under way finishes
%% first); then the products are all accounted for.
pause() ->
    ok = cell_controller:pause(),
    settle(fun(S) -> S =/= ready end).

stop() ->
    ok = cell_controller:stop(),
    settle(fun(S) -> S =:= off end).

estop(true) ->
    ok = cell_controller:estop(true),
    settle(fun(S) -> S =:= off end);
estop(false) ->
    cell_controller:estop(false).

%% Kills a segment and returns once its restart has booted (a concurrent kill of
%% the same segment may have done it already).
kill_task(Id) ->
    ok = cell_events:subscribe([task_crashed]),
    case cell_task_proc:whereis(Id) of
        undefined ->
            await_crashed(Id);
        Pid ->
            MRef = monitor(process, Pid),
            exit(Pid, kill),
            receive {'DOWN', MRef, process, Pid, _} -> ok end,
            await_crashed(Id)
    end.

await_crashed(Id) ->
    receive
        {cell_event, #{type := task_crashed, task := Id}} -> ok
    after ?BOUND ->
        {no_restart, Id}
    end.

kill_link(Link) ->
    case cell_handshake_link:whereis(Link) of
        undefined -> ok;
        Pid -> exit(Pid, kill), ok
    end.

%% Runs the line until every product fed in is out, answering the operator's
%% questions as someone who finds each product where the cell says it is.
drain() ->
    ok = cell_events:subscribe([alarm_raised, task_state]),
    drain(erlang:monotonic_time(millisecond) + ?BOUND).

drain(Deadline) ->
    answer_errors(),
    %% A product the operator's Reset made a segment forget does not come out.
    Missing = [S || {{fed, S}, _} <- ets:match_object(tab(), {{fed, '_'}, '_'}),
                    not ets:member(out_tab(), S), not ets:member(tab(), {forgotten, S})],
    case Missing of
        [] ->
            check();
        _ ->
            Left = Deadline - erlang:monotonic_time(millisecond),
            receive
                {cell_event, _} -> drain(Deadline);
                {line_out, _, _} -> drain(Deadline)
            after max(0, Left) ->
                {stuck, Missing, states(), cell_alarms:list(), detail()}
            end
    end.

answer_errors() ->
    lists:foreach(fun(#{id := Id, kind := error, solutions := Sols}) ->
                          Answer = case lists:member(ignore, Sols) of
                                       true -> ignore;
                                       false -> retry
                                   end,
                          _ = cell_alarms:answer(Id, Answer, <<"property">>);
                     (_) ->
                          ok
                  end, cell_alarms:list()).

%% Waits, within the bound, until every segment runs and is in a state the predicate
%% accepts; then checks conservation.
settle(Accept) ->
    case ets:lookup(tab(), mode) of
        [{mode, parallel}] ->
            ok;
        [] ->
            ok = cell_events:subscribe([task_state, task_crashed]),
            settle(Accept, erlang:monotonic_time(millisecond) + ?BOUND)
    end.

settle(Accept, Deadline) ->
    States = states(),
    Done = lists:all(fun(undefined) -> false;
                        ({ready, _, _}) -> Accept(ready);
                        (S) -> Accept(S)
                     end, States),
    case Done of
        true ->
            check();
        false ->
            Left = Deadline - erlang:monotonic_time(millisecond),
            receive
                {cell_event, _} -> settle(Accept, Deadline)
            after max(0, Left) ->
                {deadlock, States}
            end
    end.

%% What each segment does, for a report of a line that does not move.
detail() ->
    [{T, maps:with([phase, product, marker, waits, down, links], info(T))} || T <- tasks(size())].

info(T) ->
    case cell_task_proc:whereis(T) of
        undefined -> #{};
        Pid -> try cell_task_proc:info(Pid) catch exit:_ -> #{} end
    end.

states() ->
    ok = catch_sync(),
    [case cell_task_proc:whereis(T) of
         undefined -> undefined;
         Pid -> try cell_task_proc:state(Pid) catch exit:_ -> undefined end
     end || T <- tasks(size())].

catch_sync() ->
    try cell_controller:sync() catch exit:_ -> ok end.

%% Every product fed in is out, waiting in the feed, or owned by exactly one segment:
%% on disk (the highest generation, never shared) and in memory.
check() ->
    %% A segment may be inside a step that sends a product out (the drain saw it in
    %% the out table): the files are read once every segment is between steps.
    ok = catch_sync(),
    #{root := Root, feed := Feed} = config(),
    Files = filelib:wildcard(filename:join([Root, "Data", "*.product"])),
    Stored = [{S, G} || F <- Files, {ok, #{product := #{serial := S}, gen := G}}
                                        <- [cell_product:load(F)]],
    Owners = lists:usort([S || {S, _} <- Stored]),
    Shared = [S || S <- Owners,
                   begin
                       Gens = [G || {S1, G} <- Stored, S1 =:= S],
                       length([G || G <- Gens, G =:= lists:max(Gens)]) > 1
                   end],
    InMemory = lists:sort([S || T <- tasks(size()), #{product := #{serial := S}} <- [info(T)]]),
    Fed = lists:sort([S || {{fed, S}, _} <- ets:match_object(tab(), {{fed, '_'}, '_'})]),
    Out = [S || {S, _} <- ets:tab2list(out_tab())],
    Waiting0 = [S || {_, S} <- ets:tab2list(Feed)],
    %% The first segment saves a new product before its feed entry goes: for a moment
    %% (or until its init after a crash) it is both owned and waiting.
    First = case info(task(1)) of
                #{product := #{serial := S1}} -> [S1];
                _ -> []
            end,
    Waiting = Waiting0 -- First,
    %% What the operator's Reset made a segment forget (it said the product is not
    %% there): gone by the operator's word, never by the line's doing.
    Forgotten = [S || {{forgotten, S}, _} <- ets:match_object(tab(), {{forgotten, '_'}, '_'})],
    Twice = [S || {{duplicate_out, S}, _} <- ets:match_object(tab(), {{duplicate_out, '_'}, '_'})],
    Accounted = Out ++ Owners ++ Waiting,
    Problems =
        [{shared_owner, Shared} || Shared =/= []]
        ++ [{duplicate_in_memory, InMemory} || lists:usort(InMemory) =/= InMemory]
        ++ [{memory_and_disk, InMemory, Owners} || InMemory =/= Owners]
        ++ [{out_and_owned, [S || S <- Owners, lists:member(S, Out)]}
            || [S || S <- Owners, lists:member(S, Out)] =/= []]
        ++ [{sent_out_twice, Twice} || Twice =/= []]
        ++ [{lost, Fed -- (Accounted ++ Forgotten)} || Fed -- (Accounted ++ Forgotten) =/= []]
        ++ [{extra_or_twice, Accounted -- Fed} || Accounted -- Fed =/= []]
        ++ [{twice, Accounted -- lists:usort(Accounted)}
            || lists:sort(Accounted) =/= lists:usort(Accounted)],
    case Problems of
        [] -> ok;
        _ -> {conservation, Problems}
    end.

%% After every run: release the emergency stop, drain what is left, then stop — each
%% step within the bound — and account for every product.
final_check() ->
    true = ets:delete(tab(), mode),
    ok = cell_controller:estop(false),
    case cell_controller:start() of
        ok ->
            case drain() of
                ok -> stop();
                Other -> Other
            end;
        Error ->
            Error
    end.

%% -------------------------------------------------------------------------------------
%% A fresh line for each run
%% -------------------------------------------------------------------------------------

setup(Size) ->
    setup(Size, cell_line_task).

%% A fresh line of `Size' segments of the task module `Module'.
setup(Size, Module) ->
    setup(Size, Module, 1).

%% As setup/2, the segments' moves `Slower' times as long (transfers that take longer
%% are more often cut off by the commands).
setup(Size, Module, Slower) ->
    Root = filename:join(["/tmp", "prop_cell_line", os:getpid()]),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    Tab = ets:new(prop_cell_line_tab, [named_table, public]),
    Feed = ets:new(prop_cell_line_feed, [ordered_set, public]),
    Out = ets:new(prop_cell_line_out, [named_table, public]),
    Ref = make_ref(),
    true = ets:insert(Tab, {config, #{root => Root, feed => Feed, ref => Ref, size => Size}}),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    Tasks = [#{id => task(I), module => Module, zone => <<"Seg">>,
               lane => integer_to_binary(I),
               args => #{prev => case I of 1 -> undefined; _ -> hs_link(I - 1) end,
                         next => case I of Size -> undefined; _ -> hs_link(I) end,
                         feed => Feed, out => Out, ref => Ref, notify => self(), sensors => Tab,
                         delay => (I * 3) rem 5 * Slower}}
             || I <- lists:seq(1, Size)],
    Links = [#{id => hs_link(I), from => task(I), to => task(I + 1)} || I <- lists:seq(1, Size - 1)],
    ok = application:set_env(cell, cell_spec, #{tasks => Tasks, links => Links}),
    quiet(),
    {ok, _} = application:ensure_all_started(cell),
    ok.

teardown() ->
    ok = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    ets:delete(maps:get(feed, config())),
    ets:delete(prop_cell_line_tab),
    ets:delete(prop_cell_line_out),
    flush().

tab() -> prop_cell_line_tab.
out_tab() -> prop_cell_line_out.
config() -> ets:lookup_element(tab(), config, 2).
size() -> maps:get(size, config()).

flush() ->
    receive _ -> flush() after 0 -> ok end.

quiet() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, true).
