%% @doc The default cell: a standard inline router (seed 000 §2.3), written as a user
%% of cellrt writes a cell. This module is the cell spec the controller builds the cell
%% from (the `cell' application's `cell_module').
%%
%% ```
%%   previous   ┌─────────┐ load_work ┌──────┐ work_route ┌───────┐ route_pick ┌───────┐ pick_unload ┌───────────┐   next
%%   machine ──▶│ loading │──────────▶│ work │───────────▶│ lower │───────────▶│ upper │────────────▶│ unloading │──▶ machine
%%              └─────────┘           └──────┘            └───────┘            └───────┘             └───────────┘
%% '''
%%
%% Per lane (front, and rear when the machine settings say `dual_lane'): a loading
%% conveyor segment with a code reader above its stopper (a hardware object wired
%% through the PLC's IO, {@link cell_hal_code_reader_io}), a work segment with the
%% routing fixture, whose clamps are a unit (seed 001, {@link router_clamps_unit}) the
%% work segment orders, an unloading conveyor segment. Shared by the lanes: the lower
%% routing robot, which routes the panel in
%% whichever fixture offers one, and the upper manipulator robot, which lifts the
%% routed modules out of the nest and puts them on the unloading segment of their lane.
%% Every arrow is a handshake link (seed §2.3.6); the panel's serial travels along them.
%%
%% As in seed 000 §2.3.3 the settings choose the cell when it boots: `simulation_mode'
%% connects the IO groups to a simulated PLC moved by {@link router_sim}, otherwise to
%% the router's PLC over Modbus TCP (`plc_host', `plc_port', `plc_unit' of the
%% `router' settings); `dual_lane' adds the rear lane. The task modules are the same
%% either way: they only know their IO by name. A change of these settings applies at
%% the next boot of the cell. The settings are read, and the PLC chosen, with the
%% helpers every cell spec uses ({@link cell_spec_helpers}).
-module(router_cell).

-export([cell_spec/0, cell_spec/2, hal/2, hal/3, monitor/1, lanes/1, group/2, task/2, reader/1,
         router_settings/0, simulation/1, machine_actions/1, inspect_blocks/1]).

-define(CONN, router_plc).

%% @doc The cell spec, from the settings files as they are at boot.
-spec cell_spec() -> map().
cell_spec() ->
    cell_spec(cell_spec_helpers:machine_settings(), router_settings()).

%% @doc The cell spec for given machine and router settings.
-spec cell_spec(map(), map()) -> map().
cell_spec(Machine, Router) ->
    Lanes = lanes(Machine),
    LaneTasks = lists:append([lane_tasks(L, Router) || L <- Lanes]),
    Robots = [#{id => lower, module => router_lower_task, zone => <<"Lower robot">>,
                lane => <<"Shared">>, io => [lower_io], settings => router,
                args => #{prevs => [link(work_route, L) || L <- Lanes], next => route_pick}},
              #{id => upper, module => router_upper_task, zone => <<"Upper robot">>,
                %% The module nests' sensors read too: after a Reset it empties them;
                %% and the unloading conveyors', to tell whose modules in its gripper
                %% that it holds no record of are.
                lane => <<"Shared">>,
                io => [upper_io | [group(K, L) || K <- [work, unloading], L <- Lanes]],
                settings => router,
                args => #{prev => route_pick,
                          nexts => maps:from_list([{L, link(pick_unload, L)} || L <- Lanes])}}],
    Links = lists:append([[#{id => link(load_work, L), from => task(loading, L),
                             to => task(work, L)},
                           #{id => link(work_route, L), from => task(work, L), to => lower},
                           #{id => link(pick_unload, L), from => upper,
                             to => task(unloading, L)}] || L <- Lanes])
        ++ [#{id => route_pick, from => lower, to => upper}],
    #{name => maps:get(cell_name, Machine, <<"Router">>),
      tasks => LaneTasks ++ Robots,
      links => Links,
      settings => [router_settings, router_sim_settings],
      hal => hal(Machine, Router),
      monitor => monitor(Machine)}.

