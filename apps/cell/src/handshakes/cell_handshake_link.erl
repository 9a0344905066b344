%% @doc One handshake link between an upstream (previous) and a downstream (next)
%% device task: the seed's Available / NotBusy / Abort signals with Data (seed 000
%% §2.3.6), kept as a commit protocol in one process, which is the point where the
%% seed's race (upstream withdraws a nanosecond after downstream commits) is decided.
%%
%% The phases, and what the link decides in each, are in {@link
%% cell_handshake_link_core}; this process feeds it the partners' calls, messages and
%% stops, and carries out what it decides: answers, messages to the partners,
%% monitors.
%%
%% A partner that stops mid-transfer ends it: the other side is told
%% `{interrupted, Why, Phase}' and the link is idle again, so that side can go on. Both
%% partners are told of every signal change by message (`{cell_handshake, Link,
%% signals, Status}', numbered, so a partner never takes an older status for a newer
%% one) and of the protocol's own steps (`{cell_handshake, Link, Step}', or
%% `{cell_handshake, Link, Step, Status}' when the step changes the signals: one
%% message for both); every answer to a partner carries the status it leaves. The
%% partners are monitored, across nodes too, and a partner that stops in any phase
%% ends the transfer on the other side, never leaves it waiting. Every change is
%% published as a `link_phase' event (`link', `phase', `serial') for the panel.
%%
%% The link's fence (what it released, per serial, and whether downstream owns it; see
%% the core) is kept in `Data/<Link>.link', a record file of cell_file written durably
%% before the answer or message that depends on it, and read when the link starts, so
%% a link restarted after a crash or a power cut of its node still refuses a stale copy.
-module(cell_handshake_link).
-behaviour(gen_server).

-export([start_link/1, child_spec/1, whereis/1, name/1, host/1]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2]).
-export([fence_path/1]).

-export_type([phase/0, role/0, spec/0]).

%% A name looked up on a connected node: its answer is a round trip; a node that takes
%% longer is as good as out of reach for this ask.
-define(LOOKUP_TIMEOUT, 2000).

-type phase() :: cell_handshake_link_core:phase().
-type role() :: cell_handshake_link_core:role().
-type task_ref() :: cell_handshake_link_core:task_ref().
-type spec() :: #{id := atom(), from := task_ref(), to := task_ref()}.

-record(state, {core :: cell_handshake_link_core:core() | undefined,
                spec :: spec(),
                %% The fence's file, kept open between writes.
                fence :: cell_file:record_file() | undefined,
                %% The monitors of the attached partners.
                mrefs = #{} :: #{role() => reference()}}).

%% @doc Starts a link, registered on its node under its local name. The cell's spec
%% says which node runs it (the downstream's, see {@link cell_spec:hosted_links/1}),
%% so a partner on another node finds it there without a name registry spanning the
%% line: no global name, no synchronisation of names after a network cut or a node
%% that restarts.
-spec start_link(spec()) -> {ok, pid()} | {error, term()}.
start_link(#{id := Id} = Spec) ->
    gen_server:start_link({local, name(Id)}, ?MODULE, Spec, []).

-spec child_spec(spec()) -> supervisor:child_spec().
child_spec(#{id := Id} = Spec) ->
    #{id => Id, start => {?MODULE, start_link, [Spec]}}.

%% @doc The name a link is registered under on its node.
-spec name(atom()) -> atom().
name(Id) -> list_to_atom("cell_handshake_" ++ atom_to_list(Id)).

%% @doc The link process, wherever the running cell's spec places it; `undefined'
%% while it is not running or its node is not connected. A node out of reach is not
%% dialled here (cell_peers connects to the line's nodes, with a backoff): a task that
%% asks again and again never waits for a connection of its own. A link the spec does
%% not name is looked for on this node.
-spec whereis(atom()) -> pid() | undefined.
whereis(Id) ->
    Name = name(Id),
    Node = host(Id),
    case Node =:= node() of
        true ->
            erlang:whereis(Name);
        false ->
            case lists:member(Node, nodes()) of
                true ->
                    try erpc:call(Node, erlang, whereis, [Name], ?LOOKUP_TIMEOUT)
                    catch error:{erpc, _} -> undefined
                    end;
                false ->
                    undefined
            end
    end.

%% @doc The node a link runs on by the running cell's spec: the downstream task's, or
%% the upstream's for a link with none (this node for a link it does not name).
-spec host(atom()) -> node().
host(Id) ->
    #{links := Links} = cell_spec:running(),
    case [L || #{id := I} = L <- Links, I =:= Id] of
        [#{to := {_, Node}}] -> Node;
        [#{to := undefined, from := {_, Node}}] -> Node;
        _ -> node()
    end.

%% -------------------------------------------------------------------------------------

-spec init(spec()) -> {ok, #state{}, {continue, load}}.
init(Spec) ->
    {ok, #state{spec = Spec}, {continue, load}}.

%% The fence its predecessor left, before any partner is heard.
-spec handle_continue(load, #state{}) -> {noreply, #state{}}.
handle_continue(load, #state{spec = #{id := Id} = Spec} = State) ->
    Fence = load_fence(Id),
    %% A restarted link tells its partners, who attach again.
    {Core, Effects} = cell_handshake_link_core:new(Spec#{fence => Fence}, self()),
    File = cell_file:record_file(fence_path(Id)),
    {noreply, effects(Effects, State#state{core = Core, fence = File})}.

%% @doc The file of a link's fence.
-spec fence_path(atom()) -> binary().
fence_path(Id) ->
    unicode:characters_to_binary(filename:join(cell_config:dir(data),
                                               atom_to_list(Id) ++ ".link"),
                                 unicode, file:native_name_encoding()).

%% The atoms of the record are named here, so `safe' decoding finds them.
load_fence(Id) ->
    Path = fence_path(Id),
    case cell_file:get_record(Path) of
        {error, enoent} ->
            #{};
        {ok, #{fence := Fence}} when is_map(Fence) ->
            case lists:all(fun valid_entry/1, maps:to_list(Fence)) of
                true -> Fence;
                false -> damaged(Id, Path, bad_entry)
            end;
        {ok, _Other} ->
            damaged(Id, Path, not_a_fence);
        {error, Why} ->
            damaged(Id, Path, Why)
    end.

valid_entry({S, #{gen := G, state := State, up := Up}})
  when is_binary(S), is_integer(G), G >= 0, is_binary(Up) ->
    State =:= released orelse State =:= owned;
valid_entry(_) ->
    false.

%% The link still runs: without the fence it is as safe as the generations alone make
%% it, and the operator is told so.
damaged(Id, Path, Why) ->
    cell_log:error(Id, "the handshake's record of the products it handed on (~ts) cannot "
                   "be read (~tp): a copy left behind at the previous station after a "
                   "network cut is no longer recognised as handed on; check the line for "
                   "a product held twice", [Path, Why]),
    #{}.

-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, term(), #state{}} | {noreply, #state{}}.
handle_call(Request, From, #state{core = Core} = State) ->
    case cell_handshake_link_core:call(Request, From, Core) of
        {reply, Reply, Core1, Effects} ->
            {reply, Reply, effects(Effects, State#state{core = Core1})};
        {noreply, Core1, Effects} ->
            {noreply, effects(Effects, State#state{core = Core1})}
    end.

%% Downstream owns the released product on disk: upstream may forget its copy. A
%% message, not a call: nothing downstream does next depends on it.
-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast(Msg, #state{core = Core} = State) when element(1, Msg) =:= owned ->
    {Core1, Effects} = cell_handshake_link_core:cast(Msg, Core),
    {noreply, effects(Effects, State#state{core = Core1})}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'DOWN', MRef, process, _Pid, Reason}, #state{core = Core, mrefs = MRefs} = State) ->
    case [Role || {Role, R} <- maps:to_list(MRefs), R =:= MRef] of
        [Role] ->
            State1 = State#state{mrefs = maps:remove(Role, MRefs)},
            {Core1, Effects} = cell_handshake_link_core:partner_down(Role, Reason, Core),
            {noreply, effects(Effects, State1#state{core = Core1})};
        [] ->
            %% The monitor of a partner that has since detached.
            {noreply, State}
    end.

%% -------------------------------------------------------------------------------------

%% Carries out the core's effects, in their order.
effects([], State) ->
    State;
effects([{send, Pid, Msg} | Rest], State) ->
    Pid ! Msg,
    effects(Rest, State);
effects([{reply, From, Reply} | Rest], State) ->
    ok = gen_server:reply(From, Reply),
    effects(Rest, State);
effects([{monitor, Role, Pid} | Rest], #state{mrefs = MRefs} = State) ->
    effects(Rest, State#state{mrefs = MRefs#{Role => monitor(process, Pid)}});
effects([{demonitor, Role} | Rest], #state{mrefs = MRefs} = State) ->
    _ = case MRefs of
            #{Role := MRef} -> demonitor(MRef, [flush]);
            #{} -> true
        end,
    effects(Rest, State#state{mrefs = maps:remove(Role, MRefs)});
effects([{hello, Task, Id} | Rest], State) ->
    ok = cell_handshake:hello(Task, Id),
    effects(Rest, State);
effects([{persist, Fence} | Rest], #state{fence = File} = State) ->
    %% Nothing that depends on it goes out before it is on disk; a fence that cannot
    %% be written stops the link (its supervisor restarts it) rather than let it go on
    %% promising what it could not keep.
    ok = cell_file:put_record(File, #{fence => Fence}, #{}),
    effects(Rest, State);
effects([{phase, Id, Phase, Serial} | Rest], State) ->
    ok = cell_events:publish(link_phase, cell, #{link => Id, phase => Phase, serial => Serial}),
    effects(Rest, State).
