%% IO groups for the monitor's tests, laid out as a Modbus PLC would hold them (the
%% simulated PLC keeps each point apart by name, whatever its field): `#{part =>
%% general}' the general IO (emergency-stop voltage, service key, door lock, air
%% pressure, the four beacon lamps), `#{part => axes}' one servo drive's status bits,
%% error code, reset output and speed override.
-module(cell_monitor_test_io).
-behaviour(cell_hal_group).

-export([points/1]).

points(#{part := general}) ->
    [in(estop_voltage, <<"A1.01.00">>, <<"Emergency-stop circuit has voltage">>, 0),
     in(service_key, <<"A1.01.01">>, <<"Service key switch">>, 1),
     in(door_locked, <<"A1.01.02">>, <<"Doors locked">>, 2),
     in(air_ok, <<"A1.01.03">>, <<"Air pressure above minimum">>, 3),
     out(beacon_red, <<"A1.20.00">>, <<"Beacon red">>, 0),
     out(beacon_yellow, <<"A1.20.01">>, <<"Beacon yellow">>, 1),
     out(beacon_green, <<"A1.20.02">>, <<"Beacon green">>, 2),
     out(beacon_blue, <<"A1.20.03">>, <<"Beacon blue">>, 3)];
points(#{part := axes}) ->
    [in(x_error, <<"A2.01.00">>, <<"X drive error">>, 8),
     in(x_warning, <<"A2.01.01">>, <<"X drive warning">>, 9),
     #{name => x_code, dir => in, type => uint16, address => <<"A2.IW0">>,
       caption => <<"X drive error code">>, field => {input_register, 0}},
     out(x_reset, <<"A2.20.00">>, <<"X drive reset">>, 8),
     #{name => x_override, dir => out, type => int16, address => <<"A2.QW0">>,
       caption => <<"X axis speed override (%)">>, field => {holding_register, 0}},
     #{name => y_override, dir => out, type => lreal, address => <<"A2.QW4">>,
       caption => <<"Y axis velocity factor (0..1)">>, field => {holding_register, 4}}].

in(Name, Address, Caption, Bit) ->
    #{name => Name, dir => in, type => bool, address => Address, caption => Caption,
      field => {discrete_input, Bit}}.

out(Name, Address, Caption, Bit) ->
    #{name => Name, dir => out, type => bool, address => Address, caption => Caption,
      field => {coil, Bit}}.
