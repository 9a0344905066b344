%% The data of a device task's engine: what cell_task_proc keeps between events and
%% cell_task_core's transitions change (see cell_task_core). Private to the two.
-record(engine, {
    task :: #task{},
    spec :: cell_task:spec(),
    request = stop :: start | pause | stop,
    estop = false :: boolean(),
    initialized = false :: boolean(),    %% init ran, uninit has not yet
    pending :: cell_task_core:pending(),                 %% what READY does next
    resume :: cell_ipc:ready() | undefined,
    down :: cell_task_core:down_reason() | undefined,
    gen = 0 :: non_neg_integer(),         %% step messages and timers of older rounds are ignored
    armed = [] :: [cell_task_core:armed()],
    load_error :: term(),                 %% the product file could not be read
    retain_error :: term(),               %% the retained-data file could not be read
    crash :: term(),                      %% how the previous incarnation ended
    crash_ask = false :: boolean(),       %% the crash is the operator's to answer
    resumed = false :: boolean(),         %% went on by itself after a crash, not yet waited
    cause = start :: cell_task:cause(),   %% why the next init runs, for reconcile
    crash_outputs :: #{atom() => map()} | undefined, %% as the crashed incarnation left them
    predecessor :: cell_task:held() | undefined, %% what reconcile checks, until it agrees
    settings = #{} :: map(),              %% the snapshot for the next start
    deferred :: pause | service | undefined, %% a pause a transfer holds back
    conns = #{} :: #{atom() => up | down},   %% the HAL connections of the task's IO
    lost = [] :: [atom()],                %% connections lost since init or the last resume
    reoffer = [] :: [atom()],             %% offers a pause withdrew, made again at resume
    dropped = false :: boolean(),         %% its product dropped while paused: Start reconciles
    handed_on :: binary() | undefined,    %% the serial whose copy it last dropped as old
    estop_flag :: atomics:atomics_ref(),   %% the node's emergency-stop flag, read before every step
    held :: atomics:atomics_ref() | undefined %% secured; OFF not yet announced (the barrier)
}).
