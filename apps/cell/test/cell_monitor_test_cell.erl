%% @doc The cell the monitor's tests run: a PLC simulated by the HAL (`plc1', the
%% general IO and the drives of cell_monitor_test_io), a simulated camera, and the
%% monitor's map of roles to points. Shared by cell_monitor_SUITE and
%% prop_cell_monitor_proc.
-module(cell_monitor_test_cell).

-export([hal/1, hal/2, monitor/0]).

%% The HAL's part of the cell spec; `Extra' connections besides `plc1'.
-spec hal([map()]) -> map().
hal(Extra) ->
    hal(Extra, #{}).

%% The same, with `plc1''s options changed by `PlcOpts' (its poll period, say).
-spec hal([map()], map()) -> map().
hal(Extra, PlcOpts) ->
    Opts = #{poll_ms => 10, reconnect_ms => 50, max_reconnect_ms => 200, timeout_ms => 500},
    Conns = [#{id => plc1, driver => cell_hal_sim, opts => maps:merge(Opts, PlcOpts)}
             | Extra],
    #{connections => Conns,
      groups => [#{id => general, module => cell_monitor_test_io, connection => plc1,
                   opts => #{part => general}},
                 #{id => axes, module => cell_monitor_test_io, connection => plc1,
                   opts => #{part => axes}}],
      hardware => [#{id => camera, kind => camera, type => sim, opts => #{exposure_ms => 1}},
                   #{id => reader, kind => code_reader, type => none}]}.

%% The monitor's part: the general IO's roles and two drives, X with every point.
-spec monitor() -> map().
monitor() ->
    #{io => #{estop_ok => {general, estop_voltage}, service_key => {general, service_key},
              door_locked => {general, door_locked}, air_ok => {general, air_ok},
              beacon_red => {general, beacon_red}, beacon_yellow => {general, beacon_yellow},
              beacon_green => {general, beacon_green}, beacon_blue => {general, beacon_blue}},
      drives => [#{id => x_axis, caption => <<"X axis">>, error => {axes, x_error},
                   warning => {axes, x_warning}, code => {axes, x_code},
                   reset => {axes, x_reset}, override => {axes, x_override}},
                 #{id => y_axis, caption => <<"Y axis">>, override => {axes, y_override},
                   override_scale => 0.01}]}.
