%% @doc The fixture clamps' GoHome, Stop and FaultReaction sequences
%% ({@link router_clamps_unit}), chosen by the `sequence' arg.
%%
%% GoHome recovers from the sensors alone, whatever the unit's process knew before (a
%% crash, a power cut, the operator's Reset after a fault): with a panel in the
%% fixture (its position sensor) and a clamp seen closed, the panel may be one the
%% lower robot routes, so both clamps close (the closed one does not move); otherwise
%% both open. The work segment's order then decides in Automatic.
%%
%% <pre>
%%  sequence        step        does                                   next
%%  home            look        reads the fixture and the clamps      move
%%                  move        both clamps to the end chosen         → done
%%  stop            hold        nothing moves: the valves hold        → done
%%  fault_reaction  coils_off   every coil off: the valves hold       → done
%% </pre>
-module(router_clamps_sequences).
-behaviour(cell_sequence).

-export([init/2, step/2, home_end/2]).

-spec init(map(), cell_sequence:seq()) -> {ok, atom(), cell_sequence:seq()}.
init(#{sequence := home}, Seq) -> {ok, look, Seq};
init(#{sequence := stop}, Seq) -> {ok, hold, Seq};
init(#{sequence := fault_reaction}, Seq) -> {ok, coils_off, Seq}.

-spec step(term(), cell_sequence:seq()) -> cell_sequence:result().
step(look, Seq) ->
    Panel = cell_sequence:in(Seq, {cell_sequence:arg(Seq, work_io, undefined),
                                   panel_in_position}),
    Closed = [cell_sequence:in(Seq, P) || #{is_closed := P} <- router_clamps_io:clamps()],
    End = home_end(Panel, Closed),
    Seq1 = case End of
               closed -> cell_sequence:log(Seq, brief, "a panel lies in the fixture with a "
                                           "clamp closed on it: both clamps close", []);
               open -> Seq
           end,
    cell_sequence:next(cell_sequence:put(Seq1, home_end, End), move);
step(move, Seq0) ->
    End = cell_sequence:get(Seq0, home_end),
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) -> lists:foldl(fun(C, Acc) -> cell_cylinder:move(Acc, C, End) end,
                                        S, [clamp_a, clamp_b])
                  end),
    cell_sequence:await(Seq, [clamp_a, clamp_b], home_done);
step(home_done, Seq) ->
    cell_sequence:done(Seq);
step(hold, Seq) ->
    cell_sequence:done(Seq);
step(coils_off, Seq) ->
    cell_sequence:done(
      lists:foldl(fun(#{close := Close, open := Open}, S) ->
                          cell_sequence:out(cell_sequence:out(S, Close, false), Open, false)
                  end, Seq, router_clamps_io:clamps()));
step(Other, Seq) ->
    cell_sequence:abort(Seq, {unhandled_step, Other}).

%% @doc Where GoHome takes the clamps: closed when a panel lies in the fixture and a
%% clamp is closed on it (opening could spoil a panel being routed), open otherwise.
-spec home_end(boolean(), [boolean()]) -> closed | open.
home_end(true, Closed) ->
    case lists:member(true, Closed) of
        true -> closed;
        false -> open
    end;
home_end(false, _Closed) ->
    open.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

home_end_test_() ->
    [?_assertEqual(closed, home_end(true, [true, true])),
     ?_assertEqual(closed, home_end(true, [false, true])),
     ?_assertEqual(open, home_end(true, [false, false])),
     ?_assertEqual(open, home_end(false, [true, true])),
     ?_assertEqual(open, home_end(false, [false, false]))].
-endif.
