%% The handshake link's decisions, without processes: the seed's phases 1-4,
%% TryAbortOffering, PeekBoardAvailable, Abort before and after release, partners
%% attaching, detaching, restarting and stopping in each phase.
-module(cell_handshake_link_core_tests).

-include_lib("eunit/include/eunit.hrl").

-define(P, #{serial => <<"S1">>}).

%% The link's process, upstream's, downstream's, upstream's next incarnation: the core
%% only compares and addresses them.
pid(link) -> list_to_pid("<0.900.0>");
pid(up) -> list_to_pid("<0.901.0>");
pid(down) -> list_to_pid("<0.902.0>");
pid(up_restarted) -> list_to_pid("<0.903.0>").

new() ->
    L = pid(link),
    {C, _} = cell_handshake_link_core:new(#{id => l, from => u, to => d}, L),
    C.

%% Both partners attached, nothing held.
attached() ->
    U = pid(up), D = pid(down),
    {reply, {ok, _}, C1, _} = call({attach, up, u, U, none}, new()),
    {reply, {ok, _}, C2, _} = call({attach, down, d, D, none}, C1),
    C2.

%% The effects of a call, without the phase published for the panel (checked on its
%% own in phases_are_published_for_the_panel_test).
call(Req, C) -> call_as(Req, from, C).

call_as(Req, From, C) ->
    case cell_handshake_link_core:call(Req, From, C) of
        {reply, R, C1, Effects} -> {reply, R, C1, unpublished(Effects)};
        {noreply, C1, Effects} -> {noreply, C1, unpublished(Effects)}
    end.

partner_down(Role, Why, C) ->
    {C1, Effects} = cell_handshake_link_core:partner_down(Role, Why, C),
    {C1, unpublished(Effects)}.

unpublished(Effects) ->
    [E || E <- Effects, element(1, E) =/= phase].

%% A partner's step: its answer, the status it leaves, the core, the effects.
step(Req, C) ->
    {reply, {Reply, Status}, C1, Effects} = call(Req, C),
    {Reply, Status, C1, Effects}.

offered() ->
    P = ?P,
    U = pid(up),
    {ok, _, C, _} = step({offer, U, P, 3}, attached()),
    C.

committed() ->
    P = ?P,
    D = pid(down),
    {{ok, P, 3}, _, C, _} = step({commit, D}, offered()),
    C.

released() ->
    U = pid(up),
    {ok, _, C, _} = step({release, U}, committed()),
    C.

phase(C) -> maps:get(phase, element(2, call(status, C))).

%% -------------------------------------------------------------------------------------

phases_are_published_for_the_panel_test() ->
    U = pid(up), D = pid(down),
    Phases = fun(Req, C) ->
                     {reply, _, C1, Effects} = cell_handshake_link_core:call(Req, from, C),
                     {[E || {phase, _, _, _} = E <- Effects], C1}
             end,
    {E1, C1} = Phases({offer, U, ?P, 3}, attached()),
    ?assertEqual([{phase, l, offered, <<"S1">>}], E1),
    {E2, C2} = Phases({commit, D}, C1),
    ?assertEqual([{phase, l, committed, <<"S1">>}], E2),
    {E3, C3} = Phases({release, U}, C2),
    ?assertEqual([{phase, l, released, <<"S1">>}], E3),
    {E4, _} = Phases({complete, D}, C3),
    ?assertEqual([{phase, l, idle, undefined}], E4),
    %% A peek changes nothing, so nothing is published.
    ?assertMatch({[], _}, Phases({peek, D}, C1)).

new_says_hello_to_its_partners_test() ->
    L = pid(link),
    ?assertMatch({_, [{hello, u, l}, {hello, {d, n@h}, l}]},
                 cell_handshake_link_core:new(#{id => l, from => u, to => {d, n@h}}, L)),
    ?assertMatch({_, [{hello, d, l}]},
                 cell_handshake_link_core:new(#{id => l, from => undefined, to => d}, L)).

attach_monitors_and_answers_the_status_test() ->
    L = pid(link), U = pid(up),
    {reply, {ok, S}, C, Effects} = call({attach, up, u, U, none}, new()),
    ?assertEqual([{monitor, up, U}], Effects),
    ?assertMatch(#{phase := idle, available := false, not_busy := false, seq := 0,
                   link := _}, S),
    ?assertEqual(L, maps:get(link, S)),
    %% Attaching again is harmless.
    ?assertMatch({reply, {ok, _}, _, []}, call({attach, up, u, U, none}, C)).

attach_tells_the_other_side_what_it_holds_test() ->
    U = pid(up), D = pid(down),
    C = attached(),
    ?assertMatch({reply, {ok, _}, _, [{send, U, {cell_handshake, l, {holder, <<"S">>, 2}}}]},
                 call({attach, down, d, D, {<<"S">>, 2}}, C)).

another_task_cannot_take_an_end_test() ->
    U2 = pid(up_restarted),
    C = attached(),
    ?assertMatch({reply, {error, {attached, u}}, _, []}, call({attach, up, x, U2, none}, C)).

a_restarted_task_replaces_its_predecessor_test() ->
    P = ?P,
    U = pid(up), D = pid(down), U2 = pid(up_restarted),
    C = committed(),
    {reply, {ok, S}, C1, Effects} = call({attach, up, u, U2, none}, C),
    %% The old incarnation is no longer watched, downstream hears the transfer ended,
    %% the new one is watched.
    ?assertMatch([{demonitor, up},
                  {send, D, {cell_handshake, l, {interrupted, partner_restarted, committed}}},
                  {send, U, {cell_handshake, l, signals, #{phase := idle}}},
                  {send, D, {cell_handshake, l, signals, #{phase := idle}}},
                  {monitor, up, U2}], Effects),
    ?assertMatch(#{phase := idle}, S),
    ?assertMatch({ok, _, _, _}, step({offer, U2, P, 4}, C1)).

%% -------------------------------------------------------------------------------------
%% Phases 1-4

a_transfer_through_phases_1_to_4_test() ->
    P = ?P,
    U = pid(up), D = pid(down),
    C0 = attached(),
    {ok, S1, C1, E1} = step({offer, U, P, 3}, C0),
    ?assertMatch(#{phase := offered, available := true, not_busy := false, seq := 1,
                   product := P, gen := 3}, S1),
    %% Only downstream is told by message; upstream learns it from its answer.
    ?assertMatch([{send, D, {cell_handshake, l, signals, #{seq := 1}}}], E1),
    {{ok, P, 3}, S2, C2, E2} = step({commit, D}, C1),
    ?assertMatch(#{phase := committed, available := true, not_busy := true, seq := 2}, S2),
    ?assertMatch([{send, U, {cell_handshake, l, signals, #{seq := 2}}}], E2),
    {ok, S3, C3, E3} = step({release, U}, C2),
    ?assertMatch(#{phase := released, available := false, not_busy := true}, S3),
    %% The fence on disk first: the link let generation 3 of S1 go.
    ?assertMatch([{persist, #{<<"S1">> := #{gen := 3, state := released}}},
                  {send, D, {cell_handshake, l, {released, P, 3}, #{seq := 3}}}], E3),
    {ok, S4, C4, E4} = step({complete, D}, C3),
    ?assertMatch(#{phase := idle, product := undefined, gen := 0, seq := 4}, S4),
    ?assertMatch([{send, U, {cell_handshake, l, completed, #{phase := idle}}}], E4),
    ?assertEqual(idle, phase(C4)).

steps_out_of_turn_are_refused_test() ->
    P = ?P,
    U = pid(up), D = pid(down), U2 = pid(up_restarted),
    C = attached(),
    ?assertMatch({{error, not_available}, #{phase := idle}, _, []}, step({commit, D}, C)),
    ?assertMatch({{error, {not_now, release, idle}}, _, _, []}, step({release, U}, C)),
    ?assertMatch({{error, {not_released, committed}}, _, _, []},
                 step({complete, D}, committed())),
    ?assertMatch({{error, {busy, offered}}, #{gen := 3}, _, []},
                 step({offer, U, P, 4}, offered())),
    %% Downstream cannot offer, a stranger cannot do anything.
    ?assertMatch({{error, not_attached}, #{phase := idle}, _, []}, step({offer, D, P, 1}, C)),
    ?assertMatch({reply, {{error, not_attached}, #{phase := idle}}, _, []},
                 call({commit, U2}, C)).

%% -------------------------------------------------------------------------------------
%% TryAbortOffering and PeekBoardAvailable

try_abort_offering_withdraws_until_downstream_commits_test() ->
    U = pid(up), D = pid(down),
    {true, S, C, E} = step({try_abort_offering, U}, offered()),
    ?assertMatch(#{phase := idle, product := undefined, available := false}, S),
    ?assertMatch([{send, D, {cell_handshake, l, signals, #{phase := idle}}}], E),
    %% Nothing offered: nothing to withdraw, and nothing changes.
    ?assertMatch({true, #{seq := 2}, _, []}, step({try_abort_offering, U}, C)),
    %% Downstream has begun to take it: too late.
    ?assertMatch({false, #{phase := committed}, _, []},
                 step({try_abort_offering, U}, committed())),
    ?assertMatch({false, #{phase := released}, _, []},
                 step({try_abort_offering, U}, released())).

peek_looks_without_locking_test() ->
    P = ?P,
    U = pid(up), D = pid(down),
    C = offered(),
    {{ok, P}, S, C1, []} = step({peek, D}, C),
    %% Nothing changed: upstream may still withdraw, downstream still commit.
    ?assertMatch(#{phase := offered, seq := 1}, S),
    ?assertMatch({true, _, _, _}, step({try_abort_offering, U}, C1)),
    ?assertMatch({{ok, P, 3}, _, _, _}, step({commit, D}, C1)),
    ?assertMatch({none, _, _, []}, step({peek, D}, attached())),
    ?assertMatch({none, _, _, []}, step({peek, D}, committed())).

%% -------------------------------------------------------------------------------------
%% Abort

abort_before_release_leaves_the_product_upstream_test() ->
    U = pid(up), D = pid(down),
    {kept_by_upstream, S, _, E} = step({abort, D}, committed()),
    ?assertMatch(#{phase := idle, abort := true, product := undefined}, S),
    ?assertMatch([{send, U, {cell_handshake, l, aborted, #{abort := true}}}], E).

abort_after_release_waits_for_upstream_to_take_it_back_test() ->
    P = ?P,
    U = pid(up), D = pid(down),
    {noreply, C, E} = call_as({abort, D}, waiter, released()),
    ?assertMatch([{send, U, {cell_handshake, l, {take_back, P, 3}}},
                  {send, U, {cell_handshake, l, signals, #{phase := aborting}}},
                  {send, D, {cell_handshake, l, signals, #{phase := aborting}}}], E),
    ?assertEqual(aborting, phase(C)),
    {ok, S, C1, E1} = step({taken_back, U}, C),
    ?assertMatch(#{phase := idle}, S),
    %% Upstream owns it again: nothing fenced.
    ?assertMatch([{persist, Empty},
                  {send, D, {cell_handshake, l, signals, #{phase := idle}}},
                  {reply, waiter, {given_back, #{phase := idle}}}] when map_size(Empty) =:= 0, E1),
    ?assertEqual(idle, phase(C1)).

abort_after_release_without_upstream_keeps_it_downstream_test() ->
    D = pid(down),
    {C, _} = partner_down(up, killed, released()),
    ?assertMatch({kept, #{phase := idle}, _, []}, step({abort, D}, C)).

upstream_stopping_while_taking_back_leaves_it_downstream_test() ->
    U = pid(up), D = pid(down),
    {noreply, C, _} = call_as({abort, D}, waiter, released()),
    {C1, E} = partner_down(up, noconnection, C),
    ?assertMatch([{demonitor, up},
                  {send, D, {cell_handshake, l, {interrupted, node_down}}},
                  {send, U, {cell_handshake, l, signals, #{phase := idle}}},
                  {send, D, {cell_handshake, l, signals, #{phase := idle}}},
                  {reply, waiter, {kept, #{phase := idle}}}], E),
    ?assertEqual(idle, phase(C1)).

%% -------------------------------------------------------------------------------------
%% Partners stopping, interrupts, detaching

a_stopped_upstream_withdraws_its_offer_test() ->
    U = pid(up), D = pid(down),
    {C, E} = partner_down(up, killed, offered()),
    ?assertMatch([{demonitor, up}, {send, U, _},
                  {send, D, {cell_handshake, l, signals, #{phase := idle}}}], E),
    ?assertEqual(idle, phase(C)),
    %% It is no longer attached.
    ?assertMatch({reply, {{error, not_attached}, _}, _, []}, call({release, U}, C)).

a_stopped_downstream_leaves_an_offer_open_test() ->
    {C, E} = partner_down(down, killed, offered()),
    ?assertEqual([{demonitor, down}], E),
    ?assertEqual(offered, phase(C)).

a_partner_stopping_mid_transfer_ends_it_for_the_other_test() ->
    U = pid(up), D = pid(down),
    [begin
         {C, E} = partner_down(Role, shutdown, Core),
         ?assertMatch([{demonitor, Role},
                       {send, Other, {cell_handshake, l, {interrupted, partner_stopped, Phase}}}
                       | _], E),
         ?assertEqual(idle, phase(C))
     end || {Role, Other} <- [{up, D}, {down, U}],
            {Phase, Core} <- [{committed, committed()}, {released, released()}]],
    %% Idle: nothing to end.
    ?assertMatch({_, [{demonitor, down}]},
                 partner_down(down, killed, attached())).

interrupt_ends_the_transfer_test() ->
    U = pid(up), D = pid(down),
    ?assertMatch({ok, #{phase := idle}, _,
                  [{send, U, {cell_handshake, l, {interrupted, stopped, committed}}},
                   {send, U, {cell_handshake, l, signals, _}},
                   {send, D, {cell_handshake, l, signals, _}}]},
                 step({interrupt, D}, committed())),
    ?assertMatch({ok, #{phase := idle, seq := 0}, _, []}, step({interrupt, U}, attached())).

detach_only_when_free_test() ->
    U = pid(up), D = pid(down), U2 = pid(up_restarted),
    ?assertMatch({reply, {error, {busy, offered}}, _, []}, call({detach, up, U}, offered())),
    {reply, ok, C, E} = call({detach, down, D}, offered()),
    ?assertEqual([{demonitor, down}], E),
    ?assertEqual(offered, phase(C)),
    ?assertMatch({reply, {error, {busy, committed}}, _, []},
                 call({detach, down, D}, committed())),
    ?assertMatch({reply, {error, not_attached}, _, []}, call({detach, down, U2}, attached())),
    ?assertMatch({reply, ok, _, [{demonitor, up}]}, call({detach, up, U}, attached())).

%% -------------------------------------------------------------------------------------
%% The copy handed on

owned_tells_upstream_and_marks_its_copy_stale_test() ->
    U = pid(up), D = pid(down), U2 = pid(up_restarted),
    {C, E} = cell_handshake_link_core:cast({owned, D}, released()),
    ?assertEqual([{persist, #{<<"S1">> => #{gen => 3, state => owned, up => <<"u">>}}},
                  {send, U, {cell_handshake, l, owned}}], E),
    %% Only downstream may say so, and only while the product is released.
    ?assertMatch({_, []}, cell_handshake_link_core:cast({owned, U}, released())),
    ?assertMatch({_, []}, cell_handshake_link_core:cast({owned, D}, committed())),
    {ok, _, C1, _} = step({complete, D}, C),
    %% Upstream restarted, still holding that copy: told it is stale.
    {reply, {ok, S}, _, _} = call({attach, up, u, U2, {<<"S1">>, 3}}, C1),
    ?assertMatch(#{stale := true}, S),
    %% Another copy is not.
    {reply, {ok, S2}, _, _} = call({attach, up, u, U2, {<<"S1">>, 4}}, C1),
    ?assertNot(maps:is_key(stale, S2)).

unknown_requests_crash_test() ->
    ?assertError(function_clause, call({what, 1, 2}, attached())),
    ?assertError(function_clause, cell_handshake_link_core:cast(hello, attached())).

%% -------------------------------------------------------------------------------------
%% The fence: what the link released, per serial, on disk

%% A network cut after release: the link loses upstream (noconnection) before
%% downstream's `owned' reaches it. Downstream's word still settles the fence, and
%% the copy upstream kept is refused when it is offered again after the heal.
owned_after_upstream_lost_still_fences_the_copy_test() ->
    U2 = pid(up_restarted), D = pid(down),
    {C1, _} = partner_down(up, noconnection, released()),
    ?assertEqual(idle, phase(C1)),
    {C2, E2} = cell_handshake_link_core:cast({owned, D, <<"S1">>, 4}, C1),
    %% No upstream to tell: only the fence changes.
    ?assertEqual([{persist, #{<<"S1">> => #{gen => 3, state => owned, up => <<"u">>}}}], E2),
    %% Upstream back (the same task, after the heal), holding its copy: stale.
    {reply, {ok, S}, C3, _} = call({attach, up, u, U2, {<<"S1">>, 3}}, C2),
    ?assertMatch(#{stale := true}, S),
    %% An operator who said "it is here" makes it offer it again: refused.
    ?assertMatch({{error, {stale, <<"S1">>}}, #{phase := idle}, _, []},
                 step({offer, U2, ?P, 3}, C3)),
    %% A newer record of the same serial (taken back, say) is not fenced.
    ?assertMatch({ok, #{phase := offered}, _, _}, step({offer, U2, ?P, 5}, C3)).

%% Downstream stopped before it said: the copy's owner is not known, so it is neither
%% offered nor dropped until downstream says what it holds.
unsettled_until_downstream_says_what_it_holds_test() ->
    U = pid(up), U2 = pid(up_restarted), D2 = list_to_pid("<0.904.0>"),
    {C1, _} = partner_down(down, killed, released()),
    {reply, {ok, S}, C2, _} = call({attach, up, u, U2, {<<"S1">>, 3}}, C1),
    ?assertMatch(#{unsettled := true}, S),
    ?assertMatch({{error, {unsettled, <<"S1">>}}, _, _, []}, step({offer, U2, ?P, 3}, C2)),
    %% Downstream back, holding it in the next generation: upstream is told.
    {reply, {ok, _}, C3, E3} = call({attach, down, d, D2, {<<"S1">>, 4}}, C2),
    ?assertMatch([{send, U2, {cell_handshake, l, {holder, <<"S1">>, 4}}},
                  {monitor, down, D2},
                  {persist, #{<<"S1">> := #{state := owned}}},
                  {send, U2, {cell_handshake, l, {settled, <<"S1">>, owned}}}], E3),
    ?assertMatch({{error, {stale, _}}, _, _, []}, step({offer, U2, ?P, 3}, C3)),
    %% Downstream back holding nothing: it never wrote it, upstream's copy is the
    %% owner and may be offered again.
    {reply, {ok, _}, C4, E4} = call({attach, down, d, D2, none}, C2),
    ?assertMatch([{monitor, down, D2},
                  {persist, Empty},
                  {send, U2, {cell_handshake, l, {settled, <<"S1">>, yours}}}]
                   when map_size(Empty) =:= 0, E4),
    ?assertMatch({ok, _, _, _}, step({offer, U2, ?P, 3}, C4)),
    %% While the transfer is live, downstream re-attaching settles nothing.
    {reply, {ok, _}, _, E5} = call({attach, down, d, pid(down), none}, released()),
    ?assertEqual([], [E || {persist, _} = E <- E5]),
    _ = U,
    ok.

%% Upstream offering another serial holds that one now: the fence of the last goes.
the_fence_is_kept_per_upstream_until_it_offers_another_serial_test() ->
    U = pid(up), D = pid(down),
    {C, _} = cell_handshake_link_core:cast({owned, D}, released()),
    {ok, _, C1, _} = step({complete, D}, C),
    ?assertMatch({reply, {ok, #{stale := true}}, _, _},
                 call({attach, up, u, U, {<<"S1">>, 3}}, C1)),
    {ok, _, C2, E2} = step({offer, U, #{serial => <<"S2">>}, 1}, C1),
    ?assertMatch([{persist, Empty} | _] when map_size(Empty) =:= 0, E2),
    ?assertMatch({reply, {ok, S}, _, _} when not is_map_key(stale, S),
                 call({attach, up, u, U, {<<"S1">>, 3}}, C2)).

%% A link restarted on its folder starts from the fence its predecessor wrote.
a_restarted_link_keeps_the_fence_test() ->
    U = pid(up),
    Fence = #{<<"S1">> => #{gen => 3, state => owned, up => <<"u">>}},
    {C, _} = cell_handshake_link_core:new(#{id => l, from => u, to => d, fence => Fence},
                                          pid(link)),
    ?assertMatch({reply, {ok, #{stale := true}}, _, _},
                 call({attach, up, u, U, {<<"S1">>, 3}}, C)).

%% Downstream forgot the product on the operator's word (held by two tasks, "not
%% here"): the panel is still upstream, its serial read again in a new record of
%% generation 1. The fence lets that copy be offered, and upstream is told it is its
%% own. Only downstream may say so; a serial the fence does not hold changes nothing.
disowned_by_downstream_the_copy_is_offered_again_test() ->
    U = pid(up), D = pid(down),
    {C, _} = cell_handshake_link_core:cast({owned, D}, released()),
    {ok, _, C1, _} = step({complete, D}, C),
    ?assertMatch({{error, {stale, <<"S1">>}}, _, _, []}, step({offer, U, ?P, 1}, C1)),
    ?assertMatch({{error, not_attached}, _, _, []}, step({disown, U, <<"S1">>}, C1)),
    {ok, _, C2, E2} = step({disown, D, <<"S1">>}, C1),
    ?assertMatch([{persist, Empty}, {send, U, {cell_handshake, l, {settled, <<"S1">>, yours}}}]
                   when map_size(Empty) =:= 0, E2),
    ?assertMatch({ok, #{phase := offered}, _, _}, step({offer, U, ?P, 1}, C2)),
    ?assertMatch({ok, _, _, []}, step({disown, D, <<"S9">>}, C1)),
    %% While the product is on its way, downstream's word does not lift the fence of
    %% the transfer under way.
    {C3, _} = cell_handshake_link_core:cast({owned, D}, released()),
    ?assertMatch({ok, #{phase := released}, _, []}, step({disown, D, <<"S1">>}, C3)).
