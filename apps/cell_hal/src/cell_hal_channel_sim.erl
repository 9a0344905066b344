%% A simulated interpolation channel (type `sim' of kind `channel') over axis objects of
%% the HAL (`axes': two or three ids, the path's X, Y and Z in that order).
%%
%% A path is planned as one trapezoidal profile along its length (the path velocity,
%% acceleration and deceleration) and handed to every axis as a coupled motion
%% (cell_hal_axis's `follow'): each samples the same profile on its own time base and
%% takes its coordinate of the path's point there, so the axes stay on the path. The
%% channel keeps the same time base to tell the progress. Before it starts, each axis
%% must accept: powered, homed, standing or moving, and the path's range of its
%% coordinate within its software limits (found from the path's segment ends and a
%% thousand points along it). An axis that faults fails the path, and the channel halts
%% the others; an axis commanded elsewhere aborts it.
%%
%% `time_scale' is its axes' (see cell_hal_axis_sim), so that its progress keeps pace
%% with them.
%%
%% ```
%% #{id => router, kind => channel, type => sim, opts => #{axes => [x, y, z]}}
%% '''
-module(cell_hal_channel_sim).
-behaviour(cell_hal_channel).

-export([check_opts/1, init/2, follow/4, halt/3, set_override/2, status/1, handle_call/2,
         handle_info/2]).

%% The channel's own stop when it halts its axes after a fault or an abort.
-define(HALT_DECELERATION, 5000).
-define(RANGE_SAMPLES, 1000).

-record(job, {kind :: follow | halt,
              owner :: {pid(), reference()},
              %% The axes' job refs not yet done, by ref.
              left = #{} :: #{reference() => atom()}}).

-record(s, {id :: atom(),
            axes :: [atom()],
            job :: #job{} | undefined,
            path :: cell_hal_path:path() | undefined,
            profile :: cell_hal_axis_profile:profile() | undefined,
            tau0 = 0.0 :: float(),
            t0 = 0 :: integer(),
            rate = 1.0 :: float(),
            %% The machine's seconds in one real second (1 / time_scale).
            speed = 1.0 :: float(),
            %% Where it stopped (the end of the last path, or where it was halted).
            along = 0.0 :: float()}).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    cell_hal_hw:check_opts(Opts, #{axes => {undefined, fun axes/1},
                                   time_scale => {1.0, fun(V) -> is_number(V) andalso V > 0 end}}).

axes([_, _ | _] = Axes) when length(Axes) =< 3 ->
    lists:all(fun erlang:is_atom/1, Axes) andalso length(lists:usort(Axes)) =:= length(Axes);
axes(_) ->
    false.

%% @private
-spec init(atom(), map()) -> {ok, #s{}} | {error, {bad_option, axes}}.
init(_Id, #{axes := undefined}) ->
    {error, {bad_option, axes}};
init(Id, #{axes := Axes, time_scale := Scale}) ->
    {ok, #s{id = Id, axes = Axes, t0 = now_ms(), speed = 1 / Scale}}.

%% @private
-spec follow(pid(), cell_hal_path:path(), cell_hal_axis_fsm:params(), #s{}) ->
          {reply, {ok, reference()} | {error, term()}, #s{}}.
follow(_Owner, _Path, _Params, #s{job = #job{}} = S) ->
    {reply, {error, busy}, S};
follow(Owner, Path0, #{velocity := V, acceleration := A, deceleration := D} = Params, S)
  when is_number(V), V > 0, is_number(A), A > 0, is_number(D), D > 0 ->
    %% From where the axes stand: to the path's start first, if it is elsewhere.
    Path = case positions(S#s.axes) of
               {ok, Here} -> cell_hal_path:from(Path0, Here);
               error -> Path0
           end,
    Profile = cell_hal_axis_profile:move({0, 0}, cell_hal_path:length(Path), Params),
    Ranges = ranges(Path, length(S#s.axes)),
    Started = start_axes(lists:zip(S#s.axes, lists:seq(1, length(S#s.axes))), Path, Profile,
                         Ranges, []),
    case Started of
        {ok, Refs} ->
            Ref = make_ref(),
            {reply, {ok, Ref},
             S#s{job = #job{kind = follow, owner = {Owner, Ref}, left = maps:from_list(Refs)},
                 path = Path, profile = Profile, tau0 = 0.0, t0 = now_ms(), along = 0.0}};
        {error, Axis, Why, Refs} ->
            _ = [cell_hal_axis:halt(X, ?HALT_DECELERATION) || {_, X} <- Refs],
            {reply, {error, {Axis, Why}}, S}
    end;
follow(_Owner, _Path, Params, S) ->
    {reply, {error, {bad_params, Params}}, S}.

start_axes([], _Path, _Profile, _Ranges, Refs) ->
    {ok, Refs};
start_axes([{Axis, I} | Rest], Path, Profile, Ranges, Refs) ->
    Motion = #{path => Path, profile => Profile, axis => I, range => element(I, Ranges)},
    case cell_hal_axis:follow(Axis, Motion) of
        {ok, Ref} -> start_axes(Rest, Path, Profile, Ranges, [{Ref, Axis} | Refs]);
        {error, Why} -> {error, Axis, Why, Refs}
    end.

%% @private
-spec halt(pid(), number(), #s{}) -> {reply, {ok, reference()} | {error, term()}, #s{}}.
halt(Owner, Dec, #s{axes = Axes} = S) when is_number(Dec), Dec > 0 ->
    S1 = end_job(aborted, S),
    Refs = [{Ref, X} || X <- Axes, {ok, Ref} <- [cell_hal_axis:halt(X, Dec)]],
    Ref = make_ref(),
    case Refs of
        [] -> Owner ! {Ref, done}, {reply, {ok, Ref}, S1};
        _ -> {reply, {ok, Ref}, S1#s{job = #job{kind = halt, owner = {Owner, Ref},
                                                left = maps:from_list(Refs)}}}
    end;
halt(_Owner, Dec, S) ->
    {reply, {error, {bad_deceleration, Dec}}, S}.

%% @private
-spec set_override(number(), #s{}) -> {reply, ok | {error, term()}, #s{}}.
set_override(Pct, #s{axes = Axes} = S) when is_number(Pct), Pct >= 0, Pct =< 100 ->
    _ = [cell_hal_axis:set_override(X, Pct) || X <- Axes],
    Now = now_ms(),
    {reply, ok, S#s{tau0 = tau(Now, S), t0 = Now, rate = Pct / 100}};
set_override(Pct, S) ->
    {reply, {error, {bad_override, Pct}}, S}.

%% @private
-spec status(#s{}) -> {reply, cell_hal_channel:status(), #s{}}.
status(#s{path = undefined} = S) ->
    {reply, #{state => idle, along => 0.0, length => 0.0, segment => 0, segments => 0,
              connecting => false, position => undefined}, S};
status(#s{path = Path, job = Job} = S) ->
    Along = along(S),
    {I, N, Role} = cell_hal_path:segment_at(Path, Along),
    State = case Job of
                #job{kind = follow} -> following;
                #job{kind = halt} -> halting;
                undefined -> idle
            end,
    {reply, #{state => State, along => Along, length => cell_hal_path:length(Path),
              segment => I, segments => N, connecting => Role =:= connecting,
              position => cell_hal_path:at(Path, Along)}, S}.

%% @private
-spec handle_call(term(), #s{}) -> no_return().
handle_call(Request, _S) ->
    erlang:error({unexpected_call, Request}).

%% @private
-spec handle_info(term(), #s{}) -> {noreply, #s{}}.
handle_info({Ref, Result}, #s{job = #job{left = Left} = Job} = S) when is_map_key(Ref, Left) ->
    Axis = maps:get(Ref, Left),
    case Result of
        done ->
            case maps:remove(Ref, Left) of
                Empty when map_size(Empty) =:= 0 -> {noreply, end_job(done, S)};
                Rest -> {noreply, S#s{job = Job#job{left = Rest}}}
            end;
        {error, Code} ->
            {noreply, halt_others(maps:remove(Ref, Left), end_job({error, {Axis, Code}}, S))};
        aborted ->
            {noreply, halt_others(maps:remove(Ref, Left), end_job(aborted, S))}
    end;
handle_info({Ref, _}, S) when is_reference(Ref) ->
    %% An axis's word on a job the channel already ended.
    {noreply, S}.

%%--------------------------------------------------------------------

%% The job ends: its owner told, the progress kept where it is.
end_job(_Result, #s{job = undefined} = S) ->
    S;
end_job(Result, #s{job = #job{kind = Kind, owner = {Pid, Ref}}, path = Path} = S) ->
    Pid ! {Ref, Result},
    %% A path done is at its end (the axes' clocks ran a moment ahead of this one).
    Along = case {Kind, Result} of
                {follow, done} -> cell_hal_path:length(Path);
                _ -> along(S)
            end,
    S#s{job = undefined, along = Along, profile = undefined}.

halt_others(Left, S) ->
    _ = [cell_hal_axis:halt(X, ?HALT_DECELERATION) || X <- maps:values(Left)],
    S.

along(#s{profile = undefined, along = A}) ->
    A;
along(#s{profile = Profile} = S) ->
    element(1, cell_hal_axis_profile:at(Profile, tau(now_ms(), S))).

%% Where the axes stand, as a point (Z 0 for a channel of two).
positions(Axes) ->
    case [P || X <- Axes, {ok, #{position := P}} <- [cell_hal_axis:status(X)]] of
        Ps when length(Ps) =:= length(Axes) ->
            {ok, list_to_tuple(Ps ++ lists:duplicate(3 - length(Ps), 0.0))};
        _ ->
            error
    end.

%% Each coordinate's range over the path: at every segment's ends and a thousand
%% points between.
ranges(Path, N) ->
    L = cell_hal_path:length(Path),
    {Ends, _} = lists:mapfoldl(fun({_, _, Len}, S) -> {S + Len, S + Len} end, 0.0,
                               cell_hal_path:segments(Path)),
    Points = [cell_hal_path:at(Path, At)
              || At <- [0.0 | Ends] ++ [L * K / ?RANGE_SAMPLES || K <- lists:seq(0, ?RANGE_SAMPLES)]],
    list_to_tuple([begin
                       Xs = [element(I, P) || P <- Points],
                       {lists:min(Xs), lists:max(Xs)}
                   end || I <- lists:seq(1, N)]).

tau(Now, #s{tau0 = Tau0, t0 = T0, rate = Rate, speed = Speed}) ->
    Tau0 + Rate * Speed * (Now - T0) / 1000.

now_ms() ->
    erlang:monotonic_time(millisecond).
