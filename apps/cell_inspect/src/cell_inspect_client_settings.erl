%% @doc One camera client of a block.
-module(cell_inspect_client_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> inspect_client.
name() -> inspect_client.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => id, type => {string, 64}, default => <<"camera">>,
       doc => <<"The client's name; a client belongs to one block.">>},
     #{name => type, type => {string, 32}, default => <<"sim">>,
       doc => <<"The client's type: sim (a simulated camera) or a type the cell adds.">>},
     #{name => points, type => {list, {string, 16}, 256}, default => [],
       doc => <<"The points it takes images for; empty: every point of the block.">>},
     #{name => images, type => boolean, default => true,
       doc => <<"It takes images.">>},
     #{name => messages, type => boolean, default => true,
       doc => <<"It shows the PLC's messages and takes answers.">>},
     #{name => delay_ms, type => {integer, 0, 600000}, default => 0, unit => <<"ms">>,
       doc => <<"Simulated cameras: time to take an image.">>},
     #{name => manual, type => boolean, default => false,
       doc => <<"Simulated cameras: take an image only when told to.">>},
     #{name => scene, type => {string, 64}, default => <<"PASS">>,
       doc => <<"Simulated cameras: what the simulated processing reads (PASS, FAIL, "
                "PASS text).">>},
     #{name => fail_rate, type => {float, 0.0, 1.0}, default => 0.0,
       doc => <<"Simulated cameras: chance that an image shows a bad part (the "
                "simulated processing reads FAIL whatever the scene).">>}].
