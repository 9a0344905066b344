%% The record a device task's callbacks receive; opaque to task modules, which use the
%% functions of cell_task on it.
-record(task, {
    id :: atom(),
    module :: module(),
    zone :: binary(),
    lane :: binary(),
    args = #{} :: map(),
    io = [] :: [atom()],                       %% IO group instances; the first is the default
    settings = #{} :: map(),                   %% the snapshot taken at Start
    data = #{} :: map(),                       %% the task module's own fields
    product :: cell_product:product() | undefined,
    gen = 0 :: non_neg_integer(),              %% the product's generation (see cell_product)
    marker :: cell_product:marker(),           %% set while the product is in transit
    %% The serial whose taking by this task is in the trace journal (cell_trace_journal).
    traced :: binary() | undefined,
    product_path :: binary(),
    %% The product file kept open for the task's writes (cell_file:record_file/1).
    product_file :: cell_file:record_file(),
    %% The task's retained data (cell_retain) as its file holds it, the file's name and
    %% its handle.
    retained = #{} :: cell_retain:data(),
    retain_path :: binary(),
    retain_file :: cell_file:record_file(),
    links = #{} :: #{atom() => map()},         %% handshake links: role, last signals
    ipc = off :: cell_ipc:state(),
    answer :: cell_alarms:solution() | undefined,
    woken_by :: term(),
    service_mode = false :: boolean(),
    %% The outputs this task commanded since its last init, as it last commanded them
    %% (cell_task_outputs): what is written again when a lost connection is back.
    commanded = #{} :: cell_task_outputs:image()
}).
