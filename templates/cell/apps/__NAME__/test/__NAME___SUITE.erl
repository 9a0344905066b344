%% The __NAME__ cell, run in this node on its simulated line: parts pass the line,
%% each with a serial of its own; the serial counter goes on after the cell is
%% stopped and started again (retained data), never repeating one; a press stroke
%% that sticks is the operator's question, and their answer does what it says.
%%
%% The simulation runs fast (`sim_time_scale'); every wait is for an event of the
%% cell with a deadline. The operator panel and the SHDR adapter are not started here
%% (they are applications of the release), so no port is taken.
-module(__NAME___SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([parts_pass_the_line/1, serials_survive_a_restart/1, stuck_stroke_answers/1]).

-define(DEADLINE_MS, 60000).
-define(EVENTS, [item_transfer_out, alarm_raised, cell_state]).

all() ->
    [parts_pass_the_line, serials_survive_a_restart, stuck_stroke_answers].

init_per_testcase(Case, Config) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    Own = maps:merge(#{sim_time_scale => 0.05, sim_arrival_ms => 0, hal_poll_ms => 5,
                       transfer_timeout_ms => 5000, stroke_timeout_ms => 2000},
                     settings(Case)),
    ok = cell_testkit:write_settings(Root, #{machine => #{simulation_mode => true},
                                             __NAME__ => Own}),
    ok = start(Root),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    stop().

settings(stuck_stroke_answers) -> #{sim_stick_rate => 1.0};
settings(_) -> #{}.

%% -------------------------------------------------------------------------------------

%% Ten parts enter, are pressed and leave, each with a serial of its own, in order.
parts_pass_the_line(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Out = collect_out(10, fun never_answer/1),
    ok = stop_cell(),
    ?assertEqual(Out, lists:usort(Out)),
    ?assertEqual(<<"P000001">>, hd(Out)),
    #{delivered := Delivered} = __NAME___sim:world(),
    ?assert(Delivered >= 10).

%% The cell stopped and its applications started again (as at a new boot of the
%% node): the parts the tasks held are reconciled with the sensors and go on, first
%% out; the infeed's serial counter goes on from where it was.
serials_survive_a_restart(Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    First = collect_out(3, fun never_answer/1),
    ok = stop_cell(),
    Held = lists:sort([S || #{serial := S} <- cell_controller:tasks(), is_binary(S)]),
    ok = stop(),
    ok = start(?config(root, Config)),
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    Second = collect_out(3, fun never_answer/1),
    ok = stop_cell(),
    All = First ++ Second,
    ?assertEqual(length(All), length(lists:usort(All))),
    ?assertEqual(Held, lists:sublist(Second, length(Held))),
    ?assert(lists:max(First) < lists:min(Second)).

%% Every stroke sticks: the press asks; Retry presses again (it sticks again), Ignore
%% sends the part on, marked failed.
stuck_stroke_answers(_Config) ->
    ok = cell_events:subscribe(?EVENTS),
    ok = cell_controller:start(<<"suite">>),
    {ok, #{id := Id}} = await_alarm(<<"Press stroke not completed">>),
    ok = cell_alarms:answer(Id, retry, <<"suite">>),
    {ok, #{id := Id2}} = await_alarm(<<"Press stroke not completed">>),
    ok = cell_alarms:answer(Id2, ignore, <<"suite">>),
    [Serial] = collect_out(1, fun(_) -> ok end),
    ok = stop_cell(fun(#{id := A, kind := error}) ->
                           %% The next part's stroke: it may be withdrawn as the cell stops.
                           _ = cell_alarms:answer(A, ignore, <<"suite">>),
                           ok;
                      (_) -> ok
                   end),
    ?assertEqual(<<"P000001">>, Serial).

%% -------------------------------------------------------------------------------------

%% The cell in this node, as the release runs it (cellrt's cell_testkit), once its
%% PLC is connected and the simulation has set up the machine.
start(Root) ->
    ok = cell_testkit:start(Root, __NAME__, __NAME__),
    ok = cell_testkit:await_connection(__NAME___plc, ?DEADLINE_MS),
    __NAME___sim:ready(?DEADLINE_MS).

stop() ->
    cell_testkit:stop(__NAME__, [__NAME___plc]).

stop_cell() ->
    stop_cell(fun never_answer/1).

%% Stop, and wait until every task is OFF; errors raised meanwhile go to `Answer'.
stop_cell(Answer) ->
    ok = cell_events:subscribe(?EVENTS),
    cell_testkit:stop_cell(Answer, ?DEADLINE_MS).

await_alarm(Caption) ->
    Deadline = erlang:monotonic_time(millisecond) + ?DEADLINE_MS,
    receive
        {cell_event, #{type := alarm_raised, alarm := #{caption := Caption} = A}} -> {ok, A}
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail({no_alarm, Caption, cell_alarms:list()})
    end.

%% The serials of the next N parts the press sends out; alarms go to `Answer'.
collect_out(N, Answer) ->
    cell_testkit:collect(N, fun(#{type := item_transfer_out, task := press, item := S}) ->
                                    {true, S};
                               (_) ->
                                    false
                            end, Answer, ?DEADLINE_MS).

never_answer(#{kind := error} = A) -> ct:fail({unexpected_error, A});
never_answer(_) -> ok.
