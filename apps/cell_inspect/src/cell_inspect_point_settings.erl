%% @doc One inspection point of a block: its InspectionPointID and its processing.
-module(cell_inspect_point_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

-spec name() -> inspect_point.
name() -> inspect_point.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => id, type => {string, 16}, default => <<"POINT">>,
       doc => <<"The InspectionPointID the PLC writes (at most 16 characters).">>},
     #{name => caption, type => {string, 64}, default => <<>>,
       doc => <<"What the point inspects, for people.">>},
     #{name => processing, type => {string, 32}, default => <<"none">>,
       doc => <<"Image processing: none (the image is recorded and the inspection "
                "passes), sim (simulated), or a type the cell adds.">>},
     #{name => workspace, type => {string, 256}, default => <<>>,
       doc => <<"What the processing loads (its IPM workspace); required unless the "
                "processing is none.">>}].

%% @doc Point ids are printable, without spaces at either end.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{id := Id}) ->
    case Id =/= <<>> andalso string:trim(Id) =:= Id of
        true -> ok;
        false -> {error, [id], {not_an_id, Id}}
    end.
