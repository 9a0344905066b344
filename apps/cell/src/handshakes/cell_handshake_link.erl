%% @doc One handshake link between an upstream (previous) and a downstream (next)
%% device task: the seed's Available / NotBusy / Abort signals with Data (seed 000
%% §2.3.6), kept as a commit protocol in one process, which is the point where the
%% seed's race (upstream withdraws a nanosecond after downstream commits) is decided.
%%
%% <pre>
%%  phase       Available NotBusy  what happened
%%  idle        false     false
%%  offered     true      false    upstream offers its product (phase 1)
%%  committed   true      true     downstream took it (phase 2): from here the offer
%%                                 can no longer be withdrawn
%%  released    false     true     the product left upstream (phase 3): downstream
%%                                 owns it on disk from here
%%  aborting    false     false    downstream aborted after release; upstream takes
%%                                 the product back
%% </pre>
%%
%% Completion (phase 4) and an abort before release return to idle. A partner that
%% stops mid-transfer ends it: the other side is told `{interrupted, Why, Phase}' and
%% the link is idle again, so that side can go on. Both partners are told of every
%% signal change by message (`{cell_handshake, Link, signals, Status}', numbered, so a
%% partner never takes an older status for a newer one) and of the protocol's own
%% steps (`{cell_handshake, Link, Step}', or `{cell_handshake, Link, Step, Status}'
%% when the step changes the signals: one message for both); every answer to a partner
%% carries the status it leaves. The
%% partners are monitored, across nodes too, and a partner that stops in any phase
%% ends the transfer on the other side, never leaves it waiting. Every change is
%% published as a `link_phase' event (`link', `phase', `serial') for the panel.
-module(cell_handshake_link).
-behaviour(gen_server).

-export([start_link/1, child_spec/1, whereis/1, name/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([phase/0, role/0, spec/0]).

-type phase() :: idle | offered | committed | released | aborting.
-type role() :: up | down.
-type task_ref() :: atom() | {atom(), node()} | undefined.
-type spec() :: #{id := atom(), from := task_ref(), to := task_ref()}.

-record(end_, {task :: task_ref(),
               pid :: pid() | undefined,
               mref :: reference() | undefined}).

-record(state, {id :: atom(),
                up :: #end_{},
                down :: #end_{},
                phase = idle :: phase(),
                product :: term(),
                gen = 0 :: non_neg_integer(),
                abort = false :: boolean(),
                seq = 0 :: non_neg_integer(),
                waiter :: gen_server:from() | undefined,
                %% The copy upstream last handed on: downstream owns the product in a
                %% newer record (it said so), so this one is stale wherever it is.
                handed = none :: {binary(), non_neg_integer()} | none}).

%% @doc Starts a link; it registers globally, so a partner on another node finds it.
-spec start_link(spec()) -> {ok, pid()} | {error, term()}.
start_link(#{id := Id} = Spec) ->
    gen_server:start_link({global, name(Id)}, ?MODULE, Spec, []).

-spec child_spec(spec()) -> supervisor:child_spec().
child_spec(#{id := Id} = Spec) ->
    #{id => Id, start => {?MODULE, start_link, [Spec]}}.

%% @doc The global name of a link.
-spec name(atom()) -> {cell_handshake, atom()}.
name(Id) -> {cell_handshake, Id}.

-spec whereis(atom()) -> pid() | undefined.
whereis(Id) ->
    case global:whereis_name(name(Id)) of
        undefined -> undefined;
        Pid -> Pid
    end.

%% -------------------------------------------------------------------------------------

-spec init(spec()) -> {ok, #state{}}.
init(#{id := Id, from := From, to := To}) ->
    State = #state{id = Id, up = #end_{task = From}, down = #end_{task = To}},
    %% A restarted link tells its partners, who attach again.
    _ = [cell_handshake:hello(T, Id) || T <- [From, To], T =/= undefined],
    {ok, State}.

-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, term(), #state{}} | {noreply, #state{}}.
handle_call({attach, Role, Task, Pid, Holding}, _From, State) ->
    %% What the attaching task holds goes to the other side, which may be on another
    %% node and hold an older copy of it.
    case Holding of
        {Serial, Gen} -> tell(other(Role), {holder, Serial, Gen}, State);
        none -> ok
    end,
    case attach(Role, Task, Pid, State) of
        %% An upstream task restarted before it forgot the copy it handed on: its
        %% record is stale, though downstream may have sent the product out since and
        %% hold no newer record for anyone to compare.
        {reply, {ok, Status}, State1} when Role =:= up, Holding =/= none,
                                           Holding =:= State#state.handed ->
            {reply, {ok, Status#{stale => true}}, State1};
        Reply ->
            Reply
    end;
handle_call({detach, Role, Pid}, _From, State) ->
    detach(Role, Pid, State);
handle_call(status, _From, State) ->
    {reply, status(State), State};
handle_call({Op, Pid} = Request, From, State) when is_atom(Op) ->
    case role_of(Pid, State) of
        undefined -> {reply, {{error, not_attached}, status(State)}, State};
        Role -> numbered(op(Role, Request, From, State))
    end;
handle_call({offer, Pid, Product, Gen}, _From, State) ->
    numbered(case {role_of(Pid, State), State#state.phase} of
                 {up, idle} ->
                     {reply, ok, change(up, State#state{phase = offered, product = Product,
                                                    gen = Gen, abort = false})};
                 {up, Phase} ->
                     {reply, {error, {busy, Phase}}, State};
                 _ ->
                     {reply, {error, not_attached}, State}
             end).

%% Downstream owns the released product on disk: upstream may forget its copy. A
%% message, not a call: nothing downstream does next depends on it.
-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({owned, Pid}, #state{phase = released, product = #{serial := S}, gen = G} = State) ->
    case role_of(Pid, State) of
        down ->
            tell(up, owned, State),
            {noreply, State#state{handed = {S, G}}};
        _ ->
            {noreply, State}
    end;
handle_cast({owned, _Pid}, State) ->
    %% The transfer ended meanwhile (interrupted): upstream keeps a stale copy, which
    %% the generations recognise.
    {noreply, State}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'DOWN', MRef, process, _Pid, Reason}, #state{up = #end_{mref = MRef}} = State) ->
    {noreply, partner_lost(up, Reason, State)};
handle_info({'DOWN', MRef, process, _Pid, Reason}, #state{down = #end_{mref = MRef}} = State) ->
    {noreply, partner_lost(down, Reason, State)};
handle_info({'DOWN', _MRef, process, _Pid, _Reason}, State) ->
    %% The monitor of a partner that has since detached.
    {noreply, State}.

%% Every answer to a partner carries the status it leaves, numbered: the partner sees
%% the signals as they are after its own step, and ignores any older status message
%% still on its way.
numbered({reply, Reply, State}) -> {reply, {Reply, status(State)}, State};
numbered({noreply, State}) -> {noreply, State}.

%% -------------------------------------------------------------------------------------
%% The protocol
%% -------------------------------------------------------------------------------------

%% Upstream: withdraw the offer unless downstream has already begun to take it.
op(up, {try_abort_offering, _}, _From, #state{phase = offered} = State) ->
    {reply, true, change(up, State#state{phase = idle, product = undefined, gen = 0})};
op(up, {try_abort_offering, _}, _From, #state{phase = idle} = State) ->
    {reply, true, State};
op(up, {try_abort_offering, _}, _From, State) ->
    {reply, false, State};
%% Upstream, phase 3: the product has left.
op(up, {release, _}, _From, #state{phase = committed} = State) ->
    {reply, ok, change(up, {released, State#state.product, State#state.gen},
                       State#state{phase = released})};
%% Upstream took an aborted product back: downstream may forget its copy.
op(up, {taken_back, _}, _From, #state{phase = aborting, waiter = Waiter} = State) ->
    State1 = change(up, State#state{phase = idle, product = undefined, gen = 0, waiter = undefined}),
    Waiter =/= undefined andalso gen_server:reply(Waiter, {given_back, status(State1)}),
    {reply, ok, State1};
%% Downstream: look without locking (PeekBoardAvailable).
op(down, {peek, _}, _From, #state{phase = offered, product = P} = State) ->
    {reply, {ok, P}, State};
op(down, {peek, _}, _From, State) ->
    {reply, none, State};
%% Downstream, phase 2: takes the offered product (reads Available with locking and
%% sets NotBusy in one step, so upstream can no longer withdraw it).
op(down, {commit, _}, _From, #state{phase = offered, product = P, gen = G} = State) ->
    {reply, {ok, P, G}, change(down, State#state{phase = committed, abort = false})};
op(down, {commit, _}, _From, State) ->
    {reply, {error, not_available}, State};
%% Downstream, phase 4: the product has arrived.
op(down, {complete, _}, _From, #state{phase = released} = State) ->
    {reply, ok, change(down, completed, State#state{phase = idle, product = undefined, gen = 0})};
op(down, {complete, _}, _From, State) ->
    {reply, {error, {not_released, State#state.phase}}, State};
%% Downstream aborts: before release upstream still owns the product; after release
%% upstream must take it back before downstream forgets its copy.
op(down, {abort, _}, _From, #state{phase = committed} = State) ->
    {reply, kept_by_upstream, change(down, aborted, State#state{phase = idle, abort = true,
                                                          product = undefined, gen = 0})};
op(down, {abort, _}, From, #state{phase = released, up = #end_{pid = Up}} = State)
  when Up =/= undefined ->
    tell(up, {take_back, State#state.product, State#state.gen}, State),
    {noreply, change(State#state{phase = aborting, abort = true, waiter = From})};
op(down, {abort, _}, _From, State) ->
    %% Nobody to give it to (upstream stopped): downstream keeps it.
    {reply, kept, change(down, State#state{phase = idle, product = undefined, gen = 0})};
%% Either side: an emergency stop or a stop mid-transfer.
op(Role, {interrupt, _}, _From, State) ->
    {reply, ok, interrupt(Role, stopped, State)};
op(_Role, {Op, _}, _From, State) ->
    {reply, {error, {not_now, Op, State#state.phase}}, State}.

%% A partner stopped in some phase: the transfer ends for the other side.
interrupt(_Role, _Why, #state{phase = idle} = State) ->
    State;
interrupt(up, _Why, #state{phase = offered} = State) ->
    %% An offer of a partner that is gone is withdrawn.
    change(State#state{phase = idle, product = undefined, gen = 0});
interrupt(down, _Why, #state{phase = offered} = State) ->
    State;
interrupt(Role, Why, #state{phase = aborting, waiter = Waiter} = State) when Role =:= up ->
    tell(down, {interrupted, Why}, State),
    State1 = change(State#state{phase = idle, product = undefined, gen = 0, waiter = undefined}),
    Waiter =/= undefined andalso gen_server:reply(Waiter, {kept, status(State1)}),
    State1;
interrupt(Role, Why, #state{phase = Phase} = State) ->
    tell(other(Role), {interrupted, Why, Phase}, State),
    change(State#state{phase = idle, product = undefined, gen = 0}).

partner_lost(Role, Reason, State) ->
    Why = case Reason of
              noconnection -> node_down;
              replaced -> partner_restarted;
              _ -> partner_stopped
          end,
    State1 = interrupt(Role, Why, State),
    set_end(Role, (get_end(Role, State1))#end_{pid = undefined, mref = undefined}, State1).

%% -------------------------------------------------------------------------------------

attach(Role, Task, Pid, State) ->
    End = get_end(Role, State),
    case End of
        #end_{pid = Pid} ->
            {reply, {ok, status(State)}, State};
        #end_{pid = Old, task = Task, mref = MRef} when is_pid(Old) ->
            %% A restarted task attaching before its predecessor's 'DOWN' reached this
            %% process: one task has one live incarnation, so the old one is gone.
            demonitor(MRef, [flush]),
            attach(Role, Task, Pid, partner_lost(Role, replaced, State));
        #end_{pid = Old} when is_pid(Old) ->
            {reply, {error, {attached, End#end_.task}}, State};
        _ ->
            MRef = monitor(process, Pid),
            State1 = set_end(Role, End#end_{task = Task, pid = Pid, mref = MRef}, State),
            {reply, {ok, status(State1)}, State1}
    end.

%% Upstream detaches when no offer is open; downstream unless it is taking a product
%% (an open offer stays for whoever connects next, the seed's feeders).
detach(Role, Pid, #state{phase = Phase} = State) ->
    Free = case Role of
               up -> Phase =:= idle;
               down -> Phase =:= idle orelse Phase =:= offered
           end,
    case get_end(Role, State) of
        #end_{pid = Pid, mref = MRef} = End when Free ->
            demonitor(MRef, [flush]),
            {reply, ok, set_end(Role, End#end_{pid = undefined, mref = undefined}, State)};
        #end_{pid = Pid} ->
            {reply, {error, {busy, Phase}}, State};
        _ ->
            {reply, {error, not_attached}, State}
    end.

%% The signals as both partners see them, numbered; `link' tells one incarnation of
%% the link from the next.
status(#state{phase = P, product = Product, gen = G, abort = A, seq = Seq}) ->
    #{phase => P, product => Product, gen => G, abort => A,
      available => lists:member(P, [offered, committed]),
      not_busy => lists:member(P, [committed, released]),
      seq => Seq, link => self()}.

