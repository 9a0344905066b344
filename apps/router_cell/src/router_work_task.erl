%% @doc The work segment (seed 000 §2.3): brings a panel from the loading segment into
%% the routing fixture, has it clamped, and hands it to the lower routing robot. Once
%% the upper robot has lifted the routed modules out of the nest, it has the clamps
%% opened and runs the panel's frame out into the waste bin, and the fixture is free
%% again.
%%
%% The clamps are a unit of their own ({@link router_clamps_unit}, the task's arg
%% `clamps'): the task gives it the standing order `clamp' (`cell_unit:order/3',
%% true to close, false to open) and waits for both clamps' end sensors. A clamp that
%% sticks is the unit's fault, the error the operator answers there (RESET, once it is
%% free); the task waits meanwhile, giving its order again each `motion_timeout_ms'
%% (a unit that restarted has lost it), and goes on once the sensors show the clamps
%% where it ordered them. It gives the order as it goes on even when the sensors showed
%% the clamps there at once: the unit keeps its last order across a Stop and a Start,
%% and an order left from before (to close, given at a restart) would move the clamps
%% away again under the task, closing them on the frame as the belt runs it out.
%%
%% <pre>
%%  phase      waits for                                    then
%%  idle       the fixture free (no panel in position)     → take; a panel in position: see
%%                                                          below
%%  take       the loading segment's offer (STARVED)        commit (phase 2), belt on → moving_in
%%  moving_in  the panel off the loading segment            → arriving
%%             (Available off, phase 3)
%%  arriving   the panel in position, or the watchdog       belt off; complete (phase 4,
%%                                                          ItemTransferIn) → clamping
%%  clamping   both clamps closed (ordered; again at each   offer it to the routing robot
%%             watchdog)                                    (phase 1, BLOCKED) → offered
%%  offered    the robot's NotBusy                          release at once: the panel stays
%%                                                          clamped, the robot takes charge → released
%%  released   the robot's NotBusy off                      ItemTransferOut → emptying
%%  emptying   the module nest empty (the upper robot       → unclamping
%%             lifted the modules)
%%  unclamping both clamps open (ordered; again at each     belt on → ejecting
%%             watchdog)
%%  ejecting   the frame out of position, or the watchdog   belt off → idle
%%  in_transit the operator, after a transfer was cut off   Ignore: here → clamping; Reset → idle
%% </pre>
%%
%% Restarted (reconcile), the fixture's sensor decides: with a product, arriving (the
%% panel seen in position is completed and clamped; not yet there, the belt brings it);
%% without one, a panel in position is decided as below; none is idle.
%%
%% A panel in position while the task holds no product (restarted, or idle): its frame
%% (the nest empty) or a robot's panel is emptied (emptying). Restarted, the task has a
%% robot's panel clamped (ordered again); never a frame, whose modules are out: its
%% clamps open for it to leave. Whose a whole panel is
%% ({@link router_task:fixture/1}) follows only the records whose product can lie there,
%% each checked against the sensor that would see it elsewhere: the routing robot's
%% product of this lane; the upper robot's unless its gripper sensor sees modules and
%% it is away from this nest (its move elsewhere done);
%% the loading segment's once its stopper sensor sees no panel. A product the loading
%% segment offers on the link to this fixture is then the panel lying here, arrived
%% before a restart cut its hand-over off: the task takes it in through the hand-over
%% as it lies (take; the loading segment, its stopper empty, lets go of it at once).
%% Held by the loading segment but not offered, its record is still being settled (a
%% restart, its question to the operator): the task waits a transfer time for the
%% offer (idle), then asks the operator to answer the loading segment's question
%% first, then RETRY here (`fixture_unsettled').
%%
%% A whole panel in the fixture that no record holds would keep the fixture for ever:
%% nobody routes it, and the segment waits for its nest to empty. The task asks the
%% operator to take it out of the machine instead (the clamps open), and looks again at
%% RETRY (`unheld'). It asks only what a look taken once the machine has settled finds:
%% records and sensors are read one after the other while the robots move on (the
%% routed panel between the two robots' records, the upper robot's next position
%% written before its command to go), so a first look that finds no record waits a
%% transfer time, or for the nest to empty, and looks again (idle). A panel the
%% operator's Reset made the cell forget while it lay in the fixture ends so, whatever
%% the robots carry elsewhere meanwhile.
-module(router_work_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T0) ->
    {ok, cell_task:out(cell_handover:after_reset(T0), belt_run, false)}.

%% The fixture's sensor decides: a panel in position with no record is the routing
%% robot's (or its frame), to be emptied; with one, it is clamped and offered again.
-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(_Held, T2) ->
    case {cell_task:product(T2), cell_task:in(T2, panel_in_position)} of
        {undefined, true} ->
            %% Looked at again after the operator's answer: the machine stood meanwhile.
            case in_fixture(T2, cell_task:answer(T2) =/= undefined) of
                frame ->
                    %% Its modules are out: the clamps open for it to leave (unclamping
                    %% orders them so), never closed on it again.
                    {ok, phase(T2, emptying)};
                {robot, _} ->
                    %% A panel a robot has: the clamps hold it until the modules are out.
                    {ok, phase(order(T2, true), emptying)};
                {arrived, S} ->
                    {ok, arrived(T2, S)};
                {loading, _S} ->
                    %% The idle step gives the loading segment a moment to offer it.
                    {ok, phase(T2, idle)};
                look_again ->
                    %% The idle step looks again once the machine has settled.
                    {ok, phase(T2, idle)};
                unheld ->
                    unheld_error(T2)
            end;
        {undefined, false} ->
            {ok, phase(T2, idle)};
        {_, _} ->
            {ok, phase(T2, arriving)}
    end.

%% The belt stops; the clamps stay as they are (opening them under a panel the robot
%% routes would spoil it).
-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    cell_task:out(T, belt_run, false).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

%% -- empty: take a panel from the loading segment ------------------------------------
step(idle, Woken, T) ->
    case cell_task:in(T, panel_in_position) andalso in_fixture(T, settled(Woken)) of
        false -> {continue, phase(T, take)};
        {arrived, S} -> {continue, arrived(T, S)};
        Robot when Robot =:= frame; element(1, Robot) =:= robot ->
            {continue, phase(T, emptying)};
        {loading, S} -> loading_holds(Woken, S, T);
        look_again -> look_again(T);
        unheld -> unheld_error(T)
    end;
step(take, _Woken, T) ->
    %% Phase 2: both belts run.
    cell_handover:take(T, prev(T), moving_in, fun(T1) -> cell_task:out(T1, belt_run, true) end);
step(moving_in, {handshake, _Prev, interrupted}, T) ->
    cell_handover:interrupted(cell_task:out(T, belt_run, false), arriving, idle);
step(moving_in, {handshake, _Prev, available, false}, T) ->
    watch(T, arriving, panel_in_position, true, transfer_timeout_ms);
step(moving_in, _Woken, T) ->
    {wait, {handshake, prev(T), available, false}, T};
step(arriving, {timer, _}, T) ->
    fault(T, "did not arrive in the fixture", "Free the panel between the loading "
          "conveyor and the fixture");
step(arriving, _Woken, T) ->
    case cell_task:in(T, panel_in_position) of
        true ->
            T1 = cell_task:out(T, belt_run, false),
            T2 = case cell_handshake:phase(T1, prev(T1)) of
                     released -> cell_handshake:complete(T1, prev(T1));
                     _ -> T1                   %% after a restart: it is here already
                 end,
            {continue, phase(T2, clamping)};
        false ->
            watch(cell_task:out(T, belt_run, true), arriving, panel_in_position, true,
                  transfer_timeout_ms)
    end;
step(clamping, Woken, T) ->
    case clamps_at(T, closed) of
        true ->
            %% Ordered even when the sensors show them closed already: the unit keeps
            %% its last order across a Stop, and one to open would open them under the
            %% panel being routed.
            T1 = cell_handshake:offer(order(T, true), next(T)),
            {wait, {handshake, next(T), not_busy, true}, phase(T1, offered)};
        false ->
            await_clamps(T, Woken, closed, clamping)
    end;
%% -- full: the routing robot takes charge of the clamped panel -------------------------
step(offered, {handshake, Next, not_busy, true}, T) ->
    %% Nothing moves: the panel is the robot's to route where it lies.
    T1 = cell_handshake:release(T, Next),
    {wait, {handshake, Next, not_busy, false}, phase(T1, released)};
step(offered, _Woken, T) ->
    cell_handover:offered(T, next(T), clamping);
step(released, {handshake, _Next, interrupted}, T) ->
    cell_handover:interrupted(T, clamping, emptying);
step(released, _Woken, T) ->
    cell_handover:finish(T, next(T), emptying, clamping);
%% -- the modules are out: the frame goes --------------------------------------------------
step(emptying, _Woken, T) ->
    case cell_task:in(T, nest_empty) of
        true -> {continue, phase(T, unclamping)};
        false -> {wait, {io, nest_empty, {eq, true}}, phase(T, emptying)}
    end;
step(unclamping, Woken, T) ->
    case clamps_at(T, open) of
        true ->
            %% Ordered even when the sensors show them open already: the unit keeps its
            %% last order across a Stop, and one to close would close them on the frame
            %% as the belt runs, which the fixture's end stop then holds for good.
            watch(cell_task:out(order(T, false), belt_run, true), ejecting,
                  panel_in_position, false, transfer_timeout_ms);
        false -> await_clamps(T, Woken, open, unclamping)
    end;
step(ejecting, {timer, _}, T) ->
    fault(T, "did not leave the fixture", "Take the panel frame out of the fixture");
step(ejecting, _Woken, T) ->
    case cell_task:in(T, panel_in_position) of
        false -> {continue, phase(cell_task:out(T, belt_run, false), idle)};
        true -> watch(cell_task:out(T, belt_run, true), ejecting, panel_in_position, false,
                      transfer_timeout_ms)
    end;
%% -- the operator said the panel of an interrupted transfer is here --------------------
step(in_transit, _Woken, T) ->
    {continue, phase(cell_handshake:confirm_here(T), arriving)}.

%% -- a panel in the fixture that no record holds ------------------------------------------

%% A panel in position while the task holds no product: a frame (the nest empty), or
%% whose the whole panel is by the records that can explain it there and the sensors
%% that rule them out (router_task:fixture/1).
in_fixture(T, Again) ->
    %% The robots' sensors read before the nest's: modules that left the nest with the
    %% robot show in it by then.
    Facts = fixture_facts(T, Again),
    case cell_task:in(T, nest_empty) of
        true -> frame;
        false -> router_task:fixture(Facts)
    end.

fixture_facts(T, Again) ->
    Lane = router_task:lane(T),
    Offered = case cell_handshake:peek(T, prev(T)) of
                  {ok, #{serial := S}} -> S;
                  none -> none
              end,
    #{lane => Lane, others => cell_task:others_products(T),
      loading => router_cell:task(loading, Lane),
      stopper => cell_task:in(T, router_cell:group(loading, Lane), panel_at_stop),
      offered => Offered,
      gripper => cell_task:in(T, upper_io, product_present),
      upper_away => not cell_task:in(T, upper_io, router_upper_io:at(nest, Lane)),
      again => Again}.

%% A first look found the panel in no record: a snapshot of a machine that moves on
%% (router_task:fixture/1). The machine has a transfer time to settle, the modules
%% leaving the nest ending it early; then the idle step looks again (`settled/1').
look_again(T) ->
    cell_task:log(T, brief, "a panel lies in the fixture and no record holds it at a first "
                  "look; looked at again once the robots have settled", []),
    {wait, [{io, nest_empty, {eq, true}}, router_task:watchdog(T, transfer_timeout_ms, 10000)],
     phase(T, idle)}.

%% Whether what woke the idle step comes after the machine had time to settle: a
%% transfer time waited (look_again/1, loading_holds/3), or the operator's answer.
settled({timer, _}) -> true;
settled({answer, _}) -> true;
settled(_) -> false.

%% The panel the loading segment offers lies here already (a restart cut its
%% hand-over off after it arrived): taken in through the hand-over as it lies; the
%% loading segment, its stopper empty, lets go of it at once.
arrived(T, S) ->
    cell_task:log(T, brief, "panel ~ts, offered by the loading conveyor, lies in the fixture "
                  "already: taken in as it lies", [S]),
    phase(T, take).

%% The loading segment holds it past its stopper without offering it: its record is
%% being settled (a restart, its question to the operator). It has a transfer time to
%% offer it; then the operator is asked, and RETRY waits for the offer again.
loading_holds({timer, _}, S, T) ->
    not_offered(S, T);
loading_holds({handshake, _Prev, available, true}, S, T) ->
    %% Offered, but not that product.
    not_offered(S, T);
loading_holds(_Woken, _S, T) ->
    {wait, [{handshake, prev(T), available, true},
            router_task:watchdog(T, transfer_timeout_ms, 10000)], T}.

not_offered(S, T) ->
    {error, cell_task:error_spec(
              <<"fixture_unsettled">>, "Panel in the fixture not offered",
              io_lib:format("A panel lies in the work fixture of lane ~ts. Records say panel "
                            "~ts is on the loading conveyor, whose stopper sensor sees no "
                            "panel, and it is not offered to this segment.~nAnswer the "
                            "loading conveyor's question first: IGNORE there if this panel "
                            "is ~ts (it is handed over as it lies); if it is not, take it "
                            "out of the machine. Then select RETRY.",
                            [router_task:lane(T), S, S]),
              [retry]),
     phase(cell_task:out(T, belt_run, false), idle)}.

%% The operator takes it out; the clamps open for the hand, the belt stays off. RETRY
%% looks again (reconcile, or the idle step).
unheld_error(T) ->
    cell_handover:unheld_error(
      phase(order(cell_task:out(T, belt_run, false), false), idle),
      "Panel in the fixture unknown", "A panel lies in the work fixture of lane ~ts",
      [router_task:lane(T)]).

%% A watchdog ran out: the belt stops, the operator looks, Retry goes on where it was.
fault(T, What, Check) ->
    %% Once the robot has the panel, what is left in the fixture is its frame.
    Which = case cell_task:product(T) of
                undefined -> <<"The panel frame">>;
                #{serial := S} -> [<<"Panel ">>, S]
            end,
    {error, cell_task:error_spec(
              <<"fixture">>, "Work segment fault",
              io_lib:format("~ts ~ts in time: the belt is stopped.~n~ts, then select RETRY.",
                            [Which, What, Check]),
              [retry]),
     cell_task:out(T, belt_run, false)}.

%% -- the clamps' unit ---------------------------------------------------------------------

%% The clamps' unit is ordered to close (true) or open (false) them. A unit without a
%% process (it restarts) is ordered again at the next watchdog.
order(T, Close) ->
    Unit = clamps(T),
    case cell_unit:order(Unit, clamp, Close) of
        ok ->
            T;
        {error, not_running} ->
            ok = cell_task:log(T, brief, "the clamps' unit ~ts is not running: ordered again "
                               "later", [Unit]),
            T
    end.

%% Whether both clamps' sensors show them at that end.
clamps_at(T, End) ->
    Group = router_cell:group(clamps, router_task:lane(T)),
    lists:all(fun(P) -> cell_task:in(T, Group, P) end, sensors(End)).

sensors(End) ->
    [maps:get(Key, C) || C <- router_clamps_io:clamps(),
                         Key <- [case End of closed -> is_closed; open -> is_open end]].

%% The clamps ordered to an end, and their sensors awaited; the watchdog gives the
%% order again (the unit's own timeout raises a stuck clamp to the operator).
await_clamps(T, Woken, End, Phase) ->
    case Woken of
        {timer, _} ->
            ok = cell_task:log(T, brief, "the clamps are not ~ts yet: waiting for their unit "
                               "~ts (see its state and error), ordered again", [End, clamps(T)]);
        _ ->
            ok
    end,
    Group = router_cell:group(clamps, router_task:lane(T)),
    {wait, [{io, Group, P, {eq, true}} || P <- sensors(End)]
         ++ [router_task:watchdog(T, motion_timeout_ms, 30000)],
     phase(order(T, End =:= closed), Phase)}.

clamps(T) -> cell_task:arg(T, clamps, undefined).

watch(T, Phase, Point, Value, Watchdog) ->
    router_task:watch(T, Phase, Point, Value, Watchdog).

prev(T) -> cell_task:arg(T, prev, undefined).
next(T) -> cell_task:arg(T, next, undefined).

phase(T, Phase) -> cell_handover:phase(T, Phase).
