%% The statistics when their database cannot be used (here: a database of another
%% node name in Databases/): the cell runs all the same, the log says why in words,
%% what happens is counted and recorded in memory, and once the folder is moved aside
%% the statistics start an empty database and write what they kept.
%%
%% The time of tasks that stay in one state: counted up to the last write without the
%% statistics doing anything for them, and across a crash of the statistics kept in
%% the state the task was in up to the last write before it, the gap counted as OFF.
-module(cell_stats_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").
-include_lib("proper/include/proper.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([database_unusable_then_back/1, database_lost_then_back/1,
         a_long_outage_of_the_database/1, writer_crash/1,
         time_in_a_state_across_a_crash/1,
         shifts_split_the_time/1, a_product_in_the_cell_and_after/1,
         a_product_left_across_a_crash/1, a_failed_product_left_across_a_crash/1,
         a_product_taken_again_across_a_crash/1,
         an_answer_across_a_crash/1, an_answer_without_a_product_across_a_crash/1,
         a_journal_cut_short_at_boot/1, a_product_held_but_never_recorded/1,
         a_product_left_but_still_in_its_file/1, the_journal_alone/1,
         books_across_crashes/1, a_journal_at_its_bound/1,
         a_read_back_without_the_database/1, records_in_order_while_closed/1,
         a_product_failed_after_a_restart/1, a_product_saved_again_while_closed/1]).

-define(RETRY_WAIT_MS, 30000).

all() ->
    [database_unusable_then_back, database_lost_then_back, a_long_outage_of_the_database,
     writer_crash,
     time_in_a_state_across_a_crash,
     shifts_split_the_time,
     a_product_in_the_cell_and_after,
     a_product_left_across_a_crash,
     a_failed_product_left_across_a_crash,
     a_product_taken_again_across_a_crash,
     a_product_failed_after_a_restart,
     a_product_saved_again_while_closed,
     an_answer_across_a_crash,
     an_answer_without_a_product_across_a_crash,
     a_journal_cut_short_at_boot,
     a_product_held_but_never_recorded,
     a_product_left_but_still_in_its_file,
     the_journal_alone,
     books_across_crashes,
     a_journal_at_its_bound,
     a_read_back_without_the_database,
     records_in_order_while_closed].

