%% Rows of the HAL's tables (see cell_hal_store). Internal to cell_hal.

%% A configured connection and its worker's view of it.
-record(hal_conn, {id :: atom(),
                   driver :: module(),
                   opts :: map(),                 %% the driver's checked options
                   worker_opts :: map(),          %% poll_ms, reconnect_ms ...
                   status = down :: up | down,
                   pid :: pid() | undefined,
                   endpoint = <<>> :: binary(),
                   since :: integer() | undefined,  %% system time of the last change, ms
                   reason :: term()}).              %% why it is down

%% A configured group instance.
-record(hal_group, {id :: atom(),
                    module :: module(),
                    conn :: atom(),
                    opts :: map()}).

%% A point's description: what the IO page shows and what the driver needs.
-record(hal_point, {key :: {atom(), atom()},
                    conn :: atom(),
                    dir :: in | out,
                    type :: cell_hal_type:type(),
                    field :: term(),                 %% as the driver resolved it
                    declared :: term(),              %% as the group module declared it
                    address :: binary(),
                    caption :: binary(),
                    unit = <<>> :: binary(),             %% of the value, for the IO page
                    seq = 0 :: non_neg_integer()}).      %% its place in its group's list

%% A point's value, read without a process hop. `none' until first read or commanded.
%% `fault' says, in words, why the driver cannot read or write the point (a symbol
%% the PLC lacks, an address a Modbus PLC refuses), while the connection is up; the
%% rest of its group works on.
-record(hal_value, {key :: {atom(), atom()},
                    conn :: atom(),
                    dir :: in | out,
                    type :: cell_hal_type:type(),
                    value = none :: none | {ok, cell_hal_type:value()},
                    fault :: binary() | undefined}).
