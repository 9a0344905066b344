%% @doc The cell's recipes (one a part type): a recipe's settings are the standard
%% recipe settings object ({@link cell_recipe_settings}); the press reads the part's
%% `board_thickness' from it and presses that deep. A new cell starts with the demo
%% recipe. The panel has no recipe page: recipes are made over its REST API (`GET
%% /api/recipes', `PUT /api/recipes/NAME' with a recipe file, by a `service' user) or in
%% the node: `cell_recipe:save(<<"thick-part">>, #{description => <<"4 mm">>, settings =>
%% #{board_thickness => 4.0}}, <<"your name">>)'; the setting `recipe' says which one
%% the line produces.
-module(__NAME___recipes).

-export([ensure_demo/0, stroke_depth/1]).

-define(DEMO, <<"demo-part">>).

%% @doc Saves the demo recipe unless there is one of that name.
-spec ensure_demo() -> ok.
ensure_demo() ->
    case lists:member(?DEMO, cell_recipe:list()) of
        true -> ok;
        false -> ok = cell_recipe:save(?DEMO, #{description => <<"A 2.5 mm part, pressed flat">>,
                                                settings => #{board_thickness => 2.5}},
                                       <<"__NAME__">>)
    end.

%% @doc The press's stroke depth for a recipe, in tenths of a millimetre (what the
%% PLC's `stroke_depth' register holds), or why there is none.
-spec stroke_depth(binary()) -> {ok, 1..32767} | {error, term()}.
stroke_depth(Name) ->
    case cell_recipe:load(Name) of
        {ok, #{settings := #{board_thickness := Mm}}} -> {ok, depth(Mm)};
        {ok, _} -> {error, no_thickness};
        {error, _} = Error -> Error
    end.

depth(Mm) ->
    max(1, min(32767, round(Mm * 10))).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

depth_test() ->
    ?assertEqual(25, depth(2.5)),
    ?assertEqual(1, depth(0.01)).
-endif.
