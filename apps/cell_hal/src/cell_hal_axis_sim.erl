%% A simulated NC axis (type `sim' of kind `axis'): PLCopen's states
%% (cell_hal_axis_fsm) and trapezoidal profiles (cell_hal_axis_profile) in real time.
%%
%% Nothing ticks: the axis's position and velocity are its profile sampled at the
%% profile's own time, which runs at the speed override times real time, so a status
%% read computes them for the moment it is asked, and one timer marks the end of the
%% job that runs (none at override 0, where the axis holds its place). A change of
%% override moves the time base, not the profile.
%%
%% A coupled motion (`{follow, Motion}', an interpolation channel's path,
%% cell_hal_channel_sim) is sampled the same way: the path's own profile along its
%% length, at the profile's time, and this axis's coordinate of the path's point there.
%%
%% With `time_scale' below 1 the simulated machine runs faster than real time (a test's
%% physics): every profile's time and the homing time are scaled by it, while positions,
%% velocities and the override read as the machine's own.
%%
%% Homing takes `home_ms' and sets the position to the homing position. A fault (a
%% following error, code 16#4550 as TwinCAT NC reports it) can be injected: at
%% `fault_rate' (the chance a move faults, midway), on the next move (`fault_next/1'),
%% or at once (`fault/2'); the axis then stops with `quick_deceleration' in ErrorStop
%% until reset.
%%
%% With `publish' the axis writes its actual position (and velocity) into the PLC's
%% image, as an NC does into the PLC's axis structure every cycle: every `period_ms'
%% while it moves, and once where it comes to rest. Into inputs of a simulated PLC, set
%% as a sensor would: the HAL then reads them as any input, so the panel's IO page, the
%% SHDR adapter's configured points and the latch's samples see the axis move. Into
%% outputs of any PLC, written through the HAL like any output: a PLC whose NC is not
%% its own (the simulated axes of a machine whose PLC has none) learns so where its
%% axes are, in the order of the cell's other writes: a job's end is told after the
%% position it ended at was written; and again each time the PLC's connection comes up
%% (a PLC restarted holds its outputs at zero). (A real axis's position is the PLC's own point;
%% nothing is published.)
%%
%% ```
%% #{id => x, kind => axis, type => sim,
%%   opts => #{limits => {0.0, 1200.0}, home_ms => 100, fault_rate => 0.0,
%%             publish => #{group => axes_io, position => x_pos, velocity => x_vel}}}
%% '''
-module(cell_hal_axis_sim).
-behaviour(cell_hal_axis).

-export([check_opts/1, init/2, command/3, set_override/2, status/1, handle_call/2,
         handle_info/2]).
-export([fault_next/1, fault/2]).

-define(FOLLOWING_ERROR, 16#4550).

%% What the axis runs: its own profile, or its coordinate (1, 2 or 3) of a point moving
%% along a path with the path's profile.
-type motion() :: cell_hal_axis_profile:profile()
                | {coupled, cell_hal_axis_profile:profile(), cell_hal_path:path(), 1..3}.

-record(s, {id :: atom(),
            fsm :: cell_hal_axis_fsm:axis(),
            %% At rest: the position. Moving: the profile, sampled at its time.
            position = 0.0 :: float(),
            profile :: motion() | undefined,
            %% The profile's time Tau0 at monotonic time T0 (ms), running at Rate.
            tau0 = 0.0 :: float(),
            t0 = 0 :: integer(),
            rate = 1.0 :: float(),
            timer :: reference() | undefined,
            fault_timer :: reference() | undefined,
            fault_next = false :: boolean(),
            publish_timer :: reference() | undefined,
            %% The last failure to publish, logged once.
            publish_error :: term(),
            %% The connection of the outputs it publishes into, once subscribed to.
            publish_conn :: atom() | undefined,
            %% Who is told of each job's end: {Pid, Ref} by job id.
            owners = #{} :: #{pos_integer() => {pid(), reference()}},
            opts :: map()}).

%% @doc The axis's next move faults (a following error) halfway.
-spec fault_next(atom()) -> ok | {error, term()}.
fault_next(Id) ->
    cell_hal_hw:call(Id, {impl, fault_next}, 5000).

%% @doc The axis faults now with `Code' (its drive or its NC).
-spec fault(atom(), pos_integer()) -> ok | {error, term()}.
fault(Id, Code) ->
    cell_hal_hw:call(Id, {impl, {fault, Code}}, 5000).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    cell_hal_hw:check_opts(Opts, #{limits => {none, fun limits/1},
                                   home_ms => {100, fun(V) -> is_integer(V) andalso V >= 0 end},
                                   fault_rate => {0.0, fun(V) -> is_number(V) andalso V >= 0
                                                                     andalso V =< 1 end},
                                   quick_deceleration => {10000, fun positive/1},
                                   position => {0.0, fun erlang:is_number/1},
                                   time_scale => {1.0, fun positive/1},
                                   publish => {none, fun publish/1},
                                   rotary => {false, fun erlang:is_boolean/1}}).

