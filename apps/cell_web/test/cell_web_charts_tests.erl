%% The statistics charts' figures (cell_web_charts), both sides of every limit.
-module(cell_web_charts_tests).
-include_lib("eunit/include/eunit.hrl").

-define(H, 3600000).

selection_test_() ->
    Shifts = [{{{2024, 5, 1}, 1}, 0, 10}, {{{2024, 5, 1}, 2}, 10, 20},
              {{{2024, 5, 2}, 1}, 20, 30}],
    [?_assertEqual([{{2024, 5, 1}, 1}, {{2024, 5, 1}, 2}],
                   cell_web_charts:selection({day, {2024, 5, 1}}, Shifts)),
     ?_assertEqual([], cell_web_charts:selection({day, {2024, 5, 3}}, Shifts)),
     %% A range overlapping a shift by a millisecond holds it; touching it does not.
     ?_assertEqual([{{2024, 5, 1}, 2}], cell_web_charts:selection({range, 10, 11}, Shifts)),
     ?_assertEqual([{{2024, 5, 1}, 2}, {{2024, 5, 2}, 1}],
                   cell_web_charts:selection({range, 19, 21}, Shifts)),
     ?_assertEqual([], cell_web_charts:selection({range, 30, 40}, Shifts))].

add_test_() ->
    A = #{from => 0, to => 10, cell => #{in => 2, out => 1, good => 1, failed => 0, scrapped => 0},
          tasks => #{t => #{time_ms => #{executing => 5, off => 5}, in => 2, out => 1}}},
    B = #{from => 10, to => 30, cell => #{in => 1, out => 2, good => 1, failed => 1, scrapped => 1},
          tasks => #{t => #{time_ms => #{executing => 7, down => 3}, in => 1, out => 2},
                     u => #{time_ms => #{off => 20}, in => 0, out => 0}}},
    Sum = cell_web_charts:add([A, B]),
    [?_assertMatch(#{from := 0, to := 30,
                     cell := #{in := 3, out := 3, good := 2, failed := 1, scrapped := 1}}, Sum),
     ?_assertEqual(#{executing => 12, off => 5, down => 3},
                   maps:get(time_ms, maps:get(t, maps:get(tasks, Sum)))),
     ?_assertEqual(#{off => 20}, maps:get(time_ms, maps:get(u, maps:get(tasks, Sum)))),
     ?_assertMatch(#{from := null, tasks := #{}, cell := #{out := 0}}, cell_web_charts:add([]))].

hourly_test_() ->
    T0 = 1000 * ?H,
    Exits = [{T0 + 5, good}, {T0 + ?H - 1, failed}, {T0 + ?H, good}, {T0 + 3 * ?H, good},
             {T0 - 1, good}],
    [?_assertEqual([#{start => T0, out => 2, good => 1, failed => 1},
                    #{start => T0 + ?H, out => 1, good => 1, failed => 0},
                    #{start => T0 + 2 * ?H, out => 0, good => 0, failed => 0}],
                   cell_web_charts:hourly(Exits, T0 + 1, T0 + 2 * ?H + 10)),
     %% The first hour is the whole hour the span starts in (above, the exit before the
     %% span is not counted).
     ?_assertEqual([#{start => T0 - ?H, out => 1, good => 1, failed => 0},
                    #{start => T0, out => 1, good => 1, failed => 0}],
                   cell_web_charts:hourly(Exits, T0 - 10, T0 + 5)),
     ?_assertEqual([], cell_web_charts:hourly(Exits, 10, 9)),
     ?_assertEqual([#{start => 0, out => 0, good => 0, failed => 0}],
                   cell_web_charts:hourly([], 0, 0))].

cycles_test_() ->
    [?_assertEqual([], cell_web_charts:cycles([])),
     ?_assertEqual([], cell_web_charts:cycles([{5, good}])),
     ?_assertEqual([3, 10], cell_web_charts:cycles([{18, good}, {5, failed}, {8, good}]))].

histogram_test_() ->
    [?_assertEqual([], cell_web_charts:histogram([], 12)),
     ?_assertEqual([#{from => 7, to => 8, count => 3}], cell_web_charts:histogram([7, 7, 7], 12)),
     %% 10 to 29 in 2 bins of 10; the largest falls in the last.
     ?_assertEqual([#{from => 10, to => 20, count => 2}, #{from => 20, to => 30, count => 2}],
                   cell_web_charts:histogram([10, 19, 20, 29], 2)),
     %% Every value is counted once, whatever the bins.
     ?_assertEqual(100, lists:sum([C || #{count := C} <- cell_web_charts:histogram(
                                                          lists:seq(1, 100), 7)]))].

oee_test_() ->
    %% Two tasks, each 100 s planned (not OFF), one down 20 s: run 90 s on average.
    S = #{cell => #{out => 8, good => 6},
          tasks => #{a => #{time_ms => #{executing => 60000, starved => 40000, off => 50000}},
                     b => #{time_ms => #{executing => 50000, down => 15000, setup => 5000,
                                         blocked => 30000}}}},
    O = cell_web_charts:oee(S, 10000),
    [?_assertMatch(#{planned_ms := 100000, run_ms := 90000, availability := 0.9,
                     quality := 0.75}, O),
     ?_assertEqual(round(10000 * 8 / 90000 * 10000) / 10000, maps:get(performance, O)),
     ?_assertEqual(round(0.9 * maps:get(performance, O) * 0.75 * 10000) / 10000, maps:get(oee, O)),
     %% Nothing out: no quality, no OEE.
     ?_assertMatch(#{quality := null, oee := null, performance := 0.0},
                   cell_web_charts:oee(S#{cell := #{out => 0, good => 0}}, 10000)),
     %% No task: nothing planned.
     ?_assertMatch(#{availability := null, performance := null, oee := null},
                   cell_web_charts:oee(#{cell => #{out => 1, good => 1}, tasks => #{}}, 1000))].
