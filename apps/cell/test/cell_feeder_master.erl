%% The seed's dynamic handshake (seed 000 §2.3.6): a master task connects its
%% handshake to one feeder after another — disconnect, connect the next, take a
%% product, complete, and so on round the list of feeders.
-module(cell_feeder_master).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, cell_task:put(T, turn, 0)}.

%% No sensors: what the product file says is where the product is.
-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    {ok, T}.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    T.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    Feeders = cell_task:arg(T, feeders, []),
    Turn = cell_task:get(T, turn),
    Link = lists:nth(Turn rem length(Feeders) + 1, Feeders),
    case cell_task:get(T, connected, undefined) of
        undefined ->
            {ok, T1} = cell_handshake:connect(T, Link, down),
            {continue, cell_task:put(T1, connected, Link)};
        Link ->
            take(T, Link)
    end.

take(T, Link) ->
    case {cell_task:product(T), cell_task:woken_by(T)} of
        {undefined, _} ->
            case cell_handshake:available(T, Link) of
                true ->
                    case cell_handshake:commit(T, Link) of
                        {ok, T1} -> {wait, {handshake, Link, available, false}, T1};
                        {not_available, T1} -> {wait, {handshake, Link, available, true}, T1}
                    end;
                false ->
                    {wait, {handshake, Link, available, true}, T}
            end;
        {#{serial := S}, {handshake, Link, available, false}} ->
            T1 = cell_handshake:complete(T, Link),
            cell_task:arg(T, notify, self()) ! {master_took, Link, S},
            T2 = cell_task:clear_product(T1),
            {ok, T3} = cell_handshake:disconnect(T2, Link),
            {continue, cell_task:put(cell_task:put(T3, connected, undefined), turn,
                                     cell_task:get(T3, turn) + 1)};
        {#{}, _} ->
            {wait, {handshake, Link, available, false}, T}
    end.
