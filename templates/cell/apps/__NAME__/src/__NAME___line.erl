%% @doc The physics of the simulated line, as pure functions: what the machine does
%% when the PLC's outputs change and when a move it started ends. {@link __NAME___sim}
%% runs them against the simulated PLC; the property in `__NAME___line_tests' checks
%% them (no part made or lost, the sensors always telling the truth).
%%
%% The world: a part at the infeed stopper or none, a part in the press or none, the
%% ram's position, the count of parts that arrived and of parts delivered to the next
%% machine, and the moves under way. Each function returns the new world and the
%% effects for the simulation to carry out: `{set, Input, Value}' (a sensor changes)
%% and `{'after', Ms, Event}' (an event of this module, `Ms' milliseconds later). The
%% sensors that go off are set before those that come on, so a part moving on is never
%% seen at two stations at once.
%%
%% <ul>
%% <li>A part arrives at the infeed `arrival_ms' after the infeed emptied.</li>
%% <li>A part moves from the infeed into the press while both belts run, in
%%     `transfer_ms'; a belt that stops stops the move (the part stays at the infeed).</li>
%% <li>The press belt running with a part in the press carries it out, in
%%     `eject_ms'.</li>
%% <li>The ram comes down at `ram_speed' (mm/s) over its clearance and the stroke
%%     depth the PLC holds (tenths of a mm); at the bottom the force sensor reads
%%     40 kN per mm of depth, a part being there. A ram that sticks (the caller's
%%     roll below `stick_rate') never reaches the bottom until it is raised again.</li>
%% </ul>
-module(__NAME___line).

-export([new/0, start/2, output/4, event/3, inputs/1, parts/1, params/1, persisted/1,
         moved/2]).

-export_type([world/0, effect/0, event/0]).

-type kind() :: arrival | transfer | eject | ram.
-type event() :: {kind(), pos_integer()}.
-type effect() :: {set, atom(), boolean() | integer()} | {'after', non_neg_integer(), event()}.
-type world() :: #{infeed := boolean(), press := boolean(),
                   ram := up | lowering | down | raising | stuck,
                   arrived := non_neg_integer(), delivered := non_neg_integer(),
                   outs := #{atom() => boolean() | integer()},
                   pending := #{kind() => {pos_integer(), non_neg_integer()}},
                   gen := non_neg_integer()}.
%% `pending': the moves under way, each with its generation (an event of an older one
%% is ignored) and its duration.

-define(KN_PER_MM, 40).

%% @doc An empty line, the ram up.
-spec new() -> world().
new() ->
    #{infeed => false, press => false, ram => up, arrived => 0, delivered => 0,
      outs => #{}, pending => #{}, gen => 0}.

%% @doc The simulation's parameters from the cell's settings.
-spec params(map()) -> map().
params(Settings) ->
    #{arrival_ms => maps:get(sim_arrival_ms, Settings, 1500),
      transfer_ms => 800, eject_ms => 600, ram_speed => 50.0, clearance_mm => 20.0,
      return_ms => 300,
      stick_rate => maps:get(sim_stick_rate, Settings, 0.0), roll => 1.0}.

%% @doc The world as the simulation starts with it (a saved one, or {@link new/0}),
%% with the PLC's outputs as they are: every sensor set to what it sees, moves under
%% way taken up again.
-spec start(map(), world()) -> {world(), [effect()]}.
start(P, W0) ->
    %% A move under way when the simulation stopped starts again from its beginning.
    W = W0#{pending := #{}, ram := case maps:get(ram, W0) of
                                      down -> down;
                                      _ -> up
                                  end},
    {W1, Fx} = settle(P, W, W),
    {W1, [{set, K, V} || {K, V} <- maps:to_list(inputs(W1))] ++ Fx}.

%% @doc The PLC's output `Point' took `Value'.
-spec output(atom(), boolean() | integer(), map(), world()) -> {world(), [effect()]}.
output(Point, Value, P, #{outs := Outs} = W0) ->
    Old = maps:get(Point, Outs, undefined),
    W = W0#{outs := Outs#{Point => Value}},
    case {Point, Value} of
        {_, Old} ->
            {W, []};
        {ram_lower, true} ->
            lower(P, W);
        {ram_lower, false} ->
            raise(P, W);
        _ ->
            settle(P, W0, W)
    end.

%% @doc A move the world started has ended (one cancelled since is ignored).
-spec event(event(), map(), world()) -> {world(), [effect()]}.
event({Kind, Gen}, P, #{pending := Pending} = W0) ->
    case Pending of
        #{Kind := {Gen, _}} -> done(Kind, P, W0, W0#{pending := maps:remove(Kind, Pending)});
        #{} -> {W0, []}
    end.

%% @doc What each sensor sees.
-spec inputs(world()) -> #{atom() => boolean() | integer()}.
inputs(#{infeed := Infeed, press := Press, ram := Ram, outs := Outs}) ->
    #{part_at_infeed => Infeed, part_in_press => Press,
      ram_up => Ram =:= up, ram_down => Ram =:= down,
      force_kn => case Ram of
                      down when Press -> force(Outs);
                      _ -> 0
                  end}.

%% @doc How many parts are in the machine.
-spec parts(world()) -> 0..2.
parts(#{infeed := Infeed, press := Press}) ->
    length([x || true <- [Infeed, Press]]).

%% @doc What of the world is kept across a restart of the node: where the parts are,
%% the ram, the counts. {@link start/2} takes it up again (merged into {@link new/0}):
%% the moves under way start again, the outputs are read anew. A station added to the
%% line is added here too.
-spec persisted(world()) -> map().
persisted(W) ->
    maps:with([infeed, press, ram, arrived, delivered], W).

%% @doc Whether a part arrived, moved on or left from `Old' to `New': when the world is
%% worth saving again.
-spec moved(world(), world()) -> boolean().
moved(Old, New) ->
    Places = [infeed, press, delivered],
    maps:with(Places, Old) =/= maps:with(Places, New).