publish(none) ->
    true;
publish(#{group := G, position := P} = M) when is_atom(G), is_atom(P) ->
    lists:all(fun({group, _}) -> true;
                 ({position, _}) -> true;
                 ({velocity, V}) -> is_atom(V);
                 ({period_ms, Ms}) -> is_integer(Ms) andalso Ms > 0;
                 (_) -> false
              end, maps:to_list(M));
publish(_) ->
    false.

limits(none) -> true;
limits({Min, Max}) -> is_number(Min) andalso is_number(Max) andalso Min < Max;
limits(_) -> false.

positive(V) -> is_number(V) andalso V > 0.

%% @private
-spec init(atom(), map()) -> {ok, #s{}}.
init(Id, #{limits := Limits, position := P} = Opts) ->
    S = #s{id = Id, fsm = cell_hal_axis_fsm:new(#{limits => Limits}), position = float(P),
           t0 = now_ms(), opts = Opts},
    {ok, publish_now(S)}.

%% @private
-spec command(pid(), cell_hal_axis_fsm:command(), #s{}) ->
          {reply, {ok, reference()} | {error, term()}, #s{}}.
command(Owner, Command, #s{fsm = Fsm} = S) ->
    {X, _V} = actual(S),
    case cell_hal_axis_fsm:command(Command, X, Fsm) of
        {ok, Fsm1, Effects} ->
            Ref = make_ref(),
            S1 = case [J || {run, #{id := J}} <- Effects] of
                     [JobId] -> S#s{owners = (S#s.owners)#{JobId => {Owner, Ref}}};
                     [] -> Owner ! {Ref, done}, S
                 end,
            {reply, {ok, Ref}, effects(Effects, S1#s{fsm = Fsm1})};
        {error, _} = Error ->
            {reply, Error, S}
    end.

%% @private
-spec set_override(number(), #s{}) -> {reply, ok | {error, term()}, #s{}}.
set_override(Pct, #s{fsm = Fsm} = S) ->
    case cell_hal_axis_fsm:set_override(Pct, Fsm) of
        {ok, Fsm1, Effects} -> {reply, ok, effects(Effects, S#s{fsm = Fsm1})};
        {error, _} = Error -> {reply, Error, S}
    end.

%% @private
-spec status(#s{}) -> {reply, cell_hal_axis:status(), #s{}}.
status(#s{fsm = Fsm, rate = Rate} = S) ->
    {X, V} = actual(S),
    {reply, #{state => cell_hal_axis_fsm:state(Fsm), position => X, velocity => V * Rate,
              error => cell_hal_axis_fsm:error_code(Fsm),
              homed => cell_hal_axis_fsm:homed(Fsm),
              powered => cell_hal_axis_fsm:powered(Fsm),
              override => cell_hal_axis_fsm:override(Fsm)}, S}.

%% @private
-spec handle_call(term(), #s{}) -> {reply, ok, #s{}}.
handle_call(fault_next, S) ->
    {reply, ok, S#s{fault_next = true}};
handle_call({fault, Code}, S) when is_integer(Code), Code > 0 ->
    {reply, ok, event({fault, Code}, S)}.

%% @private
-spec handle_info(term(), #s{}) -> {noreply, #s{}}.
handle_info({timeout, Ref, {job_end, Id}}, #s{timer = Ref} = S) ->
    {noreply, event({done, Id}, S#s{timer = undefined})};
handle_info({timeout, Ref, publish}, #s{publish_timer = Ref} = S) ->
    {noreply, published(S#s{publish_timer = undefined})};
handle_info({timeout, Ref, fault}, #s{fault_timer = Ref} = S) ->
    {noreply, event({fault, ?FOLLOWING_ERROR}, S#s{fault_timer = undefined})};
handle_info({cell_hal_conn, _Conn, up}, S) ->
    %% A PLC connected again may hold other values (restarted, its outputs at zero):
    %% told where the axis stands, as an NC's cyclic write would tell it.
    {noreply, publish_now(S#s{publish_error = undefined})};
handle_info({cell_hal_conn, _Conn, down}, S) ->
    {noreply, S};
handle_info({timeout, _Stale, _}, S) ->
    %% A timer cancelled after it fired.
    {noreply, S}.

%%--------------------------------------------------------------------

event(Event, #s{fsm = Fsm} = S) ->
    {Fsm1, Effects} = cell_hal_axis_fsm:event(Event, Fsm),
    effects(Effects, S#s{fsm = Fsm1}).

effects(Effects, S) ->
    lists:foldl(fun effect/2, S, Effects).

effect({run, #{kind := home} = Job}, S) ->
    %% Homing: the reference found after home_ms; the axis (in standstill, as homing
    %% starts) stands meanwhile: a stop from rest, which is no motion at all.
    run(Job, cell_hal_axis_profile:stop(actual(S), 1), home_ms(S), S);
effect({run, #{kind := move, target := To, params := Params} = Job}, S) ->
    Profile = cell_hal_axis_profile:move(actual(S), To, Params),
    faulting(Profile, run(Job, Profile, undefined, S));
effect({run, #{kind := follow, motion := #{path := Path, profile := Profile, axis := I}} = Job},
       S) ->
    Coupled = {coupled, Profile, Path, I},
    faulting(Coupled, run(Job, Coupled, undefined, S));
effect({run, #{deceleration := Dec} = Job}, S) ->
    %% Halt and stop.
    run(Job, cell_hal_axis_profile:stop(actual(S), Dec), undefined, S);
effect({done, #{id := Id, kind := home, target := At}}, S) ->
    tell(Id, done, publish_now((stand(S))#s{position = float(At)}));
effect({done, #{id := Id}}, S) ->
    %% The job's motion ended: the axis stands at its end.
    tell(Id, done, stand(S));
effect({aborted, #{id := Id}}, S) ->
    tell(Id, aborted, S);
effect({failed, #{id := Id}, Code}, S) ->
    tell(Id, {error, Code}, S);
effect(power_on, S) ->
    S;
effect(power_off, S) ->
    %% The drive lets go: the simulated axis stays where it is.
    stand(S);
effect(quick_stop, #s{opts = #{quick_deceleration := Dec}} = S) ->
    S1 = cancel(S),
    published(S1#s{profile = cell_hal_axis_profile:stop(actual(S), Dec), tau0 = 0.0,
                   t0 = now_ms()});
effect({override, Pct}, S) ->
    rebase(Pct / 100, S).

%% A job runs: its profile from now, a timer at its end (`Ms' real ms for homing).
run(#{id := Id}, Profile, Ms, S) ->
    S1 = (cancel(S))#s{profile = Profile, tau0 = 0.0, t0 = now_ms()},
    published(arm(Id, Ms, S1)).

arm(Id, undefined, #s{profile = Profile, tau0 = Tau0, rate = Rate} = S) when Rate > 0 ->
    Left = (duration(Profile) - Tau0) / (Rate * speed(S)),
    S#s{timer = erlang:start_timer(ceil(max(Left, 0.0) * 1000), self(), {job_end, Id})};
arm(_Id, undefined, S) ->
    %% Override 0: the axis holds; the job ends once the override is raised.
    S;
arm(Id, Ms, S) ->
    S#s{timer = erlang:start_timer(Ms, self(), {job_end, Id})}.

%% The override changed: the profile's time base moves on from now at the new rate,
%% and the end of the job that runs is timed again.
rebase(Rate, #s{fsm = Fsm} = S) ->
    Now = now_ms(),
    S1 = S#s{tau0 = tau(Now, S), t0 = Now, rate = Rate},
    case {cell_hal_axis_fsm:job(Fsm), S1#s.timer} of
        {#{kind := home}, _} ->
            S1;
        {#{id := Id}, Timer} ->
            _ = [erlang:cancel_timer(Timer) || Timer =/= undefined],
            arm(Id, undefined, S1#s{timer = undefined});
        {undefined, _} ->
            S1
    end.

%% A move that faults: at fault_rate, or the one after fault_next/1, halfway.
faulting(Profile, #s{fault_next = Next, opts = #{fault_rate := Rate}} = S) ->
    case Next orelse rand:uniform() < Rate of
        true ->
            Half = duration(Profile) / 2,
            S#s{fault_next = false,
                fault_timer = erlang:start_timer(
                                ceil(Half * 1000 / (max(S#s.rate, 0.01) * speed(S))),
                                self(), fault)};
        false ->
            S
    end.

tell(Id, What, #s{owners = Owners} = S) ->
    case maps:take(Id, Owners) of
        {{Pid, Ref}, Rest} -> Pid ! {Ref, What}, S#s{owners = Rest};
        error -> S
    end.

%% The axis stands where it is now.
stand(S) ->
    {X, _} = actual(S),
    publish_now((cancel(S))#s{position = X, profile = undefined, tau0 = 0.0}).

%% The position written now and, while the axis moves, again each period.
published(#s{opts = #{publish := none}} = S) ->
    S;
published(#s{profile = undefined} = S) ->
    publish_now(S);
published(#s{profile = Profile, timer = undefined, fsm = Fsm} = S) when Profile =/= undefined ->
    %% No job's end to wait for (the stop after a fault): at rest once its profile ran
    %% out.
    case cell_hal_axis_fsm:job(Fsm) =:= undefined andalso tau(now_ms(), S) >= duration(Profile) of
        true -> {X, _} = actual(S), publish_now(S#s{position = X, profile = undefined});
        false -> tick(S)
    end;
published(S) ->
    tick(S).

tick(#s{opts = #{publish := Pub}, publish_timer = undefined} = S) ->
    S1 = publish_now(S),
    S1#s{publish_timer = erlang:start_timer(maps:get(period_ms, Pub, 20), self(), publish)};
tick(S) ->
    publish_now(S).

publish_now(#s{opts = #{publish := none}} = S) ->
    S;
publish_now(#s{id = Id, opts = #{publish := #{group := G} = Pub}, rate = Rate} = S) ->
    {X, V} = actual(S),
    Writes = [{maps:get(position, Pub), X}]
        ++ [{P, V * Rate} || P <- [maps:get(velocity, Pub, none)], P =/= none],
    case [R || {P, Value} <- Writes, R <- [put_point(G, P, Value)], R =/= ok] of
        [] ->
            subscribed(G, S#s{publish_error = undefined});
        [Error | _] when Error =:= S#s.publish_error ->
            S;
        [Error | _] ->
            %% The group not added yet, or not on a simulated PLC: said once.
            cell_log:warning(Id, "axis ~s cannot publish its position to ~s: ~tp",
                             [Id, G, Error]),
            S#s{publish_error = Error}
    end.

%% Publishing into outputs, the axis hears when their connection comes up again, to
%% write them anew.
subscribed(_G, #s{publish_conn = C} = S) when C =/= undefined ->
    S;
subscribed(G, #s{opts = #{publish := #{position := P}}} = S) ->
    case cell_hal:describe(G, P) of
        {ok, #{dir := out, connection := C}} ->
            case cell_hal:subscribe_connection(C) of
                {ok, _} -> S#s{publish_conn = C};
                {error, _} -> S
            end;
        _ ->
            S
    end.

%% An input is set in the simulated PLC's image, an output written through the HAL.
put_point(G, P, Value) ->
    case cell_hal:describe(G, P) of
        {ok, #{dir := out}} -> cell_hal:write(G, P, Value);
        _ -> cell_hal_sim:set({G, P}, Value)
    end.

cancel(#s{timer = T, fault_timer = F, publish_timer = P} = S) ->
    _ = [erlang:cancel_timer(R) || R <- [T, F, P], R =/= undefined],
    S#s{timer = undefined, fault_timer = undefined, publish_timer = undefined}.

actual(#s{profile = undefined, position = X}) ->
    {X, 0.0};
actual(#s{profile = Profile} = S) ->
    sample(Profile, tau(now_ms(), S)).

sample({coupled, Profile, Path, I}, Tau) ->
    {Along, Speed} = cell_hal_axis_profile:at(Profile, Tau),
    X = element(I, cell_hal_path:at(Path, Along)),
    %% The velocity: the path's direction here times its speed along it.
    Ds = 1.0e-3,
    Ahead = element(I, cell_hal_path:at(Path, Along + Ds)),
    {X, case Speed == 0.0 of
            true -> 0.0;
            false -> (Ahead - X) / Ds * Speed
        end};
sample(Profile, Tau) ->
    cell_hal_axis_profile:at(Profile, Tau).

duration({coupled, Profile, _, _}) -> cell_hal_axis_profile:duration(Profile);
duration(Profile) -> cell_hal_axis_profile:duration(Profile).

tau(Now, #s{tau0 = Tau0, t0 = T0, rate = Rate} = S) ->
    Tau0 + Rate * speed(S) * (Now - T0) / 1000.

%% How many of the machine's seconds pass in one real second.
speed(#s{opts = #{time_scale := Scale}}) ->
    1 / Scale.

home_ms(#s{opts = #{home_ms := Ms, time_scale := Scale}}) ->
    round(Ms * Scale).

now_ms() ->
    erlang:monotonic_time(millisecond).
