%% @doc The interpolation channel, a hardware object (seed 000 §2.3.7: TwinCAT NC's
%% multi-axis interpolation, the NcChannel): a group of two or three axes that follows
%% a path of lines and arcs ({@link cell_hal_path}: the router's cut lines in
%% `ExecOrder', {@link cell_recipe_path}) at a path velocity, with its progress along
%% the path reported.
%%
%% As an axis's moves, a path is asynchronous: {@link follow/3} is accepted or refused
%% at once (`{ok, Ref}' or `{error, Why}'), and its end comes to the caller as `{Ref,
%% done | aborted | {error, {Axis, Code}}}' — an error when one of the axes faulted
%% (the others are halted), aborted when an axis was commanded elsewhere or the channel
%% halted. {@link status/1} tells the progress: how far along the path, on which
%% segment of how many, and where.
%%
%% ```
%% {ok, Path} = cell_hal_path:new(Segments),
%% {ok, Ref} = cell_hal_channel:follow(router, Path, #{velocity => 200,
%%                                                   acceleration => 2000,
%%                                                   deceleration => 2000})
%% '''
%%
%% Implementations: `sim' ({@link cell_hal_channel_sim}, over the axes' simulated NC)
%% and `ads' (cell_hal_ads_channel in the cell_hal_ads application, a TwinCAT NC I
%% channel that runs the path in the NC).
-module(cell_hal_channel).

-export([follow/3, halt/2, set_override/2, status/1]).

-export_type([status/0]).

-type status() :: #{state := idle | following | halting,
                    along := float(),
                    length := float(),
                    segment := non_neg_integer(),
                    segments := non_neg_integer(),
                    connecting := boolean(),
                    position := {float(), float(), float()} | undefined}.

-callback check_opts(map()) -> {ok, map()} | {error, term()}.
-callback init(atom(), map()) -> {ok, State :: term()} | {ok, State :: term(), up | down}
                                     | {error, term()}.
-callback follow(pid(), cell_hal_path:path(), cell_hal_axis_fsm:params(), State :: term()) ->
    {reply, {ok, reference()} | {error, term()}, State :: term()}.
-callback halt(pid(), number(), State :: term()) ->
    {reply, {ok, reference()} | {error, term()}, State :: term()}.
-callback set_override(number(), State :: term()) -> {reply, ok | {error, term()}, State :: term()}.
-callback status(State :: term()) -> {reply, status(), State :: term()}.
-callback handle_call(term(), State :: term()) -> {reply, term(), State :: term()}.
%% `unchanged': nothing its status shows changed, so the object's watchers are not told
%% (see cell_hal_hw:watch/1).
-callback handle_info(term(), State :: term()) ->
    {noreply, State :: term()} | {noreply, State :: term(), unchanged}.

-define(TIMEOUT, 5000).

%% @doc Follows `Path' with the path velocity, acceleration and deceleration given:
%% every axis of the channel powered, homed and standing, and the path within their
%% software limits.
-spec follow(atom(), cell_hal_path:path(), cell_hal_axis_fsm:params()) ->
          {ok, reference()} | {error, term()}.
follow(Id, Path, Params) ->
    cell_hal_hw:call(Id, {channel, {follow, self(), Path, Params}}, ?TIMEOUT).

%% @doc Halts the channel's axes with `Deceleration' (the path followed is aborted).
-spec halt(atom(), number()) -> {ok, reference()} | {error, term()}.
halt(Id, Deceleration) ->
    cell_hal_hw:call(Id, {channel, {halt, self(), Deceleration}}, ?TIMEOUT).

%% @doc The speed override in percent (0–100) of the channel and its axes.
-spec set_override(atom(), number()) -> ok | {error, term()}.
set_override(Id, Pct) ->
    cell_hal_hw:call(Id, {channel, {override, Pct}}, ?TIMEOUT).

%% @doc The channel's progress along its path.
-spec status(atom()) -> {ok, status()} | {error, term()}.
status(Id) ->
    case cell_hal_hw:call(Id, {channel, status}, ?TIMEOUT) of
        #{} = Status -> {ok, Status};
        {error, _} = Error -> Error
    end.
