%% The line's physics ({@link __NAME___line}) under any order of what the PLC commands
%% and of the moves ending: a PropEr property. Whatever happens, no part is made or
%% lost (every part that arrived was delivered or is in the machine), the sensors say
%% what the world holds, a part moving on is never seen at two stations between two
%% effects, the ram is never at both ends, the world as saved starts again with its
%% parts where they were, and the line, its belts run, delivers.
-module(__NAME___line_tests).

-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

line_property_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_line(), [{to_file, user}, {numtests, 300}]))}.

%% One step: an output the PLC takes, or the n-th of the moves under way ending.
step() ->
    oneof([{out, oneof([infeed_belt, press_belt, ram_lower]), boolean()},
           {out, stroke_depth, range(0, 100)},
           {fire, range(1, 4)},
           {roll, float(0.0, 1.0)}]).

prop_line() ->
    ?FORALL(Steps, list(step()),
            begin
                P0 = __NAME___line:params(#{sim_stick_rate => 0.2}),
                {W0, Fx0} = __NAME___line:start(P0, __NAME___line:new()),
                {W, Sensors, _P} = lists:foldl(fun run/2, {W0, apply_sets(Fx0, #{}), P0}, Steps),
                conserved(W) andalso Sensors =:= __NAME___line:inputs(W)
                    andalso restarts(W, P0) andalso delivers(W)
            end).

run({roll, R}, {W, Sensors, P}) ->
    {W, Sensors, P#{roll => R}};
run({out, Point, V}, {W, Sensors, P}) ->
    {W1, Fx} = __NAME___line:output(Point, V, P, W),
    check(W1, Fx, Sensors, P);
run({fire, N}, {W, Sensors, P}) ->
    case pending(W) of
        [] -> {W, Sensors, P};
        Events ->
            Event = lists:nth((N - 1) rem length(Events) + 1, Events),
            {W1, Fx} = __NAME___line:event(Event, P, W),
            check(W1, Fx, Sensors, P)
    end.

check(W, Fx, Sensors0, P) ->
    true = conserved(W),
    Sensors = apply_sets(Fx, Sensors0),
    true = never_twice(Fx, Sensors0, Sensors),
    #{ram_up := Up, ram_down := Down} = Sensors,
    false = Up andalso Down,
    {W, Sensors, P}.

%% As the PLC may read them after each effect, the part sensors (part_*) never show more
%% parts than they did before the effects or after them: a part that moves on leaves one
%% station before it is seen at the next.
never_twice(Fx, Before, After) ->
    Most = max(shown(Before), shown(After)),
    {_, Ok} = lists:foldl(fun({set, K, V}, {S, Ok}) ->
                                  S1 = S#{K => V},
                                  {S1, Ok andalso shown(S1) =< Most};
                             (_, Acc) ->
                                  Acc
                          end, {Before, true}, Fx),
    Ok.

shown(Sensors) ->
    length([K || {K, true} <- maps:to_list(Sensors),
                 lists:prefix("part_", atom_to_list(K))]).

conserved(#{arrived := A, delivered := D} = W) ->
    A =:= D + __NAME___line:parts(W).

%% The world as saved, taken up again by a node started again: the same parts where
%% they were, none made or lost.
restarts(W, P) ->
    {W1, _} = __NAME___line:start(P, maps:merge(__NAME___line:new(), __NAME___line:persisted(W))),
    conserved(W1) andalso maps:with([arrived, delivered], W1) =:= maps:with([arrived, delivered], W)
        andalso parts_seen(W1) =:= parts_seen(W).

parts_seen(W) ->
    maps:filter(fun(K, _) -> lists:prefix("part_", atom_to_list(K)) end,
                __NAME___line:inputs(W)).

%% The belts and the ram left as they are, the moves under way run to their end: with
%% both belts on, every part that arrives goes through and out.
delivers(W0) ->
    P = __NAME___line:params(#{sim_stick_rate => 0.0}),
    {W1, _} = __NAME___line:output(ram_lower, false, P, W0),
    {W2, _} = __NAME___line:output(infeed_belt, true, P, W1),
    {W3, _} = __NAME___line:output(press_belt, true, P, W2),
    #{delivered := Before} = W3,
    #{delivered := After} = drain(W3, P, 20),
    After >= Before + 2.

drain(W, _P, 0) ->
    W;
drain(W, P, N) ->
    case pending(W) of
        [] -> W;
        [E | _] -> {W1, _} = __NAME___line:event(E, P, W), drain(W1, P, N - 1)
    end.

pending(#{pending := Pending}) ->
    lists:sort([{Kind, G} || {Kind, {G, _Ms}} <- maps:to_list(Pending)]).

apply_sets(Effects, Sensors) ->
    lists:foldl(fun({set, K, V}, Acc) -> Acc#{K => V};
                   (_, Acc) -> Acc
                end, Sensors, Effects).

serials_test() ->
    ?assertEqual(<<"P000001">>, __NAME___infeed_task:serial(<<"P">>, 1)).
