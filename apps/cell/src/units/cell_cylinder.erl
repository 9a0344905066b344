%% @doc A pneumatic cylinder with two end positions, each confirmed by a sensor: the
%% seed's VerticalLift (up / down) and HorizontalMove (left / right).
%%
%% ```
%% vertical_lift => {cell_cylinder, #{up => #{out => lift_up, sensor => lift_is_up},
%%                                    down => #{out => lift_down, sensor => lift_is_down},
%%                                    timeout_ms => 2000}}
%% '''
%%
%% Exactly two ends, named as the machine names them. Each end has its `sensor' (an
%% input, true at that end) and may have an `out' (the valve coil that drives it
%% there): two coils for a bistable valve, one for a monostable valve with a spring
%% (moving to the end without a coil switches the other coil off). `timeout_ms'
%% (default 5000): the longest a move may take. `safe' — what the emergency stop or a
%% crash leaves the valves at: `keep' (default: the valve holds), `off' (every coil
%% off: a closed-centre valve stops the cylinder), or an end (driven there).
%%
%% A move is done when the target end's sensor confirms it — at once if it already
%% does — and fails if it has not within the timeout: "vertical_lift did not reach up
%% within 2000 ms (sensor picker_io.lift_is_up stayed off)".
-module(cell_cylinder).
-behaviour(cell_actuator).

-export([move/3, move_up/2, move_down/2]).
-export([new/3, command/3, event/2, status/1, interrupt/1, secure/1, describe/1,
         format_error/2]).

-record(cyl, {name :: atom(),
              ends :: #{atom() => #{sensor := cell_actuator:point(),
                                    out => cell_actuator:point()}},
              timeout_ms :: pos_integer(),
              safe :: keep | off | atom(),
              status = idle :: idle | {moving, atom()} | {error, term()},
              position = unknown :: atom()}).

-define(DEFAULT_TIMEOUT_MS, 5000).

%% @doc Starts moving a cylinder to an end (the seed's `MoveUpAsync(THIS^)'); await it
%% by its name.
-spec move(cell_sequence:seq(), atom(), atom()) -> cell_sequence:seq().
move(Seq, Name, End) ->
    cell_sequence:command(Seq, Name, {move, End}).

-spec move_up(cell_sequence:seq(), atom()) -> cell_sequence:seq().
move_up(Seq, Name) -> move(Seq, Name, up).

-spec move_down(cell_sequence:seq(), atom()) -> cell_sequence:seq().
move_down(Seq, Name) -> move(Seq, Name, down).

%% cell_actuator

