%% Properties of the guard's no-progress decisions ({@link cell_guard_core}), driven the
%% way cell_guard drives them: a timer that fires at the deadline it was armed for, a
%% progress stamp read when it fires, and one word of the next progress once the guard
%% sleeps. The model is the rule in the guard's documentation and nothing else: the
%% warning stands exactly while the cell is Started, no error waits, it holds products,
%% and nothing has moved for the no-progress time since the later of the last progress
%% and the start of watching.
-module(prop_cell_guard).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(LIMIT, 100).

-record(world, {now = 0 :: integer(),
                core :: cell_guard_core:core(),
                timer :: integer() | undefined,
                wake = false :: boolean(),
                last = 0 :: integer(),
                products = false :: boolean(),
                started = false :: boolean(),
                error = false :: boolean(),
                since = 0 :: integer(),          %% the model: when watching began
                warning = false :: boolean()}).

model_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_warning_follows_the_model(),
                                              [{to_file, user}, {numtests, 1000}]))}.

prop_warning_follows_the_model() ->
    ?FORALL(Steps, list({range(0, 3 * ?LIMIT), action()}),
            begin
                W0 = #world{core = cell_guard_core:new(?LIMIT)},
                {Result, W} = run(Steps, W0),
                ?WHENFAIL(io:format("~p~nat ~p: ~p~n", [Steps, W#world.now, Result]),
                          Result =:= ok)
            end).

action() ->
    oneof([progress, products_in, products_out, {conditions, boolean(), boolean()}]).

run([], W) ->
    {check(W), W};
run([{Dt, Action} | Rest], W0) ->
    W1 = fire_until(W0#world.now + Dt, W0),
    W = act(Action, W1),
    case check(W) of
        ok -> run(Rest, W);
        Error -> {Error, W}
    end.

%% Every timer due by `Until' fires at its own deadline, as erlang:start_timer does.
fire_until(Until, #world{timer = T} = W) when T =/= undefined, T =< Until ->
    W1 = W#world{now = max(T, W#world.now), timer = undefined, wake = true},
    #world{now = Now, last = Last, products = P, core = C} = W1,
    W2 = effects(cell_guard_core:timeout(Now, Last, P, C), W1),
    case check(W2) of
        ok -> fire_until(Until, W2);
        Error -> erlang:error({after_timeout, Error, W2})
    end;
fire_until(Until, W) ->
    W#world{now = Until}.

%% A product coming or going moves it: progress too.
act(progress, W) -> progressed(W);
act(products_in, W) -> progressed(W#world{products = true});
act(products_out, W) -> progressed(W#world{products = false});
act({conditions, Started, Error}, #world{now = Now, core = C} = W) ->
    Was = W#world.started andalso not W#world.error,
    Is = Started andalso not Error,
    Since = case {Was, Is} of
                {false, true} -> Now;
                _ -> W#world.since
            end,
    W1 = W#world{started = Started, error = Error, since = Since},
    effects(cell_guard_core:conditions(#{started => Started, error => Error}, Now, C), W1).

progressed(#world{now = Now, wake = true, core = C} = W) ->
    effects(cell_guard_core:progress(Now, C), W#world{last = Now, wake = false});
progressed(#world{now = Now} = W) ->
    W#world{last = Now}.

effects({C, Effects}, W) ->
    lists:foldl(fun effect/2, W#world{core = C}, Effects).

effect({arm, D}, W) -> W#world{timer = D, wake = false};
effect(disarm, W) -> W#world{timer = undefined, wake = false};
effect(sleep, W) -> W;
effect(warn, W) -> W#world{warning = true};
effect(clear, W) -> W#world{warning = false}.

check(#world{now = Now, started = S, error = E, products = P, last = L, since = Since,
             warning = Warning}) ->
    Due = S andalso not E andalso P andalso Now - max(L, Since) >= ?LIMIT,
    case Warning =:= Due of
        true -> ok;
        false -> {warning, Warning, due, Due}
    end.