%%--------------------------------------------------------------------

%% `Before': the world as the event found it, whose sensors the effects change.
done(arrival, P, Before, W) ->
    settle(P, Before, W#{infeed := true, arrived := maps:get(arrived, W) + 1});
done(transfer, P, Before, W) ->
    settle(P, Before, W#{infeed := false, press := true});
done(eject, P, Before, W) ->
    settle(P, Before, W#{press := false, delivered := maps:get(delivered, W) + 1});
done(ram, _P, Before, #{ram := lowering} = W) ->
    W1 = W#{ram := down},
    {W1, sensors(Before, W1)};
done(ram, _P, Before, #{ram := raising} = W) ->
    W1 = W#{ram := up},
    {W1, sensors(Before, W1)}.

lower(#{roll := Roll, stick_rate := Rate} = P, W) ->
    case Roll < Rate of
        true ->
            W1 = cancel(ram, W#{ram := stuck}),
            {W1, sensors(W, W1)};
        false ->
            Mm = maps:get(clearance_mm, P) + depth_mm(maps:get(outs, W)),
            schedule(ram, round(Mm / maps:get(ram_speed, P) * 1000), W#{ram := lowering}, W)
    end.

raise(P, #{ram := up} = W) ->
    settle(P, W, W);
raise(P, W) ->
    schedule(ram, maps:get(return_ms, P), W#{ram := raising}, W).

%% The moves the belts allow start; those they no longer allow stop. The effects: the
%% sensors that changed since `Before', the timers of the moves started.
settle(P, Before, W0) ->
    W1 = arrival(P, W0),
    Belts = {out(infeed_belt, W1), out(press_belt, W1)},
    W2 = case {W1, Belts} of
             {#{infeed := true, press := false}, {true, true}} -> start_move(transfer, P, W1);
             _ -> cancel(transfer, W1)
         end,
    W3 = case {W2, Belts} of
             {#{press := true}, {_, true}} -> start_move(eject, P, W2);
             _ -> cancel(eject, W2)
         end,
    {W3, sensors(Before, W3) ++ timers(W0, W3)}.

arrival(_P, #{infeed := true} = W) ->
    cancel(arrival, W);
arrival(P, W) ->
    start_move(arrival, P, W).

start_move(Kind, P, #{pending := Pending, gen := G} = W) ->
    case Pending of
        #{Kind := _} -> W;
        #{} -> W#{pending := Pending#{Kind => {G + 1, duration(Kind, P)}}, gen := G + 1}
    end.

duration(arrival, P) -> maps:get(arrival_ms, P);
duration(transfer, P) -> maps:get(transfer_ms, P);
duration(eject, P) -> maps:get(eject_ms, P).

cancel(Kind, #{pending := Pending} = W) ->
    W#{pending := maps:remove(Kind, Pending)}.

schedule(Kind, Ms, W, Before) ->
    #{gen := G, pending := Pending} = W,
    W1 = W#{gen := G + 1, pending := Pending#{Kind => {G + 1, Ms}}},
    {W1, sensors(Before, W1) ++ [{'after', Ms, {Kind, G + 1}}]}.

%% The timers of the moves started since `W0', each armed once.
timers(#{pending := Old}, #{pending := New}) ->
    [{'after', Ms, {Kind, G}}
     || {Kind, {G, Ms}} <- maps:to_list(New), maps:get(Kind, Old, undefined) =/= {G, Ms}].

%% The sensors that changed, those that go off first: a part leaves one sensor before it
%% reaches the next, so the PLC never shows it at two stations in one scan (set in the
%% order of their names, a part moving to a station named later would be seen at both,
%% and taken there for another part).
sensors(W0, W1) ->
    Old = inputs(W0),
    Changed = [{set, K, V} || {K, V} <- maps:to_list(inputs(W1)), maps:get(K, Old) =/= V],
    [C || {set, _, false} = C <- Changed] ++ [C || {set, _, V} = C <- Changed, V =/= false].

out(Point, #{outs := Outs}) ->
    maps:get(Point, Outs, false) =:= true.

depth_mm(Outs) ->
    case maps:get(stroke_depth, Outs, 0) of
        D when is_integer(D), D > 0 -> D / 10;
        _ -> 0.0
    end.

force(Outs) ->
    min(32767, round(depth_mm(Outs) * ?KN_PER_MM)).
