%% @doc The decisions of {@link cell_guard}, without processes: when a Started cell
%% that makes no progress is a silent deadlock the operator must hear of, and the
%% words that tell which task waits for what.
%%
%% The cell is watched while it is Started (request Start, no emergency stop) and no
%% error waits for an answer; the clock starts again whenever watching starts. Progress
%% is a product moving or work starting or ending; the process reads when it last
%% happened when its timer fires, so a transfer costs the guard no message. At the
%% deadline (the no-progress time after the later of progress and the start of
%% watching):
%%
%% <ul>
%% <li>progress came meanwhile: the timer is armed again for its new deadline;</li>
%% <li>no product in the cell: nothing can be stuck; the guard sleeps until the next
%%     progress (a product coming in is one);</li>
%% <li>else: the warning, and the guard sleeps until the next progress, which clears
%%     it.</li>
%% </ul>
%%
%% Effects: `{arm, Deadline}' (monotonic ms; replaces any timer), `disarm', `sleep'
%% (no timer; tell me of the next progress), `warn', `clear'.
-module(cell_guard_core).

-export([new/1, conditions/3, limit/3, progress/2, timeout/4, watching/1, warned/1]).
-export([wait_text/1, task_line/1, warning_text/2, double_text/3]).

-export_type([core/0, effect/0]).

-record(core, {limit :: pos_integer(),
               started = false :: boolean(),
               error = false :: boolean(),
               since = 0 :: integer(),
               warned = false :: boolean()}).

-opaque core() :: #core{}.
-type effect() :: {arm, integer()} | disarm | sleep | warn | clear.

%% @doc A guard with a no-progress time in milliseconds, not yet watching.
-spec new(pos_integer()) -> core().
new(LimitMs) when is_integer(LimitMs), LimitMs > 0 ->
    #core{limit = LimitMs}.

