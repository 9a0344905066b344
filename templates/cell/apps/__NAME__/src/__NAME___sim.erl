%% @doc The simulated line: the physics of {@link __NAME___line} behind the simulated
%% PLC ({@link cell_hal_sim}), so the device tasks run exactly as on the real machine,
%% knowing their IO only by name.
%%
%% It puts a rule on every output of the `line_io' group (the simulated PLC tells it
%% when the HAL wrote one), hands each change to the physics, and carries out what the
%% physics returns: it sets the inputs as the sensors would see the machine, and arms
%% a timer for each move. It never polls. The world (what the physics says is kept,
%% `__NAME___line:persisted/1') is saved in `Data/__NAME___sim.world' whenever a part
%% moves, so a node started again finds its parts where they were, as a real machine
%% would.
%%
%% It starts after the cell's monitor has connected the HAL; should the HAL go away
%% under it (the monitor restarted), a write fails, it crashes and, started again by
%% its supervisor, waits for the HAL to be back.
-module(__NAME___sim).
-behaviour(gen_server).

-export([start_link/0, world/0, ready/1]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2, terminate/2]).

-define(GROUP, line_io).
-define(WORLD_FILE, "__NAME___sim.world").
-define(ATTACH_MS, 100).

%%====================================================================
%% API
%%====================================================================

