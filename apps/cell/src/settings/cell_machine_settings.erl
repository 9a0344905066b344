%% @doc The machine settings every cell has (seed 000 §3.1, `MachineSettings'): the file
%% `Settings/machine.json'. The defaults are those of the seed's constructor where it
%% gives one, and otherwise the safe choice: a new installation runs simulated tasks
%% until someone says the hardware is there (seed 000 §2.3.3).
%%
%% A cell adds its own objects (per-task settings, a tool manager ...) as further
%% schemas, each registered with {@link cell_settings:register/1} and kept in a file
%% of its own.
-module(cell_machine_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

-spec name() -> machine.
name() -> machine.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => cell_name, type => {string, 64}, default => <<"cell">>,
       doc => <<"The cell's name, shown on the operator panel and in reports.">>},
     #{name => simulation_mode, type => boolean, default => true,
       doc => <<"Run simulated device tasks instead of driving the hardware; "
                "read at Start.">>},
     #{name => dual_lane, type => boolean, default => false,
       doc => <<"The cell has a rear lane as well as the front lane; read at Start.">>},
     %% The seed's constructor says verbose; the runtime says brief, because every
     %% state change of every task is a verbose line, which floods the log of a large
     %% cell and slows its emergency stop. Verbose is for diagnosis (cell_log:verbose_for/2).
     #{name => log_level, type => {enum, [silent, brief, verbose]}, default => brief,
       doc => <<"How much the device tasks write to the task log: silent (mandatory "
                "messages only), brief, verbose.">>},
     #{name => speed_override, type => {integer, 1, 100}, default => 50, unit => <<"%">>,
       doc => <<"Speed of every axis as a share of its taught speed.">>},
     #{name => no_progress_ms, type => {integer, 100, 3600000}, default => 60000,
       unit => <<"ms">>,
       doc => <<"A started cell holding products that makes no progress (no product "
                "moved, no work started or ended) for this long while no error waits "
                "raises a warning naming what each task waits for; longer than the "
                "longest work cycle.">>},
     #{name => ads_ams_net_id, type => {string, 23}, default => <<>>,
       doc => <<"AMS Net ID of the Beckhoff PLC (six numbers 0-255 joined by dots, "
                "as 5.18.40.112.1.1); empty when the cell has none.">>}].

%% @doc The AMS Net ID is empty or six numbers 0-255 joined by dots.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{ads_ams_net_id := <<>>}) ->
    ok;
check(#{ads_ams_net_id := Id}) ->
    Parts = binary:split(Id, <<".">>, [global]),
    case length(Parts) =:= 6 andalso lists:all(fun is_byte_text/1, Parts) of
        true -> ok;
        false -> {error, [ads_ams_net_id], {not_an_ams_net_id, Id}}
    end.

is_byte_text(B) when byte_size(B) >= 1, byte_size(B) =< 3 ->
    case [C || <<C>> <= B, C < $0 orelse C > $9] of
        [] -> binary_to_integer(B) =< 255;
        _ -> false
    end;
is_byte_text(_) ->
    false.
