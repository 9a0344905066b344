%% @doc The inspection blocks' API: what each block shows, the traceability records of
%% a part, and the messages waiting for the operator panel.
%%
%% ```
%% [#{id := line1, status := complete, error := no_error, ...}] = cell_inspect:blocks(),
%% {ok, #{inspections := [#{point := <<"STATION1">>, result := pass, ...}],
%%        overrides := []}} = cell_inspect:traceability(<<"SN-4711">>).
%% '''
-module(cell_inspect).

-export([blocks/0, block/1, subscribe/0, traceability/1]).

%% @doc Every block as it shows now (from a table, no process hop).
-spec blocks() -> [map()].
blocks() ->
    cell_inspect_block:views().

%% @doc One block, by the binary of its id (from a URL: matched, never made an atom).
-spec block(binary() | atom()) -> {ok, map()} | {error, unknown_block}.
block(Id) when is_atom(Id) ->
    cell_inspect_block:view(Id);
block(Name) when is_binary(Name) ->
    case [V || #{id := Id} = V <- blocks(), atom_to_binary(Id) =:= Name] of
        [V] -> {ok, V};
        [] -> {error, unknown_block}
    end.

%% @doc The caller receives `{cell_inspect, view, View}' whenever a block's view changes.
-spec subscribe() -> ok.
subscribe() ->
    cell_inspect_block:subscribe().

%% @doc Every inspection and override recorded for a part serial, oldest first.
-spec traceability(binary()) -> {ok, #{inspections := [map()], overrides := [map()]}}
                                | {error, term()}.
traceability(Serial) when is_binary(Serial) ->
    cell_inspect_db:by_serial(Serial).
