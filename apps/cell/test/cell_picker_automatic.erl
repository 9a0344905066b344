%% The seed's PickerAutomaticSequence, step for step. Where the seed's listing names
%% a next step it never defines, the step that follows in the listing is meant:
%% AutomaticVerticalDown is SwitchMagnetOn, AutomaticAufnehmenVertikalAuf ("pick up,
%% vertical up") is FetchVerticalUp, AutomaticMoveDown is SwitchMagnetOff. The REPEAT
%% loop around the steps is the `several' mode. TransportSpeed has no counterpart: the
%% cylinders have no speed.
%%
%% Besides the seed: the sequence reports IPC-2541 events — STARVED while it waits for
%% a part, EXECUTING while it carries one — so the cell and SHDR see the picker work.
-module(cell_picker_automatic).
-behaviour(cell_sequence).

-export([init/2, step/2, mode/0]).

mode() -> several.

%% OnStart: the delays of this run.
init(Args, Seq) ->
    {ok, automatic_begin,
     cell_sequence:put(cell_sequence:put(Seq, pick_delay, maps:get(pick_delay_ms, Args, 500)),
                       release_delay, maps:get(release_delay_ms, Args, 200))}.

step(automatic_begin, Seq) ->
    cell_sequence:next(Seq, begin_vertical_up);

step(begin_vertical_up, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun(S) -> cell_cylinder:move_up(S, vertical_lift) end),
    cell_sequence:await(Seq, vertical_lift, wait_part_at_end);

step(wait_part_at_end, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun cell_sequence:starved/1),
    cell_sequence:await(Seq, {io, part_is_at_end, {eq, true}}, move_right);

step(move_right, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) ->
                          S1 = cell_cylinder:move(cell_sequence:unstarved(S), horizontal_move, right),
                          cell_cylinder:move_down(S1, vertical_lift)
                  end),
    cell_sequence:await2(Seq, horizontal_move, vertical_lift, switch_magnet_on);

step(switch_magnet_on, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) ->
                          S1 = cell_sequence:out(S, magnet, true),
                          cell_seq_timer:run_async(S1, timer, cell_sequence:get(S1, pick_delay))
                  end),
    cell_sequence:await(Seq, timer, fetch_vertical_up);

step(fetch_vertical_up, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) -> cell_cylinder:move_up(cell_sequence:work_start(S), vertical_lift) end),
    cell_sequence:await(Seq, vertical_lift, move_left);

step(move_left, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) ->
                          S1 = cell_cylinder:move(S, horizontal_move, left),
                          cell_cylinder:move_down(S1, vertical_lift)
                  end),
    cell_sequence:await2(Seq, horizontal_move, vertical_lift, switch_magnet_off);

step(switch_magnet_off, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) ->
                          S1 = cell_sequence:out(S, magnet, false),
                          cell_seq_timer:run_async(S1, timer, cell_sequence:get(S1, release_delay))
                  end),
    cell_sequence:await(Seq, timer, release_vertical_up);

step(release_vertical_up, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun(S) -> cell_cylinder:move_up(S, vertical_lift) end),
    cell_sequence:await(Seq, vertical_lift, automatic_end);

step(automatic_end, Seq) ->
    %% The seed repeats the sequence.
    cell_sequence:next(cell_sequence:work_complete(Seq), automatic_begin);

step(Other, Seq) ->
    cell_sequence:abort(Seq, {unhandled_step, Other}).
