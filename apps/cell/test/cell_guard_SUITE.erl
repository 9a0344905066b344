%% The cell's guard on a line of conveyor segments (cell_line_task): a serial taken
%% while another task holds it is an error on both holders naming both; an answer that
%% would let a holder go on with it is refused, and Reset on one holder settles it; a
%% started line holding products that makes no progress while no error waits raises a
%% warning naming what each task waits for, and the next progress clears it.
-module(cell_guard_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([held_twice_is_an_error_naming_both/1, answer_that_would_hold_twice_is_refused/1,
         not_here_downstream_lets_the_copy_upstream_go_on/1,
         handed_on_serial_back_again_is_an_error/1,
         held_twice_read_back_at_boot/1, stalled_line_warns_and_progress_clears/1]).

-define(SEGMENTS, [src, a, sink]).
-define(TIMEOUT, 10000).
-define(NO_PROGRESS_MS, 300).
%% Each move of the stalled line's product: long beside the no-progress time.
-define(MOVE_MS, 2000).

all() ->
    [held_twice_is_an_error_naming_both, answer_that_would_hold_twice_is_refused,
     not_here_downstream_lets_the_copy_upstream_go_on, handed_on_serial_back_again_is_an_error,
     held_twice_read_back_at_boot, stalled_line_warns_and_progress_clears].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Feed = ets:new(feed, [ordered_set, public]),
    Out = ets:new(out, [set, public]),
    Ref = make_ref(),
    {Delay, Jam} = case Case of
                       stalled_line_warns_and_progress_clears -> {?MOVE_MS, false};
                       %% A move of its own, so a product sticks on arriving.
                       _ -> {1, true}
                   end,
    Config1 = [{root, Root}, {feed, Feed}, {out, Out}, {ref, Ref} | Config],
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, line_spec(Config1, Delay, Jam)),
    {ok, _} = application:ensure_all_started(cell_base),
    ok = before_cell(Case),
    {ok, _} = application:ensure_all_started(cell),
    ok = cell_settings:put(machine, #{no_progress_ms => ?NO_PROGRESS_MS}, <<"suite">>),
    Config1.

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok.

%% -------------------------------------------------------------------------------------

%% sink holds P (it sticks on arrival: sink's error waits); the same serial read again
%% at src makes src hold it too. Both get an error naming both; Reset on src's makes
%% src forget it and both go; sink goes on with it.
held_twice_is_an_error_naming_both(Config) ->
    {Serial, JamId} = hold_twice(Config),
    ok = cell_alarms:answer(<<"src:held_twice">>, reset, <<"op">>),
    await_alarm(alarm_cleared, <<"sink:held_twice">>),
    ?assertEqual([sink], [Id || {Id, _} <- cell_registry:holders(Serial)]),
    ?assertEqual([], [I || #{id := I} <- cell_alarms:list(), I =:= <<"src:held_twice">>]),
    ok = cell_alarms:answer(JamId, retry, <<"op">>),
    receive {line_out, sink, Serial} -> ok
    after ?TIMEOUT -> ct:fail(not_out)
    end.

%% The other answer: P is at src (sink's record is the one left behind, as when the
%% power went as a product moved), so Reset goes on sink's error. Sink forgets it; the
%% links that handed it on (src to a, a to sink) no longer take src's copy for a stale
%% one, and P goes down the line again and out.
not_here_downstream_lets_the_copy_upstream_go_on(Config) ->
    {Serial, JamId} = hold_twice(Config),
    ok = cell_alarms:answer(<<"sink:held_twice">>, reset, <<"op">>),
    await_alarm(alarm_cleared, <<"src:held_twice">>),
    %% Sink's jam waited on the product it no longer has: withdrawn with it.
    await_alarm(alarm_cleared, JamId),
    out_answering_jams(Serial).

%% P went down the line and out; a part with P's serial comes to src again. src's
%% copy is refused by the link that handed P on and dropped; read once more (the part
%% is still there), it is an error for the operator, not a round of drops for ever.
%% Reset starts src again, and the line goes on with the next part.
handed_on_serial_back_again_is_an_error(Config) ->
    ok = cell_events:subscribe([alarm_raised, alarm_cleared]),
    [Serial] = feed(Config, [<<"P-1">>]),
    ok = cell_controller:start(),
    out_answering_jams(Serial),
    _ = feed(Config, [Serial, Serial]),
    #{description := Text} = await_alarm(alarm_raised, <<"src:handed_on_again">>),
    ?assertNotEqual(nomatch, string:find(Text, <<"This station has product P-1 again">>)),
    ?assertEqual([], cell_registry:holders(Serial)),
    ok = cell_alarms:answer(<<"src:handed_on_again">>, reset, <<"op">>),
    await_alarm(alarm_cleared, <<"src:handed_on_again">>),
    [Next] = feed(Config, [<<"P-2">>]),
    out_answering_jams(Next).

%% Two product files of one serial, in records of the same generation (a copy restored
%% by hand, say): read back at boot, each holder gets the error before anyone presses
%% Start; Reset on one while the cell is stopped settles it.
held_twice_read_back_at_boot(_Config) ->
    ok = cell_guard:sync(),
    Errors = [A || #{id := Id} = A <- cell_alarms:list(),
                   lists:member(Id, [<<"src:held_twice">>, <<"a:held_twice">>])],
    ?assertMatch([#{kind := error, solutions := [reset]}, #{kind := error, solutions := [reset]}],
                 Errors),
    ?assertEqual([a, src], lists:sort([Id || {Id, _} <- cell_registry:holders(<<"B-1">>)])),
    ok = cell_alarms:answer(<<"a:held_twice">>, reset, <<"op">>),
    ok = cell_guard:sync(),
    ?assertEqual([src], [Id || {Id, _} <- cell_registry:holders(<<"B-1">>)]),
    ?assertEqual([], [Id || #{id := Id} <- cell_alarms:list()]),
    ?assertEqual(undefined, maps:get(product, cell_task_proc:info(a))),
    ?assertMatch(#{product := #{serial := <<"B-1">>}}, cell_task_proc:info(src)).

%% While P is held twice, Retry on sink's own error would let sink go on with it:
%% refused, naming the other holder, and the error stays; Reset on the double-holding
%% error is accepted.
answer_that_would_hold_twice_is_refused(Config) ->
    {Serial, JamId} = hold_twice(Config),
    ?assertEqual({error, {double_holding, Serial, [src]}},
                 cell_alarms:answer(JamId, retry, <<"op">>)),
    ?assertMatch({ok, #{kind := error}}, cell_alarms:get(JamId)),
    ?assertEqual(down, cell_task_proc:state(sink)),
    %% sink is right: the product is at sink, and src's copy is the one to go.
    ok = cell_alarms:answer(<<"src:held_twice">>, reset, <<"op">>),
    await_alarm(alarm_cleared, <<"sink:held_twice">>),
    ok = cell_alarms:answer(JamId, retry, <<"op">>),
    receive {line_out, sink, Serial} -> ok
    after ?TIMEOUT -> ct:fail(not_out)
    end.

%% Each move takes longer than the no-progress time: while src moves the product out
%% and a waits for it, the warning names src's timer, a's handshake and sink's; the
%% product arriving clears it.
stalled_line_warns_and_progress_clears(Config) ->
    ok = cell_events:subscribe([alarm_raised, alarm_cleared]),
    [Serial] = feed(Config, [<<"S-1">>]),
    ok = cell_controller:start(),
    #{description := Text} = await_alarm(alarm_raised, <<"cell:no_progress">>),
    ct:log("~ts", [Text]),
    [?assertNotEqual(nomatch, string:find(Text, Part), Part)
     || Part <- [<<"src: READY-PROCESSING-ACTIVE, phase leaving, product S-1, waits for a timer "
                   "of 2000 ms; link l1: up, committed">>,
                 <<"a: READY-PROCESSING-ACTIVE, phase moving_in, product S-1, waits for "
                   "handshake l1: available off; link l1: down, committed">>,
                 <<"sink: READY-IDLE-STARVED, phase idle, no product, waits for handshake l2: "
                   "available on">>]],
    %% cell_diag shows the same.
    Waits = iolist_to_binary(lists:join("\n", cell_guard:waits())),
    ?assertNotEqual(nomatch, string:find(Waits, <<"phase moving_in">>)),
    ok = cell_diag:waits(),
    ok = cell_diag:status(),
    await_alarm(alarm_cleared, <<"cell:no_progress">>),
    %% Raised again at the next stall, cleared again: the product goes on to the end.
    receive {line_out, sink, Serial} -> ok
    after 4 * ?MOVE_MS + ?TIMEOUT -> ct:fail(not_out)
    end.

%% -------------------------------------------------------------------------------------

before_cell(held_twice_read_back_at_boot) ->
    Stored = cell_product:stored(cell_product:new(<<"B-1">>, <<"line">>), 3, undefined),
    ok = filelib:ensure_dir(cell_product:path(<<"src">>, <<"Front">>)),
    [ok = cell_product:save(cell_product:path(Zone, <<"Front">>), Stored)
     || Zone <- [<<"src">>, <<"a">>]],
    ok;
before_cell(_Case) ->
    ok.

%% P passes a, sink takes it and sticks; src, free again, reads P again. Answers P and
%% sink's error.
hold_twice(Config) ->
    ok = cell_events:subscribe([alarm_raised, alarm_cleared]),
    [Serial] = feed(Config, [<<"P-1">>]),
    ok = cell_controller:start(),
    #{id := JamId} = await_alarm(alarm_raised, <<"sink:jam">>),
    [_] = feed(Config, [Serial]),
    #{description := TextSrc} = await_alarm(alarm_raised, <<"src:held_twice">>),
    #{description := TextSink} = await_alarm(alarm_raised, <<"sink:held_twice">>),
    [?assertNotEqual(nomatch, string:find(Text, <<"Product P-1 is held by two tasks at once: ",
                                                  Both/binary>>))
     || {Text, Both} <- [{TextSrc, <<"src and sink">>}, {TextSink, <<"sink and src">>}]],
    ?assertEqual([sink, src], lists:sort([Id || {Id, _} <- cell_registry:holders(Serial)])),
    {Serial, JamId}.

%% Until the product leaves sink; a jam on its way answered with Retry.
out_answering_jams(Serial) ->
    receive
        {line_out, sink, Serial} -> ok;
        {cell_event, #{type := alarm_raised, alarm := #{id := <<"sink:jam">> = Id}}} ->
            ok = cell_alarms:answer(Id, retry, <<"op">>),
            out_answering_jams(Serial)
    after ?TIMEOUT ->
        ct:fail({not_out, cell_registry:holders(Serial), cell_alarms:list()})
    end.

await_alarm(Type, Id) ->
    receive
        {cell_event, #{type := Type, alarm := #{id := Id} = A}} -> A
    after ?TIMEOUT ->
        ct:fail({no_alarm_event, Type, Id, cell_alarms:list()})
    end.

line_spec(Config, Delay, Jam) ->
    N = length(?SEGMENTS),
    Link = fun(I) -> list_to_atom("l" ++ integer_to_list(I)) end,
    Links = [#{id => Link(I), from => lists:nth(I, ?SEGMENTS), to => lists:nth(I + 1, ?SEGMENTS)}
             || I <- lists:seq(1, N - 1)],
    Tasks = [#{id => Id, module => cell_line_task, zone => atom_to_binary(Id, utf8),
               lane => <<"Front">>,
               args => #{prev => case I of 1 -> undefined; _ -> Link(I - 1) end,
                         next => case I of N -> undefined; _ -> Link(I) end,
                         feed => ?config(feed, Config), out => ?config(out, Config),
                         ref => ?config(ref, Config), notify => self(), phases => false,
                         delay => Delay, jam => Jam andalso Id =:= sink}}
             || {I, Id} <- lists:zip(lists:seq(1, N), ?SEGMENTS)],
    #{tasks => Tasks, links => Links}.

feed(Config, Serials) ->
    Feed = ?config(feed, Config),
    _ = [ets:insert(Feed, {erlang:unique_integer([positive, monotonic]), S}) || S <- Serials],
    case cell_task_proc:whereis(src) of
        undefined -> ok;
        Pid -> Pid ! {?config(ref, Config), fed}
    end,
    Serials.
