%% @doc The cell's own settings object, `Settings/__NAME__.json': what the line
%% produces, its watchdogs, where the real PLC is, and how the simulation behaves.
%% The tasks run on the snapshot taken at Start; `plc_*' and `hal_poll_ms' are read
%% when the cell boots (the HAL is connected then).
%%
%% The operator panel shows the line, the errors, the log and the users, not this
%% object: it is read and changed over the panel's REST API (`GET /api/settings/__NAME__',
%% `PUT /api/settings/__NAME__' with the fields to change as JSON, by a `service' user)
%% or in the node (`bin/__NAME__ remote_console'):
%% `cell_settings:put(__NAME__, #{stroke_timeout_ms => 4000}, <<"your name">>)', which
%% `cell_settings:get(__NAME__)' reads back. A value out of range is refused with its
%% field named and nothing changed; every change is a revision with who and when.
-module(__NAME___settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> __NAME__.
name() -> __NAME__.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => recipe, type => {string, 64}, default => <<"demo-part">>,
       doc => <<"The recipe (part type) the line produces.">>},
     #{name => serial_prefix, type => {string, 16}, default => <<"P">>,
       doc => <<"What every serial the infeed gives begins with.">>},
     #{name => transfer_timeout_ms, type => {integer, 100, 600000}, default => 5000,
       unit => <<"ms">>,
       doc => <<"How long a part may take from the infeed into the press, or out of it.">>},
     #{name => stroke_timeout_ms, type => {integer, 100, 600000}, default => 3000,
       unit => <<"ms">>,
       doc => <<"How long the ram may take to reach the bottom of its stroke.">>},
     #{name => plc_host, type => {string, 255}, default => <<"192.168.0.10">>,
       doc => <<"Address of the PLC (Modbus TCP) when simulation mode is off; read when "
                "the cell boots.">>},
     #{name => plc_port, type => {integer, 1, 65535}, default => 502,
       doc => <<"Modbus TCP port of the PLC; read when the cell boots.">>},
     #{name => plc_unit, type => {integer, 0, 255}, default => 1,
       doc => <<"Modbus unit id of the PLC; read when the cell boots.">>},
     #{name => hal_poll_ms, type => {integer, 1, 1000}, default => 20, unit => <<"ms">>,
       doc => <<"How often the PLC's inputs are read; read when the cell boots.">>},
     #{name => sim_arrival_ms, type => {integer, 0, 600000}, default => 1500,
       unit => <<"ms">>,
       doc => <<"Simulation: how long after the infeed emptied the next part arrives.">>},
     #{name => sim_time_scale, type => {float, 0.0, 100.0}, default => 1.0,
       doc => <<"Simulation: every duration of the machine is multiplied by this.">>},
     #{name => sim_stick_rate, type => {float, 0.0, 1.0}, default => 0.0,
       doc => <<"Simulation: how often the ram sticks before the bottom of its stroke "
                "(0: never, 1: every stroke).">>}].
