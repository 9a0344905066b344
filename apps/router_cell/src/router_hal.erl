%% @doc Connects the router's HAL from its cell spec (the `hal' key: connections and
%% IO group instances) when the cell application starts, and disconnects it when it
%% stops: the process that connects the HAL also disconnects it (seed 000 §2.4.1).
%%
%% The groups exist before the cell's first Start, which is when the tasks look for
%% their IO (arrow 0). A connection or group that is already configured the same way
%% (after a restart of this process) is kept.
-module(router_hal).
-behaviour(gen_server).

-export([start_link/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2, terminate/2]).

-type hal() :: #{connections := [cell_hal:connection_spec()],
                 groups := [cell_hal:group_spec()]}.

-spec start_link(hal()) -> {ok, pid()} | {error, term()}.
start_link(Hal) ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, Hal, []).

%% The HAL is configured here, before the next child (the simulation) starts and
%% looks for its points. These are calls to the HAL's own server, no I/O of ours.
-spec init(hal()) -> {ok, hal()} | {stop, term()}.
init(#{connections := Conns, groups := Groups} = Hal) ->
    process_flag(trap_exit, true),
    case add(fun cell_hal:add_connection/1, Conns) of
        ok ->
            case add(fun cell_hal:add_group/1, Groups) of
                ok ->
                    cell_log:notice(router, "HAL connected: ~ts",
                                    [lists:join(", ", [atom_to_list(Id) || #{id := Id} <- Conns])]),
                    {ok, Hal};
                {error, Why} ->
                    remove(Hal),
                    {stop, {hal, Why}}
            end;
        {error, Why} ->
            remove(Hal),
            {stop, {hal, Why}}
    end.

add(Fun, Specs) ->
    lists:foldl(fun(_, {error, _} = E) -> E;
                   (Spec, ok) ->
                        case Fun(Spec) of
                            ok -> ok;
                            {error, {already_exists, _}} -> ok;
                            {error, Why} -> {error, {maps:get(id, Spec), Why}}
                        end
                end, ok, Specs).

-spec handle_call(term(), gen_server:from(), hal()) -> no_return().
handle_call(Msg, _From, _Hal) ->
    erlang:error({unexpected_call, Msg}).

-spec handle_cast(term(), hal()) -> no_return().
handle_cast(Msg, _Hal) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), hal()) -> {noreply, hal()}.
handle_info({'EXIT', _, normal}, Hal) ->
    {noreply, Hal}.

-spec terminate(term(), hal()) -> ok.
terminate(_Reason, Hal) ->
    remove(Hal),
    cell_log:notice(router, "HAL disconnected", []).

remove(#{connections := Conns, groups := Groups}) ->
    _ = [cell_hal:remove_group(Id) || #{id := Id} <- Groups],
    _ = [cell_hal:remove_connection(Id) || #{id := Id} <- Conns],
    ok.
