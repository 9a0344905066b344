%% @doc The functions a cell spec is written with: the machine settings as saved, the
%% choice between simulated and real IO that the machine setting `simulation_mode'
%% makes, and the declarations of the monitor's general IO and drives, of device
%% tasks, units and hardware objects. A cell's module calls them from its
%% `cell_spec/0' ({@link cell_spec}):
%%
%% ```
%% cell_spec() ->
%%     Machine = cell_spec_helpers:machine_settings(),
%%     Plc = cell_spec_helpers:saved_settings(my_plc_settings),
%%     #{name => <<"Press">>,
%%       tasks => [cell_spec_helpers:task(feeder, my_feeder_task,
%%                                        #{zone => <<"Feeder">>, lane => <<"Front">>,
%%                                          io => [feeder_io]}),
%%                 cell_spec_helpers:unit(picker, my_picker_unit,
%%                                        #{zone => <<"Picker">>, lane => <<"Front">>,
%%                                          io => [picker_io]})],
%%       settings => [my_plc_settings],
%%       hal => #{connections =>
%%                    [cell_spec_helpers:connection(
%%                       plc, Machine,
%%                       #{real => {cell_hal_modbus, #{host => binary_to_list(maps:get(host, Plc))}},
%%                         opts => #{poll_ms => 20}})],
%%                groups => [#{id => feeder_io, module => my_feeder_io, connection => plc},
%%                           #{id => picker_io, module => my_picker_io, connection => plc},
%%                           #{id => general, module => my_general_io, connection => plc}],
%%                hardware => [cell_spec_helpers:hardware(
%%                               camera, camera, Machine,
%%                               #{real => {gige, #{address => "10.0.0.7"}}})]},
%%       monitor => #{io => cell_spec_helpers:general_io(
%%                            general, #{estop_ok => estop_voltage, service_key => key,
%%                                       door_locked => doors, air_ok => air}),
%%                    drives => [cell_spec_helpers:drive(
%%                                 press, general, #{error => press_fault,
%%                                                   reset => press_reset})]}}.
%% '''
%%
%% They only build: what they return is checked, with the rest of the spec, by {@link
%% cell_spec:validate/1} at boot (a unit test of one's cell calls it too). The two that
%% state what the spec cannot tell by itself, {@link task/3} and {@link unit/3}, raise
%% `{bad_task, Id, Why}' when the module is of the other kind; {@link cell_spec:load/0}
%% returns that as the checks' own errors.
%%
%% An IO group follows its connection: the same group module runs on the simulated PLC
%% or on the real one, so a task never knows which. To bind a group to another
%% connection in simulation, choose its connection with {@link sim_or_real/3}.
%%
%% They live in a module of their own, not in {@link cell_spec}, because they are the
%% cell author's side of the spec while `cell_spec' is the runtime's (loading and
%% checking it at boot): a cell author reads this one module.
%%
%% This module is public API: its functions, their arguments and their results change
%% only in a release that says so, as the behaviours a cell implements ({@link
%% cell_task}, {@link cell_unit}, {@link cell_settings_schema}, {@link
%% cell_hal_group}) do.
-module(cell_spec_helpers).

-export([machine_settings/0, saved_settings/1, simulated/1, dual_lane/1,
         is_configured_cell/1]).
-export([sim_or_real/3, connection/3, hardware/4]).
-export([general_io/2, drive/3]).
-export([task/3, unit/3]).

-export_type([machine/0, io_choice/0, hardware_choice/0]).

-type machine() :: map().
%% The machine settings ({@link cell_machine_settings}): `simulation_mode',
%% `dual_lane', `cell_name', ...

-type io_choice() :: #{real := {module(), map()}, sim => map(), opts => map()}.
%% `real': the driver and its options on the machine; `sim': the simulated PLC's
%% options ({@link cell_hal_sim}; default none); `opts': options of either (the HAL
%% worker's, as `poll_ms').

-type hardware_choice() :: #{real := {atom(), map()} | none, sim => map() | none}.
%% `real': the type and options of the object on the machine, or `none' (the machine
%% has none); `sim': the simulated object's options (default none), or `none'.

