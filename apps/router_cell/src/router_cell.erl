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
%% through the PLC's IO, {@link cell_hal_code_reader_io}), a work segment with the routing fixture, an unloading conveyor
%% segment. Shared by the lanes: the lower routing robot, which routes the panel in
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

-export([cell_spec/0, cell_spec/2, hal/2, monitor/1, lanes/1, group/2, task/2, reader/1,
         router_settings/0, simulation/1]).

-define(CONN, router_plc).

%% @doc The cell spec, from the settings files as they are at boot.
-spec cell_spec() -> map().
cell_spec() ->
    cell_spec(cell_spec_helpers:machine_settings(), router_settings()).

%% @doc The cell spec for given machine and router settings.
-spec cell_spec(map(), map()) -> map().
cell_spec(Machine, Router) ->
    Lanes = lanes(Machine),
    LaneTasks = lists:append([lane_tasks(L) || L <- Lanes]),
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

lane_tasks(L) ->
    Lane = lane_name(L),
    [#{id => task(loading, L), module => router_loading_task, zone => <<"Loading">>,
       lane => Lane, io => [group(loading, L)], settings => router,
       args => #{lane => L, next => link(load_work, L), reader => reader(L)}},
     #{id => task(work, L), module => router_work_task, zone => <<"Work">>, lane => Lane,
       %% The loading stopper's and the gripper's sensors read too: they tell whose a
       %% panel in the fixture that the segment holds no record of is.
       io => [group(work, L), group(loading, L), upper_io], settings => router,
       args => #{lane => L, prev => link(load_work, L), next => link(work_route, L)}},
     #{id => task(unloading, L), module => router_unloading_task, zone => <<"Unloading">>,
       %% The gripper's sensor read too: modules in it are not on this conveyor.
       lane => Lane, io => [group(unloading, L), upper_io], settings => router,
       args => #{lane => L, prev => link(pick_unload, L)}}].

%% @doc The HAL configuration of the cell: one PLC connection (simulated or Modbus
%% TCP), the IO group instances bound to it, and the code readers, wired through the
%% PLC's IO in simulation and on the real machine alike.
-spec hal(map(), map()) -> #{connections := [cell_hal:connection_spec()],
                             groups := [cell_hal:group_spec()],
                             hardware := [cell_hal_hw:spec()]}.
hal(Machine, Router) ->
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
        ++ [#{id => lower_io, module => router_lower_io, connection => ?CONN,
              opts => #{base => 200}},
            #{id => upper_io, module => router_upper_io, connection => ?CONN,
              opts => #{base => 260}},
            #{id => general_io, module => router_general_io, connection => ?CONN,
              opts => #{base => 300}},
            #{id => drives_io, module => router_drives_io, connection => ?CONN,
              opts => #{base => 340, lanes => lanes(Machine)}}]
        ++ [#{id => group(reader, L), module => router_reader_io, connection => ?CONN,
              opts => #{base => Base}}
            || {L, Base} <- [{front, 400}, {rear, 420}], lists:member(L, lanes(Machine))],
    Readers = [#{id => reader(L), kind => code_reader, type => io,
                 opts => #{group => group(reader, L), count => read_count,
                           deadline_ms => maps:get(reader_deadline_ms, Router, 2000)}}
               || L <- lanes(Machine)],
    #{connections => [Conn], groups => Groups, hardware => Readers}.

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

%% @doc The lanes of the machine.
-spec lanes(map()) -> [front | rear].
lanes(Machine) ->
    case cell_spec_helpers:dual_lane(Machine) of
        true -> [front, rear];
        false -> [front]
    end.

%% @doc The IO group instance of a lane's segment (or of its code reader).
-spec group(loading | work | unloading | reader, front | rear) -> atom().
group(loading, front) -> loading_front_io;
group(loading, rear) -> loading_rear_io;
group(work, front) -> work_front_io;
group(work, rear) -> work_rear_io;
group(unloading, front) -> unloading_front_io;
group(unloading, rear) -> unloading_rear_io;
group(reader, front) -> reader_front_io;
group(reader, rear) -> reader_rear_io.

%% @doc The code reader above a lane's loading stopper (a hardware object).
-spec reader(front | rear) -> atom().
reader(front) -> reader_front;
reader(rear) -> reader_rear.

module(loading) -> router_loading_io;
module(work) -> router_work_io;
module(unloading) -> router_unloading_io.

%% @doc The device task of a lane's segment.
-spec task(loading | work | unloading, front | rear) -> atom().
task(loading, front) -> loading_front;
task(loading, rear) -> loading_rear;
task(work, front) -> work_front;
task(work, rear) -> work_rear;
task(unloading, front) -> unloading_front;
task(unloading, rear) -> unloading_rear.

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
span({Table, A, _Bit}, _) -> {Table, A, 1}.
-endif.
