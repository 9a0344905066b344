%% @doc Time series (seed 003): the HAL points configured with `time_series' are read
%% at their fixed rate, and every `count' samples go to the cache as one line
%% `count|rate|v1 v2 ...', stamped with the time of the last sample.
%%
%% Each series runs on absolute monotonic deadlines (one timer per sample, the next
%% deadline one period after the last), so the rate does not drift with the time a
%% read takes. A sample that cannot be read, or a deadline missed by more than a
%% period (the machine was busy), ends the batch early: the samples taken are sent,
%% and the series starts again, so a line never claims a spacing it did not have.
-module(cell_shdr_sampler).
-behaviour(gen_server).

-export([start_link/0, reconfigure/0]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2]).

-record(series, {key :: binary(), group :: binary(), point :: binary(),
                 rate :: float(), count :: pos_integer(),
                 period :: pos_integer(),                 %% µs
                 due :: integer(),                        %% monotonic µs
                 samples = [] :: [number()],
                 last :: {integer(), integer()} | undefined,
                 timer :: reference() | undefined}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Reads the configured series again (their settings changed).
-spec reconfigure() -> ok.
reconfigure() ->
    gen_server:cast(?MODULE, reconfigure).

-spec init([]) -> {ok, #{}, {continue, configure}}.
init([]) ->
    {ok, #{}, {continue, configure}}.

-spec handle_continue(configure, map()) -> {noreply, map()}.
handle_continue(configure, State) ->
    {noreply, configure(State)}.

-spec handle_call(term(), gen_server:from(), map()) -> no_return().
handle_call(Msg, _From, _State) ->
    error({unexpected_call, Msg}).

-spec handle_cast(reconfigure, map()) -> {noreply, map()}.
handle_cast(reconfigure, State) ->
    {noreply, configure(State)}.

-spec handle_info(term(), map()) -> {noreply, map()}.
handle_info({timeout, TRef, {sample, Key}}, State) ->
    case State of
        #{Key := #series{timer = TRef} = S} -> {noreply, State#{Key => sample(S)}};
        _ -> {noreply, State}
    end.

configure(Old) ->
    _ = [erlang:cancel_timer(T) || #series{timer = T} <- maps:values(Old), T =/= undefined],
    Now = erlang:monotonic_time(microsecond),
    maps:from_list(
      [{Key, schedule(#series{key = Key, group = G, point = P, rate = float(Rate),
                              count = Count, period = max(1, round(1.0e6 / Rate)),
                              due = Now})}
       || #{time_series := true, name := Key, group := G, point := P, rate := Rate,
            count := Count} <- cell_shdr_cache:points()]).

schedule(#series{key = Key, due = Due} = S) ->
    TRef = erlang:start_timer(erlang:convert_time_unit(Due, microsecond, millisecond),
                              self(), {sample, Key}, [{abs, true}]),
    S#series{timer = TRef}.

sample(#series{group = G, point = P, period = Period, due = Due} = S) ->
    Now = erlang:monotonic_time(microsecond),
    case {Now - Due > Period, number(cell_shdr_hal:read(G, P))} of
        {false, {ok, V}} ->
            Taken = {os:system_time(millisecond), Now},
            add(V, Taken, S#series{due = Due + Period});
        _ ->
            %% Late or unreadable: what was taken goes out, the series starts anew.
            schedule(flush(S#series{due = Now + Period}))
    end.

%% A reading as a sample's number (a boolean is 1 or 0), as other samples publish it.
number({ok, V0}) ->
    case cell_shdr_items:point_value(#{category => sample}, V0) of
        V when is_number(V) -> {ok, V};
        _ -> error
    end;
number({error, _}) ->
    error.

add(V, Taken, #series{samples = Samples, count = Count} = S) ->
    S1 = S#series{samples = [V | Samples], last = Taken},
    case length(Samples) + 1 >= Count of
        true -> schedule(flush(S1));
        false -> schedule(S1)
    end.

flush(#series{samples = []} = S) ->
    S;
flush(#series{key = Key, samples = Samples, last = Last, rate = Rate} = S) ->
    ok = cell_shdr_cache:time_series(Key, Last, Rate, lists:reverse(Samples)),
    S#series{samples = [], last = undefined}.
