%% @doc Simulated image processing: reads the verdict a simulated camera
%% ({@link cell_inspect_camera_sim}) wrote into its image, as a vision tool would read
%% the part. The image is a PGM whose comment line says `cellrt-sim PASS <text>' or
%% `cellrt-sim FAIL <text>'; anything else cannot be read (a ProcessingError).
%%
%% Workspaces: any name loads at once; `fail' cannot be loaded (to show
%% InspectionConfigurationError).
-module(cell_inspect_sim_ipm).
-behaviour(cell_inspect_processing).

-export([load/1, process/3, image/3]).

%% @doc Loads a workspace.
-spec load(binary()) -> {ok, binary()} | {error, term()}.
load(<<"fail">>) ->
    {error, workspace_damaged};
load(W) ->
    {ok, W}.

%% @doc Reads the verdict from the image.
-spec process(cell_inspect_processing:image(), map(), binary()) ->
          {pass | fail, binary()} | {error, term()}.
process(#{data := Data}, _Job, _Ws) ->
    case binary:split(Data, <<"\n">>, [global]) of
        [<<"P5">>, <<"# cellrt-sim ", Verdict/binary>> | _] ->
            case binary:split(Verdict, <<" ">>) of
                [<<"PASS">> | Text] -> {pass, text(Text)};
                [<<"FAIL">> | Text] -> {fail, text(Text)};
                _ -> {error, unreadable}
            end;
        _ ->
            {error, unreadable}
    end;
process(_, _, _) ->
    {error, no_image_data}.

text([]) -> <<>>;
text([T]) -> T.

%% @doc A small grey PGM image carrying a scene: `<<"PASS">>', `<<"FAIL OCR 12">>' or
%% anything (unreadable for the processing).
-spec image(binary(), pos_integer(), pos_integer()) -> binary().
image(Scene, W, H) ->
    Pixels = << <<((X * 7 + Y * 13) band 255)>> || Y <- lists:seq(1, H), X <- lists:seq(1, W) >>,
    iolist_to_binary(["P5\n# cellrt-sim ", Scene, "\n", integer_to_list(W), " ",
                      integer_to_list(H), "\n255\n", Pixels]).
