%% @doc The MTConnect SHDR adapter application: starts its supervisor, and stops so
%% that its agents see the stop.
%%
%% The adapter depends on the cell, so the node stops it first: the cell's own orderly
%% stop (`cell_app:rest/0', every task brought to rest) would come after the
%% agents' connections had gone, and an agent would see only the connection's end.
%% When the node is going down, the adapter has the cell stop first, while it still
%% streams the stop; then, whenever the adapter stops, `avail' goes UNAVAILABLE and
%% every client is sent what is left before its connection is closed.
-module(cell_shdr_app).
-behaviour(application).

-export([start/2, prep_stop/1, stop/1]).

%% How long the clients are given to take what is left of the log.
-define(CLOSE_WAIT, 5000).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    cell_shdr_sup:start_link().

-spec prep_stop(State) -> State.
prep_stop(State) ->
    case init:get_status() of
        %% The node stops: the cell's Stop, as the cell would make it after us.
        {stopping, _} -> ok = cell_app:rest();
        _ -> ok
    end,
    try cell_shdr_cache:close_clients() of
        Pids -> await_down([monitor(process, P) || P <- Pids],
                           erlang:monotonic_time(millisecond) + ?CLOSE_WAIT)
    catch
        %% The cache is restarting or gone: its clients went with it.
        exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                           Why =:= killed; element(1, Why) =:= shutdown ->
            ok
    end,
    State.

-spec stop(term()) -> ok.
stop(_State) ->
    ok.

await_down([], _Deadline) ->
    ok;
await_down([Ref | Rest], Deadline) ->
    receive
        {'DOWN', Ref, process, _, _} -> await_down(Rest, Deadline)
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        _ = [demonitor(R, [flush]) || R <- [Ref | Rest]],
        ok
    end.
