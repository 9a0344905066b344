%% @doc The simulated router's physics and the faults it injects,
%% `Settings/router_sim.json'. Read by the simulation as it goes: a change applies at
%% once. Times are those of the real machine; `time_scale' stretches or shrinks all of
%% them (0: no physical delay at all, the runtime's own ceiling).
-module(router_sim_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> router_sim.
name() -> router_sim.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => time_scale, type => {float, 0.0, 100.0}, default => 1.0,
       doc => <<"Every physical delay is multiplied by this (0: none); the robots' "
                "simulated axes take it when the cell boots.">>},
     #{name => arrival_ms, type => {integer, 0, 3600000}, default => 15000, unit => <<"ms">>,
       doc => <<"Mean time between two panels reaching the previous machine's output, per "
                "lane (0: a panel is always waiting).">>},
     #{name => arrival_jitter, type => {float, 0.0, 1.0}, default => 0.3,
       doc => <<"How irregular arrivals are: 0 a fixed rhythm, 1 anywhere between none "
                "and twice the mean.">>},
     #{name => upstream_capacity, type => {integer, 1, 1000}, default => 5,
       doc => <<"Panels the previous machine holds for the router before it stops.">>},
     #{name => intake_ms, type => {integer, 0, 600000}, default => 2500, unit => <<"ms">>,
       doc => <<"A panel from the previous machine to the loading segment's stopper.">>},
     #{name => transfer_ms, type => {integer, 0, 600000}, default => 2000, unit => <<"ms">>,
       doc => <<"A panel from the loading segment into the routing fixture.">>},
     #{name => clamp_ms, type => {integer, 0, 60000}, default => 400, unit => <<"ms">>,
       doc => <<"The fixture's clamps closing or opening.">>},
     #{name => eject_ms, type => {integer, 0, 600000}, default => 1500, unit => <<"ms">>,
       doc => <<"The panel's frame out of the fixture into the waste bin.">>},
     #{name => spindle_ramp_ms, type => {integer, 0, 60000}, default => 800, unit => <<"ms">>,
       doc => <<"The spindle reaching its speed.">>},
     #{name => plunge_ms, type => {integer, 0, 60000}, default => 250, unit => <<"ms">>,
       doc => <<"The router bit moving down to cutting depth or back up.">>},
     #{name => gripper_ms, type => {integer, 0, 60000}, default => 300, unit => <<"ms">>,
       doc => <<"The gripper closing or opening.">>},
     #{name => unload_ms, type => {integer, 0, 600000}, default => 2500, unit => <<"ms">>,
       doc => <<"Modules from the unloading segment's entry to its exit.">>},
     #{name => handout_ms, type => {integer, 0, 600000}, default => 1500, unit => <<"ms">>,
       doc => <<"Modules from the exit into the next machine.">>},
     #{name => downstream_busy_ms, type => {integer, 0, 3600000}, default => 2000,
       unit => <<"ms">>,
       doc => <<"How long the next machine is not ready after taking modules.">>},
     #{name => product_lost_rate, type => {float, 0.0, 1.0}, default => 0.03,
       doc => <<"Chance that modules slip in the upper robot's gripper on a move (the "
                "\"Product lost\" error).">>},
     #{name => reseat_ms, type => {integer, 0, 3600000}, default => 4000, unit => <<"ms">>,
       doc => <<"How long slipped modules take to be seated again (the operator's hand): "
                "Retry before that finds them still missing.">>},
     #{name => nest_stick_rate, type => {float, 0.0, 1.0}, default => 0.0,
       doc => <<"Chance that the modules stay stuck in the module nest as the upper robot "
                "lifts them: the gripper comes away empty (the \"Product lost\" error with "
                "the modules still in the machine).">>},
     #{name => read_ms, type => {integer, 0, 60000}, default => 150, unit => <<"ms">>,
       doc => <<"The code reader decoding a panel's label after its trigger.">>},
     #{name => no_read_rate, type => {float, 0.0, 1.0}, default => 0.02,
       doc => <<"Chance that the code reader finds no code on a panel's label (the "
                "\"Code not read\" error the operator answers).">>},
     #{name => jam_rate, type => {float, 0.0, 1.0}, default => 0.01,
       doc => <<"Chance that a panel sticks on a conveyor move (the \"Conveyor jam\" "
                "error).">>},
     #{name => jam_ms, type => {integer, 0, 3600000}, default => 15000, unit => <<"ms">>,
       doc => <<"How long a stuck panel stays stuck.">>},
     #{name => magazine_low_s, type => {integer, 0, 86400}, default => 300, unit => <<"s">>,
       doc => <<"Mean time between the previous machine's panel magazine running low (a "
                "warning; 0: never).">>},
     #{name => magazine_refill_s, type => {integer, 0, 86400}, default => 60, unit => <<"s">>,
       doc => <<"How long until the magazine is refilled and the warning goes.">>}].
