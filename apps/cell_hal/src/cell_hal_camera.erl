%% @doc Cameras (seed 000 §4.2, `ICamera'): the behaviour an implementation follows and
%% the API tasks use. An implementation is a callback module run by {@link cell_hal_hw}.
-module(cell_hal_camera).

-export([grab/2, grab/3]).

-export_type([image/0]).

%% A grabbed image: `data' holds `width * height' pixels row by row, one byte each for
%% `mono8', three (R, G, B) for `rgb8'. `seq' counts the camera's grabs, `time' is when
%% the exposure ended (system time, ms).
-type image() :: #{width := pos_integer(), height := pos_integer(),
                   format := mono8 | rgb8, data := binary(),
                   seq := non_neg_integer(), time := integer()}.

-callback check_opts(Opts :: map()) -> {ok, map()} | {error, {bad_option, atom()}}.
-callback init(Id :: atom(), Opts :: map()) -> {ok, State :: term()} | {error, term()}.
%% Takes one image: answers now, or `noreply' and later from handle_info/2.
-callback grab(GrabOpts :: map(), State :: term()) ->
    {reply, {ok, image()} | {error, term()}, State :: term()} | {noreply, State :: term()}.
%% Requests particular to the implementation (settings, simulation controls).
-callback handle_call(Request :: term(), State :: term()) -> {reply, term(), State :: term()}.
%% A message to the object's process; `reply' answers the operation in progress.
-callback handle_info(Msg :: term(), State :: term()) ->
    {noreply, State :: term()} | {reply, term(), State :: term()}.

%% @doc Grabs one image.
-spec grab(atom(), timeout()) -> {ok, image()} | {error, term()}.
grab(Id, Timeout) ->
    grab(Id, #{}, Timeout).

%% @doc Grabs one image with settings for this grab (`exposure_ms').
-spec grab(atom(), map(), timeout()) -> {ok, image()} | {error, term()}.
grab(Id, Opts, Timeout) when is_map(Opts) ->
    cell_hal_hw:call(Id, {camera, {grab, Opts}}, Timeout).