-type point_name() :: atom() | cell_monitor_spec:point().
%% A point of the group named beside it, or `{Group, Point}' of another group.

%%====================================================================
%% Machine settings
%%====================================================================

%% @doc The machine settings as saved in `Settings/machine.json', which is what a spec
%% is built from: the controller, which owns the settings, starts after the spec is
%% read. A missing file gives the defaults, and so does a file that does not validate
%% (the settings' owner says so in the log when it loads it).
%%
%% ```
%% Machine = cell_spec_helpers:machine_settings(),
%% Lanes = case cell_spec_helpers:dual_lane(Machine) of
%%             true -> [front, rear];
%%             false -> [front]
%%         end.
%% '''
-spec machine_settings() -> machine().
machine_settings() ->
    saved_settings(cell_machine_settings).

%% @doc A settings object as saved in `Settings/<name>.json', or its defaults (as
%% {@link machine_settings/0}): the cell's own settings a spec needs, such as the
%% address of its PLC. `Schema' is the object's {@link cell_settings_schema} module.
%%
%% ```
%% #{plc_host := Host} = cell_spec_helpers:saved_settings(my_plc_settings).
%% '''
-spec saved_settings(module()) -> map().
saved_settings(Schema) ->
    Path = filename:join(cell_config:dir(settings), atom_to_list(Schema:name()) ++ ".json"),
    case file:read_file(Path) of
        {ok, Bin} ->
            case cell_settings_schema:from_json(Schema, Bin) of
                {ok, Obj} -> Obj;
                {error, _} -> cell_settings_schema:defaults(Schema)
            end;
        {error, _} ->
            cell_settings_schema:defaults(Schema)
    end.

%% @doc Whether the machine settings say to run simulated (`simulation_mode'; a map
%% without it takes the setting's default).
%%
%% ```
%% true = cell_spec_helpers:simulated(#{simulation_mode => true}).
%% '''
-spec simulated(machine()) -> boolean().
simulated(Machine) ->
    setting(simulation_mode, Machine).