%% Tells both partners of every signal change.
change(State) ->
    change(none, State).

%% As change/1, but the partner whose call made the change learns the new status from
%% the answer, not from a message as well.
change(Caller, State) ->
    change(Caller, signals, State).

%% As change/2, the other partner told of a step of the protocol in the same message
%% (it handles the step first, then the signals, as if they had come one after the
%% other).
change(Caller, Step, #state{seq = Seq} = State0) ->
    State = State0#state{seq = Seq + 1},
    Status = status(State),
    _ = [send(get_end(Role, State), {cell_handshake, State#state.id, Step, Status})
         || Role <- [up, down], Role =/= Caller],
    %% The panel draws the link in its phase (free when nobody watches).
    ok = cell_events:publish(link_phase, cell, #{link => State#state.id,
                                                 phase => State#state.phase,
                                                 serial => serial(State#state.product)}),
    State.

serial(#{serial := S}) -> S;
serial(_) -> undefined.

tell(Role, Msg, State) ->
    send(get_end(Role, State), {cell_handshake, State#state.id, Msg}).

send(#end_{pid = Pid}, Msg) when is_pid(Pid) ->
    Pid ! Msg,
    ok;
send(_, _) ->
    ok.

other(up) -> down;
other(down) -> up.

role_of(Pid, #state{up = #end_{pid = Pid}}) -> up;
role_of(Pid, #state{down = #end_{pid = Pid}}) -> down;
role_of(_, _) -> undefined.

get_end(up, #state{up = E}) -> E;
get_end(down, #state{down = E}) -> E.

set_end(up, E, State) -> State#state{up = E};
set_end(down, E, State) -> State#state{down = E}.
