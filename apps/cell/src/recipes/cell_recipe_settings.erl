%% @doc The recipe settings object every cell has (seed 000 §3.2.1): product
%% parameters not tied to a drawing element. A cell with more (a router's cutting
%% speed and tool) declares its own schema and names it in the `cell' application's
%% `recipe_settings' environment key.
-module(cell_recipe_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> recipe.
name() -> recipe.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => board_length, type => {float, 1.0, 2000.0}, default => 100.0, unit => <<"mm">>,
       doc => <<"Length of the board (panel) in the direction of transport.">>},
     #{name => board_width, type => {float, 1.0, 2000.0}, default => 100.0, unit => <<"mm">>,
       doc => <<"Width of the board (panel) across the direction of transport.">>},
     #{name => board_thickness, type => {float, 0.1, 20.0}, default => 1.6, unit => <<"mm">>,
       doc => <<"Thickness of the board.">>},
     #{name => fixture_id, type => {string, 32}, default => <<>>,
       doc => <<"The fixture this product needs; empty when any will do.">>}].
