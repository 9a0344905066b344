%% Bare peers for the runtime benchmarks: a gen_statem that loops on a self-message
%% doing the same counter increment as a spinning task, and an idle gen_statem.
-module(cell_bench_peer).
-behaviour(gen_statem).

-export([start_spin/1, start_idle/0]).
-export([callback_mode/0, init/1, handle_event/4]).

-spec start_spin(counters:counters_ref()) -> {ok, pid()}.
start_spin(Counter) ->
    gen_statem:start(?MODULE, {spin, Counter}, []).

-spec start_idle() -> {ok, pid()}.
start_idle() ->
    gen_statem:start(?MODULE, idle, []).

-spec callback_mode() -> gen_statem:callback_mode_result().
callback_mode() -> handle_event_function.

-spec init(term()) -> gen_statem:init_result(atom()).
init({spin, Counter}) ->
    self() ! step,
    {ok, spinning, Counter};
init(idle) ->
    {ok, idle, #{}}.

-spec handle_event(gen_statem:event_type(), term(), atom(), term()) ->
          gen_statem:event_handler_result(atom()).
handle_event(info, step, spinning, Counter) ->
    counters:add(Counter, 1, 1),
    self() ! step,
    keep_state_and_data;
handle_event(info, {stop, From}, _State, _Data) ->
    From ! {stopped, self(), erlang:monotonic_time(microsecond)},
    {stop, normal}.
