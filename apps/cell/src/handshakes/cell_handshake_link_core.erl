%% @doc The decisions of a handshake link (seed 000 §2.3.6), without a process: what
%% the link answers, which partner it tells what, whom it monitors, given its phase and
%% a partner's call, message or stop. {@link cell_handshake_link} feeds its calls,
%% casts and partners' `DOWN's in and carries out the effects that come back, in their
%% order; everything here is a function of its arguments and tested without processes.
%%
%% <pre>
%%  phase       Available NotBusy  what happened
%%  idle        false     false
%%  offered     true      false    upstream offers its product (phase 1)
%%  committed   true      true     downstream took it (phase 2): from here the offer
%%                                 can no longer be withdrawn (TryAbortOffering false)
%%  released    false     true     the product left upstream (phase 3): downstream
%%                                 owns it on disk from here
%%  aborting    false     false    downstream aborted after release; upstream takes
%%                                 the product back
%% </pre>
%%
%% Decisions:
%% <ul>
%% <li>Attach and detach: a partner attaches once per incarnation (a restarted task
%%   replaces its predecessor, whose transfer ends as if it had stopped); what it
%%   holds is told to the other side; an upstream task that still holds the copy it
%%   handed on is told that copy is stale. Upstream detaches only when idle,
%%   downstream also while an offer is open (it stays for whoever comes next).</li>
%% <li>The protocol's steps: offer (phase 1), TryAbortOffering, PeekBoardAvailable
%%   (looks, locks nothing), commit (phase 2), release (phase 3), owned, complete
%%   (phase 4), abort before release (upstream still owns the product) and after it
%%   (upstream takes the product back, and downstream's call waits until it has),
%%   interrupt.</li>
%% <li>A partner that stops (or is replaced, or its node goes) ends the transfer: the
%%   other side is told `{interrupted, Why, Phase}', an open offer of a stopped
%%   upstream is withdrawn, a downstream waiting for its product to be taken back
%%   keeps it.</li>
%% <li>Every signal change is numbered and told to the partners: to the one whose call
%%   made it in its answer, to the other by message (with the protocol's step when
%%   there is one, one message for both).</li>
%% <li>The fence: the link remembers, per serial, the generation it last released and
%%   whether downstream said it owns the product in a newer record (`released',
%%   `owned'). The process keeps it on disk (the `persist' effect comes before the
%%   answer or message that depends on it), so it outlives a crash or a power cut of
%%   the link's node. An offer at or below a fenced generation is refused: the copy is
%%   stale (`owned': downstream holds the product or has sent it on) or its owner is
%%   not known yet (`released': downstream stopped before it said). An upstream task
%%   that attaches with a copy learns which (`stale', `unsettled'); downstream
%%   attaching says what it holds, which settles a `released' entry, and upstream is
%%   told `{settled, Serial, owned | yours}'. An entry goes when upstream offers
%%   another serial (its file holds that one now, durably), takes the product back, or
%%   downstream disowns it (`{disown, Pid, Serial}': the operator said the product is
%%   not at downstream, so the copy upstream sees is the product).</li>
%% </ul>
-module(cell_handshake_link_core).

-export([new/2, call/3, cast/2, partner_down/3]).

-export_type([core/0, phase/0, role/0, task_ref/0, effect/0, fence/0]).

-type phase() :: idle | offered | committed | released | aborting.
-type role() :: up | down.
-type task_ref() :: atom() | {atom(), node()} | undefined.
%% What the process does, in this order.
-type effect() :: {send, pid(), term()}               %% a message to a partner
                | {reply, gen_server:from(), term()}  %% the answer to a call that waited
                | {monitor, role(), pid()}            %% watch the partner in this role
                | {demonitor, role()}                 %% stop watching it (and its 'DOWN')
                | {hello, task_ref(), atom()}         %% a link (re)started: attach again
                | {phase, atom(), phase(), term()}    %% publish the link's phase and serial
                | {persist, fence()}.                 %% write the fence durably, now
%% Per serial: the generation the link last released, whether downstream said it owns
%% the product (in the next generation), and the upstream task that released it (as
%% text, so the file never needs an atom the node does not know).
-type fence() :: #{binary() => #{gen := non_neg_integer(), state := released | owned,
                                 up := binary()}}.

-record(end_, {task :: task_ref(),
               key :: binary(),              %% the task as a fence's entry names it
               pid :: pid() | undefined}).

-record(core, {id :: atom(),
               self :: pid(),
               up :: #end_{},
               down :: #end_{},
               phase = idle :: phase(),
               product :: term(),
               gen = 0 :: non_neg_integer(),
               abort = false :: boolean(),
               seq = 0 :: non_neg_integer(),
               waiter :: gen_server:from() | undefined,
               %% What the link released, per serial (see the module doc).
               fence = #{} :: fence(),
               %% The effects of the event being handled, last first.
               out = [] :: [effect()]}).

-opaque core() :: #core{}.

%% -------------------------------------------------------------------------------------

%% @doc A link between `from' (upstream) and `to' (downstream), run by the process
%% `Self' (its status names it, so a partner tells one incarnation from the next); it
%% says hello to its partners, who attach again after a restart. `fence' is the fence
%% its predecessor left on disk.
-spec new(#{id := atom(), from := task_ref(), to := task_ref(), fence => fence(), _ => _},
          pid()) -> {core(), [effect()]}.
new(#{id := Id, from := From, to := To} = Spec, Self) ->
    Core = #core{id = Id, self = Self, up = end_(From), down = end_(To),
                 fence = maps:get(fence, Spec, #{})},
    {Core, [{hello, T, Id} || T <- [From, To], T =/= undefined]}.

%% @doc A partner's call; `From' is kept when the answer has to wait (an abort after
%% release waits for upstream to take the product back).
-spec call(term(), gen_server:from(), core()) ->
          {reply, term(), core(), [effect()]} | {noreply, core(), [effect()]}.
call(Request, From, Core) ->
    done(request(Request, From, Core)).

%% @doc A partner's message: `{owned, Pid, Serial, Gen}' (or `{owned, Pid}' for the
%% product being released), downstream owns the released product on disk in
%% generation `Gen', so upstream may forget its copy.
-spec cast({owned, pid()} | {owned, pid(), binary(), pos_integer()}, core()) ->
          {core(), [effect()]}.
cast({owned, Pid}, #core{phase = released, product = #{serial := S}, gen = G} = Core) ->
    cast({owned, Pid, S, G + 1}, Core);
cast({owned, _Pid}, Core) ->
    done(Core);
cast({owned, Pid, S, Gen}, #core{phase = Phase, product = P} = Core) ->
    case role_of(Pid, Core) of
        down ->
            %% Said even when the transfer ended meanwhile (upstream's node went out of
            %% reach as the product was released): the fence then knows that the copy
            %% upstream kept is stale, whatever upstream is told later.
            Core1 = fence_owned(S, Gen, Core),
            case Phase =:= released andalso serial(P) =:= S of
                true -> done(tell(up, owned, Core1));
                false -> done(Core1)
            end;
        _ ->
            done(Core)
    end.

%% @doc The partner in `Role' stopped (its monitor's `Reason'): the transfer ends for
%% the other side.
-spec partner_down(role(), term(), core()) -> {core(), [effect()]}.
partner_down(Role, Reason, Core) ->
    done(partner_lost(Role, Reason, Core)).

%% -------------------------------------------------------------------------------------

done({reply, Reply, #core{out = Out} = Core}) -> {reply, Reply, Core#core{out = []}, lists:reverse(Out)};
done({noreply, #core{out = Out} = Core}) -> {noreply, Core#core{out = []}, lists:reverse(Out)};
done(#core{out = Out} = Core) -> {Core#core{out = []}, lists:reverse(Out)}.

request({attach, Role, Task, Pid, Holding}, _From, Core) ->
    %% What the attaching task holds goes to the other side, which may be on another
    %% node and hold an older copy of it.
    Core1 = case Holding of
                {Serial, Gen} -> tell(other(Role), {holder, Serial, Gen}, Core);
                none -> Core
            end,
    case attach(Role, Task, Pid, Core1) of
        {reply, {ok, Status}, Core2} when Role =:= up ->
            %% An upstream task holding a copy the link released: stale if downstream
            %% said it owns the product (it may have sent it out since and hold no
            %% newer record for anyone to compare), unsettled until downstream says
            %% what it holds.
            {reply, {ok, maps:merge(Status, fenced(Holding, Core2))}, Core2};
        {reply, {ok, _}, Core2} = Reply when Role =:= down ->
            case settle(Holding, Core2) of
                Core2 -> Reply;
                Core3 -> {reply, {ok, status(Core3)}, Core3}
            end;
        Reply ->
            Reply
    end;
request({detach, Role, Pid}, _From, Core) ->
    detach(Role, Pid, Core);
request(status, _From, Core) ->
    {reply, status(Core), Core};
request({Op, Pid} = Request, From, Core) when is_atom(Op) ->
    case role_of(Pid, Core) of
        undefined -> {reply, {{error, not_attached}, status(Core)}, Core};
        Role -> numbered(op(Role, Request, From, Core))
    end;
request({disown, Pid, S}, _From, Core) ->
    %% Downstream forgot the product on the operator's word (it is not there): the
    %% fence no longer says downstream holds it, and upstream's copy (the panel still
    %% there, its serial read again) is the owner.
    numbered(case role_of(Pid, Core) of
                 down when S =/= undefined ->
                     case maps:is_key(S, Core#core.fence) andalso live(Core) =/= S of
                         true -> {reply, ok, tell(up, {settled, S, yours}, unfence(S, Core))};
                         false -> {reply, ok, Core}
                     end;
                 _ ->
                     {reply, {error, not_attached}, Core}
             end);
request({offer, Pid, Product, Gen}, _From, Core) ->
    numbered(case {role_of(Pid, Core), Core#core.phase} of
                 {up, idle} ->
                     case fenced({serial(Product), Gen}, Core) of
                         #{stale := true} ->
                             {reply, {error, {stale, serial(Product)}}, Core};
                         #{unsettled := true} ->
                             {reply, {error, {unsettled, serial(Product)}}, Core};
                         #{} ->
                             Core1 = unfence_others(serial(Product), Core),
                             {reply, ok, change(up, Core1#core{phase = offered,
                                                               product = Product, gen = Gen,
                                                               abort = false})}
                     end;
                 {up, Phase} ->
                     {reply, {error, {busy, Phase}}, Core};
                 _ ->
                     {reply, {error, not_attached}, Core}
             end).

%% Every answer to a partner carries the status it leaves, numbered: the partner sees
%% the signals as they are after its own step, and ignores any older status message
%% still on its way.
numbered({reply, Reply, Core}) -> {reply, {Reply, status(Core)}, Core};
numbered({noreply, Core}) -> {noreply, Core}.

%% -------------------------------------------------------------------------------------
%% The protocol
%% -------------------------------------------------------------------------------------

%% Upstream: withdraw the offer unless downstream has already begun to take it.
op(up, {try_abort_offering, _}, _From, #core{phase = offered} = Core) ->
    {reply, true, change(up, Core#core{phase = idle, product = undefined, gen = 0})};
op(up, {try_abort_offering, _}, _From, #core{phase = idle} = Core) ->
    {reply, true, Core};
op(up, {try_abort_offering, _}, _From, Core) ->
    {reply, false, Core};
%% Upstream, phase 3: the product has left.
op(up, {release, _}, _From, #core{phase = committed, product = P, gen = G} = Core) ->
    %% On disk before downstream hears of it and upstream of its answer: whatever is
    %% cut after this, the link knows it let this generation go.
    Core1 = fence(serial(P), #{gen => G, state => released, up => up_key(Core)}, Core),
    {reply, ok, change(up, {released, P, G}, Core1#core{phase = released})};
%% Upstream took an aborted product back: downstream may forget its copy.
op(up, {taken_back, _}, _From, #core{phase = aborting, waiter = Waiter} = Core0) ->
    %% Upstream holds it again, in a newer record: nothing to fence.
    Core = unfence(serial(Core0#core.product), Core0),
    Core1 = change(up, Core#core{phase = idle, product = undefined, gen = 0,
                                 waiter = undefined}),
    {reply, ok, answer(Waiter, given_back, Core1)};
%% Downstream: look without locking (PeekBoardAvailable).
op(down, {peek, _}, _From, #core{phase = offered, product = P} = Core) ->
    {reply, {ok, P}, Core};
op(down, {peek, _}, _From, Core) ->
    {reply, none, Core};
%% Downstream, phase 2: takes the offered product (reads Available with locking and
%% sets NotBusy in one step, so upstream can no longer withdraw it).
op(down, {commit, _}, _From, #core{phase = offered, product = P, gen = G} = Core) ->
    {reply, {ok, P, G}, change(down, Core#core{phase = committed, abort = false})};
op(down, {commit, _}, _From, Core) ->
    {reply, {error, not_available}, Core};
%% Downstream, phase 4: the product has arrived.
op(down, {complete, _}, _From, #core{phase = released} = Core) ->
    {reply, ok, change(down, completed, Core#core{phase = idle, product = undefined,
                                                  gen = 0})};
op(down, {complete, _}, _From, Core) ->
    {reply, {error, {not_released, Core#core.phase}}, Core};
%% Downstream aborts: before release upstream still owns the product; after release
%% upstream must take it back before downstream forgets its copy.
op(down, {abort, _}, _From, #core{phase = committed} = Core) ->
    {reply, kept_by_upstream, change(down, aborted, Core#core{phase = idle, abort = true,
                                                              product = undefined,
                                                              gen = 0})};
op(down, {abort, _}, From, #core{phase = released, up = #end_{pid = Up}} = Core)
  when Up =/= undefined ->
    Core1 = tell(up, {take_back, Core#core.product, Core#core.gen}, Core),
    {noreply, change(Core1#core{phase = aborting, abort = true, waiter = From})};
op(down, {abort, _}, _From, Core) ->
    %% Nobody to give it to (upstream stopped): downstream keeps it.
    {reply, kept, change(down, Core#core{phase = idle, product = undefined, gen = 0})};
%% Either side: an emergency stop or a stop mid-transfer.
op(Role, {interrupt, _}, _From, Core) ->
    {reply, ok, interrupt(Role, stopped, Core)};
op(_Role, {Op, _}, _From, Core) ->
    {reply, {error, {not_now, Op, Core#core.phase}}, Core}.

%% A partner stopped in some phase: the transfer ends for the other side.
interrupt(_Role, _Why, #core{phase = idle} = Core) ->
    Core;
interrupt(up, _Why, #core{phase = offered} = Core) ->
    %% An offer of a partner that is gone is withdrawn.
    change(Core#core{phase = idle, product = undefined, gen = 0});
interrupt(down, _Why, #core{phase = offered} = Core) ->
    Core;
interrupt(up, Why, #core{phase = aborting, waiter = Waiter} = Core) ->
    Core1 = tell(down, {interrupted, Why}, Core),
    Core2 = change(Core1#core{phase = idle, product = undefined, gen = 0,
                              waiter = undefined}),
    answer(Waiter, kept, Core2);
interrupt(Role, Why, #core{phase = Phase} = Core) ->
    Core1 = tell(other(Role), {interrupted, Why, Phase}, Core),
    change(Core1#core{phase = idle, product = undefined, gen = 0}).

%% The partner is gone (or replaced by its next incarnation): no longer watched, its
%% transfer ended.
partner_lost(Role, Reason, Core) ->
    Why = case Reason of
              noconnection -> node_down;
              replaced -> partner_restarted;
              _ -> partner_stopped
          end,
    Core1 = interrupt(Role, Why, effect({demonitor, Role}, Core)),
    set_end(Role, (get_end(Role, Core1))#end_{pid = undefined}, Core1).

%% -------------------------------------------------------------------------------------

attach(Role, Task, Pid, Core) ->
    End = get_end(Role, Core),
    case End of
        #end_{pid = Pid} ->
            {reply, {ok, status(Core)}, Core};
        #end_{pid = Old, task = Task} when is_pid(Old) ->
            %% A restarted task attaching before its predecessor's 'DOWN' reached the
            %% link: one task has one live incarnation, so the old one is gone.
            attach(Role, Task, Pid, partner_lost(Role, replaced, Core));
        #end_{pid = Old} when is_pid(Old) ->
            {reply, {error, {attached, End#end_.task}}, Core};
        _ ->
            Core1 = set_end(Role, (end_(Task))#end_{pid = Pid},
                            effect({monitor, Role, Pid}, Core)),
            {reply, {ok, status(Core1)}, Core1}
    end.

%% Upstream detaches when no offer is open; downstream unless it is taking a product
%% (an open offer stays for whoever connects next, the seed's feeders).
detach(Role, Pid, #core{phase = Phase} = Core) ->
    Free = case Role of
               up -> Phase =:= idle;
               down -> Phase =:= idle orelse Phase =:= offered
           end,
    case get_end(Role, Core) of
        #end_{pid = Pid} = End when Free ->
            {reply, ok, set_end(Role, End#end_{pid = undefined},
                                effect({demonitor, Role}, Core))};
        #end_{pid = Pid} ->
            {reply, {error, {busy, Phase}}, Core};
        _ ->
            {reply, {error, not_attached}, Core}
    end.

%% The signals as both partners see them, numbered; `link' tells one incarnation of
%% the link from the next.
status(#core{phase = P, product = Product, gen = G, abort = A, seq = Seq, self = Self}) ->
    #{phase => P, product => Product, gen => G, abort => A,
      available => lists:member(P, [offered, committed]),
      not_busy => lists:member(P, [committed, released]),
      seq => Seq, link => Self}.

%% Tells both partners of every signal change.
change(Core) ->
    change(none, Core).

%% As change/1, but the partner whose call made the change learns the new status from
%% the answer, not from a message as well.
change(Caller, Core) ->
    change(Caller, signals, Core).

%% As change/2, the other partner told of a step of the protocol in the same message
%% (it handles the step first, then the signals, as if they had come one after the
%% other).
change(Caller, Step, #core{seq = Seq} = Core0) ->
    Core = Core0#core{seq = Seq + 1},
    Status = status(Core),
    Told = lists:foldl(fun(Role, C) -> send(Role, {cell_handshake, C#core.id, Step, Status}, C) end,
                       Core, [Role || Role <- [up, down], Role =/= Caller]),
    %% The panel draws the link in its phase.
    effect({phase, Core#core.id, Core#core.phase, serial(Core#core.product)}, Told).

serial(#{serial := S}) -> S;
serial(_) -> undefined.

%% The answer to downstream's abort that waited, with the status it leaves.
answer(undefined, _Reply, Core) ->
    Core;
answer(Waiter, Reply, Core) ->
    effect({reply, Waiter, {Reply, status(Core)}}, Core).

tell(Role, Msg, Core) ->
    send(Role, {cell_handshake, Core#core.id, Msg}, Core).

send(Role, Msg, Core) ->
    case get_end(Role, Core) of
        #end_{pid = Pid} when is_pid(Pid) -> effect({send, Pid, Msg}, Core);
        _ -> Core
    end.

effect(Effect, #core{out = Out} = Core) ->
    Core#core{out = [Effect | Out]}.

other(up) -> down;
other(down) -> up.

role_of(Pid, #core{up = #end_{pid = Pid}}) -> up;
role_of(Pid, #core{down = #end_{pid = Pid}}) -> down;
role_of(_, _) -> undefined.

get_end(up, #core{up = E}) -> E;
get_end(down, #core{down = E}) -> E.

set_end(up, E, Core) -> Core#core{up = E};
set_end(down, E, Core) -> Core#core{down = E}.

%% -------------------------------------------------------------------------------------
%% The fence
%% -------------------------------------------------------------------------------------

%% What the fence says of a copy upstream holds (or offers): `stale' when downstream
%% owns the product in a newer record, `unsettled' when the link released it and
%% downstream has not said yet.
fenced({S, G}, #core{fence = Fence}) ->
    case Fence of
        #{S := #{gen := F, state := owned}} when G =< F -> #{stale => true};
        #{S := #{gen := F, state := released}} when G =< F -> #{unsettled => true};
        #{} -> #{}
    end;
fenced(_None, _Core) ->
    #{}.

%% Downstream (re)attached holding `Holding': a released serial it holds in a newer
%% record is its own; one it does not hold never reached its file (it is written,
%% durably, before downstream says anything), so upstream's copy is the owner.
settle(Holding, #core{fence = Fence} = Core) ->
    Live = live(Core),
    maps:fold(fun(S, _Entry, Acc) when S =:= Live ->
                      %% The transfer under way: downstream says `owned' when it has
                      %% written it.
                      Acc;
                 (S, #{gen := G, state := released}, Acc) ->
                      case Holding of
                          {S, HG} when HG > G -> fence_owned(S, HG, Acc);
                          _ -> tell(up, {settled, S, yours}, unfence(S, Acc))
                      end;
                 (_S, _Entry, Acc) ->
                      Acc
              end, Core, Fence).

fence_owned(S, Gen, #core{fence = Fence} = Core) ->
    case Fence of
        #{S := #{gen := G, state := released} = E} when Gen > G ->
            Core1 = fence(S, E#{state => owned}, Core),
            case live(Core) of
                %% Upstream hears `owned' from the transfer itself.
                S -> Core1;
                _ -> tell(up, {settled, S, owned}, Core1)
            end;
        #{} ->
            Core
    end.

%% The serial of the transfer under way after release, if any.
live(#core{phase = Phase, product = P}) when Phase =:= released; Phase =:= aborting ->
    serial(P);
live(_Core) ->
    none.

%% Upstream offers another serial: it holds that one now, durably, so no copy of the
%% serials it released before is left with it.
unfence_others(S, #core{fence = Fence} = Core) ->
    Up = up_key(Core),
    Others = [O || {O, #{up := U}} <- maps:to_list(Fence), O =/= S, U =:= Up],
    lists:foldl(fun unfence/2, Core, Others).

fence(undefined, _Entry, Core) ->
    Core;
fence(S, Entry, #core{fence = Fence} = Core) ->
    Fence1 = Fence#{S => Entry},
    effect({persist, Fence1}, Core#core{fence = Fence1}).

unfence(S, #core{fence = Fence} = Core) ->
    case maps:is_key(S, Fence) of
        true ->
            Fence1 = maps:remove(S, Fence),
            effect({persist, Fence1}, Core#core{fence = Fence1});
        false ->
            Core
    end.

up_key(#core{up = #end_{key = Key}}) ->
    Key.

%% A partner, named once as a fence's entry names it (an upstream's entry says which
%% task released its serial).
end_(Task) ->
    #end_{task = Task, key = iolist_to_binary(io_lib:format("~0tp", [Task]))}.
