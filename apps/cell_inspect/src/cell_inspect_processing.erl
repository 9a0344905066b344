%% @doc Image processing for an inspection point: the behaviour a processing module
%% implements, and the processing types by name.
%%
%% A point's settings name its `processing' and its `workspace' (what the processing
%% loads: a model, a set of tools, a reference image). `none' means the point has no
%% image processing (no workspace in the seed's words): its image is recorded and the
%% inspection passes. Built in: `none' and `sim' ({@link cell_inspect_sim_ipm}); a cell
%% adds its own under the `cell_inspect' variable `processing_types',
%% `#{<<"vision">> => my_vision}'.
%%
%% `load/1' may take long (the block reports WaitingForIPM meanwhile); it runs in a
%% process of its own. `process/3' runs in a process of its own for every image, so a
%% crash in it is a ProcessingError, never a crash of the block.
-module(cell_inspect_processing).

-export([module/1, kind/2]).

-export_type([image/0, loaded/0]).

-type image() :: #{data => binary(), format => binary(), ref => binary()}.
-type loaded() :: term().

%% Loads a workspace.
-callback load(Workspace :: binary()) -> {ok, loaded()} | {error, term()}.
%% Processes one image of an inspection of `#{point, serial}'.
-callback process(image(), #{point := binary(), serial := binary()}, loaded()) ->
    {pass | fail, binary()} | {error, term()}.

%% @doc The module of a processing type named in the settings (matched against the
%% known names, never made into an atom).
-spec module(binary()) -> {ok, module()} | error.
module(Name) ->
    Types = maps:merge(#{<<"sim">> => cell_inspect_sim_ipm},
                       maps:fold(fun(K, V, Acc) when is_atom(K) -> Acc#{atom_to_binary(K) => V};
                                    (K, V, Acc) when is_binary(K) -> Acc#{K => V};
                                    (_, _, Acc) -> Acc
                                 end, #{},
                                 application:get_env(cell_inspect, processing_types, #{}))),
    maps:find(Name, Types).

%% @doc What a point's settings mean for the block: `none', `{ipm, Module}' or
%% `{misconfigured, Why}' (an unknown processing type, or a type without a workspace).
-spec kind(binary(), binary()) -> none | {ipm, module()} | {misconfigured, iolist()}.
kind(<<"none">>, _) ->
    none;
kind(Name, Workspace) ->
    case module(Name) of
        {ok, _} when Workspace =:= <<>> ->
            {misconfigured, ["processing ", Name, " has no workspace"]};
        {ok, Mod} ->
            {ipm, Mod};
        error ->
            {misconfigured, ["there is no processing named \"", Name, "\""]}
    end.
