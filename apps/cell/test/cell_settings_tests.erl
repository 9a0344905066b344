%% The settings owner: files, revisions, refused files at boot, snapshots, subscribers,
%% and a property that any sequence of good and bad changes leaves exactly the good
%% ones in force, on disk and across a restart.
-module(cell_settings_tests).

-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(R, cell_test_robot_settings).
-define(S, cell_settings_schema).

%%====================================================================
%% Fixture
%%====================================================================

settings_test_() ->
    {setup, fun start_base/0, fun stop_base/1,
     [?_test(first_boot()),
      ?_test(put_and_history()),
      ?_test(refused_put_changes_nothing()),
      ?_test(restart_keeps_everything()),
      ?_test(hand_edit_becomes_revision()),
      ?_test(hand_edit_with_error_is_refused()),
      ?_test(unreadable_history_falls_back_to_defaults()),
      ?_test(interrupted_save_is_rolled_back()),
      ?_test(missing_file_comes_back_from_history()),
      ?_test(history_is_bounded()),
      ?_test(restore_and_diff()),
      ?_test(snapshot_holds_until_next_start()),
      ?_test(bad_calls()),
      ?_test(durable_writes()),
      ?_test(restarts_with_saved_settings_under_a_supervisor()),
      {timeout, 300, ?_assert(proper:quickcheck(prop_changes_persist(),
                                                [{to_file, user}, {numtests, 40}]))}]}.

start_base() ->
    Root = tmp_dir("root"),
    os:putenv("CELLRT_ROOT", Root),
    %% Log lines reach the test through cell_log subscriptions, not the console.
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, []),
    ok = application:set_env(lager, crash_log, false),
    ok = application:set_env(lager, error_logger_redirect, false),
    {ok, Started} = application:ensure_all_started(cell_base),
    Started.

stop_base(Started) ->
    [ok = application:stop(A) || A <- lists:reverse(Started)],
    os:unsetenv("CELLRT_ROOT").

tmp_dir(What) ->
    cell_test_dir:new("settings", What).

%% Runs Fun with a settings owner on Dir, and stops it after, whatever happens.
with(Dir, Fun) ->
    with(Dir, #{}, Fun).

with(Dir, Opts, Fun) ->
    {ok, Pid} = cell_settings:start_link(maps:merge(#{dir => Dir, sync => false,
                                                      schemas => [cell_machine_settings, ?R]},
                                                    Opts)),
    try
        Fun()
    after
        unlink(Pid),
        ok = gen_server:stop(Pid)
    end.

file(Dir, Name) -> filename:join(Dir, atom_to_list(Name) ++ ".json").

rev_file(Dir, Name, Rev) ->
    filename:join([Dir, ".history", atom_to_list(Name), integer_to_list(Rev) ++ ".json"]).

read(Path) ->
    {ok, Bin} = file:read_file(Path),
    Bin.

