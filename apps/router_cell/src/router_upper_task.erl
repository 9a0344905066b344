%% @doc The upper manipulator robot (seed 000 §2.3): lifts the routed modules out of
%% the nest of the fixture they were routed in, carries them to the unloading segment
%% of their lane and puts them down there. If they are not in the gripper when it
%% arrives, it is the seed's "Product lost" error (§2.3.8), word for word.
%%
%% <pre>
%%  phase     waits for                                       then
%%  idle      the routing robot's offer (STARVED)             commit (phase 2) → taking
%%  taking    the routing robot's Available off (phase 3)     move to the lane's nest → to_nest
%%  to_nest   there, or the watchdog                          close the gripper → gripping
%%  gripping  the gripper closed, or the watchdog             modules in the gripper: complete
%%                                                            (phase 4, ItemTransferIn); move to the
%%                                                            lane's unloading segment → carrying;
%%                                                            none: "Modules not gripped", RETRY
%%                                                            → to_nest, unless another record now
%%                                                            puts a panel there: asked where
%%  carrying  there, or the watchdog                          modules still in the gripper → full;
%%                                                            not: "Product lost" → lost (noted
%%                                                            whether the nest still holds them)
%%  lost      the operator                                    RETRY: the sensor again; IGNORE: go on,
%%                                                            the product marked failed; RESET:
%%                                                            (init) → to_scrap
%%  full      -                                               offer to the unloading segment
%%                                                            (phase 1, BLOCKED) → offered
%%  offered   the unloading segment's NotBusy                 open the gripper → placing
%%  placing   the gripper open, or the watchdog               release (phase 3) → released
%%  released  the unloading segment's NotBusy off (phase 4)   ItemTransferOut → idle; cut off after
%%                                                            the modules were let go of (gripper
%%                                                            open and empty): → full, offered
%%                                                            again as they lie, no question
%%  to_scrap  after a Reset (the product kept, marked         open the gripper over the scrap bin
%%            `scrap'): at home, or the watchdog              → emptying
%%  emptying  the gripper open, or the watchdog               modules were in the nest when found
%%                                                            missing and it still holds them
%%                                                            → nest_scrap; else the product
%%                                                            forgotten (ItemWorkAbort) → idle
%%  nest_scrap  at the nest, or the watchdog                  close the gripper → nest_gripping
%%  nest_gripping the gripper closed, or the watchdog         modules in it → to_scrap; none: an
%%                                                            error, RETRY (taken out by hand, or
%%                                                            the gripper checked) → emptying
%%  in_transit the operator said the modules of a cut-off     in the gripper → to_unloading; else
%%            transfer are here (IGNORE)                      put down on the unloading conveyor
%%                                                            → full, in the nest → regrip
%%  where     the operator, after a restart found the gripper  RETRY: the gripper sensor sees
%%            empty though the record holds a product          them again → to_unloading; else in
%%                                                            the nest, if no other record puts a
%%                                                            panel there → regrip (another's:
%%                                                            asked again, saying whose);
%%                                                            IGNORE: on the unloading segment
%%                                                            → full (offered, put down as it is);
%%                                                            RESET: taken out → forgotten, idle
%%  regrip    -                                               move to the lane's nest, the gripper
%%                                                            as it is → regrip_at
%%  regrip_at at the nest, or the watchdog                    open the gripper there → reopened
%%  reopened  the gripper open, or the watchdog               close the gripper → gripping
%% </pre>
%%
%% The robot's X and Y are NC axes (seed 000 §2.1: `UpperRobotTask.Axes'), and a move
%% is a line of their interpolation channel (§2.3.7) from where the axes stand to the
%% taught position: home (0, 0, over the scrap bin), or over the module nest or the
%% unloading segment of the product's lane (the router settings `upper_nest_x',
%% `upper_unloading_x', `upper_front_y', and `rear_lane_offset' for the rear lane).
%% Each move phase (to_nest, carrying, to_scrap, nest_scrap, regrip_at) makes the axes
%% ready one command a step (router_axes: a path still followed halted, an axis in
%% error reset, powered, homed), then starts the line and waits for its end as a reply
%% under the motion watchdog; standing at the taught position, it waits for the
%% machine's in-position signal there (which comes with what the gripper's sensor saw
%% on the way) and does what the phase does there. Axes already there are not moved, so
%% a move made again (RETRY, a restart) starts from wherever the robot stopped. An
%% axis's refusal or fault is the error "Upper robot axis fault" naming the axis, with
%% RETRY; the watchdog halts the channel and is "Upper robot fault", with RETRY. A Stop
%% halts the channel.
%%
%% Restarted (reconcile), the robot believes its gripper, not its record: a product
%% held with the modules seen in the gripper goes on (gripper closed again,
%% to_unloading), one whose modules are not there is a question for the operator
%% (where), never a carry of an empty gripper. Told they are back in the nest, it grips
%% them there only if no other record puts a panel in that fixture (the work segment's
%% next panel, say): modules it cannot tell are its product's are never taken as them.
%% It opens the gripper only over the nest: modules its sensor lost that are still in it
%% would otherwise be put down wherever it stands. Holding no product, it opens the gripper,
%% unless the gripper sensor sees modules that no record holds (`unheld'): the operator
%% takes them out of the gripper, then RETRY.
%%
%% RESET to "Product lost" deletes the product's data and goes on with an empty
%% gripper, as the seed says, and leaves nothing in the machine that no record knows
%% of: the gripper is emptied over the scrap bin, and if the module nest still held the
%% modules when they were found missing (they never left it) and still does, the robot
%% takes them from there to the scrap bin too, so the work segment, which keeps the
%% panel clamped until its nest is empty, goes on. The product is forgotten only then.
%% It reads each lane's module nest sensor for this (the work groups are among its IO
%% groups); the nest is judged when the modules are found missing, not later, when it
%% may hold the next panel.
-module(router_upper_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).
-export([path_params/1]).

%% The phases that move the robot to a taught position.
-define(MOVE(Phase), (Phase =:= to_nest orelse Phase =:= carrying orelse Phase =:= to_scrap
                      orelse Phase =:= nest_scrap orelse Phase =:= regrip_at)).
%% Path acceleration and deceleration between taught positions, mm/s².
-define(ACC, 2000.0).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    case cell_handover:reset_chosen(T) of
        {scrap, T1} ->
            %% Seed §2.3.8, RESET: "delete product data and continue with empty gripper".
            %% The data goes when the modules are in the scrap bin: until then they are
            %% in the gripper, and a stop on the way leaves them there, still this
            %% task's, to be scrapped when it starts again.
            #{serial := S} = P = cell_task:product(T1),
            cell_task:log(T1, brief, "product ~ts to be forgotten; its modules go to the "
                          "scrap bin", [S]),
            %% Modules the nest still held when they were found missing are this
            %% product's (the fixture holds its panel until its nest is empty): they go
            %% too, so nothing is left in the machine that no record knows of.
            InNest = cell_task:get(T1, in_nest, false),
            P1 = P#{scrap => true, from_nest => InNest},
            {ok, to_scrap(cell_task:set_product(cell_task:put(T1, in_nest, false), P1))};
        {taken_out, T1} ->
            %% Asked after a restart (where): the modules were taken out.
            {ok, T2} = answered_where(reset, T1),
            {ok, T2};
        {_, T1} ->
            {ok, T1}
    end.

-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(Held, T) ->
    case {cell_task:product(T), cell_handover:phase(T), cell_task:answer(T)} of
        {undefined, _, _} ->
            case unheld_here(T) of
                %% Kept closed: opened, they would fall wherever the robot stands.
                true -> cell_handover:unheld_error(
                          phase(T, idle), "Modules in the gripper unknown",
                          "Modules are in the upper robot's gripper", []);
                false -> {ok, phase(cell_task:out(T, gripper_close, false), idle)}
            end;
        %% Reset by the operator (init): on the way to the scrap bin.
        {_, to_scrap, _} ->
            {ok, T};
        {#{scrap := true}, _, _} ->
            {ok, to_scrap(T)};
        {_, _, undefined} ->
            Commanded = cell_task:commanded(Held, T, gripper_close),
            case is_boolean(Commanded) andalso cell_task:in(T, gripper_closed) =/= Commanded of
                true ->
                    %% The gripper was opening or closing when the robot stopped: its
                    %% sensors say something only once it has done so.
                    {ok, phase(cell_task:put(cell_task:out(T, gripper_close, Commanded),
                                             settle_to, Commanded), settling)};
                false ->
                    gripper_check(T)
            end;
        {_, _, Answer} ->
            answered_where(Answer, T)
    end.

%% The robot stops where it is (its axes halted); the gripper keeps hold of what it
%% has.
-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    ok = router_axes:halt(channel(T)),
    T.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

%% Modules in the gripper while the task holds no product and no unloading segment holds
%% one that can be in the gripper (one it took in from the gripper, its transfer cut off
%% before the gripper opened): with modules on its conveyor (its sensors see them), an
%% unloading segment's product is there, not in the gripper.
unheld_here(T) ->
    cell_task:product(T) =:= undefined andalso cell_task:in(T, product_present)
        andalso cell_handover:unheld_anywhere(
                  [router_cell:task(unloading, L) || L <- maps:keys(cell_task:arg(T, nexts, #{})),
                                                     not on_conveyor(T, L)],
                  cell_task:others_products(T)).

on_conveyor(T, Lane) ->
    Group = router_cell:group(unloading, Lane),
    cell_task:in(T, Group, panel_at_entry) orelse cell_task:in(T, Group, panel_at_exit).

%% -- empty: take the routed modules ------------------------------------------------------
step(idle, _Woken, T) ->
    cell_handover:take(T, prev(T), taking);
step(taking, {handshake, _Prev, interrupted}, T) ->
    cell_handover:interrupted(T, to_nest, idle);
step(taking, {handshake, _Prev, available, false}, T) ->
    move(T, to_nest);
step(taking, _Woken, T) ->
    {wait, {handshake, prev(T), available, false}, T};
step(gripping, {timer, _}, T) ->
    fault(T, "close the gripper");
step(gripping, {answer, retry}, T) ->
    %% The gripper was opened: to the nest again, and grip again, unless another
    %% record now puts a panel in that fixture (the next one came in meanwhile): then
    %% what the nest holds is not this product's, and where it is is asked.
    case nest_holder(T) of
        ours ->
            move(T, to_nest);
        {other, Task, Other} ->
            where(T, refused_other(Task, Other))
    end;
step(gripping, _Woken, T) ->
    case {cell_task:in(T, gripper_closed), cell_task:in(T, product_present)} of
        {true, true} ->
            T1 = case cell_handshake:phase(T, prev(T)) of
                     released -> cell_handshake:complete(T, prev(T));
                     _ -> T                      %% after a restart: it is ours already
                 end,
            move(T1, carrying);
        {true, false} ->
            {error, cell_task:error_spec(
                      <<"not_gripped">>, "Modules not gripped",
                      io_lib:format("The gripper closed on the nest but does not hold the "
                                    "modules of panel ~ts.~nPlease check gripper sensor: ~ts "
                                    "(~ts). Select RETRY to grip again.",
                                    [serial(T), address(product_present),
                                     caption(product_present)]),
                      [retry]),
             cell_task:out(T, gripper_close, false)};
        {false, _} ->
            wait_io(cell_task:out(T, gripper_close, true), gripping, gripper_closed, true)
    end;
%% -- after a Reset: what is left in the gripper goes to the scrap bin -------------------
step(emptying, {timer, _}, T) ->
    fault(T, "open the gripper");
step(emptying, _Woken, T) ->
    case {cell_task:in(T, gripper_closed), cell_task:product(T)} of
        {false, #{serial := S, from_nest := true}} ->
            case nest_holds(T) of
                true ->
                    cell_task:log(T, brief, "modules of panel ~ts still in the module nest: "
                                  "taken from there to the scrap bin", [S]),
                    move(T, nest_scrap);
                false ->
                    %% Taken out by hand meanwhile.
                    forget_scrapped(T)
            end;
        {false, _} ->
            forget_scrapped(T);
        {true, _} ->
            wait_io(cell_task:out(T, gripper_close, false), emptying, gripper_closed, false)
    end;
%% -- after a Reset: modules left in the nest go to the scrap bin as well ----------------
step(nest_gripping, {timer, _}, T) ->
    fault(T, "close the gripper");
step(nest_gripping, {answer, retry}, T) ->
    %% Looked at again from the start: the gripper opened over the nest, the nest's
    %% sensor asked again.
    wait_io(cell_task:out(T, gripper_close, false), emptying, gripper_closed, false);
step(nest_gripping, _Woken, T) ->
    case {cell_task:in(T, gripper_closed), cell_task:in(T, product_present)} of
        {true, true} ->
            %% In the gripper now: to the scrap bin with the rest.
            P = cell_task:product(T),
            {continue, to_scrap(cell_task:set_product(T, P#{from_nest => false}))};
        {true, false} ->
            {error, cell_task:error_spec(
                      <<"nest_not_gripped">>, "Modules not gripped",
                      io_lib:format("The module nest still holds the modules of panel ~ts "
                                    "(sensor ~ts, ~ts), but the gripper closed on it does not "
                                    "hold them (~ts, ~ts).~nTake them out of the nest by "
                                    "hand, or check the gripper, then select RETRY.",
                                    [serial(T), nest_address(T), nest_caption(T),
                                     address(product_present), caption(product_present)]),
                      [retry]),
             T};
        {false, _} ->
            wait_io(cell_task:out(T, gripper_close, true), nest_gripping, gripper_closed, true)
    end;
%% -- after a restart: the gripper's last command done before its sensors are read -------
step(settling, {timer, _}, T) ->
    fault(T, "finish moving the gripper");
step(settling, {io, _Group, gripper_closed, _}, T) ->
    case gripper_check(T) of
        {ok, T1} -> {continue, T1};
        Asked -> Asked
    end;
step(settling, _Woken, T) ->
    Want = cell_task:get(T, settle_to, cell_task:in(T, gripper_closed)),
    wait_io(T, settling, gripper_closed, Want);
step(where, {answer, Answer}, T) ->
    case answered_where(Answer, T) of
        {ok, T1} -> {continue, T1};
        Asked -> Asked
    end;
step(regrip, _Woken, T) ->
    move(T, regrip_at);
step(reopened, {timer, _}, T) ->
    fault(T, "open the gripper");
step(reopened, _Woken, T) ->
    case cell_task:in(T, gripper_closed) of
        false -> wait_io(cell_task:out(T, gripper_close, true), gripping, gripper_closed, true);
        true -> wait_io(cell_task:out(T, gripper_close, false), reopened, gripper_closed, false)
    end;
step(to_unloading, _Woken, T) ->
    %% After a restart with modules in the gripper.
    move(T, carrying);
%% -- Product lost (seed §2.3.8) ----------------------------------------------------------
step(lost, {answer, ignore}, T) ->
    %% IGNORE: the sensor is not believed; the modules go on, marked for inspection.
    P = cell_task:product(T),
    T1 = cell_task:set_product(T, P#{failed => true,
                                     note => <<"lost from the gripper; the operator chose "
                                               "to go on">>}),
    {continue, phase(T1, full)};
step(lost, _Retry, T) ->
    present(T);
%% -- full: put the modules down on the unloading segment --------------------------------
step(full, _Woken, T) ->
    %% The link of the product's lane, kept: the product is gone once released.
    Next = lane_link(T),
    T1 = cell_handshake:offer(cell_task:put(T, next, Next), Next),
    {wait, {handshake, Next, not_busy, true}, phase(T1, offered)};
step(offered, {handshake, _Next, not_busy, true}, T) ->
    wait_io(cell_task:out(T, gripper_close, false), placing, gripper_closed, false);
step(offered, _Woken, T) ->
    cell_handover:offered(T, next(T), full);
step(placing, {timer, _}, T) ->
    fault(T, "open the gripper");
step(placing, _Woken, T) ->
    case cell_task:in(T, gripper_closed) of
        false ->
            T1 = cell_handshake:release(T, next(T)),
            {wait, {handshake, next(T), not_busy, false}, phase(T1, released)};
        true ->
            wait_io(cell_task:out(T, gripper_close, false), placing, gripper_closed, false)
    end;
step(released, {handshake, _Next, interrupted}, T) ->
    cell_handover:interrupted(T, full, idle, fun put_down/1);
step(released, _Woken, T) ->
    %% Given back: the modules are gripped again, to be offered again.
    cell_handover:finish(T, next(T), idle, full,
                       fun(aborted, T1) -> cell_task:out(T1, gripper_close, true);
                          (_, T1) -> T1
                       end, fun put_down/1);
%% -- a move to a taught position, on the axes --------------------------------------------
step(Phase, {timer, _}, T) when ?MOVE(Phase) ->
    %% A path still under way is given up: the move starts again on Retry.
    ok = router_axes:halt(channel(T)),
    fault(T, "reach " ++ place_words(Phase));
step(Phase, {reply, _, Failed}, T) when ?MOVE(Phase), Failed =/= done ->
    axis_fault(Failed, Phase, T);
step(Phase, _Woken, T) when ?MOVE(Phase) ->
    go(T, Phase);
step(in_transit, _Woken, T0) ->
    %% The operator said the modules are at this robot: the gripper says whether in
    %% it; if not, they are where the cut-off transfer had them, in the nest (from the
    %% routing robot) or put down on the unloading conveyor (to it).
    T = cell_handshake:confirm_here(T0),
    case {cell_task:in(T, product_present), cell_handover:transit_have(T)} of
        {true, _} -> {continue, phase(cell_task:out(T, gripper_close, true), to_unloading)};
        {false, full} -> {continue, phase(T, full)};
        {false, _} -> {continue, phase(T, regrip)}
    end.

%% Over the unloading segment: are the modules still in the gripper? If not, whether
%% the module nest still holds them is noted now: until it is empty the fixture keeps
%% this product's panel, so what the nest holds then is this product's modules (later,
%% once emptied, it may be the next panel's).
present(T) ->
    case cell_task:in(T, product_present) of
        true ->
            {continue, phase(cell_task:put(T, in_nest, false), full)};
        false ->
            %% Judged when first found missing; asked again (RETRY), the nest may have
            %% been emptied since, never filled with them again.
            InNest = case cell_handover:phase(T) of
                         lost -> cell_task:get(T, in_nest, false) andalso nest_holds(T);
                         _ -> nest_holds(T) andalso nest_holder(T) =:= ours
                     end,
            Nest = case InNest of
                       true ->
                           io_lib:format("The module nest sensor ~ts (~ts) says the modules "
                                         "are still in the module nest of the fixture.~n",
                                         [nest_address(T), nest_caption(T)]);
                       false ->
                           ""
                   end,
            cell_handover:error(
              phase(cell_task:put(T, in_nest, InNest), lost), <<"lost">>, "Product lost",
              io_lib:format("Product was lost from gripper during move.~n"
                            "Please check gripper sensor:~n\t~ts (~ts)~n~ts"
                            "Select RETRY to check sensor again.~n"
                            "Select IGNORE to ignore sensors state and continue.~n"
                            "Select RESET to delete product data and continue with empty "
                            "gripper: the gripper is emptied over the scrap bin, and modules "
                            "still in the module nest are taken from there to the scrap bin "
                            "too.", [address(product_present), caption(product_present), Nest]),
              [retry, ignore, reset], scrap)
    end.

%% The product's data goes once its modules are in the scrap bin.
forget_scrapped(T) ->
    #{serial := S} = cell_task:product(T),
    cell_task:log(T, brief, "product ~ts forgotten: its modules are in the scrap bin", [S]),
    T1 = cell_task:clear_product(cell_task:work_abort(T, <<"product lost">>)),
    {continue, phase(T1, idle)}.

%% Whose the modules in the nest of the product's lane are, if they are there: this
%% robot's product's unless another record puts a panel in that fixture.
nest_holder(T) ->
    L = lane(T),
    Mine = serial(T),
    %% A hand-over of this product not yet completed leaves it in the giver's record too.
    Others = [O || {_, #{serial := S}} = O <- cell_task:others_products(T), S =/= Mine],
    router_task:nest_holder(L, [router_cell:task(work, L), lower], Others).

refused_other(Task, Other) ->
    io_lib:format("RETRY was refused: the gripper sensor sees no modules, and ~ts's "
                  "record puts panel ~ts in the fixture, so the modules in its nest are "
                  "that panel's, not these.~n", [holder_name(Task), Other]).

holder_name(lower) -> "the routing robot";
holder_name(Task) -> io_lib:format("the work segment (~ts)", [Task]).

%% Whether the module nest of the product's lane holds modules.
nest_holds(T) ->
    not cell_task:in(T, nest_group(T), nest_empty).

nest_group(T) ->
    router_cell:group(work, lane(T)).

nest_address(T) -> point_field(nest_group(T), nest_empty, address).
nest_caption(T) -> point_field(nest_group(T), nest_empty, caption).

gripper_check(T) ->
    case cell_task:in(T, product_present) of
        true ->
            %% Modules in the gripper: hold them and carry them on.
            {ok, phase(cell_task:out(cell_handover:here(T), gripper_close, true), to_unloading)};
        false ->
            where(T)
    end.

%% The record holds a product, the gripper sensor sees none. `Refused' says why the
%% last answer was not taken, if it was not.
where(T) ->
    where(T, "").

where(T, Refused) ->
    cell_handover:error(phase(T, where), <<"where">>, "Modules not in the gripper",
              io_lib:format("Records say the modules of panel ~ts are in the upper robot's "
                            "gripper; the gripper sensor ~ts (~ts) says it is empty. Where "
                            "are they?~n~ts"
                            "Select RETRY if they are in the gripper after all (seated "
                            "again: the robot carries them on) or back in the module nest "
                            "of the fixture: the robot grips them there again.~n"
                            "Select IGNORE if they are on the unloading conveyor: they have "
                            "been put down and go on from there.~n"
                            "Select RESET if they were taken out of the machine: the product "
                            "is scrapped.",
                            [serial(T), address(product_present), caption(product_present),
                             Refused]),
                      [retry, ignore, reset], taken_out).

answered_where(retry, T) ->
    case {cell_task:in(T, product_present), nest_holder(T)} of
        {true, _} ->
            cell_task:log(T, brief, "modules of panel ~ts in the gripper after all (its "
                          "sensor sees them again): carried on", [serial(T)]),
            {ok, phase(cell_task:out(cell_handover:here(T), gripper_close, true), to_unloading)};
        {false, ours} ->
            case nest_holds(T) of
                true ->
                    cell_task:log(T, brief, "modules of panel ~ts in the module nest "
                                  "(operator): gripped there again", [serial(T)]),
                    {ok, phase(cell_handover:here(T), regrip)};
                false ->
                    cell_task:log(T, brief, "modules of panel ~ts said to be in the module "
                                  "nest (operator), but its sensor says it is empty: asked "
                                  "again", [serial(T)]),
                    where(T, io_lib:format("RETRY was refused: the gripper sensor still sees "
                                           "no modules, and the module nest sensor ~ts (~ts) "
                                           "says the nest is empty.~n",
                                           [nest_address(T), nest_caption(T)]))
            end;
        {false, {other, Task, Other}} ->
            %% Not taken as this product's: the question again, saying why.
            cell_task:log(T, brief, "modules of panel ~ts said to be in the module nest "
                          "(operator), but ~ts's record puts panel ~ts in that "
                          "fixture: asked again", [serial(T), holder_name(Task), Other]),
            where(T, refused_other(Task, Other))
    end;
answered_where(ignore, T) ->
    cell_task:log(T, brief, "modules of panel ~ts on the unloading conveyor (operator): "
                  "handed on as put down", [serial(T)]),
    {ok, phase(cell_task:out(cell_handover:here(T), gripper_close, false), full)};
answered_where(_Reset, T0) ->
    %% Answered here, not by a re-initialisation.
    T = cell_handover:drop_reset(T0),
    #{serial := S} = cell_task:product(T),
    cell_task:log(T, brief, "modules of panel ~ts taken out of the machine (operator): "
                  "the product is scrapped", [S]),
    T1 = cell_task:clear_product(cell_task:work_abort(T, <<"taken out of the machine">>)),
    {ok, phase(cell_task:out(T1, gripper_close, false), idle)}.

%% Let go of over the unloading conveyor it was offered to: the gripper open and empty.
%% The modules lie there, to be offered again as they lie.
put_down(T) ->
    not cell_task:in(T, gripper_closed) andalso not cell_task:in(T, product_present).

%% On the way to the scrap bin, the gripper holding on to the modules.
to_scrap(T) ->
    phase(cell_task:out(T, gripper_close, true), to_scrap).

%% A move to the taught position of a phase (its destination, of the product's lane),
%% then what the phase does there.
move(T, Phase) ->
    go(phase(T, Phase), Phase).

%% One step of a move: the next command the axes need to be ready, or, ready, a line of
%% the channel from where they stand to the taught position; standing there, once the
%% machine's in-position signal says so too, the phase's next action. Each command's
%% end, and the signal, wakes the phase's next step.
go(T, Phase) ->
    case router_axes:prepare(channel(T), axes(T)) of
        ready ->
            Where = destination(Phase),
            To = router_task:upper_position(T, Where, lane(T)),
            At = router_upper_io:at(Where, lane(T)),
            case router_axes:position(axes(T)) of
                {ok, Here} ->
                    case {router_axes:there(Here, To), cell_task:in(T, At)} of
                        {true, true} ->
                            arrived(Phase, T);
                        {true, false} ->
                            %% There, as the machine will see: its in-position signal
                            %% comes with what the gripper's sensor saw on the way.
                            {wait, [{io, At, {eq, true}},
                                    router_task:watchdog(T, motion_timeout_ms, 30000)],
                             phase(T, Phase)};
                        {false, _} ->
                            Speed = cell_task:setting(T, upper_speed, 1000.0),
                            motion(T, Phase, router_axes:line(channel(T), Here, To,
                                                              path_params(Speed)))
                    end;
                Failed ->
                    axis_fault(Failed, Phase, T)
            end;
        Started ->
            motion(T, Phase, Started)
    end.

%% @doc The path velocity, acceleration and deceleration of a move between taught
%% positions at `Speed' (mm/s).
-spec path_params(float()) -> cell_hal_axis_fsm:params().
path_params(Speed) ->
    #{velocity => Speed, acceleration => ?ACC, deceleration => ?ACC}.

motion(T, Phase, {ok, Ref}) ->
    {wait, [{reply, Ref}, router_task:watchdog(T, motion_timeout_ms, 30000)],
     phase(T, Phase)};
motion(T, Phase, Refused) ->
    axis_fault(Refused, Phase, phase(T, Phase)).

%% Where a move phase goes, and what it does there.
destination(to_nest) -> nest;
destination(nest_scrap) -> nest;
destination(regrip_at) -> nest;
destination(carrying) -> unloading;
destination(to_scrap) -> home.

arrived(to_nest, T) ->
    wait_io(cell_task:out(T, gripper_close, true), gripping, gripper_closed, true);
arrived(carrying, T) ->
    present(T);
arrived(to_scrap, T) ->
    %% At home, over the scrap bin.
    wait_io(cell_task:out(T, gripper_close, false), emptying, gripper_closed, false);
arrived(nest_scrap, T) ->
    wait_io(cell_task:out(T, gripper_close, true), nest_gripping, gripper_closed, true);
arrived(regrip_at, T) ->
    wait_io(cell_task:out(T, gripper_close, false), reopened, gripper_closed, false).

place_words(to_scrap) -> "its home position";
place_words(carrying) -> "the unloading segment";
place_words(_ToNest) -> "the module nest".

%% A move refused, failed or aborted: the task's error, naming the axis.
axis_fault(Failed, Phase, T) ->
    {Axis, What} = router_axes:failed(Failed, channel(T), axes(T)),
    {error, cell_task:error_spec(
              <<"axis">>, "Upper robot axis fault",
              io_lib:format("Axis ~ts of the upper robot stopped on its way to ~ts "
                            "(product ~ts): ~ts.~nCheck the robot, then select RETRY: the "
                            "axes are made ready again and the move is made again.",
                            [Axis, place_words(Phase), serial(T), What]),
              [retry]),
     T}.

wait_io(T, Phase, Point, Value) ->
    {wait, [{io, Point, {eq, Value}}, router_task:watchdog(T, motion_timeout_ms, 30000)],
     phase(T, Phase)}.

fault(T, What) ->
    {error, cell_task:error_spec(
              <<"motion">>, "Upper robot fault",
              io_lib:format("The upper robot did not ~ts in time (product ~ts).~nCheck the "
                            "robot, then select RETRY to do it again.", [What, serial(T)]),
              [retry]),
     T}.

address(Point) -> point_field(upper_io, Point, address).
caption(Point) -> point_field(upper_io, Point, caption).

point_field(Group, Point, Field) ->
    case cell_hal:describe(Group, Point) of
        {ok, Info} -> maps:get(Field, Info);
        {error, _} -> atom_to_binary(Point, utf8)
    end.

serial(T) ->
    case cell_task:product(T) of
        #{serial := S} -> S;
        undefined -> <<"-">>
    end.

prev(T) -> cell_task:arg(T, prev, route_pick).
axes(T) -> cell_task:arg(T, axes, [upper_x, upper_y]).
channel(T) -> cell_task:arg(T, channel, upper_xy).

%% The product's lane.
lane(T) ->
    case cell_task:product(T) of
        #{lane := L} -> L;
        _ -> front
    end.

%% The link to the unloading segment of the product's lane.
lane_link(T) ->
    Links = cell_task:arg(T, nexts, #{}),
    case cell_task:product(T) of
        #{lane := L} -> maps:get(L, Links);
        _ -> maps:get(front, Links)
    end.

%% The link the product was offered on.
next(T) ->
    cell_task:get(T, next).

phase(T, Phase) -> cell_handover:phase(T, Phase).