-spec watching(core()) -> boolean().
watching(#core{started = S, error = E}) -> S andalso not E.

-spec warned(core()) -> boolean().
warned(#core{warned = W}) -> W.

%% @doc Whether the cell is Started and whether an error waits, at `Now'.
-spec conditions(#{started := boolean(), error := boolean()}, integer(), core()) ->
          {core(), [effect()]}.
conditions(#{started := Started, error := Error}, Now, C0) ->
    Was = watching(C0),
    C = C0#core{started = Started, error = Error},
    case {Was, watching(C)} of
        {Same, Same} -> {C, []};
        {false, true} -> {C#core{since = Now}, [{arm, Now + C#core.limit}]};
        {true, false} -> unwarn(C, [disarm])
    end.

%% @doc A new no-progress time: the deadline moves with it.
-spec limit(pos_integer(), integer(), core()) -> {core(), [effect()]}.
limit(LimitMs, _Now, #core{limit = LimitMs} = C) ->
    {C, []};
limit(LimitMs, Now, C0) when is_integer(LimitMs), LimitMs > 0 ->
    C = C0#core{limit = LimitMs},
    case watching(C) andalso not C#core.warned of
        true -> {C, [{arm, max(Now, C#core.since + LimitMs)}]};
        false -> {C, []}
    end.

%% @doc Told of progress while sleeping: a warning goes; the clock starts again.
-spec progress(integer(), core()) -> {core(), [effect()]}.
progress(Now, C0) ->
    case watching(C0) of
        true ->
            {C, Effects} = unwarn(C0#core{since = Now}, []),
            {C, Effects ++ [{arm, Now + C#core.limit}]};
        false ->
            {C0, []}
    end.

%% @doc The timer fired at `Now'; progress last came at `Last'; `Products': whether
%% any task holds one.
-spec timeout(integer(), integer(), boolean(), core()) -> {core(), [effect()]}.
timeout(Now, Last, Products, #core{limit = Limit, since = Since} = C) ->
    From = max(Last, Since),
    case watching(C) of
        false -> {C, []};
        true when Now - From < Limit -> {C, [{arm, From + Limit}]};
        true when not Products -> {C, [sleep]};
        true when C#core.warned -> {C, [sleep]};
        true -> {C#core{warned = true}, [warn, sleep]}
    end.

unwarn(#core{warned = true} = C, Effects) -> {C#core{warned = false}, Effects ++ [clear]};
unwarn(C, Effects) -> {C, Effects}.

%% -------------------------------------------------------------------------------------
%% Words
%% -------------------------------------------------------------------------------------

%% @doc One wait of a task, as the operator reads it.
-spec wait_text(term()) -> iolist().
wait_text({timer, Ms}) ->
    io_lib:format("a timer of ~b ms", [Ms]);
wait_text({reply, _Ref}) ->
    "an answer from another process";
wait_text({io, Point, Cond}) ->
    io_lib:format("input ~ts ~ts", [Point, cond_text(Cond)]);
wait_text({io, Group, Point, Cond}) ->
    io_lib:format("input ~ts.~ts ~ts", [Group, Point, cond_text(Cond)]);
wait_text({handshake, Link, Signal, Value}) ->
    io_lib:format("handshake ~ts: ~ts ~ts", [Link, Signal, on_off(Value)]);
wait_text(Other) ->
    io_lib:format("~tp", [Other]).

cond_text({eq, V}) -> io_lib:format("= ~tp", [V]);
cond_text({ne, V}) -> io_lib:format("/= ~tp", [V]);
cond_text({gt, V}) -> io_lib:format("> ~tp", [V]);
cond_text({lt, V}) -> io_lib:format("< ~tp", [V]);
cond_text({ge, V}) -> io_lib:format(">= ~tp", [V]);
cond_text({le, V}) -> io_lib:format("=< ~tp", [V]);
cond_text(C) -> io_lib:format("~tp", [C]).

on_off(true) -> "on";
on_off(false) -> "off";
on_off(V) -> io_lib:format("~tp", [V]).

%% @doc One task's line: its state, phase, product, what it waits for, and the phase
%% of each handshake link it is in. `Info' is what {@link cell_task_proc:info/1}
%% answers (or `#{id, state}' alone for a task that did not answer).
-spec task_line(map()) -> iolist().
task_line(#{id := Id, state := State} = Info) ->
    Phase = case maps:get(phase, Info, undefined) of
                undefined -> "";
                P -> io_lib:format(", phase ~ts", [P])
            end,
    Product = case maps:get(product, Info, undefined) of
                  #{serial := S} -> io_lib:format(", product ~ts", [S]);
                  _ -> ", no product"
              end,
    Waits = case maps:get(waits, Info, []) of
                [] when State =:= off -> "";
                [] -> ", waits for nothing (a step is due)";
                Ws -> [", waits for ", lists:join(" or ", [wait_text(W) || W <- Ws])]
            end,
    Links = [io_lib:format("; link ~ts: ~ts, ~ts", [L, R, Ph])
             || {L, #{role := R, phase := Ph}} <- lists:sort(maps:to_list(maps:get(links, Info, #{}))),
                Ph =/= idle],
    Down = case maps:get(down, Info, undefined) of
               {paused, _} -> ", paused";
               _ -> ""
           end,
    [atom_to_list(Id), ": ", cell_ipc:name(State), Down, Phase, Product, Waits, Links].

%% @doc The text of the no-progress warning.
-spec warning_text(pos_integer(), [map()]) -> iolist().
warning_text(LimitMs, Infos) ->
    [io_lib:format("The cell is started and holds products, but nothing has moved for "
                   "~ts and no error waits: the tasks wait for one another or for an "
                   "input that does not come.~nCheck the first task that waits for an "
                   "input or a handshake below; stop the cell and take out by hand what "
                   "blocks it, or answer a task's error.~n", [duration(LimitMs)]),
     lists:join("\n", [task_line(I) || I <- Infos])].

duration(Ms) when Ms rem 1000 =:= 0 -> io_lib:format("~b s", [Ms div 1000]);
duration(Ms) -> io_lib:format("~b ms", [Ms]).

%% @doc The text of the error a task holding a serial that `Other' also holds gets.
-spec double_text(binary(), atom(), atom()) -> iolist().
double_text(Serial, Task, Other) ->
    io_lib:format("Product ~ts is held by two tasks at once: ~ts and ~ts. A product can be "
                  "in one place only.~nCheck where it is. Select RESET here if it is NOT "
                  "at ~ts: ~ts forgets it and starts again without it, and ~ts keeps it. "
                  "If it is in neither place, take it out by hand and select RESET on "
                  "both errors. Until then no answer that lets either task go on with it "
                  "is accepted.", [Serial, Task, Other, Task, Task, Other]).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

-define(L, 60000).

started(C) -> element(1, conditions(#{started => true, error => false}, 0, C)).

conditions_test_() ->
    C0 = new(?L),
    [?_assertEqual({C0#core{started = true, error = true}, []},
                   conditions(#{started => true, error => true}, 5, C0)),
     ?_assertMatch({_, [{arm, 60005}]}, conditions(#{started => true, error => false}, 5, C0)),
     ?_assertMatch({_, [disarm]}, conditions(#{started => true, error => true}, 9, started(C0))),
     ?_assertMatch({_, [disarm]}, conditions(#{started => false, error => false}, 9, started(C0))),
     ?_assertMatch({_, []}, conditions(#{started => true, error => false}, 9, started(C0)))].

%% Both sides of the no-progress time, with and without products, with and without
%% an error waiting.
limit_test_() ->
    C = started(new(?L)),
    [?_assertEqual({C, [{arm, ?L}]}, timeout(?L - 1, 0, true, C)),
     ?_assertMatch({_, [warn, sleep]}, timeout(?L, 0, true, C)),
     ?_assertMatch({_, [warn, sleep]}, timeout(?L + 1, 0, true, C)),
     ?_assertEqual({C, [{arm, ?L}]}, timeout(?L - 1, 0, false, C)),
     ?_assertEqual({C, [sleep]}, timeout(?L, 0, false, C)),
     %% Progress since: the deadline moves to it.
     ?_assertEqual({C, [{arm, 10 + ?L}]}, timeout(?L, 10, true, C)),
     ?_assertMatch({_, [warn, sleep]}, timeout(10 + ?L, 10, true, C))].

error_waits_test_() ->
    {C, _} = conditions(#{started => true, error => true}, 0, new(?L)),
    [?_assertEqual({C, []}, timeout(?L - 1, 0, true, C)),
     ?_assertEqual({C, []}, timeout(?L, 0, true, C)),
     ?_assertEqual({C, []}, timeout(?L * 10, 0, true, C))].

not_started_test_() ->
    C = new(?L),
    [?_assertEqual({C, []}, timeout(?L, 0, true, C)),
     ?_assertEqual({C, []}, progress(?L, C))].

%% The clock starts again when the error is answered: the time it waited is not
%% counted.
error_answered_test() ->
    {C1, _} = conditions(#{started => true, error => true}, 0, new(?L)),
    {C2, [{arm, D}]} = conditions(#{started => true, error => false}, 50000, C1),
    ?assertEqual(50000 + ?L, D),
    ?assertMatch({_, [{arm, D}]}, timeout(50000 + ?L - 1, 0, true, C2)),
    ?assertMatch({_, [warn, sleep]}, timeout(50000 + ?L, 0, true, C2)).

warned_then_progress_test() ->
    {C1, [warn, sleep]} = timeout(?L, 0, true, started(new(?L))),
    ?assert(warned(C1)),
    %% A second fire while warned warns no more.
    ?assertEqual({C1, [sleep]}, timeout(?L + 5, 0, true, C1)),
    {C2, Effects} = progress(?L + 100, C1),
    ?assertEqual([clear, {arm, 2 * ?L + 100}], Effects),
    ?assertNot(warned(C2)),
    %% An error while warned: the warning goes, the guard stops watching.
    {C3, E3} = conditions(#{started => true, error => true}, ?L + 1, C1),
    ?assertEqual([disarm, clear], E3),
    ?assertNot(warned(C3)),
    ?assertNot(watching(C3)).

new_limit_test_() ->
    C = started(new(?L)),
    [?_assertEqual([{arm, 1000}], element(2, limit(1000, 10, C))),
     ?_assertEqual([{arm, 70000}], element(2, limit(1000, 70000, C))),
     ?_assertEqual([], element(2, limit(?L, 10, C))),
     ?_assertEqual([], element(2, limit(1000, 10, new(?L))))].

sleeping_then_product_test() ->
    C = started(new(?L)),
    {C, [sleep]} = timeout(?L, 0, false, C),
    ?assertEqual({C#core{since = ?L + 7}, [{arm, 2 * ?L + 7}]}, progress(?L + 7, C)).

text_test_() ->
    Line = fun(I) -> lists:flatten(io_lib:format("~ts", [task_line(I)])) end,
    [?_assertEqual("a: READY-IDLE-BLOCKED, phase offered, product P1, waits for handshake "
                   "l1: not_busy on; link l1: up, offered",
                   Line(#{id => a, state => {ready, idle, blocked}, phase => offered,
                          product => #{serial => <<"P1">>},
                          waits => [{handshake, l1, not_busy, true}],
                          links => #{l1 => #{role => up, phase => offered},
                                     l0 => #{role => down, phase => idle}}})),
     ?_assertEqual("b: READY-PROCESSING-ACTIVE, no product, waits for input io.belt = true "
                   "or a timer of 500 ms",
                   Line(#{id => b, state => {ready, processing, active},
                          waits => [{io, io, belt, {eq, true}}, {timer, 500}]})),
     ?_assertEqual("c: OFF, no product", Line(#{id => c, state => off})),
     ?_assertMatch([_ | _], string:find(lists:flatten(io_lib:format("~ts", [double_text(<<"P9">>, a, b)])),
                                        "held by two tasks at once: a and b"))].
-endif.
