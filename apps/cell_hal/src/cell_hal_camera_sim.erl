%% @doc A simulated camera: each grab takes the exposure time, then returns the scene a
%% simulation showed it, or a test pattern that changes with every grab.
%%
%% Options: `width' (default 320), `height' (240), `exposure_ms' (20). Simulation
%% controls: {@link show/2}, {@link fail_next/2}, {@link set_link/2}.
-module(cell_hal_camera_sim).
-behaviour(cell_hal_camera).

-export([show/2, fail_next/2, set_link/2]).
-export([check_opts/1, init/2, grab/2, handle_call/2, handle_info/2]).

-record(s, {width :: pos_integer(),
            height :: pos_integer(),
            exposure_ms :: non_neg_integer(),
            seq = 0 :: non_neg_integer(),
            scene :: binary() | undefined,
            fail :: term()}).

%% @doc What the camera sees from now on: `width * height' bytes (mono8), or
%% `pattern' for the changing test pattern.
-spec show(atom(), binary() | pattern) -> ok | {error, term()}.
show(Id, Scene) ->
    cell_hal_hw:call(Id, {impl, {show, Scene}}, 5000).

%% @doc The next grab fails with `Reason'.
-spec fail_next(atom(), term()) -> ok | {error, term()}.
fail_next(Id, Reason) ->
    cell_hal_hw:call(Id, {impl, {fail_next, Reason}}, 5000).

%% @doc Unplugs (`down') or plugs (`up') the simulated camera.
-spec set_link(atom(), up | down) -> ok | {error, term()}.
set_link(Id, Link) when Link =:= up; Link =:= down ->
    cell_hal_hw:call(Id, {impl, {link, Link}}, 5000).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    Pos = fun(V) -> is_integer(V) andalso V > 0 andalso V =< 8192 end,
    cell_hal_hw:check_opts(Opts, #{width => {320, Pos}, height => {240, Pos},
                                   exposure_ms => {20, fun(V) -> is_integer(V) andalso V >= 0 end}}).

%% @private
-spec init(atom(), map()) -> {ok, #s{}}.
init(_Id, #{width := W, height := H, exposure_ms := E}) ->
    {ok, #s{width = W, height = H, exposure_ms = E}}.

%% @private
-spec grab(map(), #s{}) -> {reply, {error, term()}, #s{}} | {noreply, #s{}}.
grab(_Opts, #s{fail = Why} = S) when Why =/= undefined ->
    {reply, {error, Why}, S#s{fail = undefined}};
grab(Opts, #s{exposure_ms = E} = S) ->
    _ = erlang:send_after(maps:get(exposure_ms, Opts, E), self(), {?MODULE, exposed}),
    {noreply, S}.

%% @private
-spec handle_call(term(), #s{}) -> {reply, term(), #s{}}.
handle_call({show, pattern}, S) ->
    {reply, ok, S#s{scene = undefined}};
handle_call({show, Scene}, #s{width = W, height = H} = S)
  when is_binary(Scene), byte_size(Scene) =:= W * H ->
    {reply, ok, S#s{scene = Scene}};
handle_call({show, _}, S) ->
    {reply, {error, bad_scene}, S};
handle_call({fail_next, Why}, S) ->
    {reply, ok, S#s{fail = Why}};
handle_call({link, Link}, S) ->
    ok = cell_hal_hw:set_status(Link),
    {reply, ok, S}.

%% @private
-spec handle_info(term(), #s{}) -> {reply, {ok, cell_hal_camera:image()}, #s{}}.
handle_info({?MODULE, exposed}, #s{width = W, height = H, seq = Seq} = S) ->
    Data = case S#s.scene of
               undefined -> pattern(W, H, Seq);
               Scene -> Scene
           end,
    {reply, {ok, #{width => W, height => H, format => mono8, data => Data, seq => Seq,
                   time => os:system_time(millisecond)}}, S#s{seq = Seq + 1}}.

%% Diagonal stripes that move one pixel a grab: consecutive images always differ.
pattern(W, H, Seq) ->
    << <<((X + Y + Seq) band 255)>> || Y <- lists:seq(0, H - 1), X <- lists:seq(0, W - 1) >>.