lane_tasks(L, Router) ->
    Lane = lane_name(L),
    [#{id => task(loading, L), module => router_loading_task, zone => <<"Loading">>,
       lane => Lane, io => [group(loading, L)], settings => router,
       args => #{lane => L, next => link(load_work, L), reader => reader(L)}},
     #{id => task(work, L), module => router_work_task, zone => <<"Work">>, lane => Lane,
       %% The loading stopper's and the gripper's sensors read too: they tell whose a
       %% panel in the fixture that the segment holds no record of is; and the clamps'
       %% end sensors, to see its orders to their unit carried out.
       io => [group(work, L), group(loading, L), upper_io, group(clamps, L)],
       settings => router,
       args => #{lane => L, prev => link(load_work, L), next => link(work_route, L),
                 clamps => task(clamps, L)}},
     %% The fixture's clamps: a unit (seed 001) the work segment orders to clamp and
     %% to open. It counts no parts: the work segment does.
     cell_spec_helpers:unit(task(clamps, L), router_clamps_unit,
                            #{zone => <<"Clamps">>, lane => Lane,
                              io => [group(clamps, L), group(work, L)], work => false,
                              args => #{lane => L,
                                        timeout_ms => maps:get(clamp_timeout_ms, Router,
                                                               3000)}}),
     #{id => task(unloading, L), module => router_unloading_task, zone => <<"Unloading">>,
       %% The gripper's sensor read too: modules in it are not on this conveyor. The
       %% inspection block's tags as the PLC program sees them: the camera at the exit.
       lane => Lane, io => [group(unloading, L), upper_io, group(inspect, L)],
       settings => router,
       args => #{lane => L, prev => link(pick_unload, L)}}].

%% @doc The HAL configuration of the cell, with the physics' time scale as saved.
-spec hal(map(), map()) -> #{connections := [cell_hal:connection_spec()],
                             groups := [cell_hal:group_spec()],
                             hardware := [cell_hal_hw:spec()]}.
hal(Machine, Router) ->
    hal(Machine, Router, cell_spec_helpers:saved_settings(router_sim_settings)).

