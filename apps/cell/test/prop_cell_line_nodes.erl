%% A PropEr state-machine property over a line of three cells on three nodes, each node
%% in a Linux network namespace of its own on a bridge (cell_netns): cell `a' runs the
%% first segment, `b' the middle one and the link `x1' from `a', `c' the last segment
%% and the link `x2' from `b' (cell_line_nodes:line_spec/3). So two of the three nodes
%% host a link, and `b' is at once the host of one link and the upstream partner of a
%% link on another node.
%%
%% Commands, as a hostile tester would give them while products pass:
%% <ul>
%% <li>products put on the infeed;</li>
%% <li>time passing (50 to 1,250 ms: a partition lasts as long as the commands between
%%   its cut and its heal);</li>
%% <li>a cell cut off from the others: silently (packets dropped both ways, the nodes
%%   learn of it from their distribution ticks), cleanly (dropped, and every node drops
%%   its connection to it at once) or one way (only what it sends is dropped);</li>
%% <li>a cut made when a transfer over a given link reaches a given phase (offer,
%%   commit, release, owned, complete), at either end of it; in the release phase it is
%%   the cut that keeps `owned' from upstream (downstream's packets dropped);</li>
%% <li>a cut healed;</li>
%% <li>a node killed (SIGKILL, a power cut) and started again on its folder, during a
%%   partition or not.</li>
%% </ul>
%% The operator answers every question as the line's own recorder does: IGNORE when it
%% is offered ("it is here"), else the first solution.
%%
%% After each command: no product has gone out twice (the last segment's out log, on
%% disk, read by the test). After each run every cut is healed and every node started
%% again, and then, within a deadline:
%% <ul>
%% <li>every serial fed has left the line exactly once (nothing lost, nothing out
%%   twice);</li>
%% <li>no task holds a product, in memory or in its product file (so none is held twice
%%   after the heal);</li>
%% <li>nothing waits forever: all of it happens within the deadline;</li>
%% <li>no task crashed (a call across a cut times out and is taken as the link being
%%   down).</li>
%% </ul>
%% The nodes and cells live across runs; each run starts from where the last one left
%% the line: healed, every node up, every product out. A failed run is not shrunk (its
%% world is not clean again): its commands and what each cell saw are printed.
-module(prop_cell_line_nodes).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([feed/1, pause/1, cut/2, cut_at/4, heal/1, kill/1, restart/1]).
-export([prop_line/0, setup/2, teardown/0, cuts/0, protocols/0]).

-define(CELLS, [a, b, c]).
-define(TAB, ?MODULE).
%% A product moves for this long on each segment: a window in each phase to cut in.
-define(DELAY, 150).
%% How long a targeted cut waits for its phase before it cuts anyway (no product there).
-define(AT_MS, 4000).
%% Every product fed is out within this once the line is whole again.
-define(SETTLE_MS, 120000).
%% A run is this long: a partition spans several commands, and a heal comes after
%% other cuts and kills.
-define(MIN_COMMANDS, 15).
-define(MAX_COMMANDS, 40).
%% At most this many products fed in a run.
-define(MAX_FED, 8).

-record(m, {down = [] :: [atom()],
            cut = [] :: [atom()],
            fed = 0 :: non_neg_integer()}).

%% -- the world: namespaces, nodes, cells ---------------------------------------------

%% @doc Makes the namespaces, starts a node per cell and its cell, under `Base'; with
%% `tls' the nodes speak the distribution over TLS.
-spec setup(file:filename(), #{tls => boolean()}) -> ok.
setup(Base, Opts) ->
    _ = ets:new(?TAB, [named_table, public]),
    ok = filelib:ensure_path(Base),
    Net0 = case Opts of
               #{tls := true} -> cell_netns:tls(cell_netns:create(?CELLS),
                                                filename:join(Base, "tls"));
               #{} -> cell_netns:create(?CELLS)
           end,
    true = ets:insert(?TAB, {net, Net0}),
    Net = lists:foldl(fun(C, N) -> cell_netns:start_node(N, C, []) end, Net0, ?CELLS),
    true = ets:insert(?TAB, [{net, Net}, {base, Base}, {ref, make_ref()},
                             {line, [{C, cell_netns:node_of(Net, C)} || C <- ?CELLS]},
                             {log, filename:join(Base, "out.log")}, {fed, 0},
                             {refeed, []}, {crashes, []}, {cuts, 0}, {cut, []},
                             {down, []}]),
    lists:foreach(fun start_cell/1, ?CELLS).

%% @doc Removes everything setup/1 made.
-spec teardown() -> ok.
teardown() ->
    ok = cell_netns:destroy(world(net)),
    true = ets:delete(?TAB),
    ok.

