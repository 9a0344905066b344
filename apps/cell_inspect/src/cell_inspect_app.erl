%% @doc The inspection app: the database first (mnesia in `Databases/', this app's
%% tables), then the HAL connections it is given, then the blocks. A temporary
%% application: if it gives up, the cell runs on and the PLCs see their heartbeat stop.
-module(cell_inspect_app).
-behaviour(application).

-export([start/2, stop/1]).

-spec start(application:start_type(), term()) -> {ok, pid()} | {error, term()}.
start(_Type, _Args) ->
    case cell_inspect_db:start() of
        ok ->
            case blocks() of
                {ok, Blocks} ->
                    ok = connections(),
                    cell_inspect_sup:start_link(Blocks);
                {error, Why} ->
                    cell_log:error(inspect, "the inspection blocks are not started: ~0tp",
                                   [Why]),
                    {error, Why}
            end;
        {error, Why} ->
            cell_log:error(inspect, "the inspection blocks are not started: ~ts",
                           [cell_db:format_error(Why)]),
            {error, {database, Why}}
    end.

-spec stop(term()) -> ok.
stop(_State) ->
    %% The blocks' IO groups leave the HAL with them.
    case blocks() of
        {ok, Blocks} -> _ = [cell_hal:remove_group(Id) || #{id := Id} <- Blocks], ok;
        {error, _} -> ok
    end.

blocks() ->
    Specs = application:get_env(cell_inspect, blocks, []),
    Checked = [cell_inspect_block:check_spec(S) || S <- Specs],
    case [E || {error, _} = E <- Checked] of
        [] ->
            Ids = [Id || {ok, #{id := Id}} <- Checked],
            case length(lists:usort(Ids)) =:= length(Ids) of
                true -> {ok, [S || {ok, S} <- Checked]};
                false -> {error, {duplicate_block_ids, Ids}}
            end;
        [E | _] -> E
    end.

%% HAL connections configured with the blocks, added when the cell has not added them.
connections() ->
    lists:foreach(
      fun(#{id := Id} = Spec) ->
              case lists:member(Id, cell_hal:connections()) of
                  true -> ok;
                  false ->
                      case cell_hal:add_connection(Spec) of
                          ok -> ok;
                          {error, Why} ->
                              cell_log:error(inspect, "connection ~s cannot be added: ~0tp",
                                             [Id, Why])
                      end
              end
      end, application:get_env(cell_inspect, connections, [])).
