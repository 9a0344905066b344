%% @doc The simulated router: the machine's physics behind its simulated PLC, so the
%% device tasks run exactly as they would on the real machine.
%%
%% It watches the PLC's outputs (a rule on each output of the simulated PLC tells it
%% when the HAL wrote one) and moves the world in return, setting the PLC's inputs as
%% the sensors would see it, with timers for everything that takes time; it never
%% polls. The world: panels waiting at the previous machine's output, a panel on each
%% loading segment, in each fixture (whole, or its frame once the modules are lifted),
%% modules in the upper robot's gripper and on each unloading segment, the upper robot's
%% position, and what was delivered to the next machine or dropped into the scrap bin.
%% The world is saved in `Data/router_sim.world' whenever a panel moves, so a
%% restarted machine finds its panels where they were, as a real one would. It is saved
%% before the sensors show the move: whatever the tasks saw of the machine is in the
%% file, so a kill of the node at any moment leaves the file telling where every panel
%% physically is (the write is not flushed: a power cut may lose the last moves).
%%
%% The world keeps the machine's own ledger of what left it, `ledger' (newest first):
%% `{Serial, delivered}' for modules the next machine took, `{Serial, scrapped}' for
%% modules that fell into the scrap bin. Modules fall into the bin when the gripper
%% opens anywhere but over a free unloading segment or their own nest: that is where
%% the modules of a product the operator gave up on ("Product lost", Reset) go, the
%% upper robot opening its gripper at home. A frame left in a fixture is not the
%% product (its modules are in the gripper or beyond); frames leave by the fixture's
%% eject and are only counted. A panel the cell forgets stays where it is until the
%% operator's hand takes it out ({@link take_out/2}): `{Serial, removed}' in the ledger,
%% counted in `removed' (a frame taken out is counted in `frames').
%%
%% <ul>
%% <li>Panels arrive at the previous machine's output at the `router_sim' settings'
%%   rate (`arrival_ms', `arrival_jitter'), each with a new serial, up to
%%   `upstream_capacity'; the previous machine offers one (SMEMA) while it has any.</li>
%% <li>A conveyor move runs only while the belts it needs run: stopped, the panel
%%   stops, and goes on when they run again.</li>
%% <li>Spindle, bit, clamps and gripper take their own times. The robots' X and Y are
%%   not the PLC's: they are NC axes (router_cell's HAL), which simulate their own
%%   motion. The upper robot's NC writes where its axes stand into the PLC's outputs
%%   (`x_actual', `y_actual' of its IO), and the physics reads from them which station
%%   of the machine the gripper is over, if any: it leaves a station (lifting what it
%%   holds out of a nest) as the axes move away from it, however far the move was
%%   meant to go.</li>
%% <li>The fixture's clamps (two per lane, {@link router_clamps_io}): each a cylinder on
%%   a bistable valve, which goes where its coil last put it (both coils off: it
%%   holds). A clamp leaves its end (both its sensors off) when its valve changes and
%%   reaches the other `clamp_ms' later; only an open clamp lets a frame out. A clamp
%%   jammed from the shell ({@link jam_clamp/1}) stays where it is, or half-way if it
%%   was moving, until freed ({@link free_clamp/1}), when it goes where its valve
%%   says. Where each clamp and its valve are, and a jam, are in the world.</li>
%% <li>Faults: a conveyor move may stick (`jam_rate'; free again after `jam_ms'); the
%%   modules may slip in the gripper on a move (`product_lost_rate'; the gripper's
%%   sensor loses them until the operator has seated them again, `reseat_ms'), or stay
%%   stuck in the module nest as the robot lifts, the gripper coming away empty
%%   (`nest_stick_rate'); the
%%   previous machine's magazine runs low now and then (`magazine_low_s',
%%   `magazine_refill_s').</li>
%% <li>The code reader above each loading stopper answers its trigger after `read_ms'
%%   with the serial of the panel at the stopper, counting its reads; it finds no code
%%   now and then (`no_read_rate'), on an empty stopper, and on the next read
%%   {@link no_read_next/1} asks for. A trigger taken back before the answer gets
%%   none; its fall clears the answer.</li>
%% </ul>
%%
%% Every duration is multiplied by the settings' `time_scale' (0: none), which the
%% settings owner lets change while the cell runs.
%%
%% The simulated PLC and its points are the cell's HAL, which the cell's monitor
%% connects. A simulated PLC that dies is started again at once with its image and the
%% physics' rules (see `cell_hal_sim_device'), and runs those rules on the outputs as it
%% holds them: the physics, told an output it already acts on, does nothing more, and
%% one it had not heard of yet (the PLC killed between storing it and telling) it acts
%% on then, so it never has to attach again for that. The physics starts after it; should the HAL be taken down under it (the
%% cell's supervisor restarting the monitor), a write fails, the physics crashes and,
%% restarted, waits for the HAL to be back (retried 100 ms, then up to 5 s apart),
%% then goes on from the world it saved.
-module(router_sim).
-behaviour(gen_server).

-export([start_link/1, world/0, ready/1, take_out/2]).
-export([rest_image/1]).
-export([press_estop/0, release_estop/0, service_key/1, open_door/1, close_door/1,
         drop_air/0, restore_air/0, fault_drive/1, fault_drive/2, jam_clamp/1,
         free_clamp/1]).
-export([no_read_next/0, no_read_next/1]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-define(CONN, router_plc).
-define(WORLD_FILE, "router_sim.world").
%% The settings the arrivals and the magazine's timers were set with.
-define(RHYTHM, [time_scale, arrival_ms, arrival_jitter, upstream_capacity, magazine_low_s]).
-define(ATTACH_MIN, 100).
-define(ATTACH_MAX, 5000).
%% Where the upper robot's gripper is over each station of the machine, X and Y in mm
%% from its axes' home, and how near a station it must be to be over it.
-define(UPPER_STATIONS, [{home, {0.0, 0.0}},
                         {{nest, front}, {250.0, 150.0}}, {{nest, rear}, {250.0, 500.0}},
                         {{unloading, front}, {1100.0, 150.0}},
                         {{unloading, rear}, {1100.0, 500.0}}]).
-define(AT_MM, 1.0).

-type lane() :: front | rear.
-type door() :: loading | unloading.
-type drive() :: router_drives_io:drive().
-type poke() :: {estop, pressed | released} | {service_key, boolean()}
              | {door, door(), open | closed} | {air, boolean()}
              | {fault, drive(), pos_integer() | never}
              | {clamp, lane(), clamp(), jammed | free} | {no_read, lane()}.
-type clamp() :: a | b.
-type action() :: fun((map()) -> map()).

-record(move, {steps :: [{non_neg_integer(), action()}],   %% offset (ms) and what happens
               done = 0 :: non_neg_integer(),              %% ms run so far
               t0 :: integer() | undefined,                %% running since (monotonic ms)
               timer :: reference() | undefined}).

%%====================================================================
%% API
%%====================================================================

%% @doc Starts the physics of a router with these lanes.
-spec start_link(#{lanes := [lane()]}) -> {ok, pid()} | {error, term()}.
start_link(#{lanes := Lanes} = Opts) when is_list(Lanes) ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, Opts, []).

%% @doc The world as it is now: where every panel is, the counters `arrived',
%% `delivered', `scrapped', `frames' and `removed', and the machine's `ledger' of what left it
%% (see the module doc).
-spec world() -> map().
world() ->
    gen_server:call(?MODULE, world).

%% @doc The operator's hand takes what lies at a station out of the machine: a panel
%% (or a frame) in a lane's `loading', `work' or `unloading' segment, or the modules in
%% the upper robot's `gripper' (lane `none'). The panel goes in the ledger as
%% `{Serial, removed}' before the sensors show the station empty. Returns what was
%% taken: its serial, `frame', or `{error, empty}' when nothing lies there.
-spec take_out(loading | work | unloading | gripper, lane() | none) ->
          {ok, binary() | frame} | {error, empty}.
take_out(Where, Lane) when Where =:= loading; Where =:= work; Where =:= unloading;
                           Where =:= gripper ->
    gen_server:call(?MODULE, {take_out, Where, Lane}).

%%--------------------------------------------------------------------
%% The operator on the machine: the general IO the cell's monitor watches
%%--------------------------------------------------------------------

%% @doc Presses the emergency stop: its circuit opens (`estop_ok' off), every drive
%% loses its ready (conveyors stop under their panels; the cell stops, and with it the
%% robots' moves) until it is released.
-spec press_estop() -> ok | {error, not_running}.
press_estop() -> poke({estop, pressed}).

%% @doc Releases the emergency stop: the circuit closes, the drives without a fault
%% are ready again and the conveyors' moves they held go on.
-spec release_estop() -> ok | {error, not_running}.
release_estop() -> poke({estop, released}).

%% @doc Turns the service key switch: `true' to service, `false' back to production.
-spec service_key(boolean()) -> ok | {error, not_running}.
service_key(On) when is_boolean(On) -> poke({service_key, On}).

%% @doc Opens a safety door (`loading' or `unloading' side): the doors no longer
%% report closed and locked.
-spec open_door(door()) -> ok | {error, not_running}.
open_door(Door) when Door =:= loading; Door =:= unloading -> poke({door, Door, open}).

%% @doc Closes a safety door; the lock holds it again unless `door_unlock' is on.
-spec close_door(door()) -> ok | {error, not_running}.
close_door(Door) when Door =:= loading; Door =:= unloading -> poke({door, Door, closed}).

%% @doc The compressed air drops: the pressure falls below the switch's threshold.
-spec drop_air() -> ok | {error, not_running}.
drop_air() -> poke({air, false}).

%% @doc The compressed air is back at its pressure.
-spec restore_air() -> ok | {error, not_running}.
restore_air() -> poke({air, true}).

%% @doc A drive faults (see {@link fault_drive/2}); one reset clears it.
-spec fault_drive(drive()) -> ok | {error, not_running | no_such_drive}.
fault_drive(Drive) -> fault_drive(Drive, 1).

%% @doc A drive (`conveyor_front', `conveyor_rear', `lower', `upper') faults: its
%% fault bit on with a fault code, its ready off (what it moves stops) until `Resets'
%% pulses of its reset output have cleared it (`never': no reset clears it).
%% `{error, no_such_drive}' for the rear conveyors of a machine with one lane.
-spec fault_drive(drive(), pos_integer() | never) -> ok | {error, not_running | no_such_drive}.
fault_drive(Drive, Resets) when (Drive =:= conveyor_front orelse Drive =:= conveyor_rear
                                 orelse Drive =:= lower orelse Drive =:= upper),
                                (Resets =:= never orelse (is_integer(Resets) andalso Resets > 0)) ->
    poke({fault, Drive, Resets}).

%% @doc A fixture clamp sticks: clamp `a' of the lane's fixture (or `{Lane, a | b}')
%% does not move when its valve changes (or stops half-way if it was moving), so its
%% unit's move times out; until {@link free_clamp/1}. `{error, no_such_clamp}' for the
%% rear lane of a machine with one lane.
-spec jam_clamp(lane() | {lane(), clamp()}) -> ok | {error, not_running | no_such_clamp}.
jam_clamp({Lane, C}) when (Lane =:= front orelse Lane =:= rear), (C =:= a orelse C =:= b) ->
    poke({clamp, Lane, C, jammed});
jam_clamp(Lane) when Lane =:= front; Lane =:= rear ->
    jam_clamp({Lane, a}).

%% @doc A jammed clamp is free again: it goes where its valve says.
-spec free_clamp(lane() | {lane(), clamp()}) -> ok | {error, not_running | no_such_clamp}.
free_clamp({Lane, C}) when (Lane =:= front orelse Lane =:= rear), (C =:= a orelse C =:= b) ->
    poke({clamp, Lane, C, free});
free_clamp(Lane) when Lane =:= front; Lane =:= rear ->
    free_clamp({Lane, a}).

%% @doc The front lane's code reader finds no code on its next read (see {@link
%% no_read_next/1}).
-spec no_read_next() -> ok | {error, not_running | no_such_lane}.
no_read_next() -> no_read_next(front).

%% @doc A lane's code reader finds no code on its next read, whatever the label (a
%% smudged label, a reader out of focus): the "Code not read" error the operator
%% answers. `{error, no_such_lane}' for the rear lane of a machine with one.
-spec no_read_next(lane()) -> ok | {error, not_running | no_such_lane}.
no_read_next(Lane) when Lane =:= front; Lane =:= rear -> poke({no_read, Lane}).

poke(Poke) ->
    gen_server:call(?MODULE, {poke, Poke}).

%% @doc Returns once the physics runs and the HAL has read every input of the
%% simulated PLC as the physics set it, so a Start from now on finds the machine as it
%% is (a PLC just created reads zero everywhere until the physics has set it up).
-spec ready(timeout()) -> ok | {error, timeout}.
ready(Timeout) ->
    #{groups := Groups} = gen_server:call(?MODULE, groups, Timeout),
    Watches = [begin
                   {ok, V} = cell_hal_sim:get({G, P}),
                   {ok, Ref} = cell_hal:watch(G, P, {eq, V}),
                   Ref
               end || G <- Groups, {ok, Points} <- [cell_hal:points(G)],
                      #{name := P, dir := in} <- Points],
    Deadline = erlang:monotonic_time(millisecond) + Timeout,
    lists:foldl(fun(Ref, ok) ->
                        receive {cell_hal_watch, Ref, _} -> ok
                        after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
                            {error, timeout}
                        end;
                   (_, Error) ->
                        Error
                end, ok, Watches).

%%====================================================================
%% gen_server
%%====================================================================

-spec init(#{lanes := [lane()]}) -> {ok, map(), {continue, attach}}.
init(#{lanes := Lanes}) ->
    Groups = maps:from_list(lists:append([[{router_cell:group(K, L), {K, L}}
                                           || K <- [loading, work, unloading, clamps, reader]]
                                          || L <- Lanes])
                            ++ [{router_cell:group(inspect, L), {inspect, L}} || L <- Lanes]
                            ++ [{lower_io, {lower, none}}, {upper_io, {upper, none}},
                                {general_io, {general, none}}, {drives_io, {drives, none}}]),
    %% The inspection blocks' UDTs: the inspection application's, not needed to run.
    Blocks = maps:from_list([{router_cell:group(inspection_block, L), L} || L <- Lanes]),
    {ok, #{lanes => Lanes, groups => Groups, blocks => Blocks, outs => #{}, moves => #{},
           %% No world until restore/1 reads the saved one: a stop before that (the
           %% HAL not there yet, a crash in restore) saves nothing over it.
           rand => rand:seed_s(exsss),
           lost => undefined, busy => #{}, arrival => #{}, magazine => undefined,
           armed => #{}, attached => false, attach_ms => ?ATTACH_MIN, readers => [],
           epoch => 0, clamp_moves => #{}, no_read => #{}},
     {continue, attach}}.

-spec handle_continue(attach, map()) -> {noreply, map()}.
handle_continue(attach, S) ->
    {noreply, attach(S)}.

%% The physics needs the simulated PLC's points, which the cell's monitor adds.
attach(#{groups := Groups, attach_ms := Ms} = S) ->
    case [G || G <- maps:keys(Groups), cell_hal:points(G) =:= {error, unknown_group}] of
        [] ->
            S1 = restore(S#{attached := true}),
            _ = [gen_server:reply(R, #{groups => maps:keys(Groups)})
                 || R <- maps:get(readers, S1)],
            S1#{readers := []};
        Missing ->
            Ms =:= ?ATTACH_MIN andalso
                cell_log:notice(router, "simulated router waits for the cell's HAL (~ts)",
                                [lists:join(", ", [atom_to_list(G) || G <- lists:sort(Missing)])]),
            _ = erlang:send_after(Ms, self(), attach),
            S#{attach_ms := min(Ms * 2, ?ATTACH_MAX)}
    end.

%% The world in the file, settled; an empty one when there is none (or it cannot be
%% read: logged by cell_file).
stored_world(Lanes) ->
    case cell_file:read_term(path()) of
        {ok, #{counters := _} = W} ->
            settle(maps:merge(empty_world(Lanes), W#{clamps => saved_clamps(W, Lanes)}), Lanes);
        _ ->
            empty_world(Lanes)
    end.

%% The world as it was saved, its sensors set, and a rule on every output.
restore(#{lanes := Lanes, groups := Groups, blocks := Blocks} = S0) ->
    World = stored_world(Lanes),
    Outputs = [{{G, P}, Type} || G <- maps:keys(Groups) ++ maps:keys(Blocks),
                                 {ok, Points} <- [cell_hal:points(G)],
                                 #{name := P, dir := out, type := Type} <- Points],
    %% A rule on every output first, then the outputs read: a write the tasks make
    %% meanwhile is in the read, or in a message, or both; never in neither.
    ok = cell_hal_sim:clear_rules(?CONN),
    Self = self(),
    _ = [ok = cell_hal_sim:on_change(Key, fun(V) -> Self ! {out, Key, V}, [] end)
         || {Key, _} <- Outputs],
    %% The outputs as the PLC holds them (after a restart of this process, what the
    %% tasks commanded), but the clamps and the gripper hold what the world says.
    Holding = holding(World),
    Outs = maps:merge(maps:from_list([{Key, case cell_hal_sim:get(Key) of
                                                {ok, V} -> V;
                                                {error, _} -> zero(Type)
                                            end} || {Key, Type} <- Outputs]),
                      Holding),
    ok = cell_hal_sim:preset(?CONN, maps:merge(Holding, image(World, Outs, Lanes))),
    S1 = S0#{world => World, outs := Outs, settings => settings()},
    %% A trigger on when the physics stopped is answered now (its answer, if the
    %% reader had given one, went with the image).
    S2 = lists:foldl(fun(L, Acc) ->
                             case out(Acc, reader, L, trigger) of
                                 true -> read_label(L, Acc);
                                 false -> Acc
                             end
                     end, S1, Lanes),
    %% The upper robot where its NC last said (a PLC started anew: home, where the
    %% axes start again too); if that is not where the world had it, it left there.
    S = upper_moved(S2),
    Armed = maps:with(?RHYTHM, maps:get(settings, S)),
    cell_log:notice(router, "simulated router running: ~b panel(s) in the machine, ~b waiting "
                    "at the previous machine", [length(panels(World)), queued(World)]),
    %% A clamp that was moving when the physics stopped goes on to its valve's end.
    S3 = lists:foldl(fun(Key, Acc) -> clamp_move(Key, Acc) end, S,
                     lists:sort(maps:keys(maps:get(clamps, World)))),
    maps:remove(settings, kick(arrivals(magazine_timer(S3#{armed := Armed})))).

-spec handle_call(world | groups | {take_out, atom(), atom()} | {poke, poke()},
                  gen_server:from(), map()) ->
          {reply, term(), map()} | {noreply, map()}.
handle_call(world, _From, #{world := W} = S) ->
    {reply, W, S};
handle_call(world, _From, #{lanes := Lanes} = S) ->
    %% Waiting for the HAL: the world is the one saved.
    {reply, stored_world(Lanes), S};
handle_call({poke, Poke}, _From, #{attached := true} = S) ->
    try poked(Poke, S#{settings => settings()}) of
        {error, _} = Error -> {reply, Error, S};
        S1 -> {reply, ok, maps:remove(settings, kick(S1))}
    catch
        throw:{hal_gone, Group} -> {reply, {error, not_running}, detach(Group, S)}
    end;
handle_call({poke, _}, _From, S) ->
    {reply, {error, not_running}, S};
handle_call({take_out, Where, L}, _From, #{attached := true} = S) ->
    try hand(Where, L, S#{settings => settings()}) of
        {Reply, S1} -> {reply, Reply, maps:remove(settings, kick(S1))}
    catch
        throw:{hal_gone, Group} -> {reply, {error, empty}, detach(Group, S)}
    end;
handle_call({take_out, _Where, _L}, _From, S) ->
    {reply, {error, empty}, S};
handle_call(groups, _From, #{groups := Groups, attached := true} = S) ->
    {reply, #{groups => maps:keys(Groups)}, S};
handle_call(groups, From, #{attached := false} = S) ->
    %% Answered once attached.
    {noreply, S#{readers := [From | maps:get(readers, S)]}}.

-spec handle_cast(term(), map()) -> no_return().
handle_cast(Msg, _S) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), map()) -> {noreply, map()}.
handle_info(attach, #{attached := false} = S) ->
    {noreply, attach(S)};
handle_info(_Msg, #{attached := false} = S) ->
    %% Waiting for the HAL: what the physics armed before is over.
    {noreply, S};
handle_info(Msg, S) ->
    %% The settings as they are now, read once for everything this message causes.
    try info(Msg, rearm(S#{settings => settings()})) of
        {noreply, S1} -> {noreply, maps:remove(settings, S1)}
    catch
        throw:{hal_gone, Group} -> {noreply, detach(Group, S)}
    end.

%% The cell's HAL went away under the physics (the cell stopped, or its monitor took
%% the HAL down): the world is saved and the physics attaches again as at its start
%% (waiting, with its log line, while the HAL is gone), then goes on from the world
%% saved. Whatever it had armed is dropped.
detach(Group, #{lanes := Lanes, epoch := Epoch} = S) ->
    _ = save(S),
    cell_log:notice(router, "simulated router: the cell's HAL no longer serves ~ts", [Group]),
    {ok, Fresh, _} = init(#{lanes => Lanes}),
    attach(Fresh#{epoch := Epoch + 1}).

info({out, {G, P} = Key, V}, #{outs := Outs, blocks := Blocks} = S) when is_map_key(G, Blocks) ->
    %% The block wrote a tag of its UDT: the PLC program reads it.
    S1 = S#{outs := Outs#{Key => V}},
    case lists:member(P, router_inspect_io:mapped()) of
        true -> {noreply, set(S1, inspect, maps:get(G, Blocks), P, V)};
        false -> {noreply, S1}
    end;
info({out, Key, V}, #{outs := Outs, groups := Groups} = S) ->
    {G, P} = Key,
    S1 = S#{outs := Outs#{Key => V}},
    {noreply, kick(output(maps:get(G, Groups), P, V, maps:get(Key, Outs, undefined), S1))};
info({timeout, Ref, {step, Id}}, #{moves := Moves} = S) ->
    case maps:find(Id, Moves) of
        {ok, #move{timer = Ref} = M} -> {noreply, kick(run_move(Id, M, S))};
        _ -> {noreply, S}
    end;
info({timeout, _, {later, Epoch, Fun}}, #{epoch := Epoch} = S) ->
    {noreply, kick(Fun(S))};
info({timeout, _, {later, _, _}}, S) ->
    %% Armed before the physics last waited for the HAL.
    {noreply, S};
info({timeout, TRef, {arrive, Lane}}, #{arrival := Pending} = S) ->
    case maps:get(Lane, Pending, undefined) of
        TRef -> {noreply, kick(arrivals(arrive(Lane, S)))};
        _ -> {noreply, S}                       %% cancelled when the rhythm changed
    end;
info({timeout, TRef, magazine}, #{magazine := TRef} = S) ->
    {noreply, magazine(S#{magazine := undefined})};
info({timeout, _, magazine}, S) ->
    {noreply, S}.

-spec terminate(term(), map()) -> ok.
terminate(_Reason, S) ->
    save(S).

%%====================================================================
%% Outputs: what the machine does when the PLC commands it
%%====================================================================

%% Conveyors: a belt or SMEMA output only changes which moves can run (kick/1).
output(_Where, _Point, Same, Same, S) ->
    S;
output({clamps, L}, Point, _V, _Old, S) ->
    case [C || #{name := C, close := Close, open := Open} <- router_clamps_io:clamps(),
               Point =:= Close orelse Point =:= Open] of
        [C] -> valve(L, C, S);
        [] -> S
    end;
output({lower, _}, spindle_run, V, _Old, S) ->
    Ms = case V of true -> delay(spindle_ramp_ms, S); false -> delay(spindle_ramp_ms, S) div 2 end,
    later(Ms, fun(S1) -> set(S1, lower, none, spindle_at_speed, V) end, S);
output({lower, _}, plunge, _V, _Old, S) ->
    %% As the clamps: the bit ends where its valve is.
    later(delay(plunge_ms, S),
          fun(#{outs := Outs} = S1) ->
                  set(S1, lower, none, plunged, maps:get({lower_io, plunge}, Outs, false))
          end, S);
output({upper, _}, Axis, _V, _Old, S) when Axis =:= x_actual; Axis =:= y_actual ->
    upper_moved(S);
output({upper, _}, gripper_close, V, _Old, S) ->
    later(delay(gripper_ms, S), fun(S1) -> gripper(V, S1) end, S);
output({general, _}, door_unlock, _V, _Old, S) ->
    general(S);
output({inspect, L}, Point, V, _Old, S) ->
    %% The PLC program wrote a tag of the lane's inspection block: the block reads it.
    %% Without the inspection application its UDT is not in the HAL: nobody reads it.
    case cell_hal_sim:set({router_cell:group(inspection_block, L), Point}, V) of
        ok -> S;
        {error, Gone} when Gone =:= unknown_point; Gone =:= unknown_group -> S;
        {error, Why} -> erlang:error({cannot_set, inspection_block, L, Point, V, Why})
    end;
output({reader, L}, trigger, true, _Old, S) ->
    read_label(L, S);
output({reader, L}, trigger, false, _Old, S) ->
    set(S, reader, L, done, false);
output({drives, _}, Point, true, _Old, #{lanes := Lanes} = S) ->
    %% A reset's rising edge: one reset more towards clearing the drive's fault.
    case [D || D <- router_drives_io:drives(Lanes), router_drives_io:point(D, reset) =:= Point] of
        [D] -> reset_drive(D, S);
        [] -> S
    end;
output(_Where, _Point, _V, _Old, S) ->
    S.

%% The NC told where the upper robot's axes stand: the gripper is over the place that
%% lies there, or between places. Leaving a place, the robot lifts what it holds.
upper_moved(#{world := #{upper_at := At}, outs := Outs, lanes := Lanes} = S) ->
    case upper_place(Outs, Lanes) of
        At ->
            S;
        To ->
            %% Leaving, what it holds comes away before its in-position signal goes:
            %% whoever sees it gone sees that too.
            S1 = case At of
                     between -> S;
                     _ -> set(lift(S), upper, none, at_point(At), false)
                 end,
            #{world := W} = S1,
            S2 = S1#{world := W#{upper_at := To}},
            case To of
                between -> S2;
                _ -> set(S2, upper, none, at_point(To), true)
            end
    end.

station_of({_, L}, Lanes) -> lists:member(L, Lanes);
station_of(home, _Lanes) -> true.

at_point(home) -> router_upper_io:at(home, front);
at_point({Where, L}) -> router_upper_io:at(Where, L).

%% Where the gripper is, from the axes' actual positions as the NC wrote them: over a
%% station of the machine (within ?AT_MM of it on both axes), or between them. The
%% stations lie where the cell's taught positions put them by default (the router
%% settings' `upper_*'): the machine's build, not its settings. A machine with one lane
%% has no rear stations.
upper_place(Outs, Lanes) ->
    X = maps:get({upper_io, x_actual}, Outs, 0.0),
    Y = maps:get({upper_io, y_actual}, Outs, 0.0),
    Near = fun(A, B) -> abs(A - B) =< ?AT_MM end,
    case [Place || {Place, {Px, Py}} <- ?UPPER_STATIONS, Near(X, Px), Near(Y, Py),
                   station_of(Place, Lanes)] of
        [Place] -> Place;
        [] -> between
    end.

%% The upper robot leaves where it is: modules it holds over a nest leave the nest,
%% and may slip in the gripper on the way.
lift(#{world := #{gripper := Serial, upper_at := {nest, L}} = W} = S) when Serial =/= empty ->
    case maps:get(L, maps:get(work, W)) of
        {Serial, full} ->
            case chance(nest_stick_rate, S) of
                {true, S1} ->
                    %% Stuck in the nest: the gripper comes away empty.
                    S2 = S1#{world := (maps:get(world, S1))#{gripper := empty}},
                    save(set(S2, upper, none, product_present, false));
                {false, S1} ->
                    slip(set(world(S1, work, L, {Serial, frame}), work, L, nest_empty, true))
            end;
        _ ->
            slip(S)
    end;
lift(#{world := #{gripper := Serial}} = S) when Serial =/= empty ->
    slip(S);
lift(S) ->
    S.

slip(S) ->
    case chance(product_lost_rate, S) of
        {true, S1} ->
            Ref = make_ref(),
            S2 = set(S1#{lost := Ref}, upper, none, product_present, false),
            later(delay(reseat_ms, S2), fun(S3) -> reseated(Ref, S3) end, S2);
        {false, S1} ->
            S1
    end.

%% The operator's hand has seated the slipped modules again.
reseated(Ref, #{lost := Ref, world := #{gripper := G}} = S) when G =/= empty ->
    set(S#{lost := undefined}, upper, none, product_present, true);
reseated(_Ref, S) ->
    S.

gripper(true, #{world := #{gripper := empty, upper_at := {nest, L}} = W} = S) ->
    %% The part sensor sees the modules before the jaws report closed.
    S1 = case maps:get(L, maps:get(work, W)) of
             {Serial, full} ->
                 save(set(S#{world := W#{gripper := Serial}}, upper, none, product_present, true));
             _ ->
                 S
         end,
    set(S1, upper, none, gripper_closed, true);
gripper(true, S) ->
    set(S, upper, none, gripper_closed, true);
gripper(false, #{world := #{gripper := empty}} = S) ->
    set(S, upper, none, gripper_closed, false);
%% Modules let go of anywhere but on a free unloading segment or back in their nest
%% fall into the scrap bin.
gripper(false, #{world := #{gripper := Serial, upper_at := At} = W} = S) ->
    %% Where the modules went is in the world (and saved) before the sensors show the
    %% gripper open.
    S1 = S#{lost := undefined, world := W#{gripper := empty}},
    {S2, Placed} = case At of
                       {unloading, L} ->
                           case maps:get(L, maps:get(unloading, W)) of
                               empty -> {world(S1, unloading, L, {Serial, entry}), L};
                               _ -> {scrap(Serial, S1), none}
                           end;
                       {nest, L} ->
                           case maps:get(L, maps:get(work, W)) of
                               {Serial, full} -> {S1, none};      %% put back in the nest
                               _ -> {scrap(Serial, S1), none}
                           end;
                       _ ->
                           {scrap(Serial, S1), none}
                   end,
    S3 = set(set(S2, upper, none, gripper_closed, false), upper, none, product_present, false),
    save(case Placed of
             none -> S3;
             _ -> set(S3, unloading, Placed, panel_at_entry, true)
         end).

%%====================================================================
%% The code reader
%%====================================================================

%% The reader decodes the label of the panel at the stopper: the code, or none (an
%% empty stopper, a label it cannot read, a no-read asked for); the result and the
%% counter before done, as a reader maps its answer. A trigger taken back meanwhile
%% gets no answer.
read_label(L, S) ->
    later(delay(read_ms, S),
          fun(S1) ->
                  case out(S1, reader, L, trigger) of
                      true -> answer_read(L, S1);
                      false -> S1
                  end
          end, S).

answer_read(L, #{world := W, no_read := Forced} = S0) ->
    {Unreadable, S} = case maps:get(L, Forced, false) of
                          true -> {true, S0#{no_read := maps:remove(L, Forced)}};
                          false -> chance(no_read_rate, S0)
                      end,
    Code = case {slot(W, loading, L), Unreadable} of
               {{Serial, stop}, false} -> Serial;
               _ -> <<>>
           end,
    Count = (maps:get(L, maps:get(reads, W, #{}), 0) + 1) rem 65536,
    Unreadable andalso
        cell_log:info(router, "simulated router: the ~ts code reader finds no code",
                      [L]),
    S1 = S#{world := W#{reads => (maps:get(reads, W, #{}))#{L => Count}}},
    S2 = set(set(S1, reader, L, result, Code), reader, L, no_read, Code =:= <<>>),
    set(set(S2, reader, L, read_count, Count), reader, L, done, true).

%%====================================================================
%% The operator's hand
%%====================================================================

%% A panel taken out of a station: in the ledger first, then the sensors. A move the
%% station had under way stops (its panel is gone).
hand(gripper, _L, #{world := #{gripper := empty}} = S) ->
    {{error, empty}, S};
hand(gripper, _L, #{world := #{gripper := Serial} = W} = S) ->
    S1 = removed(Serial, S#{lost := undefined, world := W#{gripper := empty}}),
    {{ok, Serial}, set(S1, upper, none, product_present, false)};
hand(Where, L, #{world := W} = S) ->
    case maps:get(L, maps:get(Where, W), empty) of
        empty ->
            {{error, empty}, S};
        {_, frame} ->
            S1 = count(frames, world(stop_moves(Where, L, S), Where, L, empty)),
            {{ok, frame}, sensors(Where, L, S1)};
        {Serial, _} ->
            S1 = removed(Serial, world(stop_moves(Where, L, S), Where, L, empty)),
            {{ok, Serial}, sensors(Where, L, S1)}
    end.

removed(Serial, S) ->
    cell_log:info(router, "simulated router: ~ts taken out of the machine by the operator",
                  [Serial]),
    ledger(Serial, removed, count(removed, S)).

stop_moves(Where, L, #{moves := Moves} = S) ->
    Ids = case Where of
              loading -> [{intake, L}, {transfer, L}];
              work -> [{eject, L}];
              unloading -> [{unload, L}, {handout, L}]
          end,
    _ = [erlang:cancel_timer(R) || Id <- Ids, #move{timer = R} <- [maps:get(Id, Moves, #move{steps = []})],
                                   R =/= undefined],
    S#{moves := maps:without(Ids, Moves)}.

%% The sensors of a station emptied by hand.
sensors(loading, L, S) ->
    set(set(S, loading, L, panel_at_entry, false), loading, L, panel_at_stop, false);
sensors(work, L, S) ->
    set(set(S, work, L, nest_empty, true), work, L, panel_in_position, false);
sensors(unloading, L, S) ->
    set(set(S, unloading, L, panel_at_entry, false), unloading, L, panel_at_exit, false).

%%====================================================================
%% Conveyor moves
%%====================================================================

%% Starts the moves whose conditions hold, and runs or holds the others as their
%% belts run or stop.
kick(#{lanes := Lanes} = S) ->
    gate(lists:foldl(fun(L, Acc) -> start_moves(L, Acc) end, S, Lanes)).

start_moves(L, S) ->
    lists:foldl(fun(Kind, Acc) ->
                        case maps:is_key({Kind, L}, maps:get(moves, Acc)) of
                            true -> Acc;
                            false -> try_start(Kind, L, Acc)
                        end
                end, S, [intake, transfer, eject, unload, handout]).

try_start(intake, L, #{world := W} = S) ->
    case {slot(W, loading, L), maps:get(L, maps:get(upstream, W)),
          out(S, loading, L, belt_run) andalso out(S, loading, L, upstream_ready)} of
        {empty, [Serial | Rest], true} ->
            S1 = S#{world := W#{upstream := (maps:get(upstream, W))#{L := Rest}}},
            S2 = refill(L, world(S1, loading, L, {Serial, entering})),
            S3 = set(set(S2, loading, L, upstream_available, upstream(L, S2)),
                     loading, L, panel_at_entry, true),
            conveyor({intake, L}, intake_ms,
                     [{1.0, fun(X) ->
                                    X1 = set(X, loading, L, panel_at_entry, false),
                                    save(set(world(X1, loading, L, {Serial, stop}),
                                             loading, L, panel_at_stop, true))
                            end}], S3);
        _ ->
            S
    end;
try_start(transfer, L, #{world := W} = S) ->
    case {slot(W, loading, L), slot(W, work, L),
          out(S, loading, L, belt_run) andalso out(S, work, L, belt_run)} of
        {{Serial, stop}, empty, true} ->
            conveyor({transfer, L}, transfer_ms,
                     [{0.4, fun(X) -> set(X, loading, L, panel_at_stop, false) end},
                      {1.0, fun(X) ->
                                    X1 = world(world(X, loading, L, empty), work, L, {Serial, full}),
                                    save(set(set(X1, work, L, nest_empty, false),
                                             work, L, panel_in_position, true))
                            end}], S);
        _ ->
            S
    end;
try_start(eject, L, #{world := W} = S) ->
    %% Only a frame leaves: the fixture's end stop holds a whole panel, whatever the
    %% belt does, and lets the frame pass once the clamps are open.
    case {slot(W, work, L), out(S, work, L, belt_run) andalso clamps_open(L, S)} of
        {{_Serial, frame}, true} ->
            conveyor({eject, L}, eject_ms,
                     [{1.0, fun(X) ->
                                    X1 = set(world(X, work, L, empty), work, L,
                                             panel_in_position, false),
                                    save(count(frames, set(X1, work, L, nest_empty, true)))
                            end}], S);
        _ ->
            S
    end;
try_start(unload, L, #{world := W} = S) ->
    case {slot(W, unloading, L), out(S, unloading, L, belt_run)} of
        {{Serial, entry}, true} ->
            conveyor({unload, L}, unload_ms,
                     [{0.2, fun(X) -> set(X, unloading, L, panel_at_entry, false) end},
                      {1.0, fun(X) ->
                                    save(set(world(X, unloading, L, {Serial, exit}),
                                             unloading, L, panel_at_exit, true))
                            end}], S);
        _ ->
            S
    end;
%% The next machine takes modules only when told a board is available (SMEMA), and
%% only while it is ready.
try_start(handout, L, #{world := W, busy := Busy} = S) ->
    case {slot(W, unloading, L), out(S, unloading, L, belt_run)
          andalso out(S, unloading, L, board_available), maps:get(L, Busy, false)} of
        {{Serial, exit}, true, false} ->
            conveyor({handout, L}, handout_ms,
                     [{1.0, fun(X) ->
                                    X0 = ledger(Serial, delivered,
                                                count(delivered, world(X, unloading, L, empty))),
                                    X2 = set(X0, unloading, L, panel_at_exit, false),
                                    %% The next machine is busy with them for a while.
                                    X3 = set(X2#{busy := (maps:get(busy, X2))#{L => true}},
                                             unloading, L, downstream_ready, false),
                                    save(later(delay(downstream_busy_ms, X3),
                                               fun(Y) -> ready_again(L, Y) end, X3))
                            end}], S);
        _ ->
            S
    end.

ready_again(L, #{busy := Busy} = S) ->
    set(S#{busy := Busy#{L => false}}, unloading, L, downstream_ready, true).

%% A conveyor move: its steps at fractions of its duration, perhaps stuck for a while.
conveyor(Id, Setting, Fractions, S) ->
    D = delay(Setting, S),
    {Jam, S1} = chance(jam_rate, S),
    Total = case Jam of
                true -> D + delay(jam_ms, S1);
                false -> D
            end,
    Steps = [{case F of 1.0 -> Total; _ -> round(F * D) end, Fun} || {F, Fun} <- Fractions],
    S1#{moves := (maps:get(moves, S1))#{Id => #move{steps = Steps}}}.

%% Runs the moves whose belts run, holds those whose belts stopped.
gate(#{moves := Moves} = S) ->
    maps:fold(fun(Id, M, Acc) ->
                      Go = runs(Id, Acc),
                      case {Go, M#move.t0} of
                          {true, undefined} -> resume(Id, M, Acc);
                          {false, T0} when T0 =/= undefined -> hold(Id, M, Acc);
                          _ -> Acc
                      end
              end, S, Moves).

runs({_, L} = Id, S) ->
    drive_ready(conveyor(L), S) andalso belts(Id, S).

belts({intake, L}, S) -> out(S, loading, L, belt_run);
belts({transfer, L}, S) -> out(S, loading, L, belt_run) andalso out(S, work, L, belt_run);
belts({eject, L}, S) -> out(S, work, L, belt_run);
belts({unload, L}, S) -> out(S, unloading, L, belt_run);
belts({handout, L}, S) -> out(S, unloading, L, belt_run).

conveyor(front) -> conveyor_front;
conveyor(rear) -> conveyor_rear.

resume(Id, #move{steps = [{At, _} | _], done = Done} = M, #{moves := Moves} = S) ->
    Ref = erlang:start_timer(max(At - Done, 0), self(), {step, Id}),
    S#{moves := Moves#{Id => M#move{t0 = now_ms(), timer = Ref}}}.

hold(Id, #move{t0 = T0, timer = Ref, done = Done} = M, #{moves := Moves} = S) ->
    _ = erlang:cancel_timer(Ref),
    S#{moves := Moves#{Id := M#move{t0 = undefined, timer = undefined,
                                    done = Done + now_ms() - T0}}}.

%% A move's timer: the steps that are due happen; the move ends after its last.
run_move(Id, #move{t0 = T0, done = Done, steps = Steps} = M, #{moves := Moves} = S) ->
    Elapsed = Done + now_ms() - T0,
    {Due, Left} = lists:splitwith(fun({At, _}) -> At =< Elapsed end, Steps),
    S1 = S#{moves := maps:remove(Id, Moves)},
    S2 = lists:foldl(fun({_, Fun}, Acc) -> Fun(Acc) end, S1, Due),
    case Left of
        [] -> S2;
        _ -> resume(Id, M#move{steps = Left, done = Elapsed}, S2)
    end.

%%====================================================================
%% The fixture's clamps
%%====================================================================

%% A coil of a clamp's valve changed: a bistable valve goes to the end its one coil
%% on says (both off, or both on: it stays), and the clamp follows it.
valve(L, C, S) ->
    #{close := Close, open := Open} = clamp_points(C),
    case {out(S, clamps, L, Close), out(S, clamps, L, Open)} of
        {true, false} -> clamp_move({L, C}, set_valve({L, C}, closed, S));
        {false, true} -> clamp_move({L, C}, set_valve({L, C}, open, S));
        _ -> S
    end.

set_valve(Key, End, S) ->
    update_clamp(Key, fun(K) -> K#{valve := End} end, S).

%% The clamp goes where its valve is, unless it is there, on its way there, or jammed.
clamp_move(Key, #{world := W, clamp_moves := Moves} = S) ->
    #{at := At, valve := Valve, jammed := Jammed} = maps:get(Key, maps:get(clamps, W)),
    case {Jammed, At =:= Valve, maps:find(Key, Moves)} of
        {true, _, _} -> S;
        {false, true, error} -> S;
        {false, _, {ok, {_, Valve}}} -> S;
        {false, _, _} ->
            Ref = make_ref(),
            S1 = update_clamp(Key, fun(K) -> K#{at := between} end,
                              S#{clamp_moves := Moves#{Key => {Ref, Valve}}}),
            S2 = clamp_sensors(Key, save(S1)),
            later(delay(clamp_ms, S2), fun(S3) -> clamp_arrived(Key, Ref, S3) end, S2)
    end.

%% The move's time is up: the clamp is at the end it was going to, unless it jammed
%% on the way (it stays half-way) or another move replaced this one.
clamp_arrived(Key, Ref, #{clamp_moves := Moves, world := W} = S) ->
    case maps:find(Key, Moves) of
        {ok, {Ref, End}} ->
            S1 = S#{clamp_moves := maps:remove(Key, Moves)},
            case maps:get(Key, maps:get(clamps, W)) of
                #{jammed := true} -> S1;
                _ -> clamp_sensors(Key, save(update_clamp(Key, fun(K) -> K#{at := End} end, S1)))
            end;
        _ ->
            S
    end.

clamp_sensors({L, C} = Key, #{world := W} = S) ->
    #{at := At} = maps:get(Key, maps:get(clamps, W)),
    #{is_closed := IsClosed, is_open := IsOpen} = clamp_points(C),
    set(set(S, clamps, L, IsClosed, At =:= closed), clamps, L, IsOpen, At =:= open).

%% Only a fixture whose clamps are both open lets a frame out.
clamps_open(L, #{world := W}) ->
    lists:all(fun(#{name := C}) -> maps:get(at, maps:get({L, C}, maps:get(clamps, W))) =:= open
              end, router_clamps_io:clamps()).

update_clamp(Key, Fun, #{world := #{clamps := Clamps} = W} = S) ->
    S#{world := W#{clamps := Clamps#{Key := Fun(maps:get(Key, Clamps))}}}.

clamp_points(C) ->
    [P] = [P || #{name := N} = P <- router_clamps_io:clamps(), N =:= C],
    P.

%% The clamps of a fixture at one end, their valves with them.
clamps_at(L, End) ->
    [{{L, C}, #{at => End, valve => End, jammed => false}}
     || #{name := C} <- router_clamps_io:clamps()].

%% The clamps as a world saved before they were in it: closed on a panel in the
%% fixture (as the one valve did then), open on an empty one.
saved_clamps(#{clamps := Clamps}, _Lanes) ->
    Clamps;
saved_clamps(W, Lanes) ->
    Work = maps:get(work, W, #{}),
    maps:from_list(lists:append([clamps_at(L, case maps:get(L, Work, empty) of
                                                  empty -> open;
                                                  _ -> closed
                                              end) || L <- Lanes])).

%%====================================================================
%% The previous machine
%%====================================================================

%% Panels arrive at the previous machine's output, lane by lane.
arrivals(#{lanes := Lanes} = S) ->
    lists:foldl(fun refill/2, S, Lanes).

refill(L, #{world := W, arrival := Pending} = S) ->
    Queue = maps:get(L, maps:get(upstream, W)),
    Capacity = setting(upstream_capacity, S),
    case {length(Queue) < Capacity, delay(arrival_ms, S), maps:get(L, Pending, undefined)} of
        {false, _, _} -> S;
        {true, 0, _} -> refill(L, arrive(L, S));
        {true, _, TRef} when TRef =/= undefined -> S;      %% one is on its way
        {true, Mean, undefined} ->
            {U, R} = rand:uniform_s(maps:get(rand, S)),
            Jitter = setting(arrival_jitter, S),
            Ms = round(Mean * (1 - Jitter + 2 * Jitter * U)),
            S#{rand := R, arrival := Pending#{L => erlang:start_timer(Ms, self(), {arrive, L})}}
    end.

%% The settings of the rhythm changed (or the settings owner has just started): the
%% next arrivals and the magazine follow the new ones.
rearm(#{settings := Settings, armed := Armed} = S) ->
    case maps:with(?RHYTHM, Settings) of
        Armed ->
            S;
        New ->
            _ = [erlang:cancel_timer(T) || T <- maps:values(maps:get(arrival, S)),
                                           T =/= undefined],
            _ = [erlang:cancel_timer(T) || T <- [maps:get(magazine, S)], T =/= undefined],
            arrivals(magazine_timer(S#{armed := New, arrival := #{}, magazine := undefined}))
    end.

arrive(L, #{world := #{next := N} = W} = S) ->
    Serial = serial(N),
    Upstream = maps:get(upstream, W),
    S1 = S#{world := W#{next := N + 1,
                        upstream := Upstream#{L := maps:get(L, Upstream) ++ [Serial]}},
            arrival := (maps:get(arrival, S))#{L => undefined}},
    save(set(count(arrived, S1), loading, L, upstream_available, true)).

upstream(L, #{world := W}) ->
    maps:get(L, maps:get(upstream, W)) =/= [].

%% The previous machine's magazine runs low now and then, and is refilled.
magazine_timer(S) ->
    Mean = setting(magazine_low_s, S) * 1000 * scale(S),
    case Mean > 0 of
        true ->
            {U, R} = rand:uniform_s(maps:get(rand, S)),
            TRef = erlang:start_timer(round(-Mean * math:log(1 - U)), self(), magazine),
            S#{rand := R, magazine := TRef};
        false ->
            S
    end.

magazine(#{lanes := Lanes} = S) ->
    S1 = lists:foldl(fun(L, Acc) -> set(Acc, loading, L, magazine_low, true) end, S, Lanes),
    later(round(setting(magazine_refill_s, S) * 1000 * scale(S)),
          fun(S2) ->
                  magazine_timer(lists:foldl(fun(L, Acc) ->
                                                     set(Acc, loading, L, magazine_low, false)
                                             end, S2, Lanes))
          end, S1).

%%====================================================================
%% The general IO: emergency stop, service key, doors, air, drives
%%====================================================================

%% What the operator did on the machine, in the world (saved: a restarted machine
%% still has its e-stop pressed, its door open), then the inputs as they show it.
poked({estop, How}, S) -> general(update_general(fun(G) -> G#{estop := How} end, S));
poked({service_key, On}, S) -> general(update_general(fun(G) -> G#{service_key := On} end, S));
poked({door, Door, How}, S) ->
    general(update_general(fun(#{doors := D} = G) -> G#{doors := D#{Door := How}} end, S));
poked({air, On}, S) -> general(update_general(fun(G) -> G#{air := On} end, S));
poked({clamp, L, C, How}, #{lanes := Lanes} = S) ->
    case lists:member(L, Lanes) of
        true ->
            cell_log:info(router, "simulated router: clamp ~ts of the ~ts fixture ~ts",
                          [C, L, case How of jammed -> "jams"; free -> "is free again" end]),
            S1 = update_clamp({L, C}, fun(K) -> K#{jammed := How =:= jammed} end, S),
            case How of
                jammed -> save(S1);
                free -> clamp_move({L, C}, save(S1))
            end;
        false ->
            {error, no_such_clamp}
    end;
poked({no_read, L}, #{lanes := Lanes, no_read := Forced} = S) ->
    case lists:member(L, Lanes) of
        true -> S#{no_read := Forced#{L => true}};
        false -> {error, no_such_lane}
    end;
poked({fault, Drive, Resets}, #{lanes := Lanes} = S) ->
    case lists:member(Drive, router_drives_io:drives(Lanes)) of
        true ->
            cell_log:info(router, "simulated router: the drive ~ts faults",
                          [router_drives_io:caption(Drive)]),
            general(update_general(fun(#{faults := F} = G) -> G#{faults := F#{Drive => Resets}} end,
                                   S));
        false ->
            {error, no_such_drive}
    end.

%% @doc The inputs of a machine at rest (the emergency-stop circuit closed, the doors
%% closed and locked, the air on, every drive ready, the fixtures' clamps open) and
%% the clamps' valves holding them open: what its simulated PLC holds before the
%% physics sets the world it saved.
-spec rest_image([lane()]) -> #{{atom(), atom()} => term()}.
rest_image(Lanes) ->
    W = empty_world(Lanes),
    maps:merge(maps:from_list(general_image(W, fun(_) -> false end, Lanes)
                              ++ clamps_image(W) ++ reader_image(W, Lanes)),
               holding(W)).

%% The code readers at rest: no answer, their counters where they stopped.
reader_image(W, Lanes) ->
    lists:append([[{{router_cell:group(reader, L), done}, false},
                   {{router_cell:group(reader, L), no_read}, false},
                   {{router_cell:group(reader, L), result}, <<>>},
                   {{router_cell:group(reader, L), read_count},
                    maps:get(L, maps:get(reads, W, #{}), 0)}] || L <- Lanes]).

update_general(Fun, #{world := #{general := G} = W} = S) ->
    S#{world := W#{general := Fun(G)}}.

reset_drive(D, #{world := #{general := #{faults := F}}} = S) ->
    case maps:get(D, F, none) of
        none -> S;
        never -> S;
        1 ->
            cell_log:info(router, "simulated router: the drive ~ts is reset",
                          [router_drives_io:caption(D)]),
            general(update_general(fun(G) -> G#{faults := maps:remove(D, F)} end, S));
        N -> save(update_general(fun(G) -> G#{faults := F#{D := N - 1}} end, S))
    end.

%% The general inputs set as the world and the outputs say (a conveyor's move goes on
%% once its drive is ready again: kick/1).
general(#{world := W, lanes := Lanes, outs := Outs} = S) ->
    lists:foldl(fun({{_, P}, V}, Acc) -> set_general(Acc, P, V) end, save(S),
                general_image(W, fun(Key) -> maps:get(Key, Outs, false) end, Lanes)).

set_general(S, P, V) ->
    case lists:member(P, [estop_ok, service_key, door_loading_closed, door_unloading_closed,
                          doors_locked, air_ok, air_pressure]) of
        true -> set(S, general, none, P, V);
        false -> set(S, drives, none, P, V)
    end.

general_image(#{general := G}, Out, Lanes) ->
    #{estop := Estop, service_key := Key, doors := Doors, air := Air, faults := Faults} = G,
    Closed = fun(D) -> maps:get(D, Doors) =:= closed end,
    EstopOk = Estop =:= released,
    [{{general_io, estop_ok}, EstopOk},
     {{general_io, service_key}, Key},
     {{general_io, door_loading_closed}, Closed(loading)},
     {{general_io, door_unloading_closed}, Closed(unloading)},
     {{general_io, doors_locked}, Closed(loading) andalso Closed(unloading)
      andalso Out({general_io, door_unlock}) =/= true},
     {{general_io, air_ok}, Air},
     {{general_io, air_pressure}, case Air of true -> 6.0; false -> 2.5 end}]
        ++ lists:append(
             [[{{drives_io, router_drives_io:point(D, ready)},
                EstopOk andalso not maps:is_key(D, Faults)},
               {{drives_io, router_drives_io:point(D, fault)}, maps:is_key(D, Faults)},
               {{drives_io, router_drives_io:point(D, code)},
                case maps:is_key(D, Faults) of true -> fault_code(D); false -> 0 end}]
              || D <- router_drives_io:drives(Lanes)]).

%% A drive's fault code as its manufacturer numbers them: following error for the
%% robots' axes, overcurrent for the conveyors' motors.
fault_code(lower) -> 8611;
fault_code(upper) -> 8611;
fault_code(_) -> 2310.

drive_ready(D, #{world := #{general := #{estop := Estop, faults := F}}}) ->
    Estop =:= released andalso not maps:is_key(D, F).

%%====================================================================
%% The world
%%====================================================================

empty_world(Lanes) ->
    Empty = maps:from_list([{L, empty} || L <- Lanes]),
    #{upstream => maps:from_list([{L, []} || L <- Lanes]), loading => Empty, work => Empty,
      unloading => Empty, gripper => empty, upper_at => home,
      clamps => maps:from_list(lists:append([clamps_at(L, open) || L <- Lanes])),
      general => #{estop => released, service_key => false,
                   doors => #{loading => closed, unloading => closed}, air => true,
                   faults => #{}},
      next => 1, counters => #{arrived => 0, delivered => 0, scrapped => 0, frames => 0,
                             removed => 0},
      reads => maps:from_list([{L, 0} || L <- Lanes]),
      ledger => []}.

%% A world read back: a panel that was entering the loading segment is back at the
%% previous machine (the belt stopped under it); lanes the machine no longer has are
%% dropped (their panels taken out by hand).
settle(#{upstream := Up, loading := Lo} = W, Lanes) ->
    Lanes1 = [L || L <- Lanes, maps:is_key(L, Lo)],
    Back = maps:from_list([{L, case maps:get(L, Lo) of
                                   {S, entering} -> [S | maps:get(L, Up, [])];
                                   _ -> maps:get(L, Up, [])
                               end} || L <- Lanes1]),
    Loading = maps:from_list([{L, case maps:get(L, Lo) of
                                      {_, entering} -> empty;
                                      Slot -> Slot
                                  end} || L <- Lanes1]),
    Fill = fun(Key) -> maps:merge(maps:from_list([{L, empty} || L <- Lanes]),
                                  maps:with(Lanes, maps:get(Key, W))) end,
    Clamps = maps:merge(maps:from_list(lists:append([clamps_at(L, open) || L <- Lanes])),
                        maps:filter(fun({L, _}, _) -> lists:member(L, Lanes) end,
                                    maps:get(clamps, W))),
    W#{clamps := Clamps,
       upstream := maps:merge(maps:from_list([{L, []} || L <- Lanes]), Back),
       loading := maps:merge(maps:from_list([{L, empty} || L <- Lanes]), Loading),
       work := Fill(work), unloading := Fill(unloading)}.

%% The outputs that hold what the world holds: the clamps' valves where they are (a
%% bistable valve keeps its position without power), the gripper on modules.
holding(W) ->
    maps:from_list(lists:append(
                     [[{{router_cell:group(clamps, L), Close}, Valve =:= closed},
                       {{router_cell:group(clamps, L), Open}, Valve =:= open}]
                      || {{L, C}, #{valve := Valve}} <- maps:to_list(maps:get(clamps, W)),
                         #{close := Close, open := Open} <- [clamp_points(C)]])
                   ++ [{{upper_io, gripper_close}, maps:get(gripper, W) =/= empty}]).

%% Every input of the PLC for a world and the outputs as they are: what the sensors
%% see, and the actuators at rest where their outputs put them.
image(W, Outs, Lanes) ->
    Holding = maps:get(gripper, W) =/= empty,
    Out = fun(Key) -> maps:get(Key, Outs) end,
    maps:from_list(
      lists:append(
        [[{{router_cell:group(loading, L), upstream_available}, maps:get(L, maps:get(upstream, W)) =/= []},
          {{router_cell:group(loading, L), panel_at_entry}, false},
          {{router_cell:group(loading, L), panel_at_stop}, is_at(slot(W, loading, L), stop)},
          {{router_cell:group(loading, L), magazine_low}, false},
          {{router_cell:group(work, L), panel_in_position}, slot(W, work, L) =/= empty},
          {{router_cell:group(work, L), nest_empty}, not is_at(slot(W, work, L), full)},
          {{router_cell:group(unloading, L), panel_at_entry}, is_at(slot(W, unloading, L), entry)},
          {{router_cell:group(unloading, L), panel_at_exit}, is_at(slot(W, unloading, L), exit)},
          {{router_cell:group(unloading, L), downstream_ready}, true}]
         || L <- Lanes])
      ++ clamps_image(W)
      ++ [{{upper_io, gripper_closed}, Out({upper_io, gripper_close})},
          {{upper_io, product_present}, Holding}]
      ++ [{{upper_io, at_point(Place)}, maps:get(upper_at, W) =:= Place}
          || {Place, _} <- ?UPPER_STATIONS]
      ++ [{{lower_io, spindle_at_speed}, Out({lower_io, spindle_run})},
          {{lower_io, plunged}, Out({lower_io, plunge})}]
      ++ general_image(W, fun(Key) -> maps:get(Key, Outs, false) end, Lanes)
      ++ inspect_image(Outs, Lanes)
      ++ reader_image(W, Lanes)).

%% Each side of an inspection block reads what the other wrote: the PLC maps the PLC
%% program's tags onto the block's UDT. Outputs nobody has written read zero.
inspect_image(Outs, Lanes) ->
    lists:append([[{{To, P}, V} || {{From1, P}, V} <- maps:to_list(Outs), From1 =:= From,
                                   lists:member(P, router_inspect_io:mapped())]
                  || L <- Lanes,
                     {From, To} <- [{router_cell:group(inspection_block, L),
                                     router_cell:group(inspect, L)},
                                    {router_cell:group(inspect, L),
                                     router_cell:group(inspection_block, L)}]]).

%% The clamps' end sensors as the world has the clamps.
clamps_image(W) ->
    lists:append([[{{router_cell:group(clamps, L), IsClosed}, At =:= closed},
                   {{router_cell:group(clamps, L), IsOpen}, At =:= open}]
                  || {{L, C}, #{at := At}} <- maps:to_list(maps:get(clamps, W)),
                     #{is_closed := IsClosed, is_open := IsOpen} <- [clamp_points(C)]]).

is_at({_, Where}, Where) -> true;
is_at(_, _) -> false.

slot(W, Where, L) ->
    maps:get(L, maps:get(Where, W)).

world(#{world := W} = S, Where, L, Slot) ->
    S#{world := W#{Where := (maps:get(Where, W))#{L := Slot}}}.

panels(W) ->
    [P || Where <- [loading, work, unloading], {_, P} <- maps:to_list(maps:get(Where, W)),
          P =/= empty] ++ [G || G <- [maps:get(gripper, W)], G =/= empty].

queued(W) ->
    lists:sum([length(Q) || Q <- maps:values(maps:get(upstream, W))]).

count(Key, #{world := #{counters := C} = W} = S) ->
    S#{world := W#{counters := C#{Key => maps:get(Key, C, 0) + 1}}}.

scrap(Serial, S) ->
    cell_log:info(router, "simulated router: modules of ~ts dropped into the scrap bin",
                  [Serial]),
    ledger(Serial, scrapped, count(scrapped, S)).

%% What left the machine, and how.
ledger(Serial, How, #{world := W} = S) ->
    S#{world := W#{ledger := [{Serial, How} | maps:get(ledger, W, [])]}}.

%% The world saved if it changed since it was last saved: the sensors never show the
%% tasks a world the file does not have.
durable(#{world := W, saved := W} = S) -> S;
durable(#{world := _} = S) -> save(S);
durable(S) -> S.

save(#{world := W} = S) ->
    case cell_file:write_term(path(), W, #{sync => false}) of
        ok -> S#{saved => W};
        {error, Why} ->
            cell_log:error(router, "the simulated world could not be saved to ~ts: ~tp",
                           [path(), Why]),
            S
    end;
save(S) ->
    S.

path() ->
    filename:join(cell_config:dir(data), ?WORLD_FILE).

serial(N) ->
    {{Y, M, D}, _} = calendar:local_time(),
    iolist_to_binary(io_lib:format("P~2..0b~2..0b~2..0b-~6..0b", [Y rem 100, M, D, N])).

%%====================================================================
%% The PLC and the settings
%%====================================================================

%% Sets an input of a segment's (or a robot's) group in the simulated PLC, the world
%% saved first.
set(S0, Kind, L, Point, V) ->
    S = durable(S0),
    Group = case Kind of
                lower -> lower_io;
                upper -> upper_io;
                general -> general_io;
                drives -> drives_io;
                _ -> router_cell:group(Kind, L)
            end,
    case cell_hal_sim:set({Group, Point}, V) of
        ok -> S;
        {error, Gone} when Gone =:= unknown_point; Gone =:= unknown_group ->
            throw({hal_gone, Group});
        {error, Why} -> erlang:error({cannot_set, Group, Point, V, Why})
    end.

out(#{outs := Outs}, Kind, L, Point) ->
    maps:get({router_cell:group(Kind, L), Point}, Outs, false) =:= true.

later(Ms, Fun, #{epoch := Epoch} = S) ->
    _ = erlang:start_timer(Ms, self(), {later, Epoch, Fun}),
    S.

chance(Setting, #{rand := R} = S) ->
    {U, R1} = rand:uniform_s(R),
    {U < setting(Setting, S), S#{rand := R1}}.

delay(Setting, S) ->
    round(setting(Setting, S) * scale(S)).

scale(S) ->
    setting(time_scale, S).

setting(Key, #{settings := Settings}) ->
    maps:get(Key, Settings).

%% The settings as saved now (they apply at once); as the file holds them while the
%% settings owner does not run: the physics starts before the cell does, and a virtual
%% PLC ({@link cell_vplc}) runs it without the cell.
settings() ->
    Defaults = cell_settings_schema:defaults(router_sim_settings),
    try cell_settings:get(router_sim) of
        Now -> maps:merge(Defaults, Now)
    catch
        error:_ -> cell_spec_helpers:saved_settings(router_sim_settings);
        exit:_ -> cell_spec_helpers:saved_settings(router_sim_settings)
    end.

zero(bool) -> false;
zero(lreal) -> 0.0;
zero(real) -> 0.0;
zero({string, _}) -> <<>>;
zero(_) -> 0.

now_ms() ->
    erlang:monotonic_time(millisecond).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

rest_image_test() ->
    Rest = rest_image([front]),
    ?assertMatch(#{{general_io, estop_ok} := true, {general_io, service_key} := false,
                   {general_io, doors_locked} := true, {general_io, air_ok} := true,
                   {general_io, air_pressure} := 6.0,
                   {drives_io, conveyor_front_ready} := true, {drives_io, lower_ready} := true,
                   {drives_io, upper_fault} := false, {drives_io, upper_fault_code} := 0},
                 Rest),
    ?assertNot(maps:is_key({drives_io, conveyor_rear_ready}, Rest)),
    ?assert(maps:is_key({drives_io, conveyor_rear_ready}, rest_image([front, rear]))),
    %% The clamps open, held open by their valves.
    ?assertMatch(#{{clamps_front_io, a_is_open} := true, {clamps_front_io, a_is_closed} := false,
                   {clamps_front_io, b_is_open} := true, {clamps_front_io, b_close} := false,
                   {clamps_front_io, a_open} := true},
                 Rest),
    ?assertNot(maps:is_key({clamps_rear_io, a_is_open}, Rest)),
    %% The code readers unanswered, their counters at zero; the rear one with its lane.
    ?assertMatch(#{{reader_front_io, done} := false, {reader_front_io, no_read} := false,
                   {reader_front_io, result} := <<>>, {reader_front_io, read_count} := 0},
                 Rest),
    ?assertNot(maps:is_key({reader_rear_io, done}, Rest)),
    ?assertMatch(#{{reader_rear_io, done} := false}, rest_image([front, rear])).

%% Every input of the reader's group in the rest image, and no output.
rest_image_covers_the_reader_test() ->
    Ins = lists:sort([P || #{name := P, dir := in} <- router_reader_io:points(#{base => 400})]),
    ?assertEqual(Ins, lists:sort([P || {reader_front_io, P} <- maps:keys(rest_image([front]))])).

saved_clamps_test() ->
    %% A world saved before the clamps were in it: closed on a panel, open without.
    W = (empty_world([front, rear]))#{work => #{front => {<<"P1">>, full}, rear => empty}},
    Clamps = saved_clamps(maps:remove(clamps, W), [front, rear]),
    ?assertMatch(#{{front, a} := #{at := closed, valve := closed, jammed := false},
                   {front, b} := #{at := closed}, {rear, a} := #{at := open},
                   {rear, b} := #{at := open}}, Clamps),
    ?assertEqual(Clamps, saved_clamps(W#{clamps => Clamps}, [front, rear])).

general_image_test() ->
    #{general := G} = W = empty_world([front]),
    Image = fun(World, Outs) ->
                    maps:from_list(general_image(World, fun(K) -> maps:get(K, Outs, false) end,
                                                 [front]))
            end,
    %% The lock released: the doors closed but not locked.
    ?assertMatch(#{{general_io, doors_locked} := false,
                   {general_io, door_loading_closed} := true},
                 Image(W, #{{general_io, door_unlock} => true})),
    %% A door open.
    ?assertMatch(#{{general_io, doors_locked} := false,
                   {general_io, door_unloading_closed} := false},
                 Image(W#{general := G#{doors := #{loading => closed, unloading => open}}}, #{})),
    %% The e-stop pressed: no drive is ready, none faults.
    Pressed = Image(W#{general := G#{estop := pressed}}, #{}),
    ?assertMatch(#{{general_io, estop_ok} := false, {drives_io, lower_ready} := false,
                   {drives_io, conveyor_front_ready} := false, {drives_io, lower_fault} := false},
                 Pressed),
    %% A fault: that drive not ready, its fault and code on; the others ready.
    ?assertMatch(#{{drives_io, lower_ready} := false, {drives_io, lower_fault} := true,
                   {drives_io, lower_fault_code} := 8611, {drives_io, upper_ready} := true},
                 Image(W#{general := G#{faults := #{lower => 2}}}, #{})),
    %% No air.
    ?assertMatch(#{{general_io, air_ok} := false, {general_io, air_pressure} := 2.5},
                 Image(W#{general := G#{air := false}}, #{})).
-endif.
