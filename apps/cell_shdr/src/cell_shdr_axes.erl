%% @doc The cell's axes for the adapter: watches each axis the cache names (the hardware
%% objects of kind `axis' in the cell's spec) and hands the cache its status, which the
%% cache turns into the axis's items (cell_shdr_items:axis_values/2).
%%
%% An axis tells its watchers when it may have changed (cell_hal_hw:watch/1, through
%% cell_shdr_hal): a command,
%% a job's end, a fault. A simulated axis does not tell of every point of a move, so
%% while an axis moves its status is read again every `period' (100 ms), and no more
%% once it rests: an agent sees a move's course, an axis at rest costs nothing. An axis
%% that is not there (the monitor has not added it yet, or its process is restarting)
%% reads UNAVAILABLE, and is looked for again with a backoff (100 ms doubling to 2 s).
-module(cell_shdr_axes).
-behaviour(gen_server).

-export([start_link/0, watch/1]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2]).

-define(PERIOD_MS, 100).
-define(BACKOFF_MIN, 100).
-define(BACKOFF_MAX, 2000).

%% Per axis: the object's process watched (its monitor) or the wait before it is looked
%% for again, and the timer of its next read.
-record(axis, {monitor :: reference() | undefined,
               backoff = ?BACKOFF_MIN :: pos_integer(),
               timer :: reference() | undefined}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The axes to watch from now on (the cache's, as it read them from the cell).
-spec watch([atom()]) -> ok.
watch(Ids) ->
    gen_server:cast(?MODULE, {watch, Ids}).

-spec init([]) -> {ok, #{}, {continue, ask}}.
init([]) ->
    {ok, #{}, {continue, ask}}.

%% The cache may have read the cell's axes before this process was there to be told.
-spec handle_continue(ask, #{atom() => #axis{}}) -> {noreply, #{atom() => #axis{}}}.
handle_continue(ask, Axes) ->
    {noreply, set_axes(cell_shdr_cache:axes(), Axes)}.

-spec handle_call(term(), gen_server:from(), map()) -> no_return().
handle_call(Msg, _From, _Axes) ->
    error({unexpected_call, Msg}).

-spec handle_cast({watch, [atom()]}, #{atom() => #axis{}}) -> {noreply, #{atom() => #axis{}}}.
handle_cast({watch, Ids}, Axes) ->
    {noreply, set_axes(Ids, Axes)}.

-spec handle_info(term(), #{atom() => #axis{}}) -> {noreply, #{atom() => #axis{}}}.
handle_info({cell_hal_hw_changed, Id}, Axes) ->
    {noreply, read(Id, Axes)};
handle_info({timeout, TRef, {read, Id}}, Axes) ->
    case Axes of
        #{Id := #axis{timer = TRef} = A} -> {noreply, read(Id, Axes#{Id := A#axis{timer = undefined}})};
        _ -> {noreply, Axes}
    end;
handle_info({timeout, TRef, {look, Id}}, Axes) ->
    case Axes of
        #{Id := #axis{timer = TRef} = A} -> {noreply, look(Id, A#axis{timer = undefined}, Axes)};
        _ -> {noreply, Axes}
    end;
handle_info({'DOWN', Ref, process, _, _}, Axes) ->
    %% The axis's process went: unavailable until it is back.
    case [Id || {Id, #axis{monitor = R}} <- maps:to_list(Axes), R =:= Ref] of
        [Id] -> {noreply, look(Id, cancel(maps:get(Id, Axes)), Axes)};
        [] -> {noreply, Axes}
    end.

%%--------------------------------------------------------------------

set_axes(Ids, Axes) ->
    Gone = maps:without(Ids, Axes),
    _ = [forget(A) || A <- maps:values(Gone)],
    Kept = maps:with(Ids, Axes),
    lists:foldl(fun(Id, Acc) -> look(Id, #axis{}, Acc) end, Kept,
                [Id || Id <- Ids, not is_map_key(Id, Kept)]).

%% Watches the axis, or tells it unavailable and looks again later.
look(Id, A, Axes) ->
    case cell_shdr_hal:watch_axis(Id) of
        {ok, Pid} ->
            read(Id, Axes#{Id => A#axis{monitor = monitor(process, Pid), backoff = ?BACKOFF_MIN}});
        {error, not_present} ->
            ok = cell_shdr_cache:axis(Id, {error, not_present}),
            TRef = erlang:start_timer(A#axis.backoff, self(), {look, Id}),
            Axes#{Id => A#axis{monitor = undefined, timer = TRef,
                               backoff = min(A#axis.backoff * 2, ?BACKOFF_MAX)}}
    end.

%% The axis's status to the cache; read again while it moves.
read(Id, Axes) ->
    case Axes of
        #{Id := #axis{monitor = undefined}} ->
            %% Being looked for: its watch message came from a process since gone.
            Axes;
        #{Id := A} ->
            Status = cell_shdr_hal:axis_status(Id),
            ok = cell_shdr_cache:axis(Id, Status),
            Axes#{Id := again(Id, Status, A)};
        #{} ->
            Axes
    end.

again(Id, {ok, Status}, #axis{timer = undefined} = A) ->
    case cell_shdr_hal:axis_moving(Status) of
        true -> A#axis{timer = erlang:start_timer(?PERIOD_MS, self(), {read, Id})};
        false -> A
    end;
again(_Id, _Status, A) ->
    A.

cancel(#axis{timer = T} = A) ->
    _ = [erlang:cancel_timer(T) || T =/= undefined],
    A#axis{timer = undefined, monitor = undefined}.

forget(#axis{monitor = M} = A) ->
    _ = [demonitor(M, [flush]) || M =/= undefined],
    cancel(A).
