%% @doc Images of inspections, kept as files under `Data/Images/<date>/' of the cell
%% root: `<block>-<inspection>.<format>'. The reference stored with the inspection is
%% the path below `Data/'. An image a camera keeps itself (a reference without data)
%% is referenced as the camera gave it.
-module(cell_inspect_images).

-export([save/3]).

%% @doc Saves an image durably (a power cut leaves it whole or absent); returns the
%% reference to record.
-spec save(atom(), binary(), cell_inspect_processing:image()) ->
          {ok, binary()} | {error, term()}.
save(Block, Name, #{data := Data} = Image) ->
    {{Y, M, D}, _} = calendar:universal_time(),
    Day = io_lib:format("~4..0b-~2..0b-~2..0b", [Y, M, D]),
    Rel = filename:join(["Images", Day, [atom_to_list(Block), $-, safe(Name), $.,
                                         extension(maps:get(format, Image, <<"bin">>))]]),
    Path = filename:join(cell_config:dir(data), Rel),
    case filelib:ensure_dir(Path) of
        ok ->
            case cell_file:write(Path, Data) of
                ok -> {ok, unicode:characters_to_binary(Rel)};
                {error, _} = E -> E
            end;
        {error, Why} ->
            {error, {Path, Why}}
    end;
save(_Block, _Name, #{ref := Ref}) ->
    {ok, Ref};
save(_Block, _Name, _) ->
    {ok, <<>>}.

%% File names from what a camera sent: letters, digits, - and _ only.
safe(Bin) ->
    [C || <<C>> <= Bin, (C >= $a andalso C =< $z) orelse (C >= $A andalso C =< $Z)
                           orelse (C >= $0 andalso C =< $9) orelse C =:= $- orelse C =:= $_].

extension(F) ->
    case safe(F) of
        [] -> "bin";
        E -> string:lowercase(E)
    end.