%% @doc The HAL configuration of the cell: one PLC connection (simulated or Modbus
%% TCP), the IO group instances bound to it, the code readers, wired through the PLC's
%% IO in simulation and on the real machine alike, and each robot's NC: its X and Y
%% axes and the interpolation channel over them, simulated, at the physics' time scale
%% (`Sim': the router_sim settings).
-spec hal(map(), map(), map()) -> #{connections := [cell_hal:connection_spec()],
                                    groups := [cell_hal:group_spec()],
                                    hardware := [cell_hal_hw:spec()]}.
hal(Machine, Router, Sim) ->
    Conn = cell_spec_helpers:connection(
             ?CONN, Machine,
             #{real => {cell_hal_modbus, #{host => binary_to_list(maps:get(plc_host, Router)),
                                           port => maps:get(plc_port, Router),
                                           unit => maps:get(plc_unit, Router)}},
               %% A simulated PLC started anew holds the machine at rest: the
               %% emergency-stop circuit closed, the doors locked, the air on, the
               %% drives ready, until the physics sets the world it saved.
               sim => #{image => router_sim:rest_image(lanes(Machine))},
               opts => #{poll_ms => maps:get(hal_poll_ms, Router, 20)}}),
    %% Each lane's groups 100 addresses apart in the PLC's image.
    Groups = lists:append([[#{id => group(K, L), module => module(K), connection => ?CONN,
                              opts => #{base => Base + Off}}
                            || {K, Off} <- [{loading, 0}, {work, 20}, {unloading, 40}]]
                           || {L, Base} <- [{front, 0}, {rear, 100}],
                              lists:member(L, lanes(Machine))])
        %% The fixtures' clamps, 20 addresses per lane.
        ++ [#{id => group(clamps, L), module => router_clamps_io, connection => ?CONN,
              opts => #{base => Base}}
            || {L, Base} <- [{front, 440}, {rear, 460}], lists:member(L, lanes(Machine))]
        ++ [#{id => lower_io, module => router_lower_io, connection => ?CONN,
              opts => #{base => 200}},
            #{id => upper_io, module => router_upper_io, connection => ?CONN,
              opts => #{base => 260}},
            #{id => general_io, module => router_general_io, connection => ?CONN,
              opts => #{base => 300}},
            #{id => drives_io, module => router_drives_io, connection => ?CONN,
              opts => #{base => 340, lanes => lanes(Machine)}}]
        %% Per lane an inspection block's UDT (seed 004, 174 holding registers) and the
        %% PLC program's side of it, which the PLC maps onto the UDT.
        ++ lists:append([[#{id => Block, module => cell_inspect_io, connection => ?CONN,
                            opts => router_inspect_io:block_opts(Base)},
                          #{id => group(inspect, L), module => router_inspect_io,
                            connection => ?CONN, opts => #{base => Mirror, block => Base}}]
                         || #{id := Block, lane := L, base := Base, mirror := Mirror}
                                <- inspect_layout(lanes(Machine))])
        ++ [#{id => group(reader, L), module => router_reader_io, connection => ?CONN,
              opts => #{base => Base}}
            || {L, Base} <- [{front, 400}, {rear, 420}], lists:member(L, lanes(Machine))],
    Readers = [#{id => reader(L), kind => code_reader, type => io,
                 opts => #{group => group(reader, L), count => read_count,
                           deadline_ms => maps:get(reader_deadline_ms, Router, 2000)}}
               || L <- lanes(Machine)],
    #{connections => [Conn], groups => Groups,
      hardware => Readers ++ lower_nc(Sim) ++ upper_nc(Sim)}.

%% The lower robot's NC: the gantry's X along the transport, Y across it to the rear
%% lane's fixture, both homed at 0 (the front fixture's corner), and the channel that
%% routes the cut lines over them. The NC is simulated (cell_hal_axis_sim) in both
%% modes: the router's PLC has no NC of its own to reach.
lower_nc(Sim) ->
    Axis = fun(Id, Max) -> axis(Id, Max, Sim, #{}) end,
    [Axis(lower_x, 600.0), Axis(lower_y, 900.0), channel(lower_xy, [lower_x, lower_y], Sim)].

%% The upper robot's NC: the gantry's X along the transport, from home over the scrap
%% bin to the module nests and on to the unloading segments, and Y across it to the
%% rear lane, both homed at 0 (home), and the channel that moves the gripper between
%% its taught positions. Simulated as the lower robot's; the NC writes the axes' actual
%% positions into the PLC's upper robot IO, where the machine's program reads where
%% the gripper is (the physics, in the simulated PLC or the virtual one).
upper_nc(Sim) ->
    Axis = fun(Id, Max, Point) ->
                   axis(Id, Max, Sim, #{publish => #{group => upper_io, position => Point,
                                                     period_ms => 50}})
           end,
    [Axis(upper_x, 1300.0, x_actual), Axis(upper_y, 900.0, y_actual),
     channel(upper_xy, [upper_x, upper_y], Sim)].

axis(Id, Max, Sim, Opts) ->
    #{id => Id, kind => axis, type => sim,
      opts => Opts#{limits => {-10.0, Max}, home_ms => 1500, time_scale => scale(Sim)}}.

channel(Id, Axes, Sim) ->
    #{id => Id, kind => channel, type => sim, opts => #{axes => Axes, time_scale => scale(Sim)}}.

scale(Sim) ->
    max(maps:get(time_scale, Sim, 1.0), 0.001).

%% @doc The inspection blocks of the machine (seed 004, {@link cell_inspect}), one per
%% lane, on the router's PLC: for the `cell_inspect' application's `blocks'.
-spec inspect_blocks([front | rear]) -> [#{id := atom(), connection := atom(), io := map()}].
inspect_blocks(Lanes) ->
    [#{id => Id, connection => ?CONN, io => #{layout => s7, base => Base}}
     || #{id := Id, base := Base} <- inspect_layout(Lanes)].

inspect_layout(Lanes) ->
    [#{id => group(inspection_block, L), lane => L, base => Base, mirror => Mirror}
     || {L, Base, Mirror} <- [{front, 480, 840}, {rear, 660, 940}], lists:member(L, Lanes)].

%% @doc What the cell's monitor ({@link cell_monitor}) watches and drives on this
%% machine: its general IO (the emergency-stop circuit, the service key, the safety
%% doors, the air, the beacon; {@link router_general_io}) and the servo drives of the
%% conveyors and the robots ({@link router_drives_io}), each with its fault bit, fault
%% code and reset.
-spec monitor(map()) -> map().
monitor(Machine) ->
    #{io => cell_spec_helpers:general_io(
              general_io, #{estop_ok => estop_ok, service_key => service_key,
                            door_locked => doors_locked, air_ok => air_ok,
                            beacon_red => beacon_red, beacon_yellow => beacon_yellow,
                            beacon_green => beacon_green, beacon_blue => beacon_blue}),
      drives => [cell_spec_helpers:drive(
                   D, drives_io, #{error => router_drives_io:point(D, fault),
                                   code => router_drives_io:point(D, code),
                                   reset => router_drives_io:point(D, reset),
                                   caption => router_drives_io:caption(D)})
                 || D <- router_drives_io:drives(lanes(Machine))]}.

%% @doc The machine's physics, for a virtual PLC that serves this cell's IO over Modbus
%% TCP ({@link cell_vplc}): the same physics simulation mode runs behind the in-VM
%% simulated PLC.
-spec simulation(map()) -> [supervisor:child_spec()].
simulation(Machine) ->
    [#{id => router_sim, start => {router_sim, start_link, [#{lanes => lanes(Machine)}]},
       shutdown => 5000}].

%% @doc What the operator can do to the simulated machine from the panel or the shell
%% (see {@link cell_machine_actions}): the emergency stop, the service key, each safety
%% door, the compressed air and each drive, carried out by the physics'
%% ({@link router_sim}) functions wherever it runs.
-spec machine_actions(map()) -> [cell_machine_actions:action()].
machine_actions(Machine) ->
    Choice = fun(Id, Caption, F, A) -> #{id => Id, caption => Caption, run => {router_sim, F, A}} end,
    [#{id => estop, caption => <<"Emergency stop">>, group => <<"Safety">>,
       choices => [Choice(press, <<"Press">>, press_estop, []),
                   Choice(release, <<"Release">>, release_estop, [])]},
     #{id => service_key, caption => <<"Service key switch">>, group => <<"Safety">>,
       choices => [Choice(service, <<"Service">>, service_key, [true]),
                   Choice(production, <<"Production">>, service_key, [false])]}]
        ++ [#{id => Id, caption => Caption, group => <<"Safety doors">>,
              choices => [Choice(open, <<"Open">>, open_door, [Door]),
                          Choice(close, <<"Close">>, close_door, [Door])]}
            || {Id, Door, Caption} <- [{door_loading, loading, <<"Loading side door">>},
                                       {door_unloading, unloading, <<"Unloading side door">>}]]
        ++ [#{id => air, caption => <<"Compressed air">>, group => <<"Air">>,
              choices => [Choice(drop, <<"Drop">>, drop_air, []),
                          Choice(restore, <<"Restore">>, restore_air, [])]}]
        ++ [#{id => drive_action(D),
              caption => <<(router_drives_io:caption(D))/binary, " drive">>,
              group => <<"Drives">>,
              choices => [Choice(fault, <<"Fault (a reset clears it)">>, fault_drive, [D, 1]),
                          Choice(fault_stuck, <<"Fault (no reset clears it)">>, fault_drive,
                                 [D, never])]}
            || D <- router_drives_io:drives(lanes(Machine))].

drive_action(conveyor_front) -> drive_conveyor_front;
drive_action(conveyor_rear) -> drive_conveyor_rear;
drive_action(lower) -> drive_lower;
drive_action(upper) -> drive_upper.

%% @doc The lanes of the machine.
-spec lanes(map()) -> [front | rear].
lanes(Machine) ->
    case cell_spec_helpers:dual_lane(Machine) of
        true -> [front, rear];
        false -> [front]
    end.

%% @doc The IO group instance of a lane's segment (`clamps': its fixture's clamps;
%% `reader': its code reader's; `inspect': the PLC program's side of the lane's
%% inspection block; `inspection_block': the block's own, its id in the inspection
%% application).
-spec group(loading | work | unloading | clamps | reader | inspect | inspection_block,
            front | rear) -> atom().
group(loading, front) -> loading_front_io;
group(loading, rear) -> loading_rear_io;
group(work, front) -> work_front_io;
group(work, rear) -> work_rear_io;
group(unloading, front) -> unloading_front_io;
group(unloading, rear) -> unloading_rear_io;
group(clamps, front) -> clamps_front_io;
group(clamps, rear) -> clamps_rear_io;
group(reader, front) -> reader_front_io;
group(reader, rear) -> reader_rear_io;
group(inspect, front) -> inspect_front_io;
group(inspect, rear) -> inspect_rear_io;
group(inspection_block, front) -> inspect_front;
group(inspection_block, rear) -> inspect_rear.

%% @doc The code reader above a lane's loading stopper (a hardware object).
-spec reader(front | rear) -> atom().
reader(front) -> reader_front;
reader(rear) -> reader_rear.

module(loading) -> router_loading_io;
module(work) -> router_work_io;
module(unloading) -> router_unloading_io.

%% @doc The device task of a lane's segment, or the unit of its fixture's clamps.
-spec task(loading | work | unloading | clamps, front | rear) -> atom().
task(loading, front) -> loading_front;
task(loading, rear) -> loading_rear;
task(work, front) -> work_front;
task(work, rear) -> work_rear;
task(unloading, front) -> unloading_front;
task(unloading, rear) -> unloading_rear;
task(clamps, front) -> clamps_front;
task(clamps, rear) -> clamps_rear.

link(load_work, front) -> load_work_front;
link(load_work, rear) -> load_work_rear;
link(work_route, front) -> work_route_front;
link(work_route, rear) -> work_route_rear;
link(pick_unload, front) -> pick_unload_front;
link(pick_unload, rear) -> pick_unload_rear.

lane_name(front) -> <<"Front">>;
lane_name(rear) -> <<"Rear">>.

%% @doc The router settings as saved (the controller is not running yet when the cell
%% spec is built).
-spec router_settings() -> map().
router_settings() ->
    cell_spec_helpers:saved_settings(router_settings).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

machine_actions_test_() ->
    Ids = fun(Machine) ->
                  {ok, As} = cell_machine_actions:check(machine_actions(Machine)),
                  [Id || #{id := Id} <- As]
          end,
    [?_assertEqual([estop, service_key, door_loading, door_unloading, air,
                    drive_conveyor_front, drive_lower, drive_upper],
                   Ids(#{dual_lane => false})),
     ?_assert(lists:member(drive_conveyor_rear, Ids(#{dual_lane => true}))),
     %% Every choice runs an export of the physics.
     ?_assertEqual({module, router_sim}, code:ensure_loaded(router_sim)),
     ?_assertEqual([], [R || #{choices := Cs} <- machine_actions(#{dual_lane => true}),
                             #{run := {M, F, A} = R} <- Cs,
                             not erlang:function_exported(M, F, length(A))])].

%% On the real PLC every point of both lanes has addresses of its own: no two groups'
%% windows overlap in any Modbus table.
modbus_map_without_overlap_test() ->
    Machine = #{simulation_mode => false, dual_lane => true},
    Router = #{plc_host => <<"127.0.0.1">>, plc_port => 502, plc_unit => 1},
    #{groups := Groups, hardware := Hw} = hal(Machine, Router),
    Used = lists:append(
             [[{Table, A} || {Table, At, N} <- [span(F, T)], A <- lists:seq(At, At + N - 1)]
              || #{module := M} = G <- Groups,
                 #{field := F, type := T} <- M:points(maps:get(opts, G, #{}))]),
    ?assertEqual([], Used -- lists:usort(Used)),
    %% A code reader per lane, on its lane's reader group.
    ?assertEqual([{reader_front, reader_front_io}, {reader_rear, reader_rear_io}],
                 [{Id, G} || #{id := Id, type := io, opts := #{group := G}} <- Hw]).

span({Table, A}, _) when Table =:= coil; Table =:= discrete_input -> {Table, A, 1};
span({Table, A}, T) -> {Table, A, cell_hal_type_codec:registers(T)};
%% Booleans packed into a register's bits (an inspection block's UDT) share it.
span({Table, A, Bit}, _) -> {{Table, A}, Bit, 1}.
-endif.