-spec new(atom(), map(), cell_actuator:resolve()) -> {ok, #cyl{}} | {error, term()}.
new(Name, Opts, Resolve) ->
    Timeout = maps:get(timeout_ms, Opts, ?DEFAULT_TIMEOUT_MS),
    Safe = maps:get(safe, Opts, keep),
    case check_ends(maps:without([timeout_ms, safe], Opts), Resolve) of
        {error, _} = Error ->
            Error;
        {ok, _} when not (is_integer(Timeout) andalso Timeout > 0) ->
            {error, {bad_option, timeout_ms}};
        {ok, Ends} ->
            case Safe =:= keep orelse Safe =:= off orelse maps:is_key(Safe, Ends) of
                true -> {ok, #cyl{name = Name, ends = Ends, timeout_ms = Timeout, safe = Safe}};
                false -> {error, {bad_option, safe}}
            end
    end.

check_ends(Ends, Resolve) when map_size(Ends) =:= 2 ->
    maps:fold(fun(End, Def, {ok, Acc}) when is_atom(End), is_map(Def) ->
                      case {cell_actuator:check_point(Resolve, maps:find(sensor, Def)),
                            cell_actuator:check_point(Resolve, maps:find(out, Def)),
                            maps:keys(Def) -- [sensor, out]} of
                          {{ok, S}, {ok, O}, []} -> {ok, Acc#{End => #{sensor => S, out => O}}};
                          {{ok, S}, none, []} -> {ok, Acc#{End => #{sensor => S}}};
                          {{ok, _}, _, []} -> {error, {bad_option, {End, out}}};
                          {_, _, []} -> {error, {bad_option, {End, sensor}}};
                          {_, _, Unknown} -> {error, {bad_option, {End, hd(Unknown)}}}
                      end;
                 (End, _, {ok, _}) ->
                      {error, {bad_option, End}};
                 (_, _, Error) ->
                      Error
              end, {ok, #{}}, Ends);
check_ends(_Ends, _Resolve) ->
    {error, {bad_option, "a cylinder has exactly two ends"}}.

-spec command(term(), #cyl{}, cell_actuator:read()) -> {ok, #cyl{}, [cell_actuator:effect()]}
                                                       | {error, term()}.
command({move, End}, #cyl{ends = Ends, timeout_ms = Ms} = C, Read) when is_map_key(End, Ends) ->
    #{sensor := {G, P} = Sensor} = maps:get(End, Ends),
    Cancel = cancel(C),
    Writes = drive(End, Ends),
    case Read(G, P) of
        {ok, true} ->
            {ok, C#cyl{status = idle, position = End}, Cancel ++ Writes};
        _ ->
            {ok, C#cyl{status = {moving, End}, position = unknown},
             Cancel ++ Writes ++ [{watch, arrived, Sensor, {eq, true}}, {timer, timeout, Ms}]}
    end;
command({move, End}, _C, _Read) ->
    {error, {unknown_end, End}};
command(Other, _C, _Read) ->
    {error, {unknown_command, Other}}.

%% Each coil on for its own end, off for the other.
drive(End, Ends) ->
    [{write, Out, E =:= End} || {E, #{out := Out}} <- lists:sort(maps:to_list(Ends))].

-spec event({watch, term(), term()} | {timer, term()}, #cyl{}) -> {#cyl{}, [cell_actuator:effect()]}.
event({watch, arrived, true}, #cyl{status = {moving, End}} = C) ->
    {C#cyl{status = idle, position = End}, [{cancel_timer, timeout}]};
event({timer, timeout}, #cyl{status = {moving, End}, timeout_ms = Ms, ends = Ends} = C) ->
    #{sensor := Sensor} = maps:get(End, Ends),
    {C#cyl{status = {error, {timeout, End, Ms, Sensor}}}, [{cancel_watch, arrived}]};
event(_Stale, C) ->
    {C, []}.

-spec status(#cyl{}) -> idle | busy | {error, term()}.
status(#cyl{status = idle}) -> idle;
status(#cyl{status = {moving, _}}) -> busy;
status(#cyl{status = {error, _} = E}) -> E.

-spec interrupt(#cyl{}) -> {#cyl{}, [cell_actuator:effect()]}.
interrupt(#cyl{status = {moving, _}} = C) ->
    {C#cyl{status = idle, position = unknown}, cancel(C)};
interrupt(C) ->
    {C#cyl{status = idle}, []}.

cancel(#cyl{status = {moving, _}}) -> [{cancel_watch, arrived}, {cancel_timer, timeout}];
cancel(_) -> [].

-spec secure(#cyl{}) -> [cell_actuator:effect()].
secure(#cyl{safe = keep}) -> [];
secure(#cyl{safe = off, ends = Ends}) ->
    [{write, Out, false} || {_, #{out := Out}} <- lists:sort(maps:to_list(Ends))];
secure(#cyl{safe = End, ends = Ends}) -> drive(End, Ends).

-spec describe(#cyl{}) -> map().
describe(#cyl{status = S, position = P}) ->
    #{type => cylinder, position => P,
      status => case S of
                    {moving, End} -> {moving, End};
                    {error, _} -> error;
                    idle -> idle
                end}.

-spec format_error(atom(), term()) -> iodata().
format_error(Name, {timeout, End, Ms, {G, P}}) ->
    io_lib:format("~ts did not reach ~ts within ~b ms (sensor ~ts.~ts stayed off)",
                  [Name, End, Ms, G, P]);
format_error(Name, {unknown_end, End}) ->
    io_lib:format("~ts has no end ~tp", [Name, End]);
format_error(Name, {unknown_command, C}) ->
    io_lib:format("~ts cannot ~tp", [Name, C]);
format_error(Name, Why) ->
    io_lib:format("~ts failed: ~tp", [Name, Why]).