%% @doc The cuts made so far.
-spec cuts() -> non_neg_integer().
cuts() ->
    world(cuts).

%% @doc The protocols the cells' nodes speak to each other (`tcp' or `tls').
-spec protocols() -> [atom()].
protocols() ->
    lists:usort([element(4, proplists:get_value(address, Info))
                 || C <- ?CELLS, {ok, Infos} <- [call(C, net_kernel, nodes_info, [])],
                    {_, Info} <- Infos]).

start_cell(Which) ->
    Base = world(base),
    {ok, Recorder} = call(Which, cell_line_recorder, start, [#{}]),
    Spec = cell_line_nodes:line_spec(Which, world(line),
                                     #{feed => line_feed, out => line_out, ref => world(ref),
                                       notify => Recorder, delay => ?DELAY,
                                       out_log => world(log)}),
    ok = cell_line_nodes:boot(fun(M, F, A) -> call(Which, M, F, A) end,
                              filename:join(Base, atom_to_list(Which)), Spec),
    ok = call(Which, cell_line_recorder, subscribe, []),
    ok = call(Which, cell_controller, start, []).

%% -- the property --------------------------------------------------------------------

%% Run with PropEr's size at 2 * ?MAX_COMMANDS (`{start_size, 80}, {max_size, 80}'):
%% the lengths of the sequences it makes are spread up to the size.
-spec prop_line() -> proper:outer_test().
prop_line() ->
    ?FORALL(Cmds, ?SUCHTHAT(Cs, proper_statem:commands(?MODULE),
                            length(Cs) >= ?MIN_COMMANDS andalso length(Cs) =< ?MAX_COMMANDS),
            begin
                {History, State, Result} = proper_statem:run_commands(?MODULE, Cmds),
                Settled = settle(),
                ?WHENFAIL(io:format(user, "commands: ~p~nresult: ~p~nmodel: ~p~n"
                                          "settled: ~p~nwhat each cell saw: ~p~n",
                                    [Cmds, Result, State, Settled, timelines()]),
                          measure("commands in a run", length(Cmds),
                          aggregate(proper_statem:command_names(Cmds),
                                    Result =:= ok andalso Settled =:= ok
                                    andalso length(History) =:= length(Cmds))))
            end).

%% -- the model -----------------------------------------------------------------------

-spec initial_state() -> #m{}.
initial_state() ->
    #m{}.

