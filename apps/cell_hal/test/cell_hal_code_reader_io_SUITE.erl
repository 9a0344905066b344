%% A code reader wired through the PLC's IO (cell_hal_code_reader_io) against the
%% simulated PLC, the test playing the reader: a trigger answered with a code, a
%% no-read, an answer that never comes (the deadline), the connection lost mid-read
%% and back, a trigger a crashed predecessor left on, options refused.
-module(cell_hal_code_reader_io_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([refuses_bad_options/1, reads_a_code/1, no_read/1, deadline/1,
         connection_down/1, connection_gone_before_its_news/1,
         stale_trigger_cleared/1]).

-define(WAIT, 5000).
-define(G, rd).
-define(CONN, rplc).

all() ->
    [refuses_bad_options, reads_a_code, no_read, deadline, connection_down,
     connection_gone_before_its_news, stale_trigger_cleared].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

init_per_testcase(_Case, Config) ->
    %% A reader at rest: no trigger, no answer, its counter at zero.
    ok = cell_hal:add_connection(#{id => ?CONN, driver => cell_hal_sim,
                                   opts => #{poll_ms => 10, reconnect_ms => 50,
                                             timeout_ms => 500}}),
    ok = cell_hal:add_group(#{id => ?G, module => cell_hal_test_reader_io, connection => ?CONN}),
    ok = cell_hal_sim:preset(?CONN, #{{?G, trigger} => false, {?G, done} => false,
                                      {?G, no_read} => false, {?G, result} => <<>>,
                                      {?G, read_count} => 0}),
    {ok, _} = cell_hal:subscribe_connection(?CONN),
    ok = await_conn(up),
    %% The reader: a trigger tells the test; its fall clears done at once.
    Self = self(),
    ok = cell_hal_sim:on_change({?G, trigger}, fun(true) -> Self ! triggered, [];
                                                  (false) -> Self ! untriggered,
                                                             [{0, {?G, done}, false}]
                                               end),
    Config.

end_per_testcase(_Case, _Config) ->
    [ok = cell_hal_hw:remove(Id) || {Id, _, _} <- cell_hal_hw:list()],
    ok = cell_hal:remove_group(?G),
    ok = cell_hal:remove_connection(?CONN),
    ok.

