%% A PropEr state-machine model of one handshake link (seed 000 §2.3.6) between two
%% device tasks (cell_hs_model_task), written from the seed's text: the phases 1-4
%% (Available with Data, NotBusy, Available off, NotBusy off), TryAbortOffering
%% (withdraws the offer "in a thread safe manner" or answers false once the next device
%% has committed), PeekBoardAvailable (looks without setting the locking flag: the next
%% device adjusts, then locks with the formal check of Available), the Abort signal, and
%% the link, the upstream or the downstream task killed in every phase (the seed's
%% Thread.Abort: an exit under a supervisor).
%%
%% The model is what the seed says each side may believe: the phase, who holds the
%% product (the previous device until phase 3 resets its variable, the next device
%% from then; the next device keeps a copy of the reference from phase 2), whether a
%% product whose transfer was cut off while it moved waits for the operator's word.
%% After every command of a sequential run both tasks are looked at and the product
%% files read: each product is held by exactly one side, on disk (the record of the
%% highest generation) and in memory, none lost, none resurrected; TryAbortOffering
%% succeeds exactly before the commit, the commit exactly on an open offer, a peek
%% never locks.
%%
%% Parallel runs race the two sides' commands (the seed's nanosecond between a
%% TryAbortOffering and a commit) and kills; each task acts only on what it sees (as
%% the seed's loops do), and the run is judged at its end: a transfer committed to is
%% carried out, an open offer withdrawn, and every product made is held by exactly one
%% side (on disk and in memory) or shipped.
-module(prop_cell_handshake).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([new/1, up/1, down/1, release/0, kill/1]).
-export([setup/0, cleanup/1, prop_sequential/0, prop_parallel/0, start_pair/1, stop_pair/1]).
-export([init/1]).

-define(WAIT, 10000).
-define(TAB, prop_cell_handshake).
-define(SUP, prop_cell_handshake_sup).

-record(m, {n = 0 :: non_neg_integer(),                %% products made so far
            phase = idle :: idle | offered | committed | released,
            up = none :: pos_integer() | none,        %% the previous device's product
            down = none :: pos_integer() | none,      %% the next device's product
            ref = none :: pos_integer() | none,            %% the next device's copy (phase 2)
            up_transit = false :: boolean(),
            down_transit = false :: boolean(),
            outcome = undefined :: undefined | completed | aborted | interrupted,
            shipped = [] :: [pos_integer()],
            mode = sequential :: sequential | parallel}).

handshake_test_() ->
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
                Pair = start_pair(sequential),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                stop_pair(Pair),
                ?WHENFAIL(io:format(user, "History: ~p~nState: ~p~nResult: ~p~n",
                                    [History, State, Result]),
                          aggregate(command_names(Cmds), Result =:= ok))
            end).

