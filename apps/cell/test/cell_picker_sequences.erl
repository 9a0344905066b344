%% The picker's other sequences, one module with a step family each (`sequence' in the
%% args): GoHome (lift up, then to the left: the home position), Stop (lift up: the
%% load clear of everything), FaultReaction (the horizontal slide stopped where it
%% is, without waiting for anything), and the action release_part (magnet off, a
%% moment for the part to drop).
-module(cell_picker_sequences).
-behaviour(cell_sequence).

-export([init/2, step/2]).

init(#{sequence := home}, Seq) -> {ok, home_lift_up, Seq};
init(#{sequence := stop}, Seq) -> {ok, stop_lift_up, Seq};
init(#{sequence := fault_reaction}, Seq) -> {ok, fault_stop_slide, Seq};
init(#{sequence := release_part}, Seq) -> {ok, release_magnet_off, Seq}.

%% GoHome
step(home_lift_up, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun(S) -> cell_cylinder:move_up(S, vertical_lift) end),
    cell_sequence:await(Seq, vertical_lift, home_move_left);
step(home_move_left, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun(S) -> cell_cylinder:move(S, horizontal_move, left) end),
    cell_sequence:await(Seq, horizontal_move, home_done);
step(home_done, Seq) ->
    cell_sequence:done(Seq);

%% Stop
step(stop_lift_up, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun(S) -> cell_cylinder:move_up(S, vertical_lift) end),
    cell_sequence:await(Seq, vertical_lift, stop_done);
step(stop_done, Seq) ->
    cell_sequence:done(Seq);

%% FaultReaction: nothing awaited.
step(fault_stop_slide, Seq) ->
    cell_sequence:done(cell_sequence:out(cell_sequence:out(Seq, move_left, false),
                                         move_right, false));

%% The action release_part
step(release_magnet_off, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) -> cell_seq_timer:run_async(cell_sequence:out(S, magnet, false),
                                                     drop, 200)
                  end),
    cell_sequence:await(Seq, drop, release_done);
step(release_done, Seq) ->
    cell_sequence:done(Seq);

step(Other, Seq) ->
    cell_sequence:abort(Seq, {unhandled_step, Other}).
