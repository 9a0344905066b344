%% The sequences the unit benchmarks time.
%%
%% `#{bench := steps, counter := C, steps := N}': N steps in a ring, each done at
%% once (it counts itself in the counter), the mode as the args say.
%% `#{bench := sensor, notify := Pid}': waits for the sensor to be on, then off, and
%% tells Pid on entering the step after each: `{entered, On, MonotonicUs}'.
-module(cell_bench_seq).
-behaviour(cell_sequence).

-export([init/2, step/2]).

-spec init(map(), cell_sequence:seq()) -> {ok, term(), cell_sequence:seq()}.
init(#{bench := steps}, Seq) -> {ok, 1, Seq};
init(#{bench := sensor}, Seq) -> {ok, wait_on, Seq}.

-spec step(term(), cell_sequence:seq()) -> cell_sequence:result().
step(N, Seq) when is_integer(N) ->
    counters:add(cell_sequence:arg(Seq, counter, undefined), 1, 1),
    cell_sequence:next(Seq, N rem cell_sequence:arg(Seq, steps, 10) + 1);
step(wait_on, Seq) ->
    cell_sequence:await(Seq, {io, sensor, {eq, true}}, on);
step(on, Seq) ->
    entered(Seq, true),
    cell_sequence:next(Seq, wait_off);
step(wait_off, Seq) ->
    cell_sequence:await(Seq, {io, sensor, {eq, false}}, off);
step(off, Seq) ->
    entered(Seq, false),
    cell_sequence:next(Seq, wait_on).

entered(Seq, On) ->
    case cell_sequence:on_entry(Seq) of
        true -> cell_sequence:arg(Seq, notify, undefined)
                    ! {entered, On, erlang:monotonic_time(microsecond)};
        false -> ok
    end.