prop_parallel() ->
    ?FORALL(Cmds, parallel_commands(?MODULE, #m{mode = parallel}),
            begin
                Pair = start_pair(parallel),
                {Seq, Par, Result} = run_parallel_commands(?MODULE, Cmds),
                Final = final_check(),
                stop_pair(Pair),
                ?WHENFAIL(io:format(user, "Seq: ~p~nPar: ~p~nResult: ~p~nFinal: ~p~n",
                                    [Seq, Par, Result, Final]),
                          Result =:= ok andalso Final =:= ok)
            end).

%% -------------------------------------------------------------------------------------
%% The model, from the seed
%% -------------------------------------------------------------------------------------

initial_state() -> #m{}.

command(#m{mode = sequential, phase = Phase} = M) ->
    frequency([{3, {call, ?MODULE, new, [M#m.n + 1]}} || M#m.up =:= none, Phase =:= idle]
              ++ [{6, {call, ?MODULE, up, [offer]}} || M#m.up =/= none, Phase =:= idle]
              ++ [{4, {call, ?MODULE, down, [ship]}} || M#m.down =/= none]
              ++ [{6, {call, ?MODULE, down, [commit]}} || Phase =:= offered]
              ++ [{6, {call, ?MODULE, release, []}} || Phase =:= committed]
              ++ [{6, {call, ?MODULE, down, [complete]}} || Phase =:= released]
              ++ [{2, {call, ?MODULE, down, [abort]}} || Phase =/= idle, Phase =/= offered]
              ++ [{2, {call, ?MODULE, up, [confirm]}} || M#m.up_transit]
              ++ [{3, {call, ?MODULE, down, [confirm]}} || M#m.down_transit]
              ++ [{3, {call, ?MODULE, up, [try_abort_offering]}},
                  {2, {call, ?MODULE, up, [finish]}},
                  {3, {call, ?MODULE, down, [peek]}},
                  {1, {call, ?MODULE, down, [commit]}},
                  {3, {call, ?MODULE, kill, [elements([up, down, link])]}}]);
%% In parallel each side's commands are what its loop would do next; new serials come
%% from the table, since branches cannot share the model's counter.
command(#m{mode = parallel}) ->
    frequency([{3, {call, ?MODULE, new, [next]}},
               {4, {call, ?MODULE, up, [offer]}},
               {3, {call, ?MODULE, up, [try_abort_offering]}},
               {3, {call, ?MODULE, release, []}},
               {2, {call, ?MODULE, up, [finish]}},
               {3, {call, ?MODULE, down, [peek]}},
               {4, {call, ?MODULE, down, [commit]}},
               {3, {call, ?MODULE, down, [complete]}},
               {1, {call, ?MODULE, down, [abort]}},
               {2, {call, ?MODULE, down, [ship]}},
               {1, {call, ?MODULE, kill, [elements([up, down, link])]}}]).

%% What the seed's code does at each point: the previous device offers a product it
%% holds, releases once NotBusy came; the next device commits when it is empty,
%% completes once Available went off, aborts a transfer under way; the operator
%% confirms a product whose transfer was cut off while it moved.
precondition(#m{mode = parallel}, _) -> true;
%% The previous device takes its next product only once its transfer is over (phase 4:
%% the seed resets its variable after NotBusy went off, and only without Abort).
precondition(M, {call, _, new, [_]}) -> M#m.up =:= none andalso M#m.phase =:= idle;
precondition(M, {call, _, up, [offer]}) ->
    M#m.up =/= none andalso M#m.phase =:= idle andalso not M#m.up_transit;
precondition(M, {call, _, release, []}) -> M#m.phase =:= committed;
precondition(M, {call, _, up, [confirm]}) -> M#m.up_transit;
precondition(M, {call, _, down, [commit]}) -> M#m.down =:= none andalso M#m.ref =:= none;
precondition(M, {call, _, down, [complete]}) -> M#m.phase =:= released;
precondition(M, {call, _, down, [abort]}) ->
    M#m.phase =:= committed orelse M#m.phase =:= released;
precondition(M, {call, _, down, [ship]}) ->
    M#m.down =/= none andalso M#m.phase =:= idle andalso not M#m.down_transit;
precondition(M, {call, _, down, [confirm]}) -> M#m.down_transit;
precondition(_, _) -> true.

next_state(#m{mode = parallel} = M, _, _) ->
    M;
next_state(M, _, {call, _, new, [N]}) ->
    M#m{n = N, up = serial(N)};
next_state(M, _, {call, _, up, [offer]}) ->
    M#m{phase = offered, outcome = undefined};
next_state(#m{phase = offered} = M, _, {call, _, up, [try_abort_offering]}) ->
    M#m{phase = idle};
next_state(M, _, {call, _, release, []}) ->
    %% Phase 3: the product has left the previous device.
    M#m{phase = released, down = M#m.up, ref = none, up = none, down_transit = true};
next_state(M, _, {call, _, up, [finish]}) ->
    M#m{outcome = undefined};
next_state(M, _, {call, _, up, [confirm]}) ->
    M#m{up_transit = false};
next_state(#m{phase = offered} = M, _, {call, _, down, [commit]}) ->
    %% Phase 2: the next device copies the reference; the previous one still holds it.
    M#m{phase = committed, ref = M#m.up};
next_state(M, _, {call, _, down, [complete]}) ->
    M#m{phase = idle, down_transit = false, outcome = completed};
next_state(#m{phase = committed} = M, _, {call, _, down, [abort]}) ->
    M#m{phase = idle, ref = none, outcome = aborted};
next_state(#m{phase = released} = M, _, {call, _, down, [abort]}) ->
    %% After phase 3 the product goes back to the previous device.
    M#m{phase = idle, up = M#m.down, down = none, down_transit = false, outcome = aborted};
next_state(M, _, {call, _, down, [ship]}) ->
    M#m{down = none, shipped = [M#m.down | M#m.shipped]};
next_state(M, _, {call, _, down, [confirm]}) ->
    M#m{down_transit = false};
next_state(M, _, {call, _, kill, [Who]}) ->
    killed(Who, M);
next_state(M, _, _) ->
    M.

%% A side that stops ends the transfer for the other: an open offer stands for a next
%% device that comes back (it had not read Available), and goes with a previous device
%% that stopped or a link that forgot it; after the commit and before phase 3 the
%% product never left the previous device; after phase 3 it is the next device's,
%% marked as moving until the operator says it is there. A restarted previous device
%% has no outcome to finish.
killed(up, #m{phase = Phase} = M) ->
    (cut(Phase, M))#m{outcome = undefined};
killed(down, #m{phase = offered} = M) ->
    M;
killed(down, #m{phase = idle} = M) ->
    M;
killed(_, #m{phase = Phase} = M) ->
    Cut = cut(Phase, M),
    case Phase of
        committed -> Cut#m{outcome = interrupted};
        released -> Cut#m{outcome = interrupted};
        _ -> Cut
    end.

cut(idle, M) -> M;
cut(offered, M) -> M#m{phase = idle};
cut(committed, M) -> M#m{phase = idle, ref = none};
cut(released, M) -> M#m{phase = idle}.

%% -- postconditions ---------------------------------------------------------------------

postcondition(#m{mode = parallel}, Call, Res) ->
    allowed(Call, Res);
postcondition(M, {call, _, _, _} = Call, {Reply, Seen}) ->
    M1 = next_state(M, Reply, Call),
    Expected = expected_reply(M, Call),
    Checks = [{reply, Expected, Reply} || Expected =/= any, Reply =/= Expected]
             ++ seen(M1, Seen),
    case Checks of
        [] -> true;
        _ -> io:format(user, "~nFailed ~p: ~p~n", [Call, Checks]), false
    end.

expected_reply(#m{phase = P}, {call, _, up, [try_abort_offering]}) ->
    %% Clears Available before the commit; false once the next device committed.
    P =:= idle orelse P =:= offered;
expected_reply(#m{phase = offered, up = S}, {call, _, down, [peek]}) -> {ok, S};
expected_reply(_, {call, _, down, [peek]}) -> none;
expected_reply(#m{phase = offered}, {call, _, down, [commit]}) -> ok;
expected_reply(_, {call, _, down, [commit]}) -> not_available;
expected_reply(#m{outcome = undefined}, {call, _, up, [finish]}) -> pending;
expected_reply(#m{outcome = O}, {call, _, up, [finish]}) -> O;
expected_reply(#m{down = S}, {call, _, down, [ship]}) -> {ok, S};
expected_reply(_, {call, _, kill, _}) -> any;
expected_reply(_, _) -> ok.

%% What each side believes, and who owns what on disk.
seen(M, #{up := Up, down := Down, disk := Disk}) ->
    WantUp = #{phase => M#m.phase, product => M#m.up, in_transit => M#m.up_transit},
    DownHolds = case M#m.down of
                    none -> M#m.ref;
                    S -> S
                end,
    WantDown = #{phase => M#m.phase, product => DownHolds, in_transit => M#m.down_transit},
    WantDisk = lists:sort([{S, up} || S <- [M#m.up], S =/= none]
                          ++ [{S, down} || S <- [M#m.down], S =/= none]),
    [{up, WantUp, Up} || Up =/= WantUp]
        ++ [{down, WantDown, Down} || Down =/= WantDown]
        ++ [{disk, WantDisk, Disk} || Disk =/= WantDisk].

%% In parallel a command meets whatever the other side did: only answers the seed
%% allows at some moment.
allowed({call, _, up, [try_abort_offering]}, R) -> is_boolean(R) orelse refused(R);
allowed({call, _, down, [peek]}, R) -> R =:= none orelse refused(R);
allowed({call, _, down, [commit]}, R) -> R =:= ok orelse R =:= not_available orelse refused(R);
allowed({call, _, up, [finish]}, R) ->
    lists:member(R, [pending, completed, aborted, interrupted]) orelse refused(R);
allowed(_, R) -> R =:= ok orelse refused(R).

refused({not_now, _}) -> true;
refused(killed) -> true;
refused({ok, S}) -> is_integer(S);   %% a peek's product, a product shipped
refused(_) -> false.

%% The model counts products; on the machine a serial is unique across runs too (a
%% stopped task's row may outlive it in the registry).
serial(N) -> N.

real_serial(N) ->
    <<"HS-", (integer_to_binary(ets:lookup_element(?TAB, run, 2)))/binary, "-",
      (integer_to_binary(N))/binary>>.

model_serial(none) -> none;
model_serial(S) ->
    [_, _, N] = binary:split(S, <<"-">>, [global]),
    binary_to_integer(N).

%% -------------------------------------------------------------------------------------
%% Commands
%% -------------------------------------------------------------------------------------

new(next) ->
    new(ets:update_counter(?TAB, serial, 1));
new(N) ->
    Res = up({new, real_serial(N)}),
    _ = case Res of
            ok -> ets:insert(?TAB, {{made, N}, true});
            {ok, _} -> ets:insert(?TAB, {{made, N}, true});
            %% Killed between saving the new product and answering: it may hold it
            %% after its restart, as it must once its file has it.
            killed -> ets:insert(?TAB, {{maybe_made, N}, true});
            _ -> true
        end,
    Res.

up(Command) -> act(up, Command).

down(Command) -> act(down, Command).

%% Phase 3 seen from both sides: once the previous device's call returns, the next
%% device holds the product (the look below waits until it has taken the message).
release() ->
    act(up, release).

act(Side, Command) ->
    Reply = ask(Side, Command),
    _ = case Reply of
            {ok, Shipped} when Command =:= ship -> ets:insert(?TAB, {{shipped, Shipped}, true});
            _ -> true
        end,
    case mode() of
        sequential -> {Reply, observe()};
        parallel -> Reply
    end.

%% A command to a task at its wait; `killed' if the task stopped before it answered.
ask(Side, Command) ->
    [{Side, Id, Pid}] = ets:lookup(?TAB, Side),
    MRef = monitor(process, Pid),
    Pid ! {ref(), {Command, self()}},
    receive
        {hs_reply, Id, Reply, Snapshot} ->
            demonitor(MRef, [flush]),
            ets:insert(?TAB, {{seen, Side}, Snapshot#{product := model_serial(
                                                                     maps:get(product, Snapshot))}}),
            case Reply of
                {ok, S} when is_binary(S) -> {ok, model_serial(S)};
                _ -> Reply
            end;
        {'DOWN', MRef, process, Pid, _} ->
            killed
    after ?WAIT ->
        demonitor(MRef, [flush]),
        {no_answer, Side, Command}
    end.

observe() ->
    #{up => look(up), down => look(down), disk => disk()}.

look(Side) ->
    killed =/= ask(Side, look) orelse error({killed_while_looked_at, Side}),
    ets:lookup_element(?TAB, {seen, Side}, 2).

%% The owner of each serial on disk: the record of the highest generation, never two.
disk() ->
    Stored = [{S, G, Side} || Side <- [up, down],
                              {ok, #{product := #{serial := S}, gen := G}}
                                  <- [cell_product:load(file(Side))]],
    lists:sort([case [Sd || {S1, G1, Sd} <- Stored, S1 =:= S, G1 =:= G] of
                    [Side] -> {model_serial(S), Side};
                    Sides -> {model_serial(S), {shared, Sides}}
                end || {S, G, _} <- Stored,
                       G =:= lists:max([G1 || {S1, G1, _} <- Stored, S1 =:= S])]).

%% Kills a task (its supervisor restarts it, it connects again) or the link (its
%% supervisor restarts it empty, it greets both tasks). Sequential runs wait until the
%% replacement is at its first wait, or the new link has greeted both tasks.
kill(link) ->
    [{link, Link}] = ets:lookup(?TAB, link),
    Mode = mode(),
    case cell_handshake_link:whereis(Link) of
        undefined when Mode =:= sequential ->
            {ok, observe()};
        undefined ->
            ok;
        Pid ->
            MRef = monitor(process, Pid),
            exit(Pid, kill),
            receive {'DOWN', MRef, process, Pid, _} -> ok end,
            case Mode of
                sequential ->
                    %% The supervisor has restarted it once it answers; the new link
                    %% has greeted the tasks once it answers too.
                    _ = sys:get_state(link_pid()),
                    {ok, observe()};
                parallel ->
                    ok
            end
    end;
kill(Side) ->
    [{Side, Id, Pid}] = ets:lookup(?TAB, Side),
    MRef = monitor(process, Pid),
    exit(Pid, kill),
    receive {'DOWN', MRef, process, Pid, _} -> ok end,
    case mode() of
        sequential ->
            receive
                {hs_ready, Id, New, _} ->
                    true = ets:insert(?TAB, {Side, Id, New}),
                    {ok, observe()}
            after ?WAIT ->
                {no_restart, Side}
            end;
        parallel ->
            ok
    end.

%% -------------------------------------------------------------------------------------
%% After a parallel run: each task at its wait, the link answering; every product made
%% is held by exactly one side (on disk and in memory) or shipped.
%% -------------------------------------------------------------------------------------

final_check() ->
    true = ets:insert(?TAB, {mode, sequential}),
    [ready(Side) || Side <- [up, down]],
    _ = sys:get_state(link_pid()),
    ok = settle(observe()),
    #{up := Up, down := Down, disk := Disk} = observe(),
    Shipped = lists:sort([S || {{shipped, S}, _} <- ets:match_object(?TAB, {{shipped, '_'}, '_'})]),
    Held = lists:sort([{S, Side} || {Side, #{product := S}} <- [{up, Up}, {down, Down}],
                                    S =/= none]),
    Accounted = lists:sort([S || {S, _} <- Held] ++ Shipped),
    %% A product whose making was cut off by a kill counts if it was kept.
    Made = lists:sort([S || {{made, S}, _} <- ets:match_object(?TAB, {{made, '_'}, '_'})]
                      ++ [S || {{maybe_made, S}, _} <- ets:match_object(?TAB,
                                                                        {{maybe_made, '_'}, '_'}),
                               lists:member(S, Accounted)]),
    Problems = [{disk_and_memory, Disk, Held} || Disk =/= Held]
               ++ [{lost_or_twice, Made, Held, Shipped} || Made =/= Accounted],
    case Problems of
        [] -> ok;
        _ -> {conservation, Problems}
    end.

%% A transfer the next device committed to is carried out to its end (the seed: once
%% it has read Available the handshake must be fully executed); an open offer is
%% withdrawn. Then each side holds only what it owns.
settle(#{down := #{phase := committed}}) ->
    ok = ask(up, release),
    settle(observe());
settle(#{down := #{phase := released}}) ->
    ok = ask(down, complete),
    settle(observe());
settle(#{up := #{phase := offered}}) ->
    true = ask(up, try_abort_offering),
    settle(observe());
settle(_) ->
    ok.

%% The link's process as its supervisor restarted it (after its init: it greeted the
%% tasks).
link_pid() ->
    [{link, Link}] = ets:lookup(?TAB, link),
    [Pid] = [P || {Id, P, _, _} <- supervisor:which_children(?SUP), Id =:= Link, is_pid(P)],
    Pid.

%% A task killed during the run: its replacement's greeting says where it is.
ready(Side) ->
    [{Side, Id, Pid}] = ets:lookup(?TAB, Side),
    case is_process_alive(Pid) of
        true ->
            ok;
        false ->
            receive
                {hs_ready, Id, New, _} when New =/= Pid ->
                    true = ets:insert(?TAB, {Side, Id, New}),
                    ready(Side)
            after ?WAIT ->
                error({no_restart, Side})
            end
    end.

%% -------------------------------------------------------------------------------------
%% A fresh link and two fresh tasks for each run, in a cell started once
%% -------------------------------------------------------------------------------------

setup() ->
    Root = filename:join(["/tmp", "prop_cell_handshake", os:getpid()]),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, #{tasks => []}),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    {ok, Sup} = supervisor:start_link({local, ?SUP}, ?MODULE, []),
    true = unlink(Sup),
    _ = ets:new(?TAB, [named_table, public]),
    true = ets:insert(?TAB, [{run, 0}, {ref, make_ref()}]),
    Root.

cleanup(Root) ->
    ets:delete(?TAB),
    ok = gen_server:stop(?SUP),
    ok = application:stop(cell),
    _ = application:stop(mnesia),
    ok = application:unset_env(cell, cell_spec),
    _ = os:cmd("rm -rf '" ++ Root ++ "'"),
    ok.

start_pair(Mode) ->
    N = ets:update_counter(?TAB, run, 1),
    Name = fun(Prefix) -> list_to_atom(Prefix ++ integer_to_list(N)) end,
    Up = Name("hm_up_"),
    Down = Name("hm_down_"),
    Link = Name("hm_"),
    true = ets:insert(?TAB, [{mode, Mode}, {serial, 0}, {link, Link},
                             {files, #{up => file_of(N, "up"), down => file_of(N, "down")}}]),
    ets:match_delete(?TAB, {{made, '_'}, '_'}),
    ets:match_delete(?TAB, {{maybe_made, '_'}, '_'}),
    ets:match_delete(?TAB, {{shipped, '_'}, '_'}),
    {ok, _} = supervisor:start_child(?SUP,
                                     cell_handshake_link:child_spec(#{id => Link, from => Up,
                                                                      to => Down})),
    [begin
         {ok, #{tasks := [Spec]}} =
             cell_spec:validate(
               #{tasks => [#{id => Id, module => cell_hs_model_task, zone => <<"HM">>,
                             lane => iolist_to_binary([Lane, integer_to_list(N)]),
                             args => #{ref => ref(), link => Link, role => Role,
                                       notify => self(), tab => ?TAB}}]}),
         %% Connected as the controller connects a cell spec's links (seed: in the
         %% constructor), so every incarnation of the task is attached.
         {ok, _} = supervisor:start_child(?SUP, cell_task_proc:child_spec(
                                                  Spec#{links => #{Link => #{role => Role}}})),
         receive
             {hs_ready, Id, Pid, _} -> true = ets:insert(?TAB, {Role, Id, Pid})
         after ?WAIT -> error({not_ready, Id})
         end
     end || {Id, Role, Lane} <- [{Up, up, "up"}, {Down, down, "down"}]],
    {Up, Down, Link}.

stop_pair(Ids) ->
    _ = [begin
             ok = supervisor:terminate_child(?SUP, Id),
             ok = supervisor:delete_child(?SUP, Id)
         end || Id <- tuple_to_list(Ids)],
    flush().

%% The tasks and the link of the runs run under a supervisor of their own, as under
%% the cell's: the same child specs, restarted when killed, but with room for the
%% thousands of kills of a thousand runs.
init([]) ->
    {ok, {#{strategy => one_for_one, intensity => 1000000, period => 1}, []}}.

file_of(N, Lane) ->
    {ok, Root} = application:get_env(cell_base, root),
    filename:join([Root, "Data", "HM@" ++ Lane ++ integer_to_list(N) ++ ".product"]).

file(Side) -> maps:get(Side, ets:lookup_element(?TAB, files, 2)).
mode() -> ets:lookup_element(?TAB, mode, 2).
ref() -> ets:lookup_element(?TAB, ref, 2).

flush() ->
    receive _ -> flush() after 0 -> ok end.