-spec command(#m{}) -> proper_types:type().
command(#m{down = Down, cut = Cut, fed = Fed}) ->
    Up = ?CELLS -- Down,
    Whole = [L || {L, U, D} <- [{x1, a, b}, {x2, b, c}],
                  not lists:member(U, Down ++ Cut), not lists:member(D, Down ++ Cut)],
    frequency(
      [{3, {call, ?MODULE, feed, [range(1, 2)]}} || Fed < ?MAX_FED, not lists:member(a, Down)]
      ++ [{3, {call, ?MODULE, pause, [range(50, 1250)]}}]
      ++ [{3, {call, ?MODULE, cut, [oneof(?CELLS -- Cut), oneof([silent, clean, one_way])]}}
          || ?CELLS -- Cut =/= []]
      ++ [{4, {call, ?MODULE, cut_at, [oneof(Whole), oneof([offer, commit, release, owned,
                                                             complete]),
                                        oneof([up, down]), oneof([silent, clean])]}}
          || Whole =/= []]
      ++ [{5, {call, ?MODULE, heal, [oneof(Cut)]}} || Cut =/= []]
      ++ [{1, {call, ?MODULE, kill, [oneof(Up)]}} || Up =/= []]
      ++ [{3, {call, ?MODULE, restart, [oneof(Down)]}} || Down =/= []]).

-spec precondition(#m{}, proper_statem:symbolic_call()) -> boolean().
precondition(#m{down = Down, fed = Fed}, {call, _, feed, _}) ->
    Fed < ?MAX_FED andalso not lists:member(a, Down);
precondition(#m{cut = Cut}, {call, _, cut, [C, _]}) ->
    not lists:member(C, Cut);
precondition(#m{down = Down, cut = Cut}, {call, _, cut_at, [L, _, _, _]}) ->
    {U, D} = ends(L),
    [] =:= [X || X <- [U, D], lists:member(X, Down ++ Cut)];
precondition(#m{cut = Cut}, {call, _, heal, [C]}) ->
    lists:member(C, Cut);
precondition(#m{down = Down}, {call, _, kill, [C]}) ->
    not lists:member(C, Down);
precondition(#m{down = Down}, {call, _, restart, [C]}) ->
    lists:member(C, Down);
precondition(_M, {call, _, pause, _}) ->
    true.

-spec next_state(#m{}, term(), proper_statem:symbolic_call()) -> #m{}.
next_state(#m{fed = Fed} = M, _V, {call, _, feed, [K]}) ->
    M#m{fed = Fed + K};
next_state(#m{cut = Cut} = M, _V, {call, _, cut, [C, _]}) ->
    M#m{cut = [C | Cut]};
next_state(#m{cut = Cut} = M, _V, {call, _, cut_at, [L, Phase, End, _]}) ->
    M#m{cut = [target(L, Phase, End) | Cut]};
next_state(#m{cut = Cut} = M, _V, {call, _, heal, [C]}) ->
    M#m{cut = Cut -- [C]};
next_state(#m{down = Down} = M, _V, {call, _, kill, [C]}) ->
    M#m{down = [C | Down]};
next_state(#m{down = Down} = M, _V, {call, _, restart, [C]}) ->
    M#m{down = Down -- [C]};
next_state(M, _V, {call, _, pause, _}) ->
    M.

%% Nothing has left the line twice, whatever the command.
-spec postcondition(#m{}, proper_statem:symbolic_call(), term()) -> boolean().
postcondition(_M, _Call, Result) ->
    Result =:= ok andalso twice(outs()) =:= [].

%% The link's two cells, upstream first.
ends(x1) -> {a, b};
ends(x2) -> {b, c}.

%% The cell a targeted cut cuts off: in the release phase downstream (one way),
%% else the end asked for.
target(L, release, _End) -> element(2, ends(L));
target(L, _Phase, up) -> element(1, ends(L));
target(L, _Phase, down) -> element(2, ends(L)).

%% -- the commands --------------------------------------------------------------------

%% @doc Puts K new products on the infeed of the first segment.
-spec feed(pos_integer()) -> ok.
feed(K) ->
    N0 = world(fed),
    true = ets:insert(?TAB, {fed, N0 + K}),
    infeed([serial(I) || I <- lists:seq(N0 + 1, N0 + K)]).

infeed([]) ->
    ok;
infeed(Serials) ->
    call(a, cell_line_recorder, feed, [Serials, src, world(ref)]).

%% @doc Lets time pass: what the line does meanwhile is its own.
-spec pause(pos_integer()) -> ok.
pause(Ms) ->
    receive after Ms -> ok end.

%% @doc Cuts a cell off from the others.
-spec cut(atom(), silent | clean | one_way) -> ok.
cut(C, one_way) ->
    cut_off(C, {silent, C});
cut(C, How) ->
    cut_off(C, How).

%% @doc Cuts when the transfer over link `L' reaches `Phase' (or after ?AT_MS if no
%% transfer gets there): the link's upstream or downstream cell, silently or cleanly;
%% in the release phase downstream's packets only, so that `owned' does not reach
%% upstream.
-spec cut_at(x1 | x2, atom(), up | down, silent | clean) -> ok.
cut_at(L, Phase, End, How) ->
    {Who, Spec} = watch(L, Phase),
    Since = call(Who, cell_line_recorder, mark, []),
    _ = call(Who, cell_line_recorder, await, [Spec, Since, ?AT_MS], ?AT_MS + 10000),
    C = target(L, Phase, End),
    cut_off(C, case Phase of release -> {silent, C}; _ -> How end).

watch(L, Phase) ->
    {U, D} = ends(L),
    N = length(?CELLS),
    {I, J} = {index(U), index(D)},
    {UpTask, DownTask} = {cell_line_nodes:task_of(I, N), cell_line_nodes:task_of(J, N)},
    case Phase of
        offer -> {D, {link_phase, offered}};
        commit -> {D, {phase, DownTask, moving_in}};
        release -> {U, {phase, UpTask, leaving}};
        owned -> {D, {phase, DownTask, arriving}};
        complete -> {D, {phase, DownTask, full}}
    end.

cut_off(C, How) ->
    ok = cell_netns:cut(world(net), How, [C]),
    true = ets:insert(?TAB, [{cut, [C | world(cut)]}, {cuts, world(cuts) + 1}]),
    ok.

%% @doc Heals a cell's cut.
-spec heal(atom()) -> ok.
heal(C) ->
    ok = cell_netns:heal(world(net), silent, [C]),
    true = ets:insert(?TAB, {cut, world(cut) -- [C]}),
    ok.

%% @doc Kills a cell's node (SIGKILL). The products still on the first segment's
%% infeed are the machine's: they are fed again to the node's successor.
-spec kill(atom()) -> ok.
kill(C) ->
    Left = case C of
               a -> call(a, cell_line_recorder, take_feed, [src], 40000);
               _ -> []
           end,
    true = ets:insert(?TAB, [{refeed, world(refeed) ++ Left},
                             {crashes, world(crashes) ++ crashes(C)}]),
    Net = cell_netns:kill_node(world(net), C),
    true = ets:insert(?TAB, [{net, Net}, {down, [C | world(down)]}]),
    ok.

%% @doc Starts a cell's node again on its folder, and its cell.
-spec restart(atom()) -> ok.
restart(C) ->
    Net = cell_netns:start_node(world(net), C, []),
    true = ets:insert(?TAB, [{net, Net}, {down, world(down) -- [C]}]),
    ok = start_cell(C),
    case C of
        a ->
            Left = world(refeed),
            true = ets:insert(?TAB, {refeed, []}),
            infeed(Left);
        _ ->
            ok
    end.

%% -- after a run ---------------------------------------------------------------------

%% Heals every cut, starts every node killed, and checks that every product fed leaves
%% once, within the deadline, and that nothing is held any more: `ok' or what is wrong.
settle() ->
    [heal(C) || C <- world(cut)],
    [restart(C) || C <- lists:reverse(world(down))],
    Fed = [serial(I) || I <- lists:seq(1, world(fed))],
    Deadline = erlang:monotonic_time(millisecond) + ?SETTLE_MS,
    case await_all_out(Fed, Deadline) of
        ok ->
            Outs = outs(),
            Crashes = world(crashes) ++ lists:append([crashes(C) || C <- ?CELLS]),
            true = ets:insert(?TAB, {crashes, []}),
            Held = held(),
            if
                Crashes =/= [] -> {crashed, Crashes};
                Held =/= [] -> {still_held, Held};
                true ->
                    case {twice(Outs), lists:sort(Outs) =:= lists:sort(Fed)} of
                        {[], true} -> ok;
                        {[], false} -> {not_fed, Outs -- Fed};
                        {Twice, _} -> {out_twice, Twice}
                    end
            end;
        {stuck, Missing} ->
            {stuck, Missing, held()}
    end.

%% Waits, woken by the last cell's products out, until every serial fed is in the out
%% log, or the deadline.
await_all_out(Fed, Deadline) ->
    Seen = call(c, cell_line_recorder, outs, []),
    case Fed -- outs() of
        [] ->
            ok;
        Missing ->
            Left = Deadline - erlang:monotonic_time(millisecond),
            case Left > 0 andalso call(c, cell_line_recorder, await,
                                       [{outs, length(Seen) + 1}, 0, Left], Left + 10000) of
                {ok, _} -> await_all_out(Fed, Deadline);
                _ -> case Fed -- outs() of
                         [] -> ok;
                         Missing1 -> {stuck, lists:usort(Missing ++ Missing1)}
                     end
            end
    end.

%% What each task holds, in memory or in its product file.
held() ->
    N = length(?CELLS),
    Tasks = [{C, cell_line_nodes:task_of(index(C), N)} || C <- ?CELLS],
    InMemory = [{C, T, S} || {C, T} <- Tasks,
                             S <- [case catch call(C, cell_task_proc, info, [T]) of
                                       #{product := #{serial := S0}} -> S0;
                                       #{} -> none;
                                       Other -> {no_answer, Other}
                                   end],
                             S =/= none],
    OnDisk = [{C, file, S} || C <- ?CELLS,
                              F <- filelib:wildcard(filename:join([world(base), C, "Data",
                                                                   "*.product"])),
                              {ok, #{product := #{serial := S}}} <- [cell_product:load(F)]],
    InMemory ++ OnDisk.

%% -- helpers -------------------------------------------------------------------------

%% Every serial sent out so far, in order, from the last segment's log.
outs() ->
    case file:read_file(world(log)) of
        {ok, Log} -> [S || S <- binary:split(Log, <<"\n">>, [global]), S =/= <<>>];
        {error, enoent} -> []
    end.

twice(Outs) ->
    lists:usort(Outs -- lists:usort(Outs)).

crashes(C) ->
    [E || {crashed, E} <- call(C, cell_line_recorder, events, [])].

timelines() ->
    [{C, catch call(C, cell_line_recorder, timeline, [])} || C <- ?CELLS -- world(down)].

serial(I) ->
    <<"P-", (integer_to_binary(I))/binary>>.

index(C) ->
    length(lists:takewhile(fun(X) -> X =/= C end, ?CELLS)) + 1.

call(C, M, F, A) ->
    cell_netns:call(world(net), C, M, F, A).

call(C, M, F, A, Timeout) ->
    cell_netns:call(world(net), C, M, F, A, Timeout).

world(Key) ->
    ets:lookup_element(?TAB, Key, 2).
