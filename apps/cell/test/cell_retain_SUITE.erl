%% Retained task data (cell_task:retain/3 and friends, cell_retain): a serial counter
%% kept as retained data is never lost and never repeated, whether the task's process
%% is killed in the middle of its work or the whole node is killed with SIGKILL; a file
%% that cannot be read stops the task with a question for the operator instead of a
%% counter starting again from zero; a value that cannot be retained is refused with
%% the reason, and nothing of it is written; cell_diag shows the data.
-module(cell_retain_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([task_killed_mid_work/1, damaged_file_asks_the_operator/1,
         damaged_file_set_aside_on_reset/1, refused_value_is_not_written/1,
         node_killed_100_times/1]).

-define(TIMEOUT, 20000).
%% Below the task supervisor's intensity (20 restarts a minute), past which the cell
%% stops its tasks by design; the node case kills a hundred times.
-define(KILLS, 15).
-define(NODE_KILLS, 100).

all() ->
    [task_killed_mid_work, damaged_file_asks_the_operator, damaged_file_set_aside_on_reset,
     refused_value_is_not_written, node_killed_100_times].

init_per_testcase(node_killed_100_times, Config) ->
    Root = filename:join(?config(priv_dir, Config), "node_killed"),
    ok = filelib:ensure_dir(filename:join([Root, "Data", "x"])),
    [{root, Root} | Config];
init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = filelib:ensure_dir(filename:join([Root, "Data", "x"])),
    _ = [application:load(A) || A <- [cell_base, cell_hal, cell]],
    ok = application:set_env(cell_base, root, Root),
    Args = case Case of
               refused_value_is_not_written -> #{refuse_at => 3};
               _ -> #{}
           end,
    Spec = #{tasks => [#{id => serials, module => cell_retain_test_task,
                         zone => <<"Serials">>, lane => <<"1">>,
                         args => Args#{notify => self()}}]},
    ok = application:set_env(cell, cell_spec, Spec),
    rand:seed(exsss, erlang:phash2(make_ref())),
    [{root, Root}, {path, retain_path(Root)} | Config].

end_per_testcase(node_killed_100_times, _Config) ->
    ok;
end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    %% The statistics started the database in this root: it goes with the cell.
    _ = application:stop(mnesia),
    ok.

retain_path(Root) ->
    filename:join([Root, "Data", cell_retain:file_name(<<"Serials">>, <<"1">>)]).

start_cell() ->
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_events:subscribe([alarm_raised, task_crashed]),
    ok = cell_controller:start().

%% --------------------------------------------------------------------------------------

%% The task's process killed at random moments while it makes serials, ?KILLS times:
%% after each restart it goes on from the counter it last made durable. No serial it
%% reported is made again, and none is skipped but one made durable in the very step
%% the kill cut short (made, not yet reported).
task_killed_mid_work(_Config) ->
    start_cell(),
    {Pid, First} = await_made(any),
    ?assertEqual(1, First),
    {Made, _} = lists:foldl(fun(Round, {Seen, {P, Last}}) ->
                                    kill_round(Round, P, Last, Seen)
                            end, {[First], {Pid, First}}, lists:seq(1, ?KILLS)),
    ?assertEqual(length(Made), length(lists:usort(Made))),
    ct:comment("~b kills, ~b serials made", [?KILLS, length(Made)]).

%% Lets the task make a few serials, kills it at a random moment, and checks where its
%% successor goes on.
kill_round(Round, Pid, Last0, Seen0) ->
    {Last1, Seen1} = take_made(Pid, rand:uniform(4) - 1, Last0, Seen0),
    MRef = erlang:monitor(process, Pid),
    %% The delay only varies the moment of the kill: before, in and after a write.
    erlang:send_after(rand:uniform(4) - 1, self(), kill),
    receive kill -> exit(Pid, kill) end,
    %% Everything the task sent before it died comes before its 'DOWN'.
    {Last, Seen} = drain_made(Pid, MRef, Last1, Seen1),
    {Next, N} = await_made(Pid),
    %% The kill may have cut off the report of a serial already durable: then that one
    %% is skipped, never made again.
    case N of
        _ when N =:= Last + 1; N =:= Last + 2 -> ok;
        _ -> ct:fail({round, Round, last_reported, Last, next_made, N})
    end,
    {[N | Seen], {Next, N}}.

take_made(_Pid, 0, Last, Seen) ->
    {Last, Seen};
take_made(Pid, K, Last, Seen) ->
    receive
        {made, Pid, N} ->
            ?assertEqual(Last + 1, N),
            take_made(Pid, K - 1, N, [N | Seen])
    after ?TIMEOUT ->
        ct:fail({no_serial_made, Last})
    end.

drain_made(Pid, MRef, Last, Seen) ->
    receive
        {made, Pid, N} ->
            ?assertEqual(Last + 1, N),
            drain_made(Pid, MRef, N, [N | Seen]);
        {'DOWN', MRef, process, Pid, _} ->
            {Last, Seen}
    after ?TIMEOUT ->
        ct:fail(task_not_killed)
    end.

%% The first serial a task process other than `Old' makes. A task killed again before
%% it first waited is the operator's question (the engine's own): answered Retry.
await_made(Old) ->
    receive
        {made, Pid, N} when Pid =/= Old ->
            {Pid, N};
        {cell_event, #{type := alarm_raised,
                       alarm := #{kind := error, id := Id, solutions := Solutions}}} ->
            ?assert(lists:member(retry, Solutions)),
            ok = cell_alarms:answer(Id, retry, <<"test">>),
            await_made(Old);
        {cell_event, _} ->
            await_made(Old)
    after ?TIMEOUT ->
        ct:fail({no_serial_made_after_restart, Old})
    end.

await_error(Caption) ->
    receive
        {cell_event, #{type := alarm_raised,
                       alarm := #{kind := error, caption := Caption} = Alarm}} -> Alarm;
        {cell_event, _} -> await_error(Caption)
    after ?TIMEOUT ->
        ct:fail({no_error, Caption})
    end.

%% --------------------------------------------------------------------------------------

%% A damaged file: the task does not run (it would start counting from zero again);
%% the operator is asked, Retry while it is still damaged asks again, and Retry once
%% it is mended goes on from what it holds. cell_diag says so meanwhile.
damaged_file_asks_the_operator(Config) ->
    Path = ?config(path, Config),
    ok = cell_retain:save(Path, #{serial => 40}, #{}),
    {ok, Whole} = file:read_file(Path),
    ok = file:write_file(Path, binary:copy(<<16#5a>>, byte_size(Whole))),
    start_cell(),
    #{id := Id, solutions := [retry, reset], description := Text} =
        await_error(<<"Retained data damaged">>),
    ?assertNotEqual(nomatch, binary:match(Text, <<"Serials@1.retain">>)),
    ?assertEqual(down, cell_task_proc:state(serials)),
    {ok, #{retained_error := {corrupt, _}}} = cell_registry:task(serials),
    ?assertNotEqual(nomatch, string:find(diag_retained(), "file cannot be read")),
    ok = cell_alarms:answer(Id, retry, <<"test">>),
    #{id := Id2} = await_error(<<"Retained data damaged">>),
    ?assertEqual(down, cell_task_proc:state(serials)),
    %% Restored from a backup.
    ok = cell_retain:save(Path, #{serial => 41}, #{}),
    ok = cell_alarms:answer(Id2, retry, <<"test">>),
    {_, 42} = await_made(any),
    {ok, #{retained := #{serial := S}}} = cell_registry:task(serials),
    ?assert(S >= 42),
    ?assertNotEqual(nomatch, string:find(diag_retained(), "serials  serial")).

%% Reset sets the damaged file aside (never deleted) and the task starts its counter
%% again from the default, on the operator's word; the log says who.
damaged_file_set_aside_on_reset(Config) ->
    Path = ?config(path, Config),
    ok = file:write_file(Path, <<"not retained data">>),
    start_cell(),
    #{id := Id} = await_error(<<"Retained data damaged">>),
    ok = cell_alarms:answer(Id, reset, <<"test">>),
    {_, 1} = await_made(any),
    Dir = filename:dirname(Path),
    [Aside] = filelib:wildcard(filename:basename(Path) ++ ".damaged-*", Dir),
    ?assertEqual({ok, <<"not retained data">>}, file:read_file(filename:join(Dir, Aside))).

%% A step that retains its own pid: refused, the task crashes with the reason in
%% words, nothing of it is on disk, and the restarted task goes on from its counter.
refused_value_is_not_written(Config) ->
    start_cell(),
    {Pid, 1} = await_made(any),
    Crash = receive
                {cell_event, #{type := task_crashed, reason := R}} -> R
            after ?TIMEOUT -> ct:fail(no_crash)
            end,
    ?assertNotEqual(nomatch, string:find(Crash, "cannot be retained")),
    ?assertNotEqual(nomatch, string:find(Crash, "means nothing after a restart")),
    {_, 4} = await_made(Pid),
    {ok, Data} = cell_retain:load(?config(path, Config)),
    ?assertNot(maps:is_key(owner, Data)).

diag_retained() ->
    ct:capture_start(),
    ok = cell_diag:retained(),
    ct:capture_stop(),
    lists:flatten(ct:capture_get()).

%% --------------------------------------------------------------------------------------

%% A node making serials from a retained counter, killed with SIGKILL ?NODE_KILLS times
%% at random moments: each new node starts from a counter never below the last serial
%% a killed one reported, and no serial is ever made twice.
node_killed_100_times(Config) ->
    Root = ?config(root, Config),
    Path = retain_path(Root),
    {Last, Made} = lists:foldl(fun(Round, Acc) -> node_round(Root, Path, Round, Acc) end,
                               {0, 0}, lists:seq(1, ?NODE_KILLS)),
    ct:comment("~b kills, ~b serials made, the last ~b", [?NODE_KILLS, Made, Last]),
    ?assert(Made > ?NODE_KILLS).

node_round(Root, Path, Round, {Last, Made}) ->
    Port = writer(Root),
    {OsPid, Start} = receive
                         {Port, {data, {eol, "pid " ++ Line}}} ->
                             case string:split(Line, " ", all) of
                                 [P, "start", S] -> {P, list_to_integer(S)};
                                 _ -> ct:fail({writer_cannot_start, Round, Line})
                             end
                     after ?TIMEOUT -> ct:fail({writer_did_not_start, Round})
                     end,
    %% Never lost: what a node reported durable is there for the next.
    Start >= Last orelse ct:fail({lost, Round, last_reported, Last, started_from, Start}),
    %% Killed once it has made a few serials, or at once.
    Reported = collect(Port, rand:uniform(6) - 1, Start),
    erlang:send_after(rand:uniform(8) - 1, self(), kill),
    receive kill -> os:cmd("kill -9 " ++ OsPid) end,
    Final = await_exit(Port, Reported),
    %% The file is whole, and holds at least what was reported.
    {ok, #{serial := OnDisk}} = cell_retain:load(Path),
    OnDisk >= Final orelse ct:fail({lost_on_disk, Round, Final, OnDisk}),
    {Final, Made + Final - Start}.

%% Reads K serials (each the one after the last: none repeated, none skipped within a
%% node's life).
collect(_Port, 0, Last) ->
    Last;
collect(Port, K, Last) ->
    receive
        {Port, {data, {eol, "made " ++ M}}} ->
            N = list_to_integer(M),
            N =:= Last + 1 orelse ct:fail({out_of_order, Last, N}),
            collect(Port, K - 1, N);
        {Port, {exit_status, S}} ->
            ct:fail({writer_exited, S})
    after ?TIMEOUT ->
        ct:fail({writer_silent, Last})
    end.

%% The serials the node reported before it died; the last of them.
await_exit(Port, Last) ->
    receive
        {Port, {data, {eol, "made " ++ M}}} ->
            N = list_to_integer(M),
            N =:= Last + 1 orelse ct:fail({out_of_order, Last, N}),
            await_exit(Port, N);
        {Port, {data, _}} ->
            await_exit(Port, Last);
        {Port, {exit_status, _}} ->
            Last
    after ?TIMEOUT ->
        ct:fail(writer_not_killed)
    end.

writer(Root) ->
    Erl = os:find_executable("erl"),
    Paths = [filename:dirname(code:which(M))
             || M <- [cell_file, cell_config, cell_task, cell_retain_writer]],
    Args = lists:append([["-pa", P] || P <- lists:usort(Paths)])
        ++ ["-noshell", "-noinput", "-s", "cell_retain_writer", "main"],
    open_port({spawn_executable, Erl}, [{args, Args}, {line, 1024}, exit_status, use_stdio,
                                        stderr_to_stdout, {env, [{"CELLRT_ROOT", Root}]}]).
