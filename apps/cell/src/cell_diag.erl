%% @doc One-call answers for the remote shell (`bin/cellrt remote_console'): what a
%% service engineer asks first, printed as short tables.
%%
%% ```
%% cell_diag:status().            % the cell, its errors, products, shift, HAL, the node
%% cell_diag:tasks().             % every task: state, product, why it is DOWN, queue
%% cell_diag:io(loading_front_io). % the points of an IO group with their values
%% cell_diag:alarms().            % active errors and warnings, and how to answer them
%% cell_diag:waits().             % what each task waits for: state, phase, IO, handshake
%% cell_diag:product(<<"P1">>).   % where a product is, and its history
%% cell_diag:retained().          % each task's retained data (counters, last serial)
%% cell_diag:stats().             % this shift: time per state, items, cycle times
%% cell_diag:trace(work_front).   % one task's log at Verbose for a minute
%% cell_diag:top().               % the processes with the longest queues and most memory
%% cell_diag:machine().           % what can be done to the simulated machine
%% cell_diag:machine(estop, press). % done: here the e-stop pressed (wherever it runs)
%% '''
%%
%% For live views of the whole node the release carries recon
%% (`recon:proc_count(message_queue_len, 5)', `recon:bin_leak(5)') and observer_cli
%% (`observer_cli:start()'). Leave the remote shell with Ctrl-G, then `q': `q().'
%% would stop the cell.
-module(cell_diag).

-export([help/0, status/0, tasks/0, waits/0, io/1, alarms/0, product/1, retained/0, stats/0,
         stats/1, trace/1, trace/2, top/0, machine/0, machine/2]).

-define(TRACE_MS, 60000).

%% @doc What each function shows.
-spec help() -> ok.
help() ->
    print(["cell_diag:status()          the cell, errors, products, shift, HAL, node\n",
           "cell_diag:tasks()           every task: state, product, why DOWN, queue\n",
           "cell_diag:waits()           what each task waits for: state, phase, IO, handshake\n",
           "cell_diag:io(Group)         an IO group's points and values\n",
           "cell_diag:alarms()          active errors and warnings, how to answer them\n",
           "cell_diag:product(Serial)   where a product is and its history\n",
           "cell_diag:retained()        each task's retained data (counters, last serial)\n",
           "cell_diag:stats()           this shift; stats(total) since the first start\n",
           "cell_diag:trace(Task)       a task's log at Verbose for a minute; trace(Task, Ms)\n",
           "cell_diag:top()             processes with the longest queues, the most memory\n",
           "cell_diag:machine()         what can be done to the simulated machine\n",
           "cell_diag:machine(A, C)     do it: machine(estop, press), machine(air, drop)\n",
           "observer_cli:start()        live view of the node (q to leave)\n",
           "Leave this shell with Ctrl-G then q (q(). stops the cell).\n"]).

%% @doc The actions of the cell's simulated machine (see {@link cell_machine_actions}),
%% and where they are carried out: in this VM, or on the virtual PLC's node.
-spec machine() -> ok.
machine() ->
    case cell_machine_actions:list() of
        {ok, none, _} ->
            print("This machine has no simulation to act on: its PLC is a real one.\n");
        {ok, _, []} ->
            print("The cell lists no actions on its simulated machine.\n");
        {ok, Where, Actions} ->
            print([case Where of
                       local -> "The machine's simulation runs in this node.\n";
                       {vplc, Node, _} -> io_lib:format("The machine's simulation runs in the "
                                                        "virtual PLC ~s.~n", [Node])
                   end,
                   [io_lib:format("  ~-22s ~ts (~ts): ~ts~n",
                                  [Id, C, G, lists:join(" ", [atom_to_list(I) || #{id := I} <- Cs])])
                    || #{id := Id, caption := C, group := G, choices := Cs} <- Actions],
                   "Carry one out with cell_diag:machine(Action, Choice).\n"]);
        {error, Why} ->
            print(io_lib:format("The cell's list of machine actions is not well formed: ~tp~n",
                                [Why]))
    end.

%% @doc Carries out a machine action, as a service user's button on the panel does
%% (`machine(estop, press)', `machine(door_loading, open)'): `ok' once the machine has
%% taken it, or why not.
-spec machine(atom() | binary(), atom() | binary()) -> ok | {error, cell_machine_actions:failure()}.
machine(Action, Choice) ->
    case cell_machine_actions:run(text(Action), text(Choice), 5000) of
        {ok, #{caption := A}, #{caption := C}} ->
            cell_log:notice(diag, "~ts: ~ts (from the shell)", [A, C]),
            ok;
        {error, _} = Error ->
            Error
    end.

text(A) when is_atom(A) -> atom_to_binary(A, utf8);
text(B) when is_binary(B) -> B.

%% @doc The cell at a glance.
-spec status() -> ok.
status() ->
    Flags = cell_controller:flags(),
    Tasks = cell_controller:tasks(),
    Alarms = cell_alarms:list(),
    Kinds = [K || #{kind := K} <- Alarms],
    ByState = count([cell_ipc:name(S) || #{state := S} <- Tasks]),
    InCell = length([S || #{serial := S} <- Tasks, is_binary(S)]),
    #{cell := Cell, period := Period} = safe_summary(),
    print([io_lib:format("Cell ~ts: ~ts, request ~ts, emergency stop ~ts, service mode ~ts~n",
                         [cell_name(), cell_ipc:name(maps:get(state, Flags)),
                          maps:get(request, Flags), on_off(maps:get(estop, Flags)),
                          on_off(maps:get(service_mode, Flags))]),
           io_lib:format("Errors ~b, alarms ~b, warnings ~b~n",
                         [count_of(error, Kinds), count_of(alarm, Kinds),
                          count_of(warning, Kinds)]),
           io_lib:format("Tasks ~b: ~ts; products in the cell ~b~n",
                         [length(Tasks), join([[N, " ", integer_to_list(C)]
                                               || {N, C} <- ByState]), InCell]),
           io_lib:format("Shift ~ts: in ~b, out ~b (good ~b, failed ~b), scrapped ~b, "
                         "~.1f an hour~n",
                         [Period, maps:get(in, Cell, 0), maps:get(out, Cell, 0),
                          maps:get(good, Cell, 0), maps:get(failed, Cell, 0),
                          maps:get(scrapped, Cell, 0),
                          float(maps:get(throughput_per_hour, Cell, 0.0))]),
           [io_lib:format("HAL ~ts: ~ts (~ts)~ts~n",
                          [C, S, E, case R of <<>> -> ""; _ -> [": ", R] end])
            || {C, S, E, R} <- connections()],
           held_twice_lines(Tasks),
           case cell_alarms:get(<<"cell:no_progress">>) of
               {ok, _} -> "No progress and no error: see cell_diag:waits()\n";
               {error, not_found} -> ""
           end,
           node_line()]).

%% @doc What each task waits for: its state, phase and product, the IO point and
%% condition or the handshake signal of its waits, and the phase of each link it is in
%% (what the no-progress warning names).
-spec waits() -> ok.
waits() ->
    print([[L, "\n"] || L <- cell_guard:waits()]).

%% A serial two tasks hold at once.
held_twice_lines(Tasks) ->
    Serials = [S || #{serial := S} <- Tasks, is_binary(S)],
    [io_lib:format("Product ~ts is held by two tasks: ~ts~n",
                   [S, join([atom_to_list(Id) || {Id, _} <- cell_registry:holders(S)])])
     || S <- lists:usort(Serials -- lists:usort(Serials))].

%% @doc Every task with its state, product and queue.
-spec tasks() -> ok.
tasks() ->
    Rows = [[atom_to_list(Id), [Z, "@", L], cell_ipc:name(S), serial(Serial),
             integer_to_list(queue(Row)), down_text(Id, S)]
            || #{id := Id, zone := Z, lane := L, state := S, serial := Serial} = Row
                   <- cell_controller:tasks()],
    print(table(["TASK", "ZONE@LANE", "STATE", "PRODUCT", "QUEUE", "WHY DOWN"], Rows)).

%% @doc The points of an IO group: direction, type, value, wiring address, caption.
-spec io(atom()) -> ok | {error, unknown_group}.
io(Group) when is_atom(Group) ->
    case cell_hal:points(Group) of
        {ok, Points} ->
            Conn = case cell_hal:connection_of(Group) of
                       {ok, C} -> C;
                       _ -> undefined
                   end,
            Rows = [[atom_to_list(N), atom_to_list(D), cell_hal_type:name(T),
                     value(cell_hal:read(Group, N)), A, Cap]
                    || #{name := N, dir := D, type := T, address := A, caption := Cap} <- Points],
            print([io_lib:format("Group ~ts on connection ~ts (~ts)~n",
                                 [Group, Conn, conn_status(Conn)]),
                   table(["POINT", "DIR", "TYPE", "VALUE", "ADDRESS", "CAPTION"], Rows)]);
        {error, unknown_group} ->
            print(io_lib:format("No IO group ~ts; the groups are: ~ts~n",
                                [Group, join([atom_to_list(G) || G <- cell_hal:groups()])])),
            {error, unknown_group}
    end.

%% @doc Active errors, alarms and warnings, and how to answer them from here.
-spec alarms() -> ok.
alarms() ->
    case cell_alarms:list() of
        [] ->
            print("No active errors, alarms or warnings.\n");
        List ->
            print([[io_lib:format("~ts ~ts (~ts): ~ts~n  ~ts~n  solutions: ~ts~n",
                                  [Kind, Id, Task, Caption, indent(Text),
                                   join([atom_to_list(S) || S <- Sols])])
                    || #{id := Id, kind := Kind, task := Task, caption := Caption,
                         description := Text, solutions := Sols} <- List],
                   "Answer: cell_alarms:answer(<<\"Id\">>, retry, <<\"your name\">>); "
                   "close a warning: cell_alarms:close(<<\"Id\">>, <<\"your name\">>).\n"])
    end.

%% @doc Where a product is now and everything recorded about it.
-spec product(binary() | string()) -> ok | {error, not_found}.
product(Serial) when is_list(Serial) ->
    product(unicode:characters_to_binary(Serial));
product(Serial) when is_binary(Serial) ->
    Where = [[atom_to_list(Id), " (", cell_ipc:name(S), ")"]
             || #{id := Id, serial := Sr, state := S} <- cell_controller:tasks(), Sr =:= Serial],
    case cell_stats:product(Serial) of
        {ok, #{events := Events} = Info} ->
            Rows = [[time_text(T), atom_text(maps:get(task, E, undefined)),
                     atom_text(maps:get(event, E, undefined)), detail(E)]
                    || #{time := T} = E <- Events],
            print([io_lib:format("Product ~ts: ~ts, recipe ~ts, ~ts~ts~n",
                                 [Serial, maps:get(status, Info, unknown),
                                  maps:get(recipe, Info, <<>>),
                                  case maps:get(failed, Info, false) of
                                      true -> "failed";
                                      false -> "good"
                                  end,
                                  case Where of
                                      [] -> "";
                                      _ -> [", held by ", join(Where)]
                                  end]),
                   table(["TIME", "TASK", "EVENT", "DETAIL"], Rows)]);
        {error, not_found} when Where =/= [] ->
            print(io_lib:format("Product ~ts is held by ~ts; nothing recorded about it.~n",
                                [Serial, join(Where)]));
        {error, not_found} ->
            print(io_lib:format("No product ~ts has been recorded.~n", [Serial])),
            {error, not_found}
    end.

%% @doc Each task's retained data, key by key, as its file holds them (see
%% `cell_task:retain/3'), or why its file cannot be read.
-spec retained() -> ok.
retained() ->
    Rows = lists:append([retained_rows(Row) || Row <- cell_controller:tasks()]),
    print(table(["TASK", "KEY", "VALUE"], Rows)).

retained_rows(#{id := Id} = Row) ->
    Task = atom_to_list(Id),
    case Row of
        #{retained_error := Why} when Why =/= undefined ->
            [[Task, "-", ["(file cannot be read: ", cell_retain:text(Why), ")"]]];
        #{retained := Data} when is_map(Data), map_size(Data) > 0 ->
            [[Task, short(K), short(V)]
             || {K, V} <- lists:sort(maps:to_list(Data))];
        _ ->
            %% Nothing retained yet, or a unit (its sequences keep none).
            [[Task, "-", "(none)"]]
    end.

%% @doc This shift's statistics.
-spec stats() -> ok.
stats() ->
    stats(cell_stats:shift_now()).

%% @doc A period's statistics: `total' or a shift id (see `cell_stats:periods()').
-spec stats(cell_stats:period()) -> ok.
stats(Period) ->
    S = cell_stats:summary(Period),
    #{cell := Cell, tasks := Tasks} = S,
    States = [executing, active, starved, blocked, setup, down, off],
    Rows = [[atom_to_list(T) | [pct(maps:get(St, Share, 0.0)) || St <- States]]
            ++ [integer_to_list(maps:get(K, C, 0)) || K <- [in, out, errors]]
            ++ [ms(maps:get(cycle_ms, C, #{}))]
            || {T, #{share := Share} = C} <- lists:sort(maps:to_list(Tasks))],
    print([io_lib:format("Period ~ts: in ~b, out ~b (good ~b, failed ~b), scrapped ~b, "
                         "in the cell ~b; ~.1f an hour; lead time ~ts, cycle time ~ts~n",
                         [maps:get(period, S), maps:get(in, Cell), maps:get(out, Cell),
                          maps:get(good, Cell), maps:get(failed, Cell),
                          maps:get(scrapped, Cell), maps:get(in_cell, S),
                          float(maps:get(throughput_per_hour, Cell)),
                          ms(maps:get(lead_ms, Cell)), ms(maps:get(cycle_ms, Cell))]),
           table(["TASK", "EXEC%", "ACTIVE%", "STARVED%", "BLOCKED%", "SETUP%", "DOWN%",
                  "OFF%", "IN", "OUT", "ERRORS", "CYCLE ms"], Rows)]).

%% @doc Switches one task's log to Verbose for a minute.
-spec trace(atom()) -> ok.
trace(Task) ->
    trace(Task, ?TRACE_MS).

%% @doc Switches one task's log to Verbose for `Ms' milliseconds; the lines go to the
%% task log (`Logs/log YYYY-MM-DD.log') and the panel's log page.
-spec trace(atom(), pos_integer()) -> ok.
trace(Task, Ms) when is_atom(Task), is_integer(Ms), Ms > 0 ->
    ok = cell_log:verbose_for(Task, Ms),
    print(io_lib:format("~ts logs at Verbose for ~b s, then as before.~n",
                        [Task, Ms div 1000])).

%% @doc The processes with the longest message queues and the most memory.
-spec top() -> ok.
top() ->
    Queues = recon:proc_count(message_queue_len, 5),
    Memory = recon:proc_count(memory, 5),
    Row = fun({Pid, N, Info}) -> [pid_to_list(Pid), integer_to_list(N), proc_name(Info)] end,
    print(["Longest message queues\n", table(["PID", "QUEUE", "NAME"], [Row(P) || P <- Queues]),
           "Most memory (bytes)\n", table(["PID", "MEMORY", "NAME"], [Row(P) || P <- Memory])]).

%%====================================================================

safe_summary() ->
    try cell_stats:summary(cell_stats:shift_now()) of
        S -> S
    catch
        _:_ -> #{cell => #{}, period => <<"(statistics not running)">>}
    end.

cell_name() ->
    try cell_settings:get(machine, cell_name)
    catch _:_ -> <<"cell">>
    end.

connections() ->
    [case cell_hal:info(C) of
         {ok, #{status := S, endpoint := E, reason := R}} -> {C, S, E, R};
         _ -> {C, unknown, <<>>, <<>>}
     end || C <- cell_hal:connections()].

conn_status(undefined) -> "not configured";
conn_status(Conn) -> atom_to_list(cell_hal:status(Conn)).

node_line() ->
    {Up, _} = erlang:statistics(wall_clock),
    {QLen, QName} = longest_queue(),
    #{clean := Clean, unexpected := Unexpected} = cell_stats:node_restarts(),
    io_lib:format("Node ~ts: up ~ts, memory ~.1f MB, ~b processes, longest queue ~b (~ts)~n"
                  "Node restarts: ~b after an unexpected stop, ~b after a clean stop~n",
                  [node(), duration(Up), erlang:memory(total) / 1048576,
                   erlang:system_info(process_count), QLen, QName, Unexpected, Clean]).

longest_queue() ->
    case recon:proc_count(message_queue_len, 1) of
        [{_Pid, N, Info}] -> {N, proc_name(Info)};
        [] -> {0, "-"}
    end.

proc_name(Info) ->
    case [N || N <- Info, is_atom(N)] of
        [Name | _] -> atom_to_list(Name);
        [] ->
            case lists:keyfind(current_function, 1, Info) of
                {_, {M, F, A}} -> io_lib:format("~ts:~ts/~b", [M, F, A]);
                _ -> "-"
            end
    end.

queue(#{pid := Pid}) when is_pid(Pid) ->
    case erlang:process_info(Pid, message_queue_len) of
        {message_queue_len, N} -> N;
        undefined -> 0
    end;
queue(_) ->
    0.

down_text(Id, down) ->
    try cell_task_proc:info(Id) of
        #{down := {paused, pause}} -> "paused";
        #{down := {paused, service}} -> "service mode";
        #{down := {error, AlarmId, _}} ->
            case cell_alarms:get(AlarmId) of
                {ok, #{caption := C}} -> [C, " (", AlarmId, ")"];
                _ -> AlarmId
            end;
        _ -> ""
    catch
        exit:_ -> ""
    end;
down_text(_, _) ->
    "".

detail(E) ->
    D = maps:without([time, task, event, zone, lane], E),
    case map_size(D) of
        0 -> "";
        _ -> [[atom_text(K), "=", short(V), " "] || {K, V} <- lists:sort(maps:to_list(D))]
    end.

short(B) when is_binary(B) -> B;
short(A) when is_atom(A) -> atom_to_list(A);
short(N) when is_integer(N) -> integer_to_list(N);
short(T) ->
    Text = io_lib:format("~0tp", [T]),
    case string:length(Text) > 60 of
        true -> [string:slice(Text, 0, 57), "..."];
        false -> Text
    end.

value({ok, V}) -> short(V);
value({error, Why}) -> ["(", atom_text(Why), ")"].

serial(undefined) -> "-";
serial(S) -> S.

pct(X) -> io_lib:format("~.1f", [float(X)]).

ms(#{n := 0}) -> "-";
ms(#{mean := M, min := Mi, max := Ma}) ->
    io_lib:format("~b (~b-~b)", [round(M), round(Mi), round(Ma)]);
ms(_) -> "-".

time_text(Ms) ->
    {{Y, Mo, D}, {H, Mi, S}} = calendar:system_time_to_local_time(Ms, millisecond),
    io_lib:format("~4..0b-~2..0b-~2..0b ~2..0b:~2..0b:~2..0b.~3..0b",
                  [Y, Mo, D, H, Mi, S, Ms rem 1000]).

duration(Ms) ->
    S = Ms div 1000,
    io_lib:format("~bd ~2..0bh ~2..0bm ~2..0bs",
                  [S div 86400, S rem 86400 div 3600, S rem 3600 div 60, S rem 60]).

atom_text(undefined) -> "-";
atom_text(A) when is_atom(A) -> atom_to_list(A);
atom_text(Other) -> short(Other).

on_off(true) -> "ON";
on_off(false) -> "off".

count(Names) ->
    lists:foldl(fun(N, Acc) -> orddict:update_counter(N, 1, Acc) end, orddict:new(), Names).

count_of(K, Kinds) ->
    length([X || X <- Kinds, X =:= K]).

indent(Text) ->
    string:replace(Text, "\n", "\n  ", all).

join(Parts) ->
    lists:join(", ", Parts).

%% A table with columns as wide as their widest cell.
table(Header, Rows) ->
    Cells = [[lists:flatten(io_lib:format("~ts", [C])) || C <- R] || R <- [Header | Rows]],
    Widths = lists:foldl(fun(R, W) -> [max(string:length(C), X) || {C, X} <- lists:zip(R, W)] end,
                         [0 || _ <- Header], Cells),
    [[[string:pad(C, W + 2) || {C, W} <- lists:zip(R, Widths)], "\n"] || R <- Cells].

print(IoData) ->
    io:put_chars(unicode:characters_to_binary(IoData)).