revs(Name) ->
    {ok, Revs} = cell_settings:revisions(Name),
    [{R, W} || #{rev := R, who := W} <- Revs].

no_message() ->
    receive
        {cell_settings, _, _} = M -> error({unexpected, M})
    after 0 -> ok
    end.

%%====================================================================
%% Cases
%%====================================================================

first_boot() ->
    Dir = tmp_dir("first"),
    with(Dir, fun() ->
                      ?assertEqual([machine, robot], cell_settings:names()),
                      ?assertEqual(?S:defaults(cell_machine_settings), cell_settings:get(machine)),
                      ?assertEqual(50, cell_settings:get(machine, speed_override)),
                      ?assertEqual(10, cell_settings:get(robot, [home, speed])),
                      ?assertEqual({ok, ?S:defaults(?R)}, ?S:from_json(?R, read(file(Dir, robot)))),
                      ?assertEqual([{1, <<"cellrt">>}], revs(machine)),
                      ?assertEqual({ok, machine}, cell_settings:name_of(<<"machine">>)),
                      ?assertEqual({error, {unknown_settings, <<"nope">>}},
                                   cell_settings:name_of(<<"nope">>))
              end).

put_and_history() ->
    Dir = tmp_dir("put"),
    with(Dir, fun() ->
                      ok = cell_settings:subscribe(),
                      ?assertEqual(ok, cell_settings:put(robot, #{retries => 5, <<"tool">> => <<"vacuum">>},
                                                         <<"anna">>)),
                      receive {cell_settings, changed, robot} -> ok end,
                      ?assertMatch(#{retries := 5, tool := vacuum}, cell_settings:get(robot)),
                      ?assertMatch({ok, #{retries := 5}}, ?S:from_json(?R, read(file(Dir, robot)))),
                      ?assertEqual([{2, <<"anna">>}, {1, <<"cellrt">>}], revs(robot)),
                      {ok, [#{time := T} | _]} = cell_settings:revisions(robot),
                      ?assert(abs(os:system_time(millisecond) - T) < 60000),
                      %% saving what is there already is no change
                      ?assertEqual(ok, cell_settings:put(robot, #{retries => 5}, <<"bert">>)),
                      no_message(),
                      ?assertEqual([{2, <<"anna">>}, {1, <<"cellrt">>}], revs(robot)),
                      ok = cell_settings:unsubscribe(),
                      ok = cell_settings:put(robot, #{retries => 6}, <<"anna">>),
                      no_message()
              end).

refused_put_changes_nothing() ->
    Dir = tmp_dir("refused"),
    with(Dir, fun() ->
                      ok = cell_settings:subscribe(),
                      Before = cell_settings:get(robot),
                      Text = read(file(Dir, robot)),
                      Bad = [{#{retries => 11}, {invalid, [retries], {out_of_range, 11, 0, 10}}},
                             {#{axes => [#{speed => 0}]},
                              {invalid, [axes, 1, speed], {out_of_range, 0, 1, 100}}},
                             {#{<<"colour">> => <<"red">>}, {invalid, [<<"colour">>], unknown_field}},
                             {#{enabled => <<"yes">>},
                              {invalid, [enabled], {wrong_type, boolean, <<"yes">>}}},
                             {#{retries => 4, label => <<"far too long">>},
                              {invalid, [label], {too_long, 8}}}],
                      [?assertEqual({error, Why}, cell_settings:put(robot, In, <<"anna">>))
                       || {In, Why} <- Bad],
                      ?assertEqual(Before, cell_settings:get(robot)),
                      ?assertEqual(Text, read(file(Dir, robot))),
                      ?assertEqual([{1, <<"cellrt">>}], revs(robot)),
                      no_message()
              end).

restart_keeps_everything() ->
    Dir = tmp_dir("restart"),
    with(Dir, fun() -> ok = cell_settings:put(robot, #{retries => 5}, <<"anna">>) end),
    with(Dir, fun() ->
                      ?assertEqual(5, cell_settings:get(robot, retries)),
                      ?assertEqual([{2, <<"anna">>}, {1, <<"cellrt">>}], revs(robot))
              end).

hand_edit_becomes_revision() ->
    Dir = tmp_dir("hand"),
    with(Dir, fun() -> ok end),
    %% someone edits the file in a text editor: reformatted, one value changed
    Edited = <<"{\"retries\": 9,\n\"tool\":\"gripper\"}">>,
    ok = file:write_file(file(Dir, robot), Edited),
    with(Dir, fun() ->
                      ?assertMatch(#{retries := 9, tool := gripper}, cell_settings:get(robot)),
                      ?assertEqual([{2, <<"edited outside cellrt">>}, {1, <<"cellrt">>}],
                                   revs(robot)),
                      ?assertEqual({ok, [#{path => [retries], from => 3, to => 9},
                                         #{path => [tool], from => none, to => gripper}]},
                                   cell_settings:diff(robot, 1, 2))
              end),
    %% a new layout of the same values is not a change
    {ok, Obj} = ?S:validate(?R, #{retries => 9, tool => gripper}),
    ok = file:write_file(file(Dir, robot), jsx:encode(?S:encode_value({object, ?R}, Obj))),
    with(Dir, fun() -> ?assertEqual(2, length(revs(robot))) end).

hand_edit_with_error_is_refused() ->
    Dir = tmp_dir("handbad"),
    with(Dir, fun() -> ok = cell_settings:put(robot, #{retries => 4}, <<"anna">>) end),
    Bad = <<"{\"retries\": 4, \"speed\": 9000}">>,
    ok = file:write_file(file(Dir, robot), Bad),
    ok = cell_log:subscribe(),
    with(Dir, fun() ->
                     %% the log names the file and the field; the last good revision holds
                     Line = wait_log(<<"robot.json">>),
                     ?assertMatch({match, _}, re:run(Line, "speed: 9000.0 is out of range 0.5..2500.0")),
                     ?assertEqual(4, cell_settings:get(robot, retries)),
                     ?assertEqual(100.0, cell_settings:get(robot, speed)),
                     ?assertEqual(Bad, read(file(Dir, robot))),
                     ?assertEqual({error, {invalid, [speed], {out_of_range, 9000.0, 0.5, 2500.0}}},
                                  cell_settings:reload(robot)),
                     %% fixed by hand, then reloaded
                     ok = file:write_file(file(Dir, robot), <<"{\"retries\": 4, \"speed\": 900}">>),
                     ?assertEqual(ok, cell_settings:reload(robot)),
                     ?assertEqual(900.0, cell_settings:get(robot, speed)),
                     %% broken again, then replaced through the API: the typed text is kept
                     ok = file:write_file(file(Dir, robot), <<"{\"retries\": ">>),
                     ?assertEqual({error, not_json}, cell_settings:reload(robot)),
                     ok = cell_settings:put(robot, #{retries => 2}, <<"anna">>),
                     ?assertEqual(<<"{\"retries\": ">>, read(file(Dir, robot) ++ ".refused")),
                     ?assertMatch({ok, #{retries := 2}}, ?S:from_json(?R, read(file(Dir, robot))))
              end),
    ok = cell_log:unsubscribe().

unreadable_history_falls_back_to_defaults() ->
    Dir = tmp_dir("nohistory"),
    ok = file:write_file(file(Dir, machine), <<"{\"speed_override\": 0}">>),
    with(Dir, fun() ->
                      ?assertEqual(?S:defaults(cell_machine_settings), cell_settings:get(machine)),
                      ?assertEqual([], revs(machine))
              end).

interrupted_save_is_rolled_back() ->
    Dir = tmp_dir("cut"),
    with(Dir, fun() -> ok = cell_settings:put(robot, #{retries => 4}, <<"anna">>) end),
    %% a power cut after the revision was written and before the settings file was
    Rev3 = binary:replace(read(rev_file(Dir, robot, 2)), <<"\"retries\": 4">>,
                          <<"\"retries\": 8">>),
    ok = file:write_file(rev_file(Dir, robot, 3),
                         binary:replace(Rev3, <<"\"revision\": 2">>, <<"\"revision\": 3">>)),
    with(Dir, fun() ->
                      ?assertEqual(4, cell_settings:get(robot, retries)),
                      ?assertEqual([{2, <<"anna">>}, {1, <<"cellrt">>}], revs(robot)),
                      ?assertEqual(false, filelib:is_file(rev_file(Dir, robot, 3)))
              end).

missing_file_comes_back_from_history() ->
    Dir = tmp_dir("missing"),
    with(Dir, fun() -> ok = cell_settings:put(robot, #{retries => 4}, <<"anna">>) end),
    ok = file:delete(file(Dir, robot)),
    with(Dir, fun() ->
                      ?assertEqual(4, cell_settings:get(robot, retries)),
                      ?assertMatch({ok, #{retries := 4}}, ?S:from_json(?R, read(file(Dir, robot)))),
                      ?assertEqual(2, length(revs(robot)))
              end).

history_is_bounded() ->
    Dir = tmp_dir("bounded"),
    with(Dir, #{history => 3},
         fun() ->
                 [ok = cell_settings:put(robot, #{retries => N}, <<"anna">>) || N <- lists:seq(4, 8)],
                 ?assertEqual([6, 5, 4], [R || {R, _} <- revs(robot)]),
                 ?assertEqual(["4.json", "5.json", "6.json"],
                              lists:sort(filelib:wildcard("*", filename:join([Dir, ".history", "robot"])))),
                 ?assertEqual({error, {no_revision, robot, 1}}, cell_settings:revision(robot, 1)),
                 ?assertMatch({ok, #{rev := 4, who := <<"anna">>, settings := #{retries := 6}}},
                              cell_settings:revision(robot, 4))
         end).

restore_and_diff() ->
    Dir = tmp_dir("restore"),
    with(Dir, fun() ->
                      ok = cell_settings:put(robot, #{retries => 4, axes => [#{id => y}]}, <<"anna">>),
                      ok = cell_settings:put(robot, #{axes => [#{id => z, speed => 20}]}, <<"bert">>),
                      ?assertEqual({ok, [#{path => [axes, 1, id], from => y, to => z},
                                         #{path => [axes, 1, speed], from => 10, to => 20}]},
                                   cell_settings:diff(robot, 2, 3)),
                      ?assertEqual({ok, [#{path => [retries], from => 3, to => 4},
                                         #{path => [axes], from => [],
                                           to => [#{id => z, speed => 20, low => -100.0,
                                                    high => 100.0}]}]},
                                   cell_settings:diff(robot, 1, 3)),
                      ?assertEqual(ok, cell_settings:restore(robot, 1, <<"carl">>)),
                      ?assertEqual(?S:defaults(?R), cell_settings:get(robot)),
                      ?assertEqual([{4, <<"carl">>}, {3, <<"bert">>}, {2, <<"anna">>},
                                    {1, <<"cellrt">>}], revs(robot)),
                      ?assertEqual({ok, []}, cell_settings:diff(robot, 1, 4)),
                      ?assertEqual({error, {no_revision, robot, 9}},
                                   cell_settings:restore(robot, 9, <<"carl">>))
              end).

snapshot_holds_until_next_start() ->
    Dir = tmp_dir("snap"),
    with(Dir, fun() ->
                      ?assertEqual(undefined, cell_settings:last_snapshot()),
                      ?assertEqual([], cell_settings:pending()),
                      Snap = cell_settings:snapshot(),
                      ?assertEqual([machine, robot], lists:sort(maps:keys(Snap))),
                      ok = cell_settings:put(machine, #{speed_override => 80}, <<"anna">>),
                      %% tasks run on the snapshot: it does not move
                      ?assertEqual(Snap, cell_settings:last_snapshot()),
                      ?assertEqual(50, maps:get(speed_override, maps:get(machine, Snap))),
                      ?assertEqual([machine], cell_settings:pending()),
                      %% the next Start takes the change
                      Snap2 = cell_settings:snapshot(),
                      ?assertEqual(80, maps:get(speed_override, maps:get(machine, Snap2))),
                      ?assertEqual([], cell_settings:pending())
              end).

bad_calls() ->
    Dir = tmp_dir("bad"),
    ?assertEqual({error, {bad_option, colour}}, cell_settings:start_link(#{colour => red})),
    ?assertEqual({error, {bad_option, history}}, cell_settings:start_link(#{history => 0})),
    ?assertEqual({error, {bad_option, dir}}, cell_settings:start_link(#{dir => 42})),
    with(Dir, fun() ->
                      ?assertError({unknown_settings, nope}, cell_settings:get(nope)),
                      ?assertError({unknown_field, robot, [nope]}, cell_settings:get(robot, nope)),
                      ?assertEqual({error, {unknown_settings, nope}},
                                   cell_settings:put(nope, #{}, <<"anna">>)),
                      ?assertEqual({error, {bad_who, anna}}, cell_settings:put(robot, #{}, anna)),
                      ?assertEqual({error, {bad_who, <<>>}}, cell_settings:put(robot, #{}, <<>>)),
                      ?assertMatch({error, {bad_schema, cell_test_bad_settings, _}},
                                   cell_settings:register(cell_test_bad_settings)),
                      ?assertEqual(ok, cell_settings:register(?R)),
                      ?assertEqual({error, {name_taken, machine, cell_machine_settings}},
                                   cell_settings:register(cell_test_machine_twin)),
                      ?assertEqual({error, {no_revision, robot, 7}}, cell_settings:diff(robot, 1, 7)),
                      ?assertEqual({error, {unknown_settings, nope}}, cell_settings:revisions(nope))
              end).

durable_writes() ->
    %% the real path, with every flush, once
    Dir = tmp_dir("durable"),
    with(Dir, #{sync => true},
         fun() -> ok = cell_settings:put(machine, #{cell_name => <<"router 7">>}, <<"anna">>) end),
    with(Dir, fun() -> ?assertEqual(<<"router 7">>, cell_settings:get(machine, cell_name)) end),
    ?assertEqual([], filelib:wildcard("*.tmp-*", Dir)).

restarts_with_saved_settings_under_a_supervisor() ->
    Dir = tmp_dir("sup"),
    Spec = cell_settings:child_spec(#{dir => Dir, sync => false,
                                      schemas => [cell_machine_settings, ?R]}),
    {ok, Sup} = cell_test_sup:start_link([Spec]),
    unlink(Sup),
    try
        ok = cell_settings:put(robot, #{retries => 7}, <<"anna">>),
        Old = whereis(cell_settings),
        Ref = monitor(process, Old),
        exit(Old, kill),
        receive {'DOWN', Ref, process, Old, killed} -> ok end,
        New = restarted(Sup, Old, erlang:monotonic_time(millisecond) + 10000),
        ?assert(is_process_alive(New)),
        %% the table went with the old process; the new one reads the files
        ?assertEqual(7, cell_settings:get(robot, retries)),
        ?assertEqual([{2, <<"anna">>}, {1, <<"cellrt">>}], revs(robot))
    after
        ok = cell_test_sup:stop(Sup)
    end.

%% The child the supervisor runs once it has replaced Old: asked of the supervisor
%% until then, with a deadline.
restarted(Sup, Old, Deadline) ->
    erlang:monotonic_time(millisecond) < Deadline orelse error(not_restarted),
    case supervisor:which_children(Sup) of
        [{cell_settings, New, worker, _}] when is_pid(New), New =/= Old -> New;
        _ -> restarted(Sup, Old, Deadline)
    end.

wait_log(Needle) ->
    receive
        {cell_log, #{text := T}} ->
            case binary:match(T, Needle) of
                nomatch -> wait_log(Needle);
                _ -> T
            end
    after 10000 -> error({no_log_line, Needle})
    end.

%%====================================================================
%% Property: good changes persist, bad ones change nothing
%%====================================================================

prop_changes_persist() ->
    Scalars = [F || #{type := T} = F <- ?R:fields(), element(1, T) =/= list,
                    element(1, T) =/= object, T =/= {optional, {object, cell_test_axis_settings}}],
    Op = oneof([{put, cell_settings_gen:object(?R), elements([<<"anna">>, <<"bert">>])},
                ?LET(#{name := N, type := T}, elements(Scalars),
                     ?LET({_, V}, cell_settings_gen:invalid(T), {bad, N, V}))]),
    ?FORALL({Ops, Keep}, {list(Op), range(1, 5)},
            begin
                Dir = tmp_dir("prop"),
                Run = fun() ->
                              lists:foldl(fun(O, Acc) -> apply_op(O, Acc) end,
                                          {?S:defaults(?R), [<<"cellrt">>], true}, Ops)
                      end,
                {Model, Whos, Ok} = with(Dir, #{history => Keep, schemas => [?R]}, Run),
                Expected = lists:sublist(Whos, Keep),
                After = with(Dir, #{history => Keep, schemas => [?R]},
                             fun() -> {cell_settings:get(robot), [W || {_, W} <- revs(robot)]} end),
                ?WHENFAIL(io:format(user, "model ~p~nafter ~p~nexpected whos ~p~n",
                                    [Model, After, Expected]),
                          Ok andalso After =:= {Model, Expected})
            end).

%% The model: the object in force, the authors of the revisions (newest first), and
%% whether every step matched it so far.
apply_op({put, Obj, Who}, {Model, Whos, Ok}) ->
    %% Normalising the input (enum names, null) is the pure module's job, tested apart.
    {ok, New} = ?S:validate(?R, Obj),
    Result = cell_settings:put(robot, Obj, Who),
    Whos1 = case New =:= Model of
                true -> Whos;
                false -> [Who | Whos]
            end,
    {New, Whos1, Ok andalso Result =:= ok andalso cell_settings:get(robot) =:= New};
apply_op({bad, Field, V}, {Model, Whos, Ok}) ->
    Result = cell_settings:put(robot, #{Field => V}, <<"mallory">>),
    Named = case Result of
                {error, {invalid, [Field], _}} -> true;
                _ -> false
            end,
    {Model, Whos, Ok andalso Named andalso cell_settings:get(robot) =:= Model}.
