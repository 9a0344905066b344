%% @doc The monitor's settings object, `Settings/monitor.json' (see {@link
%% cell_monitor}): the beacon's rules and blink period, the speed limit in service
%% mode, the texts of the door and air warnings, how drives are reset, and how long a
%% device may take to connect at start before it is reported.
%%
%% Unlike the tasks' settings, these apply as soon as they are saved: the monitor is
%% not a task and runs on no snapshot (seed 000 §2.4.2: the speed override "is applied
%% even while machine is started").
-module(cell_monitor_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> monitor.
name() -> monitor.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => beacon, type => {list, {object, cell_monitor_beacon_rule}, 64},
       default => cell_beacon:default_rules(),
       doc => <<"Which lamp lights, steady or blinking, while which condition holds. "
                "Every rule that holds counts; a lamp no rule lights is off.">>},
     #{name => blink_period_ms, type => {integer, 200, 10000}, default => 1000,
       unit => <<"ms">>,
       doc => <<"One blink of the beacon: lit for half of it, dark for the other half.">>},
     #{name => service_speed_limit, type => {integer, 1, 100}, default => 10,
       unit => <<"%">>,
       doc => <<"In service mode the drives' speed override is at most this, whatever "
                "the machine's speed override says.">>},
     #{name => door_caption, type => {string, 128}, default => <<"Door not locked">>,
       doc => <<"The warning shown while a door is not locked.">>},
     #{name => door_text, type => {string, 512},
       default => <<"A door of the cell is not locked. Close and lock it; production "
                    "may stop while it is open.">>,
       doc => <<"What the door warning tells the operator to do.">>},
     #{name => air_caption, type => {string, 128}, default => <<"Air pressure low">>,
       doc => <<"The warning shown while the compressed air pressure is low.">>},
     #{name => air_text, type => {string, 512},
       default => <<"The compressed air pressure is too low. Check the air supply and "
                    "the main valve.">>,
       doc => <<"What the air warning tells the operator to do.">>},
     #{name => drive_reset_pulse_ms, type => {integer, 10, 5000}, default => 200,
       unit => <<"ms">>,
       doc => <<"How long a drive's reset output is held on.">>},
     #{name => drive_reset_attempts, type => {integer, 1, 10}, default => 3,
       doc => <<"Resets tried before a drive error is handed to the operator.">>},
     %% As short as a pulse: a drive that clears in a few ms need not wait longer. What
     %% bounds it from below is how soon the cell sees the error bit change (the
     %% connection's poll period or notification), which the doc tells the owner.
     #{name => drive_reset_wait_ms, type => {integer, 10, 60000}, default => 1000,
       unit => <<"ms">>,
       doc => <<"Wait after the first reset before checking the drive; doubled after "
                "each further reset. Keep it longer than the PLC connection takes to "
                "report the drive's error bit (its poll period): an error the reset "
                "cleared but not yet seen is reset again.">>},
     #{name => connect_grace_ms, type => {integer, 0, 600000}, default => 5000,
       unit => <<"ms">>,
       doc => <<"At start, how long a connection or hardware object may take to come "
                "up before its absence is reported.">>}].
