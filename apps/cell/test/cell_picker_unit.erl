%% The picker of seed 001 as a unit: it takes parts from the end of a conveyor (right)
%% with a magnet on a vertical lift, and sets them down on the left.
%%
%% Args: `pick_delay_ms' (DelayAufnehmen, 500), `release_delay_ms' (DelayAblegen, 200),
%% `lift_timeout_ms' (2000), `move_timeout_ms' (3000), `mode' of the automatic
%% sequence (several, the seed's REPEAT loop; or one), `safe_outputs' (none: the
%% magnet keeps its part).
-module(cell_picker_unit).
-behaviour(cell_unit).

-export([unit/1]).

unit(Args) ->
    Automatic = maps:with([pick_delay_ms, release_delay_ms, mode], Args),
    #{sequences => #{go_home => {cell_picker_sequences, #{sequence => home}},
                     automatic => {cell_picker_automatic, Automatic},
                     stop => {cell_picker_sequences, #{sequence => stop}},
                     fault_reaction => {cell_picker_sequences, #{sequence => fault_reaction}},
                     {action, release_part} => {cell_picker_sequences,
                                                #{sequence => release_part}}},
      actions => [release_part],
      actuators =>
          #{vertical_lift =>
                {cell_cylinder, #{up => #{out => lift_up, sensor => lift_is_up},
                                  down => #{out => lift_down, sensor => lift_is_down},
                                  timeout_ms => maps:get(lift_timeout_ms, Args, 2000)}},
            %% A closed-centre valve: with both coils off the slide stops where it is.
            horizontal_move =>
                {cell_cylinder, #{left => #{out => move_left, sensor => is_left},
                                  right => #{out => move_right, sensor => is_right},
                                  timeout_ms => maps:get(move_timeout_ms, Args, 3000),
                                  safe => off}}},
      idle => starved,
      safe_outputs => maps:get(safe_outputs, Args, [])}.
