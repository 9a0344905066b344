%% @doc The internal handshake between device tasks, as a task's step uses it (seed 000
%% §2.3.6), and the bookkeeping behind it.
%%
%% Upstream (previous device), the seed's four phases:
%% ```
%% T1 = cell_handshake:offer(T, Link),                      % phase 1: Data + Available
%% {wait, {handshake, Link, not_busy, true}, T1}             % blocked until committed
%% ... run the conveyor until the product left the sensor ...
%% T2 = cell_handshake:release(T, Link),                    % phase 3: Available off
%% {wait, {handshake, Link, not_busy, false}, T2}            % until it arrived
%% {Outcome, T3} = cell_handshake:finish(T, Link)           % completed | aborted | interrupted
%% '''
%% Downstream (next device):
%% ```
%% {wait, {handshake, Link, available, true}, T}             % starved until offered
%% {ok, T1} = cell_handshake:commit(T, Link),               % phase 2: NotBusy on
%% {wait, {handshake, Link, available, false}, T1}           % the product left upstream
%% ... run the conveyor until the product is on the sensor ...
%% T2 = cell_handshake:complete(T, Link)                    % phase 4: NotBusy off
%% '''
%% `try_abort_offering/2' withdraws an offer unless downstream has already begun to
%% take it; `peek/2' looks without committing (adjust the conveyor width first).
%% ItemTransferOut / ItemTransferIn, EquipmentBlocked / Unblocked and Starved /
%% Unstarved come out of these calls and of the waits, where the seed's examples raise
%% them.
%%
%% Ownership, durably: the product file with the highest generation owns a serial
%% (see {@link cell_product}). The commit itself changes nothing on disk: until the
%% product leaves upstream, upstream owns it. At release downstream writes it with a
%% higher generation, marked in transit, before upstream forgets its copy; completion
%% clears the mark. A transfer interrupted while the product moved leaves it with
%% one side, marked, and the operator confirms where it is before that task goes on.
%%
%% The link's fence (see {@link cell_handshake_link_core}) settles what generations
%% cannot: an offer of a copy the link handed on is refused (`stale': the engine drops
%% it; `unsettled': it waits for the link's `settled'), and an upstream task cut off
%% from the link's node after release, `owned' not heard, holds its copy without asking
%% the operator until the link, back in reach, says whether downstream took it.
-module(cell_handshake).


-export([offer/2, try_abort_offering/2, release/2, finish/2,
         available/2, not_busy/2, phase/2, peek/2, commit/2, complete/2, abort/2,
         connect/3, disconnect/2, confirm_here/1, in_transit/1]).
%% For the engine and the links.
-export([attach_all/1, handle/2, holding/1, arm/3, signal/3, hello/2, interrupt_all/1,
         disown_all/2, active_offers/1, reoffer/2]).

-export_type([view/0]).

-type view() :: #{role := cell_handshake_link:role(),
                  phase := cell_handshake_link:phase(),
                  available := boolean(), not_busy := boolean(),
                  outcome => completed | aborted | interrupted,
                  owned => boolean()}.

%% A call to a link on another node outlasts the line's distribution ticks (a silent
%% node is noticed within 6.25 s, see cell_peers): a partition ends the call as the
%% node going down, which the callers handle. A call that still times out (a link
%% that does not answer while its node does) is taken as the link being down, never
%% as a crash of the task.
-define(CALL_TIMEOUT, 8000).

%% -------------------------------------------------------------------------------------
%% Upstream
%% -------------------------------------------------------------------------------------

%% @doc Phase 1: offers the task's product on a link (Data and Available).
%% EquipmentBlocked.
-spec offer(cell_task:task(), atom()) -> cell_task:task().
offer(T0, Link) ->
    case cell_task:product(T0) of
        undefined -> erlang:error({no_product_to_offer, cell_task:id(T0), Link});
        P -> offer(T0, Link, P, cell_task_core:gen(T0))
    end.

offer(T0, Link, P, G) ->
    {T, Reply} = call(T0, Link, {offer, self(), P, G}),
    case Reply of
        ok ->
            T1 = view(T, Link, #{phase => offered, available => true, outcome => undefined,
                                 link_down => false}),
            case cell_task:state(T1) of
                {ready, idle, blocked} -> T1;
                _ -> cell_task:blocked(T1)
            end;
        {error, link_down} ->
            %% The link is restarting: no offer stands. A wait on the link ends soon
            %% (see arm/3) and the task offers again.
            view(T, Link, #{phase => idle, outcome => interrupted, link_down => true});
        {error, {stale, S}} ->
            %% The link handed this serial on and downstream owns it, or has sent it
            %% out. A task of this cell that holds it too is a product held twice (the
            %% serial read again on another panel, say): the cell's guard asks the
            %% operator about both holders, and nothing is dropped unasked. Otherwise
            %% this copy was left behind (the operator said it is here after a network
            %% cut, or a power cut brought the file back): the engine drops it as a
            %% copy older than another's record, and the task starts again without it.
            Id = cell_task:id(T),
            Idle = #{phase => idle, available => false},
            case [Other || {Other, _} <- cell_registry:holders(S), Other =/= Id] of
                [] ->
                    cell_log:warning(Id, "product ~ts was handed on over ~ts before; the "
                                     "next station holds it or has sent it on, so this "
                                     "copy is not offered again", [S, Link]),
                    self() ! {cell_registry, stale, S, G + 1},
                    view(T, Link, Idle);
                Others ->
                    cell_log:warning(Id, "product ~ts was handed on over ~ts before and ~ts "
                                     "holds it too: not offered again until the operator "
                                     "says which holds it",
                                     [S, Link, lists:join(", ", [atom_to_list(O) || O <- Others])]),
                    %% Held back until one holder is left (the guard says so) or the
                    %% link says whose it is after the operator's answer.
                    view(T, Link, Idle#{settle => {S, offer}, held_back => true})
            end;
        {error, {unsettled, S}} ->
            %% The link let this generation go and the next station has not said yet
            %% whether it took it: offered again once the link knows (settled/3).
            cell_log:notice(cell_task:id(T), "product ~ts waits for the next station "
                            "to say whether it took it (handshake ~ts)", [S, Link]),
            view(T, Link, #{phase => idle, available => false, settle => {S, offer}})
    end.

%% @doc Withdraws the offer unless downstream has begun to take the product: `{false,
%% T}' then, and the transfer must go on (seed: TryAbortOffering).
-spec try_abort_offering(cell_task:task(), atom()) -> {boolean(), cell_task:task()}.
try_abort_offering(T0, Link) ->
    {T, Reply} = call(T0, Link, {try_abort_offering, self()}),
    case Reply of
        true -> {true, view(T, Link, #{phase => idle, available => false})};
        false ->
            %% The answer told the task of the commit before the link's message did,
            %% and that message is now old news: a wait on the link, armed before
            %% this call, is looked at again.
            self() ! {cell_handshake, Link, recheck},
            {false, T};
        %% No link, no offer.
        {error, link_down} -> {true, view(T, Link, #{phase => idle, available => false})}
    end.

%% @doc Phase 3: the product has left this task (Available off). Downstream owns it
%% from here; this task holds none.
-spec release(cell_task:task(), atom()) -> cell_task:task().
release(T0, Link) ->
    Id = cell_task:id(T0),
    %% Out of the registry's holders before downstream takes the product in: its
    %% newer record then finds no older holder to tell. (After a crash in between, the
    %% restarted task holds the product again from its file.)
    ok = cell_registry:hold(Id, undefined, 0),
    LPid = link_pid(T0, Link),
    {T, Reply} = call(T0, Link, {release, self()}),
    {P, G} = {cell_task:product(T), cell_task_core:gen(T)},
    case Reply of
        ok ->
            %% The file stays until downstream owns the product on disk.
            ok = cell_registry:update(Id, #{serial => undefined, product => undefined}),
            ok = cell_task:publish(T, product_saved, #{item => undefined, product => undefined,
                                                       in_transit => false}),
            view(cell_task_core:released(T), Link,
                 #{phase => released, available => false, owned => false});
        {error, link_down} when is_pid(LPid), node(LPid) =/= node() ->
            case lists:member(node(LPid), nodes()) of
                false ->
                    %% The link's node went out of reach while it was asked: it may
                    %% have let the product go. The task holds its copy, marked in
                    %% transit, and asks the link when it is back.
                    unsettled(T, Link, P, G);
                true ->
                    interrupted_release(T, Link, P, G)
            end;
        {error, _} ->
            interrupted_release(T, Link, P, G)
    end.

%% Downstream stopped while the product was being moved out: it stays with this task,
%% marked in transit, for the operator to confirm.
interrupted_release(T, Link, P, G) ->
    Marker = #{link => Link, from => downstream, phase => in_transit},
    view(store(T, P, G, Marker, #{}), Link,
         #{phase => idle, outcome => interrupted, available => false, not_busy => false}).

%% Released, `owned' not heard, the link out of reach: not this task's again, not the
%% operator's yet. The copy is held (durably, marked in transit, for a restart to
%% find) and the task's wait for the end of the transfer stays armed; the link's
%% answer when it is back settles it (attach/3, the `settled' message): downstream
%% took it (the copy goes, ItemTransferOut), or it never had it (the transfer was
%% interrupted: the operator says where the product is).
unsettled(T0, Link, P, G) ->
    #{serial := S} = P,
    cell_log:warning(cell_task:id(T0), "product ~ts was leaving over the handshake ~ts "
                     "when the link went out of reach; whether the next station took it "
                     "is settled with the link when it is back", [S, Link]),
    Marker = #{link => Link, from => downstream, phase => in_transit},
    T = store(T0, P, G, Marker, #{}),
    view(T, Link, #{phase => idle, available => false, not_busy => true,
                    outcome => undefined, settle => {S, released}, last_product => P}).

%% @doc After NotBusy went off: how the transfer ended. `completed' raises
%% ItemTransferOut; after `aborted' the task holds its product again.
-spec finish(cell_task:task(), atom()) ->
          {completed | aborted | interrupted | pending, cell_task:task()}.
finish(T, Link) ->
    case maps:get(outcome, link_view(T, Link), undefined) of
        completed ->
            #{serial := S} = P = maps:get(last_product, link_view(T, Link)),
            T1 = view(T, Link, #{outcome => undefined}),
            {completed, cell_task:transfer_out(T1, S, P)};
        undefined ->
            {pending, T};
        Outcome ->
            {Outcome, view(T, Link, #{outcome => undefined})}
    end.

%% -------------------------------------------------------------------------------------
%% Downstream
%% -------------------------------------------------------------------------------------

%% @doc The last Available seen on a link.
-spec available(cell_task:task(), atom()) -> boolean().
available(T, Link) -> maps:get(available, link_view(T, Link), false).

%% @doc The last NotBusy seen on a link.
-spec not_busy(cell_task:task(), atom()) -> boolean().
not_busy(T, Link) -> maps:get(not_busy, link_view(T, Link), false).

%% @doc The phase of a link as the task last saw it (`idle', `offered', `committed',
%% `released', `aborting'): an upstream task whose offer is gone finds it `idle'.
-spec phase(cell_task:task(), atom()) -> cell_handshake_link:phase().
phase(T, Link) -> maps:get(phase, link_view(T, Link), idle).

%% @doc The product on offer, without committing to it (seed: PeekBoardAvailable).
-spec peek(cell_task:task(), atom()) -> {ok, cell_product:product()} | none.
peek(T, Link) ->
    case element(2, call(T, Link, {peek, self()})) of
        {ok, P} -> {ok, P};
        _ -> none
    end.

%% @doc Phase 2: takes the offered product (reads Available with locking, NotBusy on).
%% `{not_available, T}' if the offer was withdrawn first. The product becomes the
%% task's own on disk only at release: until it leaves upstream, upstream owns it.
-spec commit(cell_task:task(), atom()) -> {ok, cell_task:task()} | {not_available, cell_task:task()}.
commit(T0, Link) ->
    case call(T0, Link, {commit, self()}) of
        {T, {ok, Product, Gen}} ->
            {ok, view(cell_task_core:take(T, Product, Gen, undefined), Link,
                      #{phase => committed, not_busy => true, from_gen => Gen})};
        {T, {error, _}} ->
            {not_available, T}
    end.

%% @doc Phase 4: the product has arrived (NotBusy off). ItemTransferIn.
-spec complete(cell_task:task(), atom()) -> cell_task:task().
complete(T0, Link) ->
    #{serial := S} = P = cell_task:product(T0),
    G = cell_task_core:gen(T0),
    %% After an interruption the link has moved on; the product arrived all the same.
    {T, _} = call(T0, Link, {complete, self()}),
    %% The owner is already this task on disk; clearing the in-transit mark may be lost
    %% in a power cut without harm (the operator is then asked once too often).
    T1 = store(T, P, G, undefined, #{sync => false}),
    cell_task:transfer_in(view(T1, Link, #{phase => idle, not_busy => false}), S).

%% @doc Aborts the transfer (the seed's Abort): upstream keeps, or takes back, the
%% product. If upstream is gone (or the link restarting) the task keeps it when it had
%% been released, still marked in transit; before release it never had it.
-spec abort(cell_task:task(), atom()) -> cell_task:task().
abort(T0, Link) ->
    Phase = phase(T0, Link),
    {T, Reply} = call(T0, Link, {abort, self()}),
    case Reply of
        kept_by_upstream ->
            view(cell_task_core:take(T, undefined, 0, cell_task_core:marker(T)), Link,
                 #{phase => idle});
        given_back ->
            view(store(T, undefined, 0, undefined, #{sync => false}), Link, #{phase => idle});
        _KeptOrNoLink ->
            %% Nobody took it back (upstream stopped, or the link is restarting): as
            %% for a transfer interrupted in the phase this task saw, before release
            %% the product never left upstream and the reference taken at the commit
            %% goes; after, this task keeps it.
            view(after_interruption(down, Phase, T, Link), Link, #{phase => idle})
    end.

%% @doc Whether the task's product is marked in transit: a transfer was interrupted
%% while it moved, and the operator must say where it is.
-spec in_transit(cell_task:task()) -> boolean().
in_transit(T) ->
    case cell_task_core:marker(T) of
        #{phase := in_transit} -> true;
        _ -> false
    end.

%% @doc The product of an interrupted transfer is here (the operator said so): the
%% in-transit mark is cleared, durably. A settlement of it the task waited for on a link
%% is no longer waited for: the task goes on with the copy, and if the link handed it
%% on after all it refuses the copy when offered or attached, and the engine drops it
%% (the task reconciles again without it), never the link's late word under a step.
-spec confirm_here(cell_task:task()) -> cell_task:task().
confirm_here(T) ->
    case cell_task:product(T) of
        undefined ->
            T;
        #{serial := S} = P ->
            T1 = store(T, P, cell_task_core:gen(T), undefined, #{}),
            maps:fold(fun(Link, #{settle := {S1, released}} = View, Acc) when S1 =:= S ->
                              put_view(Acc, Link, maps:remove(settle, View));
                         (_Link, _View, Acc) ->
                              Acc
                      end, T1, links(T1))
    end.

%% @doc Connects the task to a link at run time as its upstream or downstream end
%% (seed: a master task choosing one of several feeders).
-spec connect(cell_task:task(), atom(), cell_handshake_link:role()) ->
          {ok, cell_task:task()} | {error, term()}.
connect(T, Link, Role) ->
    case plain_call(Link, {attach, Role, cell_task:id(T), self(), holding(T, x)}) of
        {{ok, Status}, _} -> {ok, put_view(T, Link, from_status(Role, Status))};
        {{error, _} = Error, _} -> Error
    end.

%% @doc Disconnects from a link; refused while a transfer is under way on it.
-spec disconnect(cell_task:task(), atom()) -> {ok, cell_task:task()} | {error, term()}.
disconnect(T, Link) ->
    #{role := Role} = link_view(T, Link),
    case plain_call(Link, {detach, Role, self()}) of
        {ok, _} -> {ok, cell_task_core:set_links(T, maps:remove(Link, links(T)))};
        {{error, _} = Error, _} -> Error
    end.

%% -------------------------------------------------------------------------------------
%% For the engine
%% -------------------------------------------------------------------------------------

%% @private Attaches the task to the links of its spec (at boot, and again when a link
%% says hello after a restart).
-spec attach_all(cell_task:task()) -> cell_task:task().
attach_all(T) ->
    maps:fold(fun(Link, #{role := Role}, Acc) -> attach(Acc, Link, Role) end, T, links(T)).

attach(T, Link, Role) ->
    Id = cell_task:id(T),
    case cell_handshake_link:whereis(Link) of
        undefined ->
            T;
        Pid ->
            Old0 = maps:get(Link, links(T), #{}),
            _ = case maps:find(mref, Old0) of
                    {ok, OldRef} -> erlang:demonitor(OldRef, [flush]);
                    error -> true
                end,
            MRef = erlang:monitor(process, Pid, [{tag, {'LINK_DOWN', Link}}]),
            Reply = try gen_server:call(Pid, {attach, Role, Id, self(), holding(T, x)},
                                        ?CALL_TIMEOUT)
                    catch exit:Why -> {error, Why}
                    end,
            case Reply of
                {ok, Status} ->
                    Old = link_view(T, Link),
                    New = (from_status(Role, Status))#{mref => MRef, link_down => false},
                    T1 = drop_stale(Status, Link,
                                    put_view(T, Link, maps:remove(retry_ms,
                                                                  maps:merge(Old, New)))),
                    case was_active(Old) andalso maps:get(phase, New) =:= idle of
                        %% The link restarted and forgot a transfer this task was in.
                        true -> element(1, interrupted(T1, Link, maps:get(phase, Old)));
                        false -> T1
                    end;
                _ ->
                    T
            end
    end.

%% The link says the copy this task holds is the one it handed on (the task restarted
%% before it forgot it): downstream owns the product, or has sent it out.
drop_stale(#{stale := true}, Link, T) ->
    case {cell_task:product(T), maps:get(settle, link_view(T, Link), none)} of
        {#{serial := S}, {S, _}} ->
            %% The transfer this task waited to settle: it ended downstream.
            element(1, settled(T, Link, S, owned));
        {#{serial := S}, _} ->
            case cell_task:state(T) of
                {ready, _, _} ->
                    %% Running on it (the operator said it is here while the link was
                    %% out of reach): the engine drops it as a copy older than
                    %% another's record and the task reconciles again without it.
                    self() ! {cell_registry, stale, S, cell_task_core:gen(T) + 1},
                    T;
                _ ->
                    cell_log:notice(cell_task:id(T), "dropped an old copy of product ~ts: "
                                    "the handshake had handed it on to the next station",
                                    [S]),
                    store(T, undefined, 0, undefined, #{sync => false})
            end;
        {undefined, _} ->
            T
    end;
drop_stale(#{unsettled := true}, _Link, T) ->
    %% Downstream has not said yet: the link tells this task when it does.
    T;
drop_stale(_Status, Link, T) ->
    case {cell_task:product(T), maps:get(settle, link_view(T, Link), none)} of
        {#{serial := S}, {S, _}} ->
            %% The link does not fence this copy: it never let it go.
            element(1, settled(T, Link, S, yours));
        _ ->
            T
    end.

%% What the task holds, told to its partners when it attaches: a partner on another
%% node with an older copy of the same product drops it.
holding(T, _) ->
    case cell_task:product(T) of
        undefined -> none;
        #{serial := S} -> {S, cell_task_core:gen(T)}
    end.

%% @private Whether a transfer holds the task's Pause and Stop (the seed allows them
%% only before downstream commits).
-spec holding(cell_task:task()) -> boolean().
holding(T) ->
    lists:any(fun was_active/1, maps:values(links(T))).

was_active(#{role := up, phase := P}) -> lists:member(P, [committed, released, aborting]);
was_active(#{role := down, phase := P}) -> lists:member(P, [committed, released]);
was_active(_) -> false.

%% @private Links on which the task has an open offer.
-spec active_offers(cell_task:task()) -> [atom()].
active_offers(T) ->
    [L || {L, #{role := up, phase := offered}} <- maps:to_list(links(T))].

%% @private Offers again what a Pause withdrew.
-spec reoffer(cell_task:task(), [atom()]) -> cell_task:task().
reoffer(T, Links) ->
    lists:foldl(fun(L, Acc) ->
                        case cell_task:product(Acc) of
                            undefined -> Acc;
                            _ -> offer(Acc, L)
                        end
                end, T, Links).

%% @private The task stops (emergency stop, Stop while an error waits): every transfer
%% it is in ends, for its partners too.
-spec interrupt_all(cell_task:task()) -> cell_task:task().
interrupt_all(T) ->
    Links = links(T),
    maps:fold(fun(Link, View, Acc) ->
                      case was_active(View) orelse maps:get(phase, View) =:= offered of
                          true ->
                              {Acc1, _} = call(Acc, Link, {interrupt, self()}),
                              element(1, interrupted(Acc1, Link, maps:get(phase, View)));
                          false ->
                              Acc
                      end
              end, T, Links).

%% @doc The operator said the product `Serial' is not at this task, which forgets it:
%% each link into the task is told, so that its fence no longer takes an upstream copy
%% of it (the panel still at the previous station, its serial read again) for a stale
%% one. A link out of reach keeps its fence; the operator is asked there when the copy
%% is offered.
-spec disown_all(cell_task:task(), binary()) -> cell_task:task().
disown_all(T, Serial) ->
    maps:fold(fun(Link, #{role := down}, Acc) ->
                      case call(Acc, Link, {disown, self(), Serial}) of
                          {Acc1, ok} ->
                              Acc1;
                          {Acc1, {error, Why}} ->
                              cell_log:warning(cell_task:id(Acc1), "handshake ~ts was not told "
                                               "that product ~ts is not here (~tp)",
                                               [Link, Serial, Why]),
                              Acc1
                      end;
                 (_Link, _View, Acc) ->
                      Acc
              end, T, links(T)).

%% @private Arms a wait on a link signal; `{cell_handshake_watch, Ref, ...}' comes when
%% it holds (at once if it already does). While the link restarts or its node is out of
%% reach, `{link_down, Ms, T}': look again in `Ms' (a backoff from 50 ms to 1 s, kept
%% in the task's view of the link until it attaches again; the link's greeting ends
%% the wait sooner).
-spec arm(cell_task:task(), atom(), {atom(), term()}) ->
          {ok, reference()} | {link_down, pos_integer(), cell_task:task()}.
%%
%% The task's view of the link's signals is kept up to date by the link's numbered
%% status messages, so a wait needs no call: it holds now, or a later status message
%% ends it (see {@link handle/2}).
arm(T, Link, {Signal, Value}) ->
    View = maps:get(Link, links(T), #{}),
    case maps:get(link_down, View, false) andalso not is_map_key(settle, View) of
        true ->
            %% The link is restarting: what the task waits for may never come from
            %% the link that replaces it.
            Ms = cell_task_core:link_retry_ms(maps:get(retry_ms, View, undefined)),
            {link_down, Ms, put_view(T, Link, View#{retry_ms => Ms})};
        false ->
            Ref = make_ref(),
            _ = signal(T, Link, Signal) =:= Value
                andalso (self() ! {cell_handshake_watch, Ref, Link, Signal, Value}),
            {ok, Ref}
    end.

%% @private A signal of a link as the task last saw it.
-spec signal(cell_task:task(), atom(), available | not_busy) -> boolean().
signal(T, Link, available) -> available(T, Link);
signal(T, Link, not_busy) -> not_busy(T, Link).

%% @private A restarted link's greeting to one of its partners, wherever it runs.
-spec hello(atom() | {atom(), node()}, atom()) -> ok.
hello({Task, Node}, Link) when Node =/= node() ->
    _ = rpc:cast(Node, ?MODULE, hello, [Task, Link]),
    ok;
hello({Task, _Node}, Link) ->
    hello(Task, Link);
hello(Task, Link) ->
    case cell_task_proc:whereis(Task) of
        undefined -> ok;
        Pid -> Pid ! {cell_handshake, Link, hello}, ok
    end.

%% @private The engine hands every message of a link here. Answers the task and
%% `{wake, Link, Why}' when a wait on that link should end, `{wake, Link, {signals,
%% Seq}}' when the signals changed and a wait on them may end.
-spec handle(term(), cell_task:task()) -> {cell_task:task(), [{wake, atom(), term()}]}.
handle({cell_handshake, Link, signals, #{seq := Seq, link := LPid} = Status}, T) ->
    case maps:find(Link, links(T)) of
        {ok, #{role := Role, lpid := LPid, seq := Seen} = Old} when Seq > Seen ->
            New = maps:merge(Old, from_status(Role, Status)),
            {put_view(T, Link, New), [{wake, Link, {signals, Seq}}]};
        _ ->
            %% Older than what the task already knows (an answer overtook it), or of
            %% an incarnation of the link the task is no longer attached to.
            {T, []}
    end;
handle({cell_handshake, Link, {released, _, _} = Step, #{seq := Seq, link := LPid} = Status},
       T) ->
    case maps:find(Link, links(T)) of
        {ok, #{lpid := LPid, seq := Seen}} when Seen > Seq ->
            %% Downstream's own abort crossed the release and its answer (upstream has
            %% taken the product back) came first: that transfer is over, and storing
            %% the product now would make a second holder of it.
            {T, []};
        _ ->
            step_and_signals(Link, Step, Status, T)
    end;
handle({cell_handshake, Link, Step, #{} = Status}, T) ->
    step_and_signals(Link, Step, Status, T);
handle({cell_handshake, _Link, {holder, Serial, Gen}}, T) ->
    case {cell_task:product(T), cell_task_core:gen(T)} of
        {#{serial := Serial}, G} when G < Gen ->
            {cell_task:store(T, undefined, 0, undefined, #{sync => false}), []};
        _ ->
            {T, []}
    end;
handle({cell_handshake, Link, recheck}, T) ->
    {T, [{wake, Link, {signals, recheck}}]};
handle({cell_handshake, Link, hello}, T) ->
    %% A restarted link (or one back in reach): attach again; whatever the task waited
    %% for on it is over, completed if the link settled a transfer so. The same link
    %% greeted again (its node came back in reach: cell_peers) with a transfer still
    %% under way on it has forgotten nothing: the transfer goes on, and a wait is only
    %% looked at again (ending it would have a downstream task that committed take the
    %% product as its own before upstream released it).
    Was = maps:with([lpid, mref], link_view(T, Link)),
    T1 = attach(T, Link, maps:get(role, link_view(T, Link), down)),
    Now = link_view(T1, Link),
    Wake = case {Now, maps:with([lpid, mref], Now)} of
               {#{outcome := completed}, _} ->
                   completed;
               {#{settle := _}, _} ->
                   %% A copy released and not yet settled (see unsettled/4): the
                   %% transfer is not over until the link says what became of it,
                   %% when this task attaches with the copy (the greeting of a link
                   %% whose name is not known here yet finds none) or when downstream
                   %% says what it holds. Not the operator's yet.
                   none;
               %% Attached again (a new monitor) to the same link.
               {_, #{lpid := Pid, mref := MRef}} when is_pid(Pid), map_get(lpid, Was) =:= Pid,
                                                     map_get(mref, Was) =/= MRef ->
                   case was_active(Now) of
                       true -> {signals, recheck};
                       false -> interrupted
                   end;
               _ ->
                   interrupted
           end,
    {T1, [{wake, Link, Wake} || Wake =/= none]};
%% Downstream: the product left upstream. It is this task's own on disk from now,
%% marked in transit, before upstream forgets its copy.
handle({cell_handshake, Link, {released, Product, Gen}}, T) ->
    Marker = #{link => Link, from => upstream, phase => in_transit},
    T1 = store(T, Product, Gen + 1, Marker, #{}),
    %% If the link is gone meanwhile, its successor learns it when this task attaches
    %% with what it holds.
    #{serial := Serial} = Product,
    _ = case link_pid(T, Link) of
            undefined -> ok;
            Pid -> gen_server:cast(Pid, {owned, self(), Serial, Gen + 1})
        end,
    {view(T1, Link, #{phase => released, available => false}), []};
%% Upstream: downstream owns the product on disk; the old copy goes.
handle({cell_handshake, Link, owned}, T) ->
    _ = cell_task:product(T) =:= undefined
        andalso cell_product:delete(cell_task_core:product_file(T), #{sync => false}),
    {view(T, Link, #{owned => true}), []};
handle({cell_handshake, Link, completed}, T) ->
    {view(T, Link, #{outcome => completed, phase => idle}), [{wake, Link, completed}]};
handle({cell_handshake, Link, aborted}, T) ->
    %% Aborted before release: the product never left, this task still owns it.
    {view(T, Link, #{outcome => aborted, phase => idle}), [{wake, Link, aborted}]};
%% Aborted after release: take the product back with a newer generation, then let
%% downstream forget its copy.
handle({cell_handshake, Link, {take_back, Product, Gen}}, T) ->
    T1 = store(T, Product, Gen + 2, undefined, #{}),
    {T2, _} = call(T1, Link, {taken_back, self()}),
    {view(T2, Link, #{outcome => aborted, phase => idle}), [{wake, Link, aborted}]};
handle({cell_handshake, Link, {settled, S, Verdict}}, T) ->
    settled(T, Link, S, Verdict);
handle({cell_registry, sole_holder, S}, T) ->
    %% An offer held back while another task of the cell held the product too: that
    %% one has let it go (or the operator answered), so it is made now and the link
    %% decides (a copy it handed on before is dropped then).
    case cell_task:product(T) of
        #{serial := S} ->
            Held = [L || {L, #{settle := {S1, offer}, held_back := true}} <- maps:to_list(links(T)),
                         S1 =:= S],
            {lists:foldl(fun(L, Acc) ->
                                 put_view(Acc, L, maps:without([settle, held_back],
                                                               link_view(Acc, L)))
                         end, T, Held),
             [{wake, L, interrupted} || L <- Held]};
        _ ->
            {T, []}
    end;
handle({cell_handshake, Link, {interrupted, _Why, Phase}}, T) ->
    interrupted(T, Link, Phase);
handle({cell_handshake, Link, {interrupted, _Why}}, T) ->
    interrupted(T, Link, aborting);
handle({cell_handshake_watch, Ref, Link, Signal, Value}, T) ->
    {T, [{wake, Link, {watch, Ref, Signal, Value}}]};
handle({{'LINK_DOWN', Link}, _MRef, process, _Pid, Reason}, T0) ->
    %% Until the restarted link says hello, waits on it are not armed (see arm/3).
    T = view(T0, Link, #{link_down => true}),
    case link_view(T, Link) of
        #{role := up, phase := released} = View
          when Reason =:= noconnection,
               not (is_map_key(owned, View) andalso map_get(owned, View)) ->
            %% The product left, downstream's `owned' was not heard, and the link's
            %% node is out of reach: the link, when back, says whether it was. (A
            %% link that restarted on a node still in reach is as a partner stopped:
            %% downstream's newer record is found, or the operator asked.)
            #{last_product := P} = View,
            {unsettled(T, Link, P, gen_of(T, P)), []};
        View ->
            case was_active(View) of
                true -> interrupted(T, Link, phase(T, Link));
                false -> {T, []}
            end
    end.

%% The generation of the copy this task released: in its file (released/1 forgot it
%% in memory).
gen_of(T, #{serial := S}) ->
    case cell_product:load(cell_task_core:product_path(T)) of
        {ok, #{product := #{serial := S}, gen := G}} -> G;
        _ -> cell_task_core:gen(T)
    end.

%% The link's word on a copy it had released (its fence, see cell_handshake_link_core):
%% `owned', downstream took it; `yours', it never reached downstream's records.
settled(T, Link, S, Verdict) ->
    case {maps:get(settle, maps:get(Link, links(T), #{}), none), cell_task:product(T)} of
        {{S, released}, #{serial := S} = P} when Verdict =:= owned ->
            cell_log:notice(cell_task:id(T), "the next station took product ~ts over ~ts "
                            "before the link went out of reach: this station's copy is "
                            "dropped", [S, Link]),
            T1 = store(T, undefined, 0, undefined, #{sync => false}),
            {put_view(T1, Link, maps:remove(settle, (link_view(T1, Link))#{
                                                      outcome => completed, phase => idle,
                                                      not_busy => false,
                                                      last_product => P})),
             [{wake, Link, completed}]};
        {{S, released}, #{serial := S}} ->
            %% The product never reached downstream's records: it was moving when the
            %% link went, and the operator says where it is.
            {put_view(T, Link, maps:remove(settle, (link_view(T, Link))#{
                                                     outcome => interrupted,
                                                     not_busy => false})),
             [{wake, Link, interrupted}]};
        {{S, offer}, #{serial := S}} when Verdict =:= owned ->
            self() ! {cell_registry, stale, S, cell_task_core:gen(T) + 1},
            {put_view(T, Link, maps:remove(settle, link_view(T, Link))), []};
        {{S, offer}, _} ->
            %% Its own again: offered anew.
            {put_view(T, Link, maps:remove(settle, link_view(T, Link))),
             [{wake, Link, interrupted}]};
        {_, P} when Verdict =:= yours ->
            %% The product is not past this link, and this task holds no copy of it
            %% either: nor is it here. A copy further upstream (the panel still
            %% there, its serial read again) is the product, so the links into this
            %% task are told too.
            case cell_product:serial(P) of
                S -> {T, []};
                _ -> {disown_all(T, S), []}
            end;
        _ ->
            {T, []}
    end.

%% A transfer ended before its end. Who owns the product follows from where it was.
interrupted(T, Link, Phase) ->
    case maps:get(Link, links(T), undefined) of
        undefined ->
            {T, []};
        #{role := Role} ->
            T1 = after_interruption(Role, Phase, T, Link),
            {view(T1, Link, #{phase => idle, outcome => interrupted, available => false,
                              not_busy => false}),
             [{wake, Link, interrupted}]}
    end.

%% Downstream before release: the product never left upstream; this task forgets it.
after_interruption(down, committed, T, _Link) ->
    cell_task_core:take(T, undefined, 0, undefined);
%% Downstream after release: this task owns it, marked in transit.
after_interruption(down, _Phase, T, _Link) ->
    T;
%% Upstream after release: if downstream never confirmed owning it, this task's copy
%% is still the owner; the product has left, so it is marked in transit.
after_interruption(up, released, T, Link) ->
    Id = cell_task:id(T),
    case cell_task:product(T) =/= undefined orelse maps:get(owned, link_view(T, Link), false) of
        true ->
            T;
        false ->
            case cell_product:load(cell_task_core:product_path(T)) of
                {ok, #{product := #{serial := S} = P, gen := G}} ->
                    %% Held first, looked at after: downstream holds its newer record
                    %% first and looks after too, so of two tasks doing this at once
                    %% one sees the other. (Looked at first, downstream's record could
                    %% come in between, see no older holder, and leave this copy held
                    %% beside it.)
                    T1 = store(T, P, G, #{link => Link, from => downstream,
                                          phase => in_transit}, #{}),
                    case cell_task_core:newer_holder(Id, G, cell_registry:holders(S)) of
                        none -> T1;
                        {ok, _} -> store(T1, undefined, 0, undefined, #{sync => false})
                    end;
                _ ->
                    T
            end
    end;
%% Upstream before release: the product never left; this task still owns it.
after_interruption(up, _Phase, T, _Link) ->
    T.

%% -------------------------------------------------------------------------------------

%% A step of the protocol and the signals it left, in one message.
step_and_signals(Link, Step, Status, T) ->
    {T1, Wakes} = handle({cell_handshake, Link, Step}, T),
    {T2, More} = handle({cell_handshake, Link, signals, Status}, T1),
    {T2, Wakes ++ More}.

link_view(T, Link) ->
    case maps:find(Link, links(T)) of
        {ok, V} -> V;
        error -> erlang:error({not_a_link_of_this_task, cell_task:id(T), Link})
    end.

view(T, Link, Fields) ->
    Old = maps:get(Link, links(T), #{}),
    Last = case cell_task:product(T) of
               undefined -> maps:get(last_product, Old, undefined);
               P -> P
           end,
    put_view(T, Link, maps:merge(Old, Fields#{last_product => Last})).

links(T) ->
    cell_task_core:links(T).

put_view(T, Link, View) ->
    cell_task_core:set_links(T, maps:put(Link, View, links(T))).

from_status(Role, #{phase := P, available := A, not_busy := N, seq := Seq, link := LPid}) ->
    #{role => Role, phase => P, available => A, not_busy => N, seq => Seq, lpid => LPid}.

store(T, Product, Gen, Marker, Opts) ->
    cell_task:store(T, Product, Gen, Marker, Opts).

%% A task's call to one of its links: a task the link does not know (it could not
%% reach the link when it booted, the link restarted, or another node just came in
%% reach) attaches and asks again. The status the answer carries goes into the task's
%% view, so a status message it overtook is not taken for news.
call(T, Link, Request) ->
    case request(T, Link, Request) of
        {{error, not_attached}, _, _} ->
            #{role := Role} = link_view(T, Link),
            T1 = attach(T, Link, Role),
            case request(T1, Link, Request) of
                {{error, not_attached}, _, LPid} ->
                    %% Still not attached: the link restarted between the two asks
                    %% (its greeting attaches the task). As a link restarting.
                    seen(T1, Link, {{error, link_down}, none, LPid});
                Answer ->
                    seen(T1, Link, Answer)
            end;
        Answer ->
            seen(T, Link, Answer)
    end.

seen(T, Link, {Reply, #{seq := Seq, link := LPid} = Status, LPid}) ->
    case maps:find(Link, links(T)) of
        {ok, #{role := Role, lpid := LPid, seq := Seen} = View} when Seq > Seen ->
            {put_view(T, Link, maps:merge(View, from_status(Role, Status))), Reply};
        _ ->
            {T, Reply}
    end;
seen(T, _Link, {Reply, _, _}) ->
    {T, Reply}.

%% The link process the task is attached to is called directly: looking its name up
%% on its node is a round trip of its own. Only when that
%% process is gone is the name looked up (a restarted link answers `not_attached').
request(T, Link, Request) ->
    Answer = case link_pid(T, Link) of
                 undefined ->
                     plain_call(Link, Request);
                 Pid ->
                     case call_pid(Pid, Request) of
                         {error, link_down} -> plain_call(Link, Request);
                         %% Asked once: another call would wait as long again.
                         {error, no_answer} -> {{error, link_down}, Pid};
                         Reply -> {Reply, Pid}
                     end
             end,
    case Answer of
        {{error, link_down}, LPid} -> {{error, link_down}, none, LPid};
        {{Reply1, Status}, LPid} -> {Reply1, Status, LPid}
    end.

link_pid(T, Link) ->
    case maps:get(Link, links(T), #{}) of
        #{lpid := Pid, link_down := false} when is_pid(Pid) -> Pid;
        #{lpid := Pid} = View when is_pid(Pid), not is_map_key(link_down, View) -> Pid;
        _ -> undefined
    end.

%% A link that is restarting, on a node that went down, or that does not answer within
%% the deadline answers `{error, link_down}'.
plain_call(Link, Request) ->
    case cell_handshake_link:whereis(Link) of
        undefined -> {{error, link_down}, undefined};
        Pid ->
            case call_pid(Pid, Request) of
                {error, no_answer} -> {{error, link_down}, Pid};
                Reply -> {Reply, Pid}
            end
    end.

call_pid(Pid, Request) ->
    try
        gen_server:call(Pid, Request, ?CALL_TIMEOUT)
    catch
        exit:{noproc, _} -> {error, link_down};
        exit:{normal, _} -> {error, link_down};
        exit:{killed, _} -> {error, link_down};
        exit:{shutdown, _} -> {error, link_down};
        exit:{{nodedown, _}, _} -> {error, link_down};
        exit:{timeout, _} ->
            Op = case Request of {O, _} -> O; {O, _, _, _} -> O; _ -> Request end,
            cell_log:warning(cell, "the handshake link on node ~ts did not answer (~p) "
                             "within ~w s; taken as down", [node(Pid), Op,
                                                            ?CALL_TIMEOUT div 1000]),
            {error, no_answer}
    end.
