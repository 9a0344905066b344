%% @doc The IO of the code reader above a loading segment's stopper (one instance per
%% lane), wired through the PLC as industrial readers are: the trigger, its answer
%% (done, no read), the code read and the reader's read counter. The cell reads it as
%% a hardware object of type `io' ({@link cell_hal_code_reader_io}), never point by
%% point.
-module(router_reader_io).
-behaviour(cell_hal_group).

-export([points/1]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {done, in, bool, <<"A1.01.11">>, <<"Code reader: answered">>},
        {no_read, in, bool, <<"A1.01.12">>, <<"Code reader: no code found">>},
        %% 16 registers and the counter after them: the group within its 20 addresses.
        {result, in, {string, 32}, <<"A1.30.11">>, <<"Code reader: code read">>},
        {read_count, in, uint16, <<"A1.30.12">>, <<"Code reader: read counter">>},
        {trigger, out, bool, <<"A1.20.11">>, <<"Code reader: trigger">>}]).
