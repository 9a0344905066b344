%% @doc The settings of one inspection block (an entry of {@link cell_inspect_settings}).
-module(cell_inspect_block_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

-spec name() -> inspect_block.
name() -> inspect_block.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => id, type => {string, 64}, default => <<"block">>,
       doc => <<"The block's id, as the cell's configuration declares it.">>},
     #{name => heartbeat_ms, type => {integer, 100, 60000}, default => 5000, unit => <<"ms">>,
       doc => <<"The Heartbeat bit toggles this often; the PLC should fault after two to "
                "four periods without a change.">>},
     #{name => processing_timeout_ms, type => {integer, 100, 600000}, default => 30000,
       unit => <<"ms">>,
       doc => <<"Longest image processing (and recording) of one inspection; longer is a "
                "ProcessingError.">>},
     #{name => panel_messages, type => boolean, default => true,
       doc => <<"The operator panel shows this block's messages and takes answers, as a "
                "client of the block, while a panel page is open.">>},
     #{name => points, type => {list, {object, cell_inspect_point_settings}, 256},
       default => [],
       doc => <<"The inspection points: the InspectionPointID keys the PLC may request.">>},
     #{name => messages, type => {list, {object, cell_inspect_message_settings}, 256},
       default => [],
       doc => <<"The messages the PLC may send, by MessageID.">>},
     #{name => clients, type => {list, {object, cell_inspect_client_settings}, 64},
       default => [],
       doc => <<"The camera clients of this block.">>}].

%% @doc Point ids and message ids are unique in a block.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{points := Points, messages := Messages}) ->
    case dup(points, [Id || #{id := Id} <- Points]) of
        ok -> dup(messages, [Id || #{id := Id} <- Messages]);
        E -> E
    end.

dup(Field, Ids) ->
    dup(Field, Ids, 1, #{}).

dup(_, [], _, _) -> ok;
dup(Field, [Id | Rest], I, Seen) ->
    case Seen of
        #{Id := _} -> {error, [Field, I, id], {duplicate, Id}};
        _ -> dup(Field, Rest, I + 1, Seen#{Id => true})
    end.