%% @doc Whether the machine has a rear lane as well as the front lane (`dual_lane';
%% a map without it takes the setting's default).
%%
%% ```
%% false = cell_spec_helpers:dual_lane(#{dual_lane => false}).
%% '''
-spec dual_lane(machine()) -> boolean().
dual_lane(Machine) ->
    setting(dual_lane, Machine).

setting(Key, Machine) ->
    case maps:find(Key, Machine) of
        {ok, V} when is_boolean(V) -> V;
        {ok, V} -> erlang:error({bad_machine_setting, Key, V});
        error -> maps:get(Key, cell_settings_schema:defaults(cell_machine_settings))
    end.

%% @doc Whether `Module' is the cell the runtime runs (the `cell' application's
%% `cell_module', `CELLRT_CELL'): a cell's application starts its simulation or its
%% demo data only then.
%%
%% ```
%% start(_Type, _Args) ->
%%     Mine = cell_spec_helpers:is_configured_cell(my_cell),
%%     my_cell_sup:start_link(Mine andalso
%%                            cell_spec_helpers:simulated(cell_spec_helpers:machine_settings())).
%% '''
-spec is_configured_cell(module()) -> boolean().
is_configured_cell(Module) when is_atom(Module) ->
    Name = atom_to_list(Module),
    case cell_config:get(cell, cell_module, undefined) of
        Module -> true;
        Name -> true;
        Bin when is_binary(Bin) -> Bin =:= list_to_binary(Name);
        _ -> false
    end.

%%====================================================================
%% Simulated or real
%%====================================================================

%% @doc `Sim' when the machine settings say simulation, `Real' otherwise: for
%% whatever else differs between the two (a group's connection, a task's args).
%%
%% ```
%% Conn = cell_spec_helpers:sim_or_real(Machine, sim_plc, plc2).
%% '''
-spec sim_or_real(machine(), Sim, Real) -> Sim | Real.
sim_or_real(Machine, Sim, Real) ->
    case simulated(Machine) of
        true -> Sim;
        false -> Real
    end.

%% @doc A connection of the `hal' key: to a simulated PLC ({@link cell_hal_sim}, the
%% device named as the connection) when the machine settings say simulation,
%% otherwise to the real one through its driver. The IO groups bound to it are the
%% same either way.
%%
%% ```
%% cell_spec_helpers:connection(plc, Machine,
%%     #{real => {cell_hal_modbus, #{host => "10.0.0.5", port => 502}},
%%       sim => #{latency_ms => 2},
%%       opts => #{poll_ms => 20}})
%% %% simulated: #{id => plc, driver => cell_hal_sim,
%% %%              opts => #{latency_ms => 2, poll_ms => 20}}
%% '''
-spec connection(atom(), machine(), io_choice()) -> cell_hal:connection_spec().
connection(Id, Machine, #{real := {Driver, RealOpts}} = Choice)
  when is_atom(Id), is_atom(Driver), is_map(RealOpts) ->
    Common = maps:get(opts, Choice, #{}),
    case simulated(Machine) of
        true -> #{id => Id, driver => cell_hal_sim,
                  opts => maps:merge(Common, maps:get(sim, Choice, #{}))};
        false -> #{id => Id, driver => Driver, opts => maps:merge(Common, RealOpts)}
    end.

%% @doc A hardware object of the `hal' key ({@link cell_hal_hw}): the built-in
%% simulated one of its kind when the machine settings say simulation, otherwise the
%% machine's own type (one the cell registers in the `hardware_types' of the
%% `cell_hal' application, here `#{{camera, gige} => my_gige_camera}'); `none' where
%% there is no such object. Run real, a `real' that is neither raises `{bad_hardware, Id,
%% {bad_option, real}}'.
%%
%% ```
%% cell_spec_helpers:hardware(top_camera, camera, Machine,
%%     #{real => {gige, #{address => "10.0.0.7"}}, sim => #{width => 320}})
%% %% simulated: #{id => top_camera, kind => camera, type => sim, opts => #{width => 320}}
%% '''
-spec hardware(atom(), cell_hal_hw:kind(), machine(), hardware_choice()) -> cell_hal_hw:spec().
hardware(Id, Kind, Machine, #{real := Real} = Choice) when is_atom(Id), is_atom(Kind) ->
    Chosen = case simulated(Machine) of
                 true ->
                     case maps:get(sim, Choice, #{}) of
                         none -> none;
                         Opts when is_map(Opts) -> {sim, Opts}
                     end;
                 false ->
                     Real
             end,
    case Chosen of
        none -> #{id => Id, kind => Kind, type => none};
        {Type, TypeOpts} when is_atom(Type), is_map(TypeOpts) ->
            #{id => Id, kind => Kind, type => Type, opts => TypeOpts};
        _ ->
            erlang:error({bad_hardware, Id, {bad_option, real}})
    end.

%%====================================================================
%% The monitor
%%====================================================================

%% @doc The `io' of the `monitor' key: the roles of the general IO (see {@link
%% cell_monitor_spec}: the inputs `estop_ok', `service_key', `door_locked', `air_ok';
%% the outputs `beacon_red', `beacon_yellow', `beacon_green', `beacon_blue'), each
%% bound to a point of `Group' or, given as `{Group2, Point}', of another group.
%%
%% ```
%% #{estop_ok := {general, estop_voltage}, beacon_red := {lamps, red}} =
%%     cell_spec_helpers:general_io(general, #{estop_ok => estop_voltage,
%%                                             beacon_red => {lamps, red}}).
%% '''
-spec general_io(atom(), #{cell_monitor_spec:role() => point_name()}) ->
          #{cell_monitor_spec:role() => cell_monitor_spec:point()}.
general_io(Group, Roles) when is_atom(Group), is_map(Roles) ->
    maps:map(fun(_Role, P) -> point(Group, P) end, Roles).

%% @doc A drive the monitor watches: its points (`error', `warning', `code', `reset',
%% `override') in `Group' (or `{Group2, Point}'), and its `caption' and
%% `override_scale' as given.
%%
%% ```
%% #{id := x_axis, error := {axes, x_error}, caption := <<"X axis">>} =
%%     cell_spec_helpers:drive(x_axis, axes, #{error => x_error, reset => x_reset,
%%                                             caption => <<"X axis">>}).
%% '''
-spec drive(atom(), atom(), #{error | warning | code | reset | override => point_name(),
                              caption => binary(), override_scale => number()}) -> map().
drive(Id, Group, Opts) when is_atom(Id), is_atom(Group), is_map(Opts) ->
    Points = [error, warning, code, reset, override],
    maps:map(fun(K, V) ->
                     case lists:member(K, Points) of
                         true -> point(Group, V);
                         false -> V
                     end
             end, Opts#{id => Id}).

point(_Group, {G, P}) when is_atom(G), is_atom(P) -> {G, P};
point(Group, P) when is_atom(P) -> {Group, P}.

%%====================================================================
%% Tasks and units
%%====================================================================

%% @doc A device task ({@link cell_task}) of the spec: `Opts' holds its `zone' and
%% `lane' and, optionally, `io', `settings' and `args' (see {@link cell_spec}).
%% Raises `{bad_task, Id, {not_a_device_task, Module}}' for a unit's module.
%%
%% ```
%% cell_spec_helpers:task(feeder, my_feeder_task,
%%                        #{zone => <<"Feeder">>, lane => <<"Front">>, io => [feeder_io]})
%% '''
-spec task(atom(), module(), map()) -> cell_task:spec().
task(Id, Module, Opts) when is_atom(Id), is_atom(Module), is_map(Opts) ->
    case cell_unit:is_unit_module(Module) of
        true -> erlang:error({bad_task, Id, {not_a_device_task, Module}});
        false -> Opts#{id => Id, module => Module}
    end.

%% @doc A unit ({@link cell_unit}) of the spec, declared as a task is (`zone', `lane',
%% `io', `settings', `args'). Raises `{bad_task, Id, {not_a_unit, Module}}' when the
%% module exports no `unit/1': the spec's checks tell units from device tasks by their
%% callbacks, so a device task's module would otherwise run as one, unnoticed.
%%
%% ```
%% cell_spec_helpers:unit(picker, my_picker_unit,
%%                        #{zone => <<"Picker">>, lane => <<"Front">>, io => [picker_io],
%%                          args => #{pick_delay_ms => 500}})
%% '''
-spec unit(atom(), module(), map()) -> cell_task:spec().
unit(Id, Module, Opts) when is_atom(Id), is_atom(Module), is_map(Opts) ->
    case cell_unit:is_unit_module(Module) of
        true -> Opts#{id => Id, module => Module};
        false -> erlang:error({bad_task, Id, {not_a_unit, Module}})
    end.