-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The world as it is now (see {@link __NAME___line}); `undefined' until the
%% simulation has attached to the HAL.
-spec world() -> __NAME___line:world() | undefined.
world() ->
    gen_server:call(?MODULE, world).

%% @doc Returns once the simulation runs and the HAL has read every input as the
%% simulation last set it: a Start from then on finds the machine as it is. (The
%% simulation watches each input for the value it set, again whenever it sets another.)
-spec ready(timeout()) -> ok | {error, timeout}.
ready(Timeout) ->
    try gen_server:call(?MODULE, ready, Timeout)
    catch exit:{timeout, _} -> {error, timeout}
    end.

%%====================================================================
%% gen_server
%%====================================================================

%% `waiting': the callers of ready/1; `unseen': the watch of each input the HAL has not
%% yet read as the simulation last set it (kept while someone waits).
-spec init([]) -> {ok, map()}.
init([]) ->
    self() ! attach,
    {ok, #{world => undefined, waiting => [], unseen => #{}}}.

-spec handle_call(world | ready, gen_server:from(), map()) ->
          {reply, term(), map()} | {noreply, map()}.
handle_call(world, _From, #{world := W} = S) ->
    {reply, W, S};
handle_call(ready, From, #{world := undefined, waiting := Waiting} = S) ->
    %% Answered once attached and seen.
    {noreply, S#{waiting := [From | Waiting]}};
handle_call(ready, From, #{world := W, waiting := Waiting} = S) ->
    {noreply, seen(watch_all(__NAME___line:inputs(W), S#{waiting := [From | Waiting]}))}.

%% A watch on each input for the value the simulation set.
watch_all(Inputs, #{unseen := Unseen} = S) ->
    S#{unseen := maps:fold(fun(P, V, Acc) ->
                                   _ = [cell_hal:cancel_watch(R) || {ok, R} <- [maps:find(P, Acc)]],
                                   {ok, Ref} = cell_hal:watch(?GROUP, P, {eq, V}),
                                   Acc#{P => Ref}
                           end, Unseen, Inputs)}.

%% Everyone waiting is answered once the HAL has seen every input.
seen(#{unseen := Unseen, waiting := Waiting} = S) when map_size(Unseen) =:= 0 ->
    _ = [gen_server:reply(From, ok) || From <- Waiting],
    S#{waiting := []};
seen(S) ->
    S.

-spec handle_cast(term(), map()) -> {noreply, map()}.
handle_cast(_Msg, S) ->
    {noreply, S}.

-spec handle_info(term(), map()) -> {noreply, map()}.
handle_info(attach, #{world := undefined} = S) ->
    {noreply, attach(S)};
handle_info({out, Point, Value}, #{world := W} = S) when W =/= undefined ->
    P = (params())#{roll => rand:uniform()},
    {noreply, apply_physics(__NAME___line:output(Point, Value, P, W), S)};
handle_info({event, Event}, #{world := W} = S) when W =/= undefined ->
    {noreply, apply_physics(__NAME___line:event(Event, params(), W), S)};
handle_info({cell_hal_watch, Ref, _}, #{unseen := Unseen} = S) ->
    {noreply, seen(S#{unseen := maps:filter(fun(_, R) -> R =/= Ref end, Unseen)})};
handle_info(_Msg, S) ->
    {noreply, S}.

-spec terminate(term(), map()) -> ok.
terminate(_Reason, #{world := undefined}) ->
    ok;
terminate(_Reason, #{world := W}) ->
    save(W).

%%====================================================================

%% The physics needs the simulated PLC's points, which the cell's monitor adds.
attach(S) ->
    case cell_hal:points(?GROUP) of
        {ok, Points} ->
            Self = self(),
            Outputs = [P || #{name := P, dir := out} <- Points],
            %% A rule on every output first, then the outputs read: a write the tasks
            %% make meanwhile is in the read, or in a message, or both; never neither.
            _ = [ok = cell_hal_sim:on_change({?GROUP, P}, fun(V) -> Self ! {out, P, V}, [] end)
                 || P <- Outputs],
            W0 = lists:foldl(fun(P, W) -> put_out(P, W) end, saved(), Outputs),
            S1 = apply_physics(__NAME___line:start(params(), W0), S),
            #{world := W1} = S1,
            cell_log:notice(__NAME__, "simulated line running: ~b part(s) in the machine",
                            [__NAME___line:parts(W1)]),
            case S1 of
                #{waiting := []} -> S1;
                #{} -> seen(watch_all(__NAME___line:inputs(W1), S1))
            end;
        {error, _} ->
            _ = erlang:send_after(?ATTACH_MS, self(), attach),
            S
    end.

put_out(P, #{outs := Outs} = W) ->
    case cell_hal_sim:get({?GROUP, P}) of
        {ok, V} -> W#{outs := Outs#{P => V}};
        {error, _} -> W
    end.

apply_physics({W, Effects}, #{world := Old} = S) ->
    Scale = maps:get(sim_time_scale, settings(), 1.0),
    Set = lists:foldl(fun({set, P, V}, Acc) ->
                              ok = cell_hal_sim:set({?GROUP, P}, V),
                              Acc#{P => V};
                         ({'after', Ms, Event}, Acc) ->
                              _ = erlang:send_after(round(Ms * Scale), self(), {event, Event}),
                              Acc
                      end, #{}, Effects),
    Moved = Old =:= undefined orelse __NAME___line:moved(Old, W),
    Moved andalso save(W),
    case S of
        #{waiting := []} -> S#{world := W};
        #{} -> watch_all(Set, S#{world := W})
    end.

params() ->
    __NAME___line:params(settings()).

%% The cell's settings as they are now (the operator may change them as it runs).
%% Before the controller owns them, as saved.
settings() ->
    try cell_settings:get(__NAME__)
    catch
        error:_ -> cell_spec_helpers:saved_settings(__NAME___settings);
        exit:_ -> cell_spec_helpers:saved_settings(__NAME___settings)
    end.

saved() ->
    case cell_file:read_term(path()) of
        {ok, #{infeed := _, press := _} = W} -> maps:merge(__NAME___line:new(), W);
        _ -> __NAME___line:new()
    end.

save(W) ->
    case cell_file:write_term(path(), __NAME___line:persisted(W)) of
        ok -> ok;
        {error, Reason} -> cell_log:warning(__NAME__, "simulated line: world not saved: ~p", [Reason])
    end.

path() ->
    filename:join(cell_config:dir(data), ?WORLD_FILE).
