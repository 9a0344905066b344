%% The recipe buffer: loads once, serves from ETS, is cleared at Start, shares one load
%% among concurrent requests, never keeps a load that straddles a clear, survives a
%% crashing loader, and restarts empty under a supervisor.
-module(cell_recipe_buffer_tests).

-include_lib("eunit/include/eunit.hrl").

-define(B, cell_recipe_buffer).

buffer_test_() ->
    {foreach, fun setup/0, fun cleanup/1,
     [fun loads_once_until_clear/1,
      fun failures_are_not_kept/1,
      fun one_load_for_many_requests/1,
      fun load_across_clear_is_not_kept/1,
      fun slow_load_times_out/1,
      fun crashing_loader/1,
      fun restarts_empty_under_a_supervisor/1]}.

setup() ->
    Dir = filename:join(cell_test_dir:new("recipe_buffer", "buffer"), "Products"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Opts = #{dir => Dir, sync => false},
    {ok, Pid} = ?B:start_link(#{recipe => Opts}),
    unlink(Pid),
    {Pid, Opts}.

cleanup({_, _}) ->
    case whereis(?B) of
        undefined -> ok;
        Pid -> gen_server:stop(Pid)
    end.

save(Name, Description, Opts) ->
    ok = cell_recipe:save(Name, #{description => Description}, <<"test">>, Opts).

description({ok, #{description := D}}) -> D.

%% Spawns of loaders by the buffer process, seen through tracing.
trace_spawns(Pid) ->
    1 = erlang:trace(Pid, true, [procs]),
    ok.

next_loader(Pid) ->
    receive
        {trace, Pid, spawn, Loader, _} -> Loader
    after 10000 -> error(no_loader_started)
    end.

no_more_loaders(Pid) ->
    receive
        {trace, Pid, spawn, Loader, _} -> error({unexpected_loader, Loader})
    after 0 -> ok
    end.

loads_once_until_clear({_, Opts}) ->
    ?_test(begin
               save(<<"P1">>, <<"first">>, Opts),
               ?assertEqual(<<"first">>, description(?B:get(<<"P1">>))),
               ?assertEqual([<<"P1">>], ?B:loaded()),
               %% changed while the machine runs: the buffer keeps what it has
               save(<<"P1">>, <<"second">>, Opts),
               ?assertEqual(<<"first">>, description(?B:get(<<"P1">>))),
               %% the next Start reads the file again
               ok = ?B:clear(),
               ?assertEqual([], ?B:loaded()),
               ?assertEqual(<<"second">>, description(?B:get(<<"P1">>)))
           end).

failures_are_not_kept({_, Opts}) ->
    ?_test(begin
               ?assertEqual({error, {no_recipe, <<"Late">>}}, ?B:get(<<"Late">>)),
               ?assertEqual({error, {bad_name, <<"a/b">>, {bad_character, "/"}}},
                            ?B:get(<<"a/b">>)),
               ?assertEqual([], ?B:loaded()),
               save(<<"Late">>, <<"here now">>, Opts),
               ?assertEqual(<<"here now">>, description(?B:get(<<"Late">>)))
           end).

one_load_for_many_requests({Pid, Opts}) ->
    ?_test(begin
               save(<<"Shared">>, <<"shared">>, Opts),
               save(<<"Other">>, <<"other">>, Opts),
               trace_spawns(Pid),
               Self = self(),
               Askers = [spawn_link(fun() -> Self ! {self(), ?B:get(<<"Shared">>)} end)
                         || _ <- lists:seq(1, 20)],
               Loader = next_loader(Pid),
               Results = [receive {A, R} -> R end || A <- Askers],
               ?assert(is_pid(Loader)),
               ?assertEqual([<<"shared">>], lists:usort([description(R) || R <- Results])),
               %% a second recipe has a load of its own
               ?assertEqual(<<"other">>, description(?B:get(<<"Other">>))),
               _ = next_loader(Pid),
               %% served from the table now: no more loads
               [?assertEqual(<<"shared">>, description(?B:get(<<"Shared">>))) || _ <- lists:seq(1, 5)],
               no_more_loaders(Pid)
           end).

load_across_clear_is_not_kept({Pid, Opts}) ->
    ?_test(begin
               save(<<"Slow">>, <<"before start">>, Opts),
               trace_spawns(Pid),
               Self = self(),
               Asker = spawn_link(fun() -> Self ! {self(), ?B:get(<<"Slow">>)} end),
               Loader = next_loader(Pid),
               true = erlang:suspend_process(Loader),
               %% Start happens while the load is under way
               ok = ?B:clear(),
               save(<<"Slow">>, <<"after start">>, Opts),
               true = erlang:resume_process(Loader),
               %% the one who asked before Start gets the load it waited for...
               receive {Asker, R} -> ?assertMatch({ok, _}, R) end,
               %% ...but it is not kept: the next request reads the file again
               ?assertEqual([], ?B:loaded()),
               ?assertEqual(<<"after start">>, description(?B:get(<<"Slow">>)))
           end).

slow_load_times_out({Pid, Opts}) ->
    ?_test(begin
               save(<<"Stuck">>, <<"stuck">>, Opts),
               trace_spawns(Pid),
               Self = self(),
               spawn_link(fun() -> Self ! {asked, ?B:get(<<"Stuck">>, 200)} end),
               Loader = next_loader(Pid),
               true = erlang:suspend_process(Loader),
               receive {asked, R} -> ?assertEqual({error, timeout}, R) end,
               true = erlang:resume_process(Loader),
               %% the load completes for later requests; the late reply went nowhere
               ?assertEqual(<<"stuck">>, description(?B:get(<<"Stuck">>))),
               receive Stray when element(1, Stray) =/= trace -> error({stray, Stray})
               after 0 -> ok
               end
           end).

crashing_loader({Pid, Opts}) ->
    ?_test(begin
               save(<<"P">>, <<"p">>, Opts),
               gen_server:stop(Pid),
               %% a schema module that does not exist: the loader crashes
               {ok, P2} = ?B:start_link(#{recipe => Opts#{schema => cell_no_such_schema}}),
               unlink(P2),
               ?assertMatch({error, {load_failed, _}}, ?B:get(<<"P">>)),
               ?assertEqual([], ?B:loaded()),
               ?assertEqual({error, {bad_option, colour}}, ?B:start_link(#{colour => red})),
               ?assertEqual({error, {bad_option, recipe}}, ?B:start_link(#{recipe => []}))
           end).

%% The child the supervisor runs once it has replaced Old: asked of the supervisor
%% until then, with a deadline.
restarted(Sup, Old, Deadline) ->
    erlang:monotonic_time(millisecond) < Deadline orelse error(not_restarted),
    case supervisor:which_children(Sup) of
        [{cell_recipe_buffer, New, worker, _}] when is_pid(New), New =/= Old -> New;
        _ -> restarted(Sup, Old, Deadline)
    end.

restarts_empty_under_a_supervisor({Pid, Opts}) ->
    ?_test(begin
               gen_server:stop(Pid),
               save(<<"S">>, <<"s">>, Opts),
               {ok, Sup} = cell_test_sup:start_link([?B:child_spec(#{recipe => Opts})]),
               {ok, _} = ?B:get(<<"S">>),
               ?assertEqual([<<"S">>], ?B:loaded()),
               Old = whereis(?B),
               Ref = monitor(process, Old),
               exit(Old, kill),
               receive {'DOWN', Ref, process, Old, killed} -> ok end,
               New = restarted(Sup, Old, erlang:monotonic_time(millisecond) + 10000),
               ?assert(is_process_alive(New)),
               ?assertEqual([], ?B:loaded()),
               ?assertEqual(<<"s">>, description(?B:get(<<"S">>))),
               unlink(Sup),
               ok = cell_test_sup:stop(Sup)
           end).
