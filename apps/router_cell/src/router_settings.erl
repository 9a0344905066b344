%% @doc The router's own settings object, `Settings/router.json' (seed 000 §3.1): what
%% each lane produces, the watchdogs and speeds the device tasks use, and where the
%% real PLC is. The tasks run on the snapshot taken at Start; `plc_*', `hal_poll_ms'
%% and `reader_deadline_ms' are read when the cell boots (the HAL is connected then).
-module(router_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> router.
name() -> router.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => recipe_front, type => {string, 64}, default => <<"demo-2x2">>,
       doc => <<"The recipe (panel type) the front lane produces.">>},
     #{name => recipe_rear, type => {string, 64}, default => <<"demo-3x1">>,
       doc => <<"The recipe the rear lane produces (dual lane only).">>},
     #{name => transfer_timeout_ms, type => {integer, 500, 600000}, default => 10000,
       unit => <<"ms">>,
       doc => <<"How long a conveyor may take to move a panel to its next sensor before "
                "the task reports a jam.">>},
     #{name => motion_timeout_ms, type => {integer, 500, 600000}, default => 30000,
       unit => <<"ms">>,
       doc => <<"How long a robot move, a gripper or the clamps may take before the task "
                "reports it.">>},
     #{name => clamp_timeout_ms, type => {integer, 100, 60000}, default => 3000,
       unit => <<"ms">>,
       doc => <<"How long a fixture clamp may take to close or open before its unit stops "
                "on a fault; read when the cell boots.">>},
     #{name => inspection, type => boolean, default => true,
       doc => <<"The modules are inspected by the camera at each unloading exit (the "
                "lane's inspection block) before they leave; off: they leave uninspected.">>},
     #{name => inspection_timeout_ms, type => {integer, 500, 600000}, default => 10000,
       unit => <<"ms">>,
       doc => <<"How long the inspection block may take to answer one step of an "
                "inspection; longer: the modules leave marked failed, not inspected.">>},
     #{name => feed_rate, type => {float, 1.0, 500.0}, default => 25.0, unit => <<"mm/s">>,
       doc => <<"Routing feed for cut lines whose recipe gives none (attribute Feed).">>},
     #{name => rapid_speed, type => {float, 1.0, 2000.0}, default => 400.0, unit => <<"mm/s">>,
       doc => <<"Speed of the routing robot between cuts, the router bit lifted.">>},
     #{name => rear_lane_offset, type => {float, 0.0, 2000.0}, default => 350.0,
       unit => <<"mm">>,
       doc => <<"Distance from the front lane's fixture to the rear lane's, across the "
                "transport direction (for both robots).">>},
     #{name => upper_nest_x, type => {float, 0.0, 2000.0}, default => 250.0, unit => <<"mm">>,
       doc => <<"The upper robot's taught X over the module nests of the fixtures (its X "
                "runs along the transport from home, 0).">>},
     #{name => upper_unloading_x, type => {float, 0.0, 2000.0}, default => 1100.0,
       unit => <<"mm">>,
       doc => <<"The upper robot's taught X over the unloading segments.">>},
     #{name => upper_front_y, type => {float, 0.0, 1000.0}, default => 150.0, unit => <<"mm">>,
       doc => <<"The upper robot's taught Y over the front lane (its Y runs across the "
                "transport from home, 0; the rear lane lies `rear_lane_offset' further).">>},
     #{name => upper_speed, type => {float, 1.0, 3000.0}, default => 1000.0,
       unit => <<"mm/s">>,
       doc => <<"Speed of the upper robot between its taught positions.">>},
     #{name => plc_host, type => {string, 255}, default => <<"192.168.0.10">>,
       doc => <<"Address of the router's PLC (Modbus TCP) when simulation mode is off; "
                "read when the cell boots.">>},
     #{name => plc_port, type => {integer, 1, 65535}, default => 502,
       doc => <<"Modbus TCP port of the PLC; read when the cell boots.">>},
     #{name => plc_unit, type => {integer, 0, 255}, default => 1,
       doc => <<"Modbus unit id of the PLC; read when the cell boots.">>},
     #{name => hal_poll_ms, type => {integer, 1, 1000}, default => 20, unit => <<"ms">>,
       doc => <<"How often the PLC's inputs are read; read when the cell boots.">>},
     #{name => reader_deadline_ms, type => {integer, 100, 60000}, default => 2000,
       unit => <<"ms">>,
       doc => <<"How long a code reader may take to answer its trigger before the read "
                "fails; read when the cell boots.">>}].