reader(Opts) ->
    ok = cell_hal_hw:add(#{id => reader, kind => code_reader, type => io,
                           opts => maps:merge(#{group => ?G, count => read_count}, Opts)}),
    %% The status now, then every change as a message.
    case cell_hal_hw:subscribe(reader) of
        {ok, up} -> ok;
        {ok, down} -> await_hw(up)
    end.

%% The reader answers: the result and the no-read bit, the counter one up, then done.
answer(Code, NoRead) ->
    N = count(),
    ok = cell_hal_sim:set({?G, result}, Code),
    ok = cell_hal_sim:set({?G, no_read}, NoRead),
    ok = cell_hal_sim:set({?G, read_count}, (N + 1) rem 65536),
    ok = cell_hal_sim:set({?G, done}, true).

count() ->
    {ok, N} = cell_hal_sim:get({?G, read_count}),
    N.

refuses_bad_options(_Config) ->
    Add = fun(Opts) -> cell_hal_hw:add(#{id => r, kind => code_reader, type => io, opts => Opts}) end,
    ?assertEqual({error, {bad_option, group}}, Add(#{})),
    ?assertEqual({error, {bad_option, deadline_ms}}, Add(#{group => ?G, deadline_ms => -1})),
    ?assertEqual({error, {bad_option, colour}}, Add(#{group => ?G, colour => red})),
    ?assertEqual({error, {unknown_group, nowhere}}, Add(#{group => nowhere})),
    %% Each point of its role's direction and type.
    ?assertEqual({error, {bad_point, trigger, lamp}}, Add(#{group => ?G, trigger => lamp, count => none})),
    ?assertEqual({error, {bad_point, done, trigger}}, Add(#{group => ?G, done => trigger, count => none})),
    ?assertEqual({error, {bad_point, result, done}}, Add(#{group => ?G, result => done, count => none})),
    ?assertEqual({error, {bad_point, count, result}}, Add(#{group => ?G, count => result})),
    ?assertEqual({error, {bad_point, no_read, nothing}}, Add(#{group => ?G, no_read => nothing, count => none})),
    ?assertEqual([], cell_hal_hw:list()).

reads_a_code(_Config) ->
    ok = reader(#{}),
    Ref = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    %% The result alone (its counter not yet moved, done not yet up) is no answer.
    ok = cell_hal_sim:set({?G, result}, <<"P-0001">>),
    ok = answer(<<"P-0001">>, false),
    ?assertEqual({ok, <<"P-0001">>}, reply(Ref)),
    %% The trigger falls with the answer taken, done after it.
    ok = untriggered(),
    ok = await_point(done, false),
    %% The next read, through the waiting call.
    Self = self(),
    spawn_link(fun() -> Self ! {read, cell_hal_code_reader:read(reader, ?WAIT)} end),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"P-0002">>, false),
    receive {read, R} -> ?assertEqual({ok, <<"P-0002">>}, R) after ?WAIT -> ct:fail(no_read) end,
    ok = untriggered(),
    %% Done up with the counter where it was: waited for until it moves.
    ok = await_point(done, false),
    Ref3 = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = cell_hal_sim:set({?G, result}, <<"P-0003">>),
    ok = cell_hal_sim:set({?G, done}, true),
    ok = await_point(done, true),
    %% The object's answer, had it given one on done alone, came before its status.
    ?assertEqual(up, cell_hal_hw:status(reader)),
    receive {Ref3, Early} -> ct:fail({answered_before_the_counter, Early}) after 0 -> ok end,
    ok = cell_hal_sim:set({?G, read_count}, count() + 1),
    ?assertEqual({ok, <<"P-0003">>}, reply(Ref3)).

no_read(_Config) ->
    ok = reader(#{}),
    Ref = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"OLD">>, true),
    ?assertEqual({error, no_read}, reply(Ref)),
    ok = untriggered(),
    ok = await_point(done, false),
    %% An empty result is no code either.
    Ref2 = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<>>, false),
    ?assertEqual({error, no_read}, reply(Ref2)).

deadline(_Config) ->
    %% The reader's default deadline: the second read below must be answered within
    %% it, across two polls and the case's own calls, also on a busy machine.
    ok = reader(#{deadline_ms => 2000}),
    Ref = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ?assertEqual({error, timeout}, reply(Ref)),
    ok = untriggered(),
    %% The answer comes late, after the trigger fell: done stays up until the reader
    %% clears it. The next read waits for done to fall before it triggers, so the late
    %% code is not taken for it.
    ok = answer(<<"LATE">>, false),
    ok = await_point(done, true),
    Ref2 = cell_hal_code_reader:read_async(reader),
    %% The read was taken before the status call: an answer would come before its reply.
    ?assertEqual(up, cell_hal_hw:status(reader)),
    receive {Ref2, Early} -> ct:fail({answered_with_done_up, Early}) after 0 -> ok end,
    ?assertEqual({ok, false}, cell_hal_sim:get({?G, trigger})),
    ok = cell_hal_sim:set({?G, done}, false),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"P-0004">>, false),
    ?assertEqual({ok, <<"P-0004">>}, reply(Ref2)).

connection_down(_Config) ->
    ok = reader(#{}),
    Ref = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = cell_hal_sim:link(?CONN, down),
    ?assertEqual({error, not_connected}, reply(Ref)),
    ok = await_hw(down),
    ?assertEqual(down, cell_hal_hw:status(reader)),
    ?assertEqual({error, not_connected}, cell_hal_code_reader:read(reader, ?WAIT)),
    ok = cell_hal_sim:link(?CONN, up),
    ok = await_hw(up),
    %% The trigger the lost read left on is off again; a read goes on as before.
    ok = untriggered(),
    Ref2 = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"P-0005">>, false),
    ?assertEqual({ok, <<"P-0005">>}, reply(Ref2)).

%% The answer came, and the connection went before the object looked at it: the
%% object learns of the loss from the HAL's read of the result before the
%% connection's own news. To the asker that is the same lost read, `not_connected',
%% never an error the task does not know.
connection_gone_before_its_news(_Config) ->
    ok = reader(#{}),
    Ref = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    [Pid] = [P || {reader, P, _, _} <- ets:lookup(cell_hal_hw_objects, reader)],
    ok = sys:suspend(Pid),
    ok = answer(<<"P-0007">>, false),
    ok = await_point(done, true),
    ok = cell_hal_sim:link(?CONN, down),
    ok = await_conn(down),
    ok = sys:resume(Pid),
    ?assertEqual({error, not_connected}, reply(Ref)),
    ok = await_hw(down),
    ok = cell_hal_sim:link(?CONN, up),
    ok = await_hw(up),
    ok = cell_hal_sim:set({?G, done}, false),
    Ref2 = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"P-0008">>, false),
    ?assertEqual({ok, <<"P-0008">>}, reply(Ref2)).

%% A reader object that crashed mid-read left the trigger on, and the reader answered
%% it: its successor clears the trigger and never takes that answer.
stale_trigger_cleared(_Config) ->
    ok = cell_hal:write(?G, trigger, true),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"STALE">>, false),
    ok = await_point(done, true),
    ok = reader(#{}),
    ok = untriggered(),
    ok = await_point(done, false),
    Ref = cell_hal_code_reader:read_async(reader),
    receive triggered -> ok after ?WAIT -> ct:fail(no_trigger) end,
    ok = answer(<<"P-0006">>, false),
    ?assertEqual({ok, <<"P-0006">>}, reply(Ref)).

%%--------------------------------------------------------------------

reply(Ref) ->
    receive {Ref, R} -> R after ?WAIT -> ct:fail(no_answer) end.

await_conn(Status) ->
    case cell_hal:status(?CONN) of
        Status -> ok;
        _ -> receive {cell_hal_conn, ?CONN, Status} -> ok after ?WAIT -> ct:fail({conn, Status}) end
    end.

%% The next change of the reader's status to `Status' (subscribed in reader/1).
await_hw(Status) ->
    receive {cell_hal_hw, reader, Status} -> ok after ?WAIT -> ct:fail({hw, Status}) end.

untriggered() ->
    receive untriggered -> ok after ?WAIT -> ct:fail(trigger_not_cleared) end.

%% An input as the HAL reads it, waited for with a watch.
await_point(P, V) ->
    {ok, Ref} = cell_hal:watch(?G, P, {eq, V}),
    receive {cell_hal_watch, Ref, V} -> ok after ?WAIT -> ct:fail({point, P, V}) end.
