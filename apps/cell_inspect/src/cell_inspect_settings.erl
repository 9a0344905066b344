%% @doc The settings object `inspect' (`Settings/inspect.json'): for each inspection
%% block declared in the cell's configuration, its heartbeat, its inspection points
%% (the InspectionPointID keys and their image processing), the messages the PLC may
%% send (MessageID keys), its camera clients, and whether the operator panel answers
%% its messages. Changes apply at once, between two commands of the PLC.
-module(cell_inspect_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).
-export([register/0, block/1]).

-spec name() -> inspect.
name() -> inspect.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => blocks, type => {list, {object, cell_inspect_block_settings}, 256},
       doc => <<"One entry per inspection block of the cell, by the block's id.">>}].

%% @doc Blocks appear once; a client belongs to one block only (seed 004).
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{blocks := Blocks}) ->
    Indexed = lists:zip(lists:seq(1, length(Blocks)), Blocks),
    case first_duplicate([{[blocks, I, id], Id} || {I, #{id := Id}} <- Indexed]) of
        {Path, Id} -> {error, Path, {duplicate, Id}};
        none ->
            Clients = [{[blocks, I, clients, J, id], C}
                       || {I, #{clients := Cs}} <- Indexed,
                          {J, #{id := C}} <- lists:zip(lists:seq(1, length(Cs)), Cs)],
            case first_duplicate(Clients) of
                {Path, C} -> {error, Path, {client_in_two_blocks, C}};
                none -> ok
            end
    end.

first_duplicate(Pairs) ->
    first_duplicate(Pairs, #{}).

first_duplicate([], _) -> none;
first_duplicate([{Path, K} | Rest], Seen) ->
    case Seen of
        #{K := _} -> {Path, K};
        _ -> first_duplicate(Rest, Seen#{K => true})
    end.

%% @doc Registers the object with `cell_settings'.
-spec register() -> ok | {error, term()}.
register() ->
    cell_settings:register(?MODULE).

%% @doc The settings of one block (its defaults when the object has no entry for it).
-spec block(atom()) -> map().
block(Id) ->
    Name = atom_to_binary(Id),
    case [B || #{id := I} = B <- cell_settings:get(inspect, blocks), I =:= Name] of
        [B | _] -> B;
        [] -> (default_block())#{id => Name}
    end.

default_block() ->
    maps:from_list([{N, D} || #{name := N, default := D}
                                  <- cell_settings_schema:fields(cell_inspect_block_settings)]).
