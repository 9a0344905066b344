%% @doc Laser markers (seed 000 §4.2, `ILaserMarker'): they mark a serial number or a
%% code on a product. The behaviour an implementation follows and the API tasks use;
%% an implementation is a callback module run by {@link cell_hal_hw}.
-module(cell_hal_laser_marker).

-export([mark/3]).

-export_type([job/0]).

%% What to mark: the text, and optionally the marker's stored layout to mark it with.
-type job() :: #{text := binary(), layout => binary()}.

-callback check_opts(Opts :: map()) -> {ok, map()} | {error, {bad_option, atom()}}.
-callback init(Id :: atom(), Opts :: map()) -> {ok, State :: term()} | {error, term()}.
%% Marks one job: `ok' when the marker finished; answers now, or `noreply' and later
%% from handle_info/2.
-callback mark(job(), State :: term()) ->
    {reply, ok | {error, term()}, State :: term()} | {noreply, State :: term()}.
%% Requests particular to the implementation (settings, simulation controls).
-callback handle_call(Request :: term(), State :: term()) -> {reply, term(), State :: term()}.
%% A message to the object's process; `reply' answers the operation in progress.
-callback handle_info(Msg :: term(), State :: term()) ->
    {noreply, State :: term()} | {reply, term(), State :: term()}.

%% @doc Marks a job and returns when the marker finished.
-spec mark(atom(), job(), timeout()) -> ok | {error, term()}.
mark(Id, #{text := Text} = Job, Timeout) when is_binary(Text), byte_size(Text) > 0 ->
    case maps:keys(maps:without([text, layout], Job)) of
        [] -> cell_hal_hw:call(Id, {laser_marker, {mark, Job}}, Timeout);
        [Key | _] -> {error, {bad_job, Key}}
    end;
mark(_Id, _Job, _Timeout) ->
    {error, {bad_job, text}}.
