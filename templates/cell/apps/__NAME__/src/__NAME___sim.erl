%% @doc The simulated line: the physics of {@link __NAME___line} behind the simulated
%% PLC ({@link cell_hal_sim}), so the device tasks run exactly as on the real machine,
%% knowing their IO only by name.
%%
%% It puts a rule on every output of the `line_io' group (the simulated PLC tells it
%% when the HAL wrote one), hands each change to the physics, and carries out what the
%% physics returns: it sets the inputs as the sensors would see the machine, and arms
%% a timer for each move. It never polls. The world is saved in
%% `Data/__NAME___sim.world' whenever a part moves, so a node started again finds its
%% parts where they were, as a real machine would.
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

%% @doc The world as it is now (see {@link __NAME___line}).
-spec world() -> __NAME___line:world().
world() ->
    gen_server:call(?MODULE, world).

%% @doc Returns once the simulation runs and the HAL has read every input as the
%% simulation set it: a Start from then on finds the machine as it is.
-spec ready(timeout()) -> ok | {error, timeout}.
ready(Timeout) ->
    Deadline = erlang:monotonic_time(millisecond) + Timeout,
    Inputs = gen_server:call(?MODULE, inputs, Timeout),
    Refs = [begin
                {ok, Ref} = cell_hal:watch(?GROUP, P, {eq, V}),
                Ref
            end || {P, V} <- maps:to_list(Inputs)],
    await_watches(Refs, Deadline).

await_watches([], _Deadline) ->
    ok;
await_watches([Ref | Rest], Deadline) ->
    receive
        {cell_hal_watch, Ref, _} -> await_watches(Rest, Deadline)
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        {error, timeout}
    end.

%%====================================================================
%% gen_server
%%====================================================================

-spec init([]) -> {ok, map()}.
init([]) ->
    self() ! attach,
    {ok, #{world => undefined, waiting => []}}.

-spec handle_call(world | inputs, gen_server:from(), map()) ->
          {reply, term(), map()} | {noreply, map()}.
handle_call(_Req, From, #{world := undefined, waiting := Waiting} = S) ->
    %% Answered once attached.
    {noreply, S#{waiting := [From | Waiting]}};
handle_call(Req, _From, #{world := W} = S) ->
    {reply, answer(Req, W), S}.

answer(world, W) -> W;
answer(inputs, W) -> __NAME___line:inputs(W).

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
handle_info(_Msg, S) ->
    {noreply, S}.

-spec terminate(term(), map()) -> ok.
terminate(_Reason, #{world := undefined}) ->
    ok;
terminate(_Reason, #{world := W}) ->
    save(W).

%%====================================================================

%% The physics needs the simulated PLC's points, which the cell's monitor adds.
attach(#{waiting := Waiting} = S) ->
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
            _ = [gen_server:reply(From, ok) || From <- Waiting],
            S1#{waiting := []};
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
    lists:foreach(fun({set, P, V}) ->
                          ok = cell_hal_sim:set({?GROUP, P}, V);
                     ({'after', Ms, Event}) ->
                          erlang:send_after(round(Ms * Scale), self(), {event, Event})
                  end, Effects),
    Moved = Old =:= undefined orelse
        maps:with([infeed, press, delivered], Old) =/= maps:with([infeed, press, delivered], W),
    Moved andalso save(W),
    S#{world := W}.

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
    case cell_file:write_term(path(), maps:with([infeed, press, ram, arrived, delivered], W)) of
        ok -> ok;
        {error, Reason} -> cell_log:warning(__NAME__, "simulated line: world not saved: ~p", [Reason])
    end.

path() ->
    filename:join(cell_config:dir(data), ?WORLD_FILE).