init_per_testcase(Case, Config) when Case =:= time_in_a_state_across_a_crash;
                                     Case =:= shifts_split_the_time;
                                     Case =:= a_product_in_the_cell_and_after;
                                     Case =:= a_product_left_across_a_crash;
                                     Case =:= a_failed_product_left_across_a_crash;
                                     Case =:= a_product_taken_again_across_a_crash;
                                     Case =:= a_product_failed_after_a_restart;
                                     Case =:= a_product_saved_again_while_closed;
                                     Case =:= an_answer_across_a_crash;
                                     Case =:= an_answer_without_a_product_across_a_crash;
                                     Case =:= a_journal_cut_short_at_boot;
                                     Case =:= a_product_held_but_never_recorded;
                                     Case =:= a_product_left_but_still_in_its_file;
                                     Case =:= books_across_crashes;
                                     Case =:= records_in_order_while_closed ->
    Config1 = init_per_testcase({Case, common}, Config),
    Tab = ets:new(stats_suite_tasks, [public]),
    Tasks = [cell_test_task:spec(Id, Tab, self()) || Id <- [waits_a, waits_b]],
    ok = application:set_env(cell, cell_spec, #{name => <<"stats suite">>, tasks => Tasks}),
    Refs = maps:from_list([{Id, Ref} || #{id := Id, args := #{ref := Ref}} <- Tasks]),
    [{tab, Tab}, {refs, Refs} | Config1];
init_per_testcase({_Case, common}, Config) ->
    init_per_testcase(common, Config);
init_per_testcase(_Case, Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    %% The priv_dir is shared by every suite of the run: a root of this suite's own.
    Root = filename:join(?config(priv_dir, Config), "cell_stats_SUITE.root"),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    {ok, _} = application:ensure_all_started(cell_base),
    ok = application:set_env(cell, cell_spec, #{name => <<"stats suite">>, tasks => []}),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok = application:unset_env(cell, cell_spec),
    ok.

database_unusable_then_back(Config) ->
    Databases = filename:join(?config(root, Config), "Databases"),
    Peer = cell_test_db:foreign(Databases),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    Why = await_log(<<"statistics: the database cannot be opened">>),
    ?assertNotEqual(nomatch, binary:match(Why, atom_to_binary(Peer))),
    ?assertNotEqual(nomatch, binary:match(Why, <<"move the folder aside">>)),
    ?assertNotEqual(nomatch, binary:match(Why, <<"counting goes on in memory">>)),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    %% A record made meanwhile is kept for the database.
    ok = cell_stats:record(<<"S-1">>, measured, #{width => 12}),
    %% The folder moved aside: the statistics start a new database at their next try.
    ok = file:rename(Databases, Databases ++ ".old"),
    _ = await_log(<<"database table cell_trace_event created">>),
    ok = cell_stats:flush(),
    {ok, #{events := [#{event := measured, detail := #{width := 12}}]}} =
        cell_stats:product(<<"S-1">>).

%% The database goes away while the cell runs: what the history gets meanwhile is kept
%% in memory, in its order, and written when the database is back.
database_lost_then_back(_Config) ->
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_stats:record(<<"S-2">>, measured, #{width => 1}),
    ok = cell_stats:flush(),
    {ok, #{events := [#{detail := #{width := 1}}]}} = cell_stats:product(<<"S-2">>),
    stopped = mnesia:stop(),
    [ok = cell_stats:record(<<"S-2">>, measured, #{width => W}) || W <- lists:seq(2, 200)],
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    Why = await_log(<<"statistics: the database stopped working">>),
    ?assertNotEqual(nomatch, binary:match(Why, <<"counting goes on in memory">>)),
    %% The statistics start the database again at their next try.
    Back = await_log(<<"statistics: the database is open; the">>),
    ?assertNotEqual(nomatch, binary:match(Back, <<" 199 records ">>)),
    ok = cell_stats:flush(),
    {ok, #{events := Events}} = cell_stats:product(<<"S-2">>),
    ?assertEqual(lists:seq(1, 200), [W || #{detail := #{width := W}} <- Events]).

%% The database away so long that the history records waiting for it reach their
%% limit: the log says so when the oldest begin to be dropped, and how many were when
%% the database is back; the newest are written.
a_long_outage_of_the_database(_Config) ->
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_stats:record(<<"S-4">>, measured, #{width => 0}),
    ok = cell_stats:flush(),
    stopped = mnesia:stop(),
    [ok = cell_stats:record(<<"S-4">>, measured, #{width => W}) || W <- lists:seq(1, 10005)],
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    Full = await_log(<<"statistics: the database has been away so long">>),
    ?assertNotEqual(nomatch, binary:match(Full, <<"the oldest are dropped">>)),
    Back = await_log(<<"statistics: the database is open; the">>),
    ?assertNotEqual(nomatch, binary:match(Back, <<" 10000 records ">>)),
    ?assertNotEqual(nomatch, binary:match(Back, <<"the 5 oldest were dropped">>)),
    ok = cell_stats:flush(),
    {ok, #{events := Events}} = cell_stats:product(<<"S-4">>),
    ?assertEqual([0 | lists:seq(6, 10005)], [W || #{detail := #{width := W}} <- Events]).

%% The writer of the histories dies: the statistics stop with it, saying so, and their
%% supervisor starts both again; what was written stays, and writing goes on.
writer_crash(_Config) ->
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_stats:record(<<"S-3">>, measured, #{width => 1}),
    ok = cell_stats:flush(),
    Stats = whereis(cell_stats),
    {links, Links} = process_info(Stats, links),
    [Writer] = [P || P <- Links, is_pid(P),
                     proc_lib:initial_call(P) =:= {cell_stats_writer, init, ['Argument__1']}],
    MRef = monitor(process, Stats),
    exit(Writer, kill),
    receive {'DOWN', MRef, process, Stats, Why} -> ?assertEqual({history_writer, killed}, Why) end,
    _ = supervisor:which_children(cell_controller_sup),
    ?assertNotEqual(Stats, whereis(cell_stats)),
    ok = cell_stats:record(<<"S-3">>, measured, #{width => 2}),
    ok = cell_stats:flush(),
    {ok, #{events := Events}} = cell_stats:product(<<"S-3">>),
    ?assertEqual([1, 2], [W || #{detail := #{width := W}} <- Events]).

time_in_a_state_across_a_crash(_Config) ->
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    Ids = [waits_a, waits_b],
    %% Each task now waits for a command in READY-IDLE-STARVED, and stays there.
    [{ready, idle, starved} = cell_task_proc:state(Id) || Id <- Ids],
    ok = cell_stats:flush(),
    Before = times(Ids),
    %% Time passes, which is what is counted here.
    receive after 300 -> ok end,
    ok = cell_stats:flush(),
    Later = times(Ids),
    %% Nothing happened to the tasks; their time in their state grew with the clock.
    [?assert(starved_ms(Id, Later) - starved_ms(Id, Before) >= 300) || Id <- Ids],
    assert_adds_up(Ids),
    %% The statistics crash; the time until their last write stays where it was.
    LastWrite = meta(flushed),
    Old = whereis(cell_stats),
    MRef = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', MRef, process, Old, killed} -> ok end,
    %% The supervisor has handled the exit (it reached it before this call) and
    %% started the statistics again.
    _ = supervisor:which_children(cell_controller_sup),
    ?assertNotEqual(Old, whereis(cell_stats)),
    ok = cell_stats:flush(),
    After = times(Ids),
    [begin
         ?assert(starved_ms(Id, After) >= starved_ms(Id, Later)),
         ?assert(maps:get(off, maps:get(Id, After), 0) > maps:get(off, maps:get(Id, Later), 0))
     end || Id <- Ids],
    ?assert(meta(flushed) > LastWrite),
    assert_adds_up(Ids).

%% When a shift ends, the time of tasks that stay in their state is split there: the
%% ended shift holds its time to the microsecond, the next one the time since.
shifts_split_the_time(Config) ->
    %% One shift a day, beginning at the next whole minute at least 5 s away, saved
    %% before the statistics start counting.
    {ok, _} = application:ensure_all_started(cell),
    NowS = erlang:system_time(second),
    BoundaryS = case (NowS div 60 + 1) * 60 of
                    B when B - NowS < 5 -> B + 60;
                    B -> B
                end,
    {_, {H, M, 0}} = calendar:system_time_to_local_time(BoundaryS, second),
    Start = iolist_to_binary(io_lib:format("~2..0b:~2..0b", [H, M])),
    ok = cell_settings:put(statistics, #{shifts => [Start]}, <<"suite">>),
    ok = application:stop(cell),
    ok = application:stop(mnesia),
    ok = file:del_dir_r(filename:join(?config(root, Config), "Databases")),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    Ids = [waits_a, waits_b],
    [{ready, idle, starved} = cell_task_proc:state(Id) || Id <- Ids],
    ok = cell_stats:flush(),
    Running = cell_stats:shift_now(),
    Boundary = BoundaryS * 1000000,
    %% Time passes until the shift ends, which is what is counted here.
    receive after BoundaryS * 1000 + 100 - os:system_time(millisecond) -> ok end,
    ok = cell_stats:flush(),
    Next = cell_stats:shift_now(),
    ?assertNotEqual(Running, Next),
    ?assertEqual([total, Running, Next], cell_stats:periods()),
    Ran = cell_stats:counters(Running),
    Later = cell_stats:counters(Next),
    [begin
         %% The ended shift: from the task's first sight to the shift's end, exactly,
         %% most of it waiting for a product.
         ?assertEqual({Id, Boundary - meta({first, Id})}, {Id, time_sum(Id, Ran)}),
         ?assert(maps:get({time, starved}, maps:get(Id, Ran)) > 1000000),
         %% The next shift: the time since, in the same state.
         ?assert(maps:get({time, starved}, maps:get(Id, Later)) > 0),
         ?assert(time_sum(Id, Later) =< os:system_time(microsecond) - Boundary)
     end || Id <- Ids],
    %% The report of the ended shift covers it up to its end.
    #{to := To, tasks := Tasks} = cell_stats:summary(Running),
    ?assertEqual(BoundaryS * 1000, To),
    [?assert(abs(maps:get(total_ms, maps:get(Id, Tasks))
                 - (Boundary - meta({first, Id})) div 1000) =< 3)
     || Id <- Ids],
    assert_adds_up(Ids).

%% A product's summary while it is in the cell follows its fields (kept with the products
%% in the cell, also across a crash of the statistics); once it is gone, the summary
%% says how it left.
a_product_in_the_cell_and_after(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved]),
    Serial = <<"S-42">>,
    Good = cell_product:new(Serial, <<"r1">>),
    save(Ref, Good),
    ?assertMatch({ok, #{serial := Serial, status := in_cell, recipe := <<"r1">>, failed := false,
                        entry_task := waits_a, left := undefined,
                        events := [#{event := entered, task := waits_a}]}},
                 cell_stats:product(Serial)),
    #{in_cell := 1} = cell_stats:summary(total),
    %% Marked failed while in the cell: the summary says so at once ...
    save(Ref, Good#{failed => true}),
    ?assertMatch({ok, #{status := in_cell, failed := true}}, cell_stats:product(Serial)),
    %% ... and after the statistics crashed and read the products in the cell again.
    Old = whereis(cell_stats),
    MRef = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', MRef, process, Old, killed} -> ok end,
    _ = supervisor:which_children(cell_controller_sup),
    ok = cell_stats:flush(),
    ?assertMatch({ok, #{status := in_cell, failed := true}}, cell_stats:product(Serial)),
    %% Forgotten by its task: found scrapped after two writes, still failed.
    ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
    receive {cell_event, #{type := product_saved, task := waits_a}} -> ok
    after ?RETRY_WAIT_MS -> ct:fail(product_not_cleared)
    end,
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    {ok, #{status := scrapped, failed := true, events := Events}} = cell_stats:product(Serial),
    ?assertEqual(scrapped, maps:get(event, lists:last(Events))),
    ?assertMatch(#{in_cell := 0, cell := #{in := 1, scrapped := 1}}, cell_stats:summary(total)).

%% A product that entered and left while the statistics took nothing (they are
%% suspended, then killed: what they were told dies with them, as in a crash of the
%% node) is recorded after their restart as left, once, with its whole history, from
%% the trace journal; it is never taken for scrapped. Killed again right after their
%% restart, before or after they wrote (whichever comes first), they still count each
%% product once and write each history entry once.
a_product_left_across_a_crash(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    ok = cell_stats:flush(),
    %% The suite's database keeps what its other cases counted.
    Before = cell_counts(),
    Journal = cell_trace_journal:path(),
    Serial = <<"S-77">>,
    in_and_out(Ref, Serial, <<"r7">>),
    ok = kill_stats(),
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertMatch({ok, #{status := out, recipe := <<"r7">>, entry_task := waits_a,
                        exit_task := waits_a}}, cell_stats:product(Serial)),
    ?assertEqual([entered, item_transfer_out, left], history(Serial)),
    ?assertEqual(#{in => 1, out => 1, good => 1, scrapped => 0}, counted_since(Before)),
    ?assertEqual(0, cell_stats:in_cell()),
    %% Written to the database: the journal lets its records go (told before the
    %% flush returned; a call to it comes after that).
    _ = sys:get_state(cell_trace_journal),
    {ok, Trimmed} = file:read_file(Journal),
    ?assertMatch({[], 0, 0}, cell_trace_journal:decode(Trimmed)),
    %% Twice in a row.
    Serial2 = <<"S-78">>,
    in_and_out(Ref, Serial2, <<"r8">>),
    ok = kill_stats(),
    ok = kill_stats(),
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertEqual([entered, item_transfer_out, left], history(Serial2)),
    ?assertEqual([entered, item_transfer_out, left], history(Serial)),
    ?assertEqual(#{in => 2, out => 2, good => 2, scrapped => 0}, counted_since(Before)),
    ?assertEqual(0, cell_stats:in_cell()).

%% A product marked failed in the cell (its inspection failed: a save of its fields,
%% which is not in the trace journal) leaves; the statistics take its exit record and
%% write its history, then are killed before their periodic write, so the books still
%% have it as it entered (not failed) and the exit record is applied again at their
%% restart. It left once: one `left' entry, as failed, and counted once, as failed.
a_failed_product_left_across_a_crash(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    %% The statistics' tables are there once they answer.
    ok = cell_stats:flush(),
    {ok, _} = mnesia:subscribe({table, cell_trace_event, simple}),
    {Serial, Lock, Before} = failed_out_before_the_write(Ref),
    %% Their periodic write, if it came, waits for the lock and dies with them.
    ok = kill_stats(),
    Lock ! release,
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertEqual([entered, changed, item_transfer_out, left], history(Serial)),
    {ok, #{status := out, failed := true, events := Events}} = cell_stats:product(Serial),
    ?assertMatch([#{quality := failed}], [E || #{event := left} = E <- Events]),
    ?assertEqual(#{in => 1, out => 1, good => 0, failed => 1, scrapped => 0},
                 counted_since(Before)).

%% A product the cell knows is taken by another task after saves of its fields that
%% the trace journal does not keep (taking it is a record: that task did not hold it);
%% the statistics take it all and write its history, then are killed before their
%% periodic write, and the records are applied again at their restart, without those
%% saves. What changed when the second task took it is in the history once, as the
%% statistics saw it the first time.
a_product_taken_again_across_a_crash(Config) ->
    #{waits_a := RefA, waits_b := RefB} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved]),
    ok = cell_stats:flush(),
    {ok, _} = mnesia:subscribe({table, cell_trace_event, simple}),
    Name = fun(Try) -> iolist_to_binary(io_lib:format("T-~b", [Try])) end,
    Steps = fun(Serial) ->
                    P = (cell_product:new(Serial, <<"rt">>))#{stage => 0},
                    ok = cell_test_task:command(waits_a, RefA, {product, P}),
                    await_event(product_saved, Serial),
                    ok = cell_test_task:command(waits_a, RefA, {product, P#{stage => 1}}),
                    await_event(product_saved, Serial),
                    ok = cell_test_task:command(waits_a, RefA, {product, undefined}),
                    await_event(product_saved, undefined),
                    ok = cell_test_task:command(waits_b, RefB,
                                                {product, P#{stage => 1, station => <<"b">>}}),
                    await_event(waits_b, product_saved, Serial)
            end,
    ByB = fun(#{event := changed, task := waits_b}) -> true;
             (_) -> false
          end,
    {Serial, Lock, _Before} = unwritten(Name, Steps, ByB, 1),
    ok = kill_stats(),
    Lock ! release,
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    {ok, #{status := in_cell, events := Events}} = cell_stats:product(Serial),
    ?assertEqual([#{station => <<"b">>}],
                 [Changes || #{changes := Changes} = E <- Events, ByB(E)]).

%% A product in the cell is marked failed (its inspection failed) after the statistics
%% restarted: they know it from its row in the cell, without the fields its task last
%% saved. The row says failed from then on, as the cell's page and the product's
%% record show it, before the product leaves, and its history has the change.
a_product_failed_after_a_restart(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    P = cell_product:new(<<"R-1">>, <<"rf">>),
    ok = save(Ref, P),
    ?assertMatch({ok, #{status := in_cell, failed := false}}, cell_stats:product(<<"R-1">>)),
    ok = kill_stats(),
    ok = save(Ref, P#{failed => true}),
    {ok, #{status := in_cell, failed := true, recipe := <<"rf">>, events := Events}} =
        cell_stats:product(<<"R-1">>),
    %% What changed, as far as the row tells: the verdict, not the recipe it kept.
    ?assertEqual([#{failed => true}], [C || #{event := changed, changes := C} <- Events]),
    sent_out(Ref, <<"R-1">>).

%% A product in the cell is saved again by its task (a save the trace journal does not
%% keep: the task took it before) while the statistics, restarted, cannot open the
%% database. When the same database opens, the product is the one it had in the cell:
%% it entered once, and is counted in once.
a_product_saved_again_while_closed(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    Databases = filename:join(?config(root, Config), "Databases"),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    ok = cell_stats:flush(),
    Before = cell_counts(),
    InCell = cell_stats:in_cell(),
    P = cell_product:new(<<"C-1">>, <<"rc">>),
    ok = save(Ref, P),
    %% The database's folder refuses the write test made before opening it: the
    %% statistics restarted cannot open it.
    ok = cell_log:subscribe(),
    stopped = mnesia:stop(),
    Probe = filename:join(Databases, ".cellrt-write-test"),
    ok = file:make_dir(Probe),
    ok = kill_stats(),
    _ = await_log(<<"statistics: the database cannot be opened">>),
    ok = cell_test_task:command(waits_a, Ref, {product, P#{stage => 1}}),
    await_event(product_saved, <<"C-1">>),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    ok = file:del_dir(Probe),
    _ = await_log(<<"statistics: the database is open">>),
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertEqual(#{in => 1, out => 0, good => 0, scrapped => 0}, counted_since(Before)),
    ?assertEqual(InCell + 1, cell_stats:in_cell()),
    ?assertEqual([entered], history(<<"C-1">>)),
    sent_out(Ref, <<"C-1">>).

%% The product enters and its entry is written; with the statistics suspended it is
%% marked failed, sent out and let go; then they take all that and write its history,
%% and none of it is in their periodic write (see unwritten/4).
failed_out_before_the_write(Ref) ->
    Enter = fun(Try) ->
                    Serial = iolist_to_binary(io_lib:format("F-~b", [Try])),
                    ok = cell_test_task:command(waits_a, Ref,
                                                {product, cell_product:new(Serial, <<"rf">>)}),
                    await_event(product_saved, Serial),
                    ok = cell_stats:flush(),
                    Serial
            end,
    Out = fun(Serial) ->
                  Failed = (cell_product:new(Serial, <<"rf">>))#{failed => true},
                  ok = cell_test_task:command(waits_a, Ref, {product, Failed}),
                  await_event(product_saved, Serial),
                  ok = cell_test_task:command(waits_a, Ref, {event, {transfer_out, Serial}}),
                  await_event(item_transfer_out, Serial),
                  ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
                  await_event(product_saved, undefined)
          end,
    unwritten(Enter, Out, fun(#{event := E}) -> E =:= left end, 1).

%% `Prepare' (given the try's number, it answers a serial), then, with the statistics
%% suspended, `Steps' on that serial; then, the counters' table locked so that no
%% periodic write can record what follows, the statistics take it all, until the
%% serial's history entry `Written' picks is written. Answers the serial, the lock's
%% holder and the counters before. A periodic write already asked for among those
%% events would record them: the product then went its way unharmed, and the next try
%% is made. The caller subscribed to the history table's events.
unwritten(_Prepare, _Steps, _Written, 10) ->
    ct:fail(periodic_write_in_every_try);
unwritten(Prepare, Steps, Written, Try) ->
    ok = cell_stats:flush(),
    Before = maps:put(failed, maps:get(failed, maps:get(cell, cell_stats:summary(total))),
                      cell_counts()),
    Serial = Prepare(Try),
    ok = sys:suspend(cell_stats),
    ok = Steps(Serial),
    {messages, Queued} = process_info(whereis(cell_stats), messages),
    case lists:member(flush, Queued) of
        true ->
            ok = sys:resume(cell_stats),
            unwritten(Prepare, Steps, Written, Try + 1);
        false ->
            Me = self(),
            Lock = spawn_link(fun() -> hold_counters(Me) end),
            receive {counters_locked, Lock} -> ok end,
            ok = sys:resume(cell_stats),
            ok = await_history(Serial, Written),
            {Serial, Lock, Before}
    end.

await_history(Serial, Written) ->
    receive
        {mnesia_table_event, {write, {cell_trace_event, Serial, _, _, Entry}, _}} ->
            case Written(Entry) of
                true -> ok;
                false -> await_history(Serial, Written)
            end
    after ?RETRY_WAIT_MS -> ct:fail({not_written, Serial})
    end.

%% Holds the counters' table locked until told to let it go.
hold_counters(Owner) ->
    {atomic, ok} = mnesia:transaction(fun() ->
                                               ok = mnesia:write_lock_table(cell_stats_counter),
                                               Owner ! {counters_locked, self()},
                                               receive release -> ok end
                                       end).

cell_counts() ->
    #{cell := Cell} = cell_stats:summary(total),
    maps:with([in, out, good, scrapped], Cell).

counted_since(Before) ->
    #{cell := #{failed := Failed}} = cell_stats:summary(total),
    maps:map(fun(K, V) -> V - maps:get(K, Before) end,
             maps:with(maps:keys(Before), (cell_counts())#{failed => Failed})).

%% An operator's answer to an error of a task holding a product, given while the
%% statistics took nothing and lost with them, is in the product's history after their
%% restart, from the trace journal: who answered, and with what.
an_answer_across_a_crash(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, alarm_raised, alarm_cleared]),
    Serial = <<"S-79">>,
    ok = cell_test_task:command(waits_a, Ref, {product, cell_product:new(Serial, <<"r9">>)}),
    await_event(product_saved, Serial),
    Id = answered_unseen(Ref, <<"operator 7">>),
    ok = kill_stats(),
    ok = cell_stats:flush(),
    {ok, #{events := Events}} = cell_stats:product(Serial),
    ?assertMatch([#{event := alarm_answered, id := Id, solution := retry,
                    who := <<"operator 7">>, task := waits_a}],
                 [E || #{event := alarm_answered} = E <- Events]).

%% An answer to an error of a task that held no product, given while the statistics
%% took nothing and lost with them; then the task takes a product. Applied from the
%% trace journal after their restart, the answer is in no product's history: not in
%% the one the task holds by then.
an_answer_without_a_product_across_a_crash(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, alarm_raised, alarm_cleared]),
    ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
    await_event(product_saved, undefined),
    _ = answered_unseen(Ref, <<"operator 8">>),
    Serial = <<"S-83">>,
    ok = cell_test_task:command(waits_a, Ref, {product, cell_product:new(Serial, <<"r13">>)}),
    await_event(product_saved, Serial),
    ok = kill_stats(),
    ok = cell_stats:flush(),
    ?assertEqual([entered], history(Serial)).

%% An error of `waits_a' raised and answered with Retry by `Who' while the statistics,
%% their counts written first, take nothing (suspended; the caller kills them next):
%% the answer's alarm id.
answered_unseen(Ref, Who) ->
    ok = cell_stats:flush(),
    ok = sys:suspend(cell_stats),
    ok = cell_test_task:command(waits_a, Ref, {error, [retry, reset]}),
    Id = receive {cell_event, #{type := alarm_raised, task := waits_a, alarm := #{id := I}}} -> I
         after ?RETRY_WAIT_MS -> ct:fail(no_error_raised)
         end,
    ok = cell_alarms:answer(Id, retry, Who),
    receive {cell_event, #{type := alarm_cleared, task := waits_a}} -> ok
    after ?RETRY_WAIT_MS -> ct:fail(error_not_cleared)
    end,
    Id.

%% A node that died after its journal took a product's entry and exit, and in the
%% middle of writing a third record, before the statistics wrote anything: at boot the
%% torn record is dropped and the log says so in words, and the product is recorded as
%% entered and left, once.
a_journal_cut_short_at_boot(Config) ->
    %% A database and products of this case alone (mnesia is stopped): its totals are
    %% this case's.
    Databases = filename:join(?config(root, Config), "Databases"),
    _ = file:del_dir_r(Databases),
    _ = file:del_dir_r(filename:join(?config(root, Config), "Data")),
    ok = filelib:ensure_dir(filename:join(Databases, "x")),
    Serial = <<"S-80">>,
    At = erlang:system_time(microsecond) - 5000000,
    Fields = #{task => waits_a, zone => <<"waits_a">>, lane => <<"Test">>, item => Serial},
    Records = [Fields#{id => {1, 1}, at => At, type => product_saved, in_transit => false,
                       product => cell_product:new(Serial, <<"r10">>)},
               Fields#{id => {1, 2}, at => At + 1000, type => item_transfer_out}],
    Third = cell_trace_journal:encode(Fields#{id => {1, 3}, at => At + 2000,
                                              type => item_transfer_in}),
    ok = file:write_file(filename:join(Databases, "cell_trace.journal"),
                         [[cell_trace_journal:encode(R) || R <- Records],
                          binary:part(Third, 0, byte_size(Third) - 3)]),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    _ = await_log(<<"trace journal ">>),
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertMatch({ok, #{status := out, recipe := <<"r10">>, entry_task := waits_a}},
                 cell_stats:product(Serial)),
    ?assertEqual([entered, item_transfer_out, left], history(Serial)),
    ?assertMatch(#{cell := #{in := 1, out := 1, scrapped := 0}}, cell_stats:summary(total)).

%% A task holds a product (its file says so) that no record of the database or the
%% journal knows (its entry was lost before the journal kept such things): it enters
%% with the recipe of its product file, never a blank one, and the log says so.
a_product_held_but_never_recorded(Config) ->
    Root = ?config(root, Config),
    _ = file:del_dir_r(filename:join(Root, "Databases")),
    _ = file:del_dir_r(filename:join(Root, "Data")),
    Serial = <<"S-81">>,
    Path = cell_product:path(<<"waits_a">>, <<"Test">>),
    ok = filelib:ensure_dir(Path),
    ok = cell_product:save(Path, cell_product:stored(cell_product:new(Serial, <<"r11">>), 1,
                                                     undefined)),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    Line = await_log(<<"statistics: product S-81 is held by waits_a">>),
    ?assertNotEqual(nomatch, binary:match(Line, <<"with the recipe of its product file">>)),
    ok = cell_stats:flush(),
    ?assertMatch({ok, #{status := in_cell, recipe := <<"r11">>, entry_task := waits_a,
                        events := [#{event := entered, recipe := <<"r11">>}]}},
                 cell_stats:product(Serial)).

%% A node killed after a task's exit record was durable and before the task cleared
%% its file: after the restart the product is recorded as left, once; the task's copy
%% is not counted again, whether the task saves it, sends it out again or lets it go,
%% and never scrapped.
a_product_left_but_still_in_its_file(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    Root = ?config(root, Config),
    _ = file:del_dir_r(filename:join(Root, "Databases")),
    _ = file:del_dir_r(filename:join(Root, "Data")),
    Serial = <<"S-82">>,
    Product = cell_product:new(Serial, <<"r12">>),
    Path = cell_product:path(<<"waits_a">>, <<"Test">>),
    ok = filelib:ensure_dir(Path),
    ok = cell_product:save(Path, cell_product:stored(Product, 1, undefined)),
    At = erlang:system_time(microsecond) - 5000000,
    Fields = #{task => waits_a, zone => <<"waits_a">>, lane => <<"Test">>, item => Serial},
    Records = [Fields#{id => {1, 1}, at => At, type => product_saved, in_transit => false,
                       product => Product},
               Fields#{id => {1, 2}, at => At + 1000, type => item_transfer_out}],
    Databases = filename:join(Root, "Databases"),
    ok = filelib:ensure_dir(filename:join(Databases, "x")),
    ok = file:write_file(filename:join(Databases, "cell_trace.journal"),
                         [cell_trace_journal:encode(R) || R <- Records]),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    _ = await_log(<<"statistics: product S-82 left the cell through waits_a">>),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    %% The task saves its copy, sends it out again, and lets it go.
    ok = cell_test_task:command(waits_a, Ref, {product, Product#{failed => true}}),
    await_event(product_saved, Serial),
    ok = cell_test_task:command(waits_a, Ref, {event, {transfer_out, Serial}}),
    await_event(item_transfer_out, Serial),
    ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
    await_event(product_saved, undefined),
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertMatch({ok, #{status := out, recipe := <<"r12">>}}, cell_stats:product(Serial)),
    %% What the task did is in the history; the product left once.
    ?assertEqual([entered, item_transfer_out, left, item_transfer_out], history(Serial)),
    ?assertMatch(#{cell := #{in := 1, out := 1, scrapped := 0}, in_cell := 0},
                 cell_stats:summary(total)).

%% A product entered before a crash (its record is in the journal only) and leaves
%% while the statistics cannot open their database: its exit, which reaches them as an
%% event, is applied after its entry, as the journal has them, once the database is
%% open. It entered and left, once; it is never taken for scrapped.
records_in_order_while_closed(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    Root = ?config(root, Config),
    Databases = filename:join(Root, "Databases"),
    _ = file:del_dir_r(Databases),
    _ = file:del_dir_r(filename:join(Root, "Data")),
    _ = cell_test_db:foreign(Databases),
    Serial = <<"S-85">>,
    Product = cell_product:new(Serial, <<"r15">>),
    Path = cell_product:path(<<"waits_a">>, <<"Test">>),
    ok = filelib:ensure_dir(Path),
    ok = cell_product:save(Path, cell_product:stored(Product, 1, undefined)),
    Entry = #{id => {1, 1}, at => erlang:system_time(microsecond) - 5000000,
              type => product_saved, task => waits_a, zone => <<"waits_a">>,
              lane => <<"Test">>, item => Serial, in_transit => false, product => Product},
    ok = file:write_file(filename:join(Databases, "cell_trace.journal"),
                         cell_trace_journal:encode(Entry)),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    _ = await_log(<<"statistics: the database cannot be opened">>),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    ok = cell_test_task:command(waits_a, Ref, {event, {transfer_out, Serial}}),
    await_event(item_transfer_out, Serial),
    ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
    await_event(product_saved, undefined),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    %% The other node's database moved aside (the journal stays): the statistics start
    %% a new one at their next try.
    Aside = Databases ++ ".other",
    ok = file:make_dir(Aside),
    [ok = file:rename(filename:join(Databases, F), filename:join(Aside, F))
     || F <- element(2, file:list_dir(Databases)), F =/= "cell_trace.journal"],
    _ = await_log(<<"database table cell_trace_event created">>),
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    ?assertEqual([entered, item_transfer_out, left], history(Serial)),
    ?assertMatch(#{cell := #{in := 1, out := 1, scrapped := 0}, in_cell := 0},
                 cell_stats:summary(total)),
    ok = application:stop(cell),
    _ = application:stop(mnesia),
    ok = file:del_dir_r(Aside).

%% The books after crashes of the statistics at any point of products' way: each
%% product enters and leaves, and the statistics are killed (once, or twice in a row,
%% replaying the journal again before they wrote) right after they took a record and
%% before their periodic write, or after a write. Whatever the crash points, the
%% counters in, out and scrapped and the products in the cell are what the histories
%% say, and `in = out + scrapped + in_cell'.
books_across_crashes(Config) ->
    #{waits_a := Ref} = ?config(refs, Config),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_controller:start(),
    ok = cell_controller:sync(),
    ok = cell_events:subscribe([product_saved, item_transfer_out]),
    %% The statistics run under an owner of the case's own that starts them again at
    %% once: killed as often as here under the controller, they would spend its
    %% restart intensity, and their restart would restart the tasks after them.
    ok = supervisor:terminate_child(cell_controller_sup, cell_stats),
    Owner = spawn(fun() -> process_flag(trap_exit, true), stats_owner() end),
    ok = start_own_stats(Owner),
    Serials = counters:new(1, []),
    Prop = ?FORALL(Plan, list({crash(), crash(), crash()}),
                   books_hold(Ref, Owner, Serials, Plan)),
    ?assert(proper:quickcheck(Prop, [{to_file, user}, {numtests, 12}, {max_size, 6}])),
    Stats = whereis(cell_stats),
    MRef = monitor(process, Stats),
    Owner ! stop,
    receive {'DOWN', MRef, process, Stats, _} -> ok end,
    {ok, _} = supervisor:restart_child(cell_controller_sup, cell_stats),
    ok.

stats_owner() ->
    receive
        {start, From} ->
            {ok, Pid} = cell_stats:start_link(#{exits => [waits_a, waits_b]}),
            From ! {stats_started, Pid},
            stats_owner();
        {'EXIT', _, _} ->
            stats_owner();
        stop ->
            exit(shutdown)
    end.

start_own_stats(Owner) ->
    Owner ! {start, self()},
    receive {stats_started, _} -> ok
    after ?RETRY_WAIT_MS -> ct:fail(statistics_not_started)
    end.

%% Kills the statistics brutally and starts them again.
kill_own_stats(Owner) ->
    Old = whereis(cell_stats),
    MRef = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', MRef, process, Old, killed} -> ok end,
    start_own_stats(Owner).

%% What happens after a step: nothing, a write, a crash, two crashes in a row.
crash() ->
    oneof([none, flush, kill, kill_twice]).

books_hold(Ref, Owner, Serials, Plan) ->
    ok = cell_stats:flush(),
    Before = cell_counts(),
    #{in_cell := InCellBefore} = cell_stats:summary(total),
    Mine = [begin
                ok = counters:add(Serials, 1, 1),
                Serial = iolist_to_binary(io_lib:format("B-~b", [counters:get(Serials, 1)])),
                ok = cell_test_task:command(waits_a, Ref,
                                            {product, cell_product:new(Serial, <<"rb">>)}),
                await_event(product_saved, Serial),
                ok = after_step(AfterIn, Owner),
                ok = cell_test_task:command(waits_a, Ref, {event, {transfer_out, Serial}}),
                await_event(item_transfer_out, Serial),
                ok = after_step(AfterOut, Owner),
                ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
                await_event(product_saved, undefined),
                ok = after_step(AfterClear, Owner),
                Serial
            end || {AfterIn, AfterOut, AfterClear} <- Plan],
    [ok = cell_stats:flush() || _ <- [1, 2, 3]],
    #{in_cell := InCell} = cell_stats:summary(total),
    Counted = counted_since(Before),
    Histories = [history(S) || S <- Mine],
    FromHistories = #{in => count_of(entered, Histories), out => count_of(left, Histories),
                      good => count_of(left, Histories),
                      scrapped => count_of(scrapped, Histories)},
    Expected = #{in => length(Plan), out => length(Plan), good => length(Plan),
                 scrapped => 0},
    ?WHENFAIL(ct:pal("plan ~p~ncounted ~p~nfrom the histories ~p~nhistories ~p~n"
                     "in the cell ~b, before ~b", [Plan, Counted, FromHistories, Histories,
                                                  InCell, InCellBefore]),
              Counted =:= FromHistories andalso Counted =:= Expected
              andalso InCell =:= InCellBefore
              andalso lists:all(fun(H) -> H =:= [entered, item_transfer_out, left] end,
                                Histories)).

%% The statistics have taken what came before (their journal's records come before the
%% events awaited), then crash, write, or go on.
after_step(none, _Owner) ->
    ok;
after_step(flush, _Owner) ->
    cell_stats:flush();
after_step(kill, Owner) ->
    _ = sys:get_state(cell_stats),
    kill_own_stats(Owner);
after_step(kill_twice, Owner) ->
    _ = sys:get_state(cell_stats),
    ok = kill_own_stats(Owner),
    kill_own_stats(Owner).

count_of(Event, Histories) ->
    length([H || H <- Histories, lists:member(Event, H)]).

%% The trace journal while the database cannot be opened: it only grows. Near its bound
%% (the statistics settings' journal_max_mb) a warning is raised and the log says so;
%% at the bound a record is refused, never written, and every record kept before stays
%% in the file; with the bound raised, records are taken again and the warning goes.
a_journal_at_its_bound(Config) ->
    Databases = filename:join(?config(root, Config), "Databases"),
    _ = file:del_dir_r(Databases),
    _ = cell_test_db:foreign(Databases),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    _ = await_log(<<"statistics: the database cannot be opened">>),
    ok = cell_settings:put(statistics, #{journal_max_mb => 1}, <<"test">>),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    %% Records of some 100 kB: eight are below 80 % of 1 MB, nine above.
    Pad = binary:copy(<<"x">>, 100 * 1024),
    Append = fun(N) -> cell_trace_journal:append(#{type => test, task => waits_a,
                                                    n => N, pad => Pad})
             end,
    Eight = [Id || N <- lists:seq(1, 8), {ok, Id} <- [Append(N)]],
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    ok = cell_alarms:sync(),
    ?assertNot(cell_alarms:has_warning(cell)),
    {ok, Ninth} = Append(9),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    Line = await_log(<<"statistics: The trace journal holds 8">>),
    ?assertNotEqual(nomatch, binary:match(Line, <<"of its 1 MB">>)),
    ok = cell_alarms:sync(),
    ?assertMatch([#{kind := warning, local_id := <<"trace_journal">>}], cell_alarms:list(cell)),
    %% The tenth fits, the eleventh does not: refused, and the log says why once.
    {ok, Tenth} = Append(10),
    ?assertEqual({error, journal_full}, Append(11)),
    Full = await_log(<<"trace journal ">>),
    ?assertNotEqual(nomatch, binary:match(Full, <<"is full">>)),
    ?assertNotEqual(nomatch, binary:match(Full, <<"nothing recorded is lost">>)),
    ?assertEqual({error, journal_full}, Append(12)),
    {ok, Bin} = file:read_file(cell_trace_journal:path()),
    {Frames, _, 0} = cell_trace_journal:decode(Bin),
    ?assertEqual(Eight ++ [Ninth, Tenth], [Id || {Id, _} <- Frames]),
    ?assert(byte_size(Bin) =< 1024 * 1024),
    %% A larger bound: taken again, and the warning goes (1 MB of 2 is below 70 %).
    ok = cell_settings:put(statistics, #{journal_max_mb => 2}, <<"test">>),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    Again = await_log(<<"trace journal ">>),
    ?assertNotEqual(nomatch, binary:match(Again, <<"new records are taken again">>)),
    {ok, Thirteenth} = Append(13),
    ?assert(Thirteenth > Tenth),
    ok = cell_alarms:sync(),
    ?assertEqual([], cell_alarms:list(cell)),
    ok = application:stop(cell),
    _ = application:stop(mnesia),
    ok = file:del_dir_r(Databases).

%% What the statistics read back when they open their database (the last write, the
%% products in the cell, the id of the last journal record applied) is read whole or
%% not at all: without the database it is an error, never an empty database (taken for
%% one, the statistics counted with no mark and never trimmed the journal, and a crash
%% then counted its records again).
a_read_back_without_the_database(_Config) ->
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_stats:flush(),
    ?assertMatch({ok, #{products := _, mark := _}}, cell_stats_db:at_open()),
    stopped = mnesia:stop(),
    ?assertMatch({error, _}, cell_stats_db:at_open()).

%% The trace journal by itself: writers at once each get their own id; its reader gets
%% every record once, in the order of the ids, before the writers are answered; the
%% file holds them; a trim keeps only the later ones; started again, it reads them
%% back and its new ids come after them.
the_journal_alone(_Config) ->
    _ = file:delete(cell_trace_journal:path()),
    {ok, J} = cell_trace_journal:start_link(),
    [] = cell_trace_journal:attach(),
    Me = self(),
    Writers = [spawn_link(fun() ->
                                  Ids = [begin
                                             {ok, Id} = cell_trace_journal:append(
                                                          #{type => test, task => waits_a,
                                                            item => <<"W">>, n => N}),
                                             Id
                                         end || N <- lists:seq(1, 50)],
                                  Me ! {ids, self(), Ids}
                          end) || _ <- lists:seq(1, 20)],
    Answered = lists:append([receive {ids, W, Ids} -> Ids end || W <- Writers]),
    ?assertEqual(1000, length(lists:usort(Answered))),
    Forwarded = forwarded(1000, []),
    ?assertEqual(lists:sort(Answered), [Id || #{id := Id} <- Forwarded]),
    {ok, Bin} = file:read_file(cell_trace_journal:path()),
    {Frames, _, 0} = cell_trace_journal:decode(Bin),
    ?assertEqual([Id || #{id := Id} <- Forwarded], [Id || {Id, _} <- Frames]),
    Upto = lists:nth(990, lists:sort(Answered)),
    ok = cell_trace_journal:trim(Upto),
    Kept = lists:nthtail(990, Forwarded),
    ?assertEqual(Kept, cell_trace_journal:attach()),
    unlink(J),
    ok = gen_server:stop(J),
    {ok, J2} = cell_trace_journal:start_link(),
    ?assertEqual(Kept, cell_trace_journal:attach()),
    {ok, Next} = cell_trace_journal:append(#{type => test, task => waits_a}),
    ?assert(Next > lists:max(Answered)),
    %% Its reader had it before its writer was answered (both are this process: the
    %% journal's messages to it arrive in the order sent).
    receive {cell_trace_journal, [#{id := Next}]} -> ok
    after 0 -> ct:fail(record_not_before_answer)
    end,
    unlink(J2),
    ok = gen_server:stop(J2).

forwarded(0, Acc) ->
    lists:append(lists:reverse(Acc));
forwarded(N, Acc) ->
    receive {cell_trace_journal, Records} -> forwarded(N - length(Records), [Records | Acc])
    after ?RETRY_WAIT_MS -> ct:fail({records_missing, N})
    end.

%% With the statistics suspended: the product enters at waits_a, leaves the cell from
%% it, and the task forgets it.
in_and_out(Ref, Serial, Recipe) ->
    ok = sys:suspend(cell_stats),
    ok = cell_test_task:command(waits_a, Ref, {product, cell_product:new(Serial, Recipe)}),
    await_event(product_saved, Serial),
    sent_out(Ref, Serial).

%% The task sends its product out and lets it go: the next case finds it gone.
sent_out(Ref, Serial) ->
    ok = cell_test_task:command(waits_a, Ref, {event, {transfer_out, Serial}}),
    await_event(item_transfer_out, Serial),
    ok = cell_test_task:command(waits_a, Ref, {product, undefined}),
    await_event(product_saved, undefined).

await_event(Type, Serial) ->
    await_event(waits_a, Type, Serial).

await_event(Task, Type, Serial) ->
    receive {cell_event, #{type := Type, task := Task, item := Serial}} -> ok
    after ?RETRY_WAIT_MS -> ct:fail({no_event, Task, Type, Serial})
    end.

%% Kills the statistics and returns once their supervisor has started them again.
kill_stats() ->
    Old = whereis(cell_stats),
    MRef = monitor(process, Old),
    exit(Old, kill),
    receive {'DOWN', MRef, process, Old, killed} -> ok end,
    _ = supervisor:which_children(cell_controller_sup),
    ok.

history(Serial) ->
    {ok, #{events := Events}} = cell_stats:product(Serial),
    [E || #{event := E} <- Events].

%% The task saves the product; returns once the statistics have written what it did.
save(Ref, Product) ->
    Serial = maps:get(serial, Product),
    ok = cell_test_task:command(waits_a, Ref, {product, Product}),
    receive {cell_event, #{type := product_saved, task := waits_a, item := Serial}} -> ok
    after ?RETRY_WAIT_MS -> ct:fail({product_not_saved, Product})
    end,
    ok = cell_stats:flush(),
    ok = cell_stats:flush().

time_sum(Id, Counters) ->
    lists:sum([V || {{time, _}, V} <- maps:to_list(maps:get(Id, Counters, #{}))]).

%% Per task, its time in each state in milliseconds, up to the last write.
times(Ids) ->
    Counters = cell_stats:counters(total),
    maps:from_list([{Id, maps:from_list([{S, V div 1000}
                                          || {{time, S}, V} <- maps:to_list(maps:get(Id, Counters))])}
                    || Id <- Ids]).

starved_ms(Id, Times) ->
    maps:get(starved, maps:get(Id, Times), 0).

%% For every task, its states add up to the time since it was first seen.
assert_adds_up(Ids) ->
    Checks = cell_stats:time_check(),
    [?assertEqual({Id, Span}, {Id, Sum}) || Id <- Ids, {Sum, Span} <- [maps:get(Id, Checks)]].

meta(Key) ->
    [{_, _, V}] = mnesia:dirty_read(cell_stats_counter, {meta, Key}),
    V.

%% The text of the first task log line that begins with `Prefix'.
await_log(Prefix) ->
    receive
        {cell_log, #{text := Text}} ->
            case binary:longest_common_prefix([Text, Prefix]) =:= byte_size(Prefix) of
                true -> Text;
                false -> await_log(Prefix)
            end
    after ?RETRY_WAIT_MS ->
        ct:fail({no_log_line, Prefix})
    end.
