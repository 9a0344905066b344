%% The peer of the unit step benchmarks: a bare gen_statem doing the same steps — a
%% counter increment each — one per self-message, or `Burst' of them per message (as
%% a unit's sequence runs several steps in one go until one comes round again).
-module(cell_bench_step_peer).
-behaviour(gen_statem).

-export([start/2]).
-export([callback_mode/0, init/1, handle_event/4]).

-spec start(counters:counters_ref(), pos_integer()) -> {ok, pid()}.
start(Counter, Burst) ->
    gen_statem:start(?MODULE, {Counter, Burst}, []).

-spec callback_mode() -> gen_statem:callback_mode_result().
callback_mode() -> handle_event_function.

-spec init({counters:counters_ref(), pos_integer()}) -> gen_statem:init_result(atom()).
init({Counter, Burst}) ->
    self() ! step,
    {ok, stepping, {Counter, Burst}}.

-spec handle_event(gen_statem:event_type(), term(), atom(), term()) ->
          gen_statem:event_handler_result(atom()).
handle_event(info, step, stepping, {Counter, Burst}) ->
    burst(Counter, Burst),
    self() ! step,
    keep_state_and_data.

burst(_Counter, 0) -> ok;
burst(Counter, N) -> counters:add(Counter, 1, 1), burst(Counter, N - 1).
