%% @doc The router's recipes (seed 000 §3.2): what the routing robot cuts, read from the
%% recipe drawing, and the demo recipes a new cell starts with.
%%
%% A router recipe's drawing holds the panel outline (`ItemType' "PanelDrawing"), one
%% container per module (`ItemType' "Module"), fiducials, and the cut lines (`ItemType'
%% "Cut"), worked in their `ExecOrder'. A cut may give its feed in mm/s (attribute
%% "Feed"); otherwise the router's `feed_rate' setting applies. The demo panels are
%% pre-routed: the router cuts the breakout tabs that still hold the modules.
-module(router_recipes).

-export([cuts/2, modules/1, demo/0, ensure_demo/0]).

-export_type([cut/0]).

-type xy() :: {float(), float()}.
-type cut() :: #{from := xy(), to := xy(), length := float(), feed := float(),
                 segments := [cell_hal_path:segment(), ...]}.

-define(AUTHOR, <<"router_cell">>).
-define(TAB, 5.0).          %% the width of the routed channels, mm

%% @doc The cut lines of a drawing in ExecOrder: where each starts and ends, how long
%% its path is (arcs and bulged polylines by their arc length), at what feed, and its
%% lines and arcs for an interpolation channel to follow.
-spec cuts(cell_recipe_drawing:drawing(), float()) -> [cut()].
cuts(Drawing, DefaultFeed) ->
    [cut(Item, DefaultFeed) || Item <- cell_recipe_drawing:items_by_type(Drawing, <<"Cut">>),
                               maps:get(kind, Item) =/= container,
                               maps:get(kind, Item) =/= polyface].

cut(Item, DefaultFeed) ->
    Feed = case cell_recipe_drawing:attr(Item, <<"Feed">>) of
               undefined -> DefaultFeed;
               Text ->
                   case cell_recipe_drawing:parse_number(Text) of
                       F when is_float(F), F > 0 -> F;
                       _ -> DefaultFeed
                   end
           end,
    {From, To, Length} = path(Item),
    {ok, Segments} = cell_recipe_path:of_item(Item),
    #{from => From, to => To, length => Length, feed => Feed, segments => Segments}.

path(#{kind := line, from := {X1, Y1, _}, to := {X2, Y2, _}}) ->
    {{X1, Y1}, {X2, Y2}, dist({X1, Y1}, {X2, Y2})};
path(#{kind := circle, center := {X, Y, _}, radius := R}) ->
    {{X + R, Y}, {X + R, Y}, 2 * math:pi() * R};
path(#{kind := arc, center := {X, Y, _}, radius := R, start_angle := A0, end_angle := A1}) ->
    Sweep = case math:fmod(A1 - A0, 360.0) of
                S when S =< 0 -> S + 360.0;
                S -> S
            end,
    {on_circle(X, Y, R, A0), on_circle(X, Y, R, A1), R * Sweep * math:pi() / 180};
path(#{kind := polyline, points := Points, bulges := Bulges, closed := Closed}) ->
    XY = [{X, Y} || {X, Y, _} <- Points],
    Ends = case Closed of
               true -> XY ++ [hd(XY)];
               false -> XY
           end,
    Segments = lists:zip3(lists:droplast(Ends), tl(Ends),
                          lists:sublist(Bulges ++ lists:duplicate(length(Ends), 0.0),
                                        length(Ends) - 1)),
    {hd(Ends), lists:last(Ends), lists:sum([segment(A, B, Bulge) || {A, B, Bulge} <- Segments])}.

%% A polyline segment with a bulge (DXF): the tangent of a quarter of its angle.
segment(A, B, Bulge) when Bulge == 0 ->
    dist(A, B);
segment(A, B, Bulge) ->
    Chord = dist(A, B),
    Theta = 4 * math:atan(abs(Bulge)),
    Chord * Theta / (2 * math:sin(Theta / 2)).

on_circle(X, Y, R, Deg) ->
    Rad = Deg * math:pi() / 180,
    {X + R * math:cos(Rad), Y + R * math:sin(Rad)}.

dist({X1, Y1}, {X2, Y2}) ->
    math:sqrt((X2 - X1) * (X2 - X1) + (Y2 - Y1) * (Y2 - Y1)).

%% @doc How many modules a panel of this drawing gives.
-spec modules(cell_recipe_drawing:drawing()) -> non_neg_integer().
modules(Drawing) ->
    length(cell_recipe_drawing:items_by_type(Drawing, <<"Module">>)).

%% @doc The demo recipes: a 2×2 panel and a 3×1 panel.
-spec demo() -> [{binary(), map()}].
demo() ->
    [{<<"demo-2x2">>, panel(<<"Demo panel, 2 x 2 modules of 70 x 50 mm, 3 tabs each">>,
                            {160.0, 120.0}, {2, 2}, {70.0, 50.0}, 3, 15.0)},
     {<<"demo-3x1">>, panel(<<"Demo panel, 3 x 1 modules of 45 x 80 mm, 2 tabs each">>,
                            {160.0, 100.0}, {3, 1}, {45.0, 80.0}, 2, 20.0)}].

%% @doc Saves the demo recipes that are not in `Products/' yet (a recipe of the same
%% name is left as it is).
-spec ensure_demo() -> ok.
ensure_demo() ->
    Have = cell_recipe:list(),
    lists:foreach(fun({Name, Recipe}) ->
                          case lists:member(Name, Have) of
                              true -> ok;
                              false -> ok = cell_recipe:save(Name, Recipe, ?AUTHOR)
                          end
                  end, demo()).

%% A pre-routed panel: modules in a grid inside a frame, each held by tabs across the
%% channel around it, the tabs cut in a path that snakes across the panel.
panel(Description, {L, W}, {Cols, Rows}, {ML, MW}, TabsEach, Feed) ->
    Margin = {(L - Cols * ML - (Cols - 1) * ?TAB) / 2, (W - Rows * MW - (Rows - 1) * ?TAB) / 2},
    Modules = [{C, R, module_origin(Margin, C, R, ML, MW)}
               || R <- lists:seq(0, Rows - 1), C <- lists:seq(0, Cols - 1)],
    Tabs = lists:append([tabs(Origin, ML, MW, TabsEach) || {_, _, Origin} <- Modules]),
    Ordered = snake(Tabs),
    FeedText = float_to_binary(Feed, [{decimals, 1}]),
    Cuts = [cell_recipe_drawing:line(From, To, #{<<"ItemType">> => <<"Cut">>,
                                                  <<"ExecOrder">> => integer_to_binary(N),
                                                  <<"Feed">> => FeedText})
            || {N, {From, To}} <- lists:zip(lists:seq(1, length(Ordered)), Ordered)],
    Outline = cell_recipe_drawing:container(
                #{<<"ItemType">> => <<"PanelDrawing">>},
                [cell_recipe_drawing:polyline([{0, 0}, {L, 0}, {L, W}, {0, W}], true)]),
    ModuleItems = [cell_recipe_drawing:container(
                     #{<<"ItemType">> => <<"Module">>,
                       <<"Name">> => iolist_to_binary(io_lib:format("M~b", [R * Cols + C + 1]))},
                     [cell_recipe_drawing:polyline([{X, Y}, {X + ML, Y}, {X + ML, Y + MW},
                                                    {X, Y + MW}], true)])
                   || {C, R, {X, Y}} <- Modules],
    Fiducials = [cell_recipe_drawing:container(#{<<"ItemType">> => <<"Fiducial">>},
                                               [cell_recipe_drawing:circle(P, 0.5)])
                 || P <- [{3.0, 3.0}, {L - 3.0, W - 3.0}]],
    #{description => Description,
      settings => #{board_length => L, board_width => W, board_thickness => 1.6},
      drawing => cell_recipe_drawing:new([Outline | ModuleItems] ++ Fiducials ++ Cuts)}.

module_origin({MX, MY}, C, R, ML, MW) ->
    {MX + C * (ML + ?TAB), MY + R * (MW + ?TAB)}.

%% The tabs of a module: one across the channel below it and one above it, at the
%% middle of those edges, and with three a third across the channel on its left.
tabs({X, Y}, ML, MW, N) ->
    Mid = X + ML / 2,
    Below = {{Mid, Y - ?TAB}, {Mid, Y}},
    Above = {{Mid, Y + MW}, {Mid, Y + MW + ?TAB}},
    case N of
        3 -> [Below, Above, {{X - ?TAB, Y + MW / 2}, {X, Y + MW / 2}}];
        2 -> [Below, Above]
    end.

%% Cuts in the order a short path visits them: by rows of their start, left to right
%% in one row and back in the next.
snake(Tabs) ->
    Rows = lists:foldl(fun({{_, Y}, _} = T, Acc) ->
                               K = round(Y),
                               maps:update_with(K, fun(L) -> [T | L] end, [T], Acc)
                       end, #{}, Tabs),
    {Ordered, _} = lists:foldl(
                     fun(K, {Acc, Dir}) ->
                             Row = lists:sort(fun({{X1, _}, _}, {{X2, _}, _}) -> X1 =< X2 end,
                                              maps:get(K, Rows)),
                             Row1 = case Dir of right -> Row; left -> lists:reverse(Row) end,
                             {Acc ++ Row1, case Dir of right -> left; left -> right end}
                     end, {[], right}, lists:sort(maps:keys(Rows))),
    Ordered.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

cuts_test_() ->
    Cut = #{<<"ItemType">> => <<"Cut">>},
    D = cell_recipe_drawing:new(
          [cell_recipe_drawing:line({0, 0}, {3, 4}, Cut#{<<"ExecOrder">> => <<"2">>}),
           cell_recipe_drawing:line({9, 9}, {9, 10}),                  %% not a cut
           cell_recipe_drawing:arc({0, 0}, 10, 0, 90, Cut#{<<"ExecOrder">> => <<"1">>,
                                                            <<"Feed">> => <<"7.5">>}),
           cell_recipe_drawing:circle({1, 1}, 1, Cut#{<<"ExecOrder">> => <<"3">>}),
           cell_recipe_drawing:polyline([{0, 0}, {2, 0}, {2, 2}], false,
                                        Cut#{<<"ExecOrder">> => <<"4">>}),
           cell_recipe_drawing:polyline([{0, 0}, {2, 0}], false,
                                        Cut#{<<"ExecOrder">> => <<"5">>})]),
    [A, L, C, P, _] = cuts(D, 20.0),
    %% A bulge of 1 is a half circle.
    Half = cell_recipe_drawing:polyline([{0, 0}, {2, 0}], false, Cut),
    [B] = cuts(cell_recipe_drawing:new([Half#{bulges => [1.0, 0.0]}]), 20.0),
    [?_assertEqual(5.0, maps:get(length, L)),
     ?_assertEqual(20.0, maps:get(feed, L)),
     ?_assertEqual(7.5, maps:get(feed, A)),
     ?_assert(abs(maps:get(length, A) - 5 * math:pi()) < 1.0e-9),
     ?_assert(abs(element(1, maps:get(to, A))) < 1.0e-9),
     ?_assert(abs(maps:get(length, C) - 2 * math:pi()) < 1.0e-9),
     ?_assertEqual(4.0, maps:get(length, P)),
     ?_assertEqual({2.0, 2.0}, maps:get(to, P)),
     ?_assert(abs(maps:get(length, B) - math:pi()) < 1.0e-9)].

demo_test_() ->
    [{Name, fun() ->
                    {ok, Checked} = cell_recipe_drawing:validate(maps:get(drawing, R)),
                    Cuts = cuts(Checked, 20.0),
                    {Modules, Tabs} = case Name of <<"demo-2x2">> -> {4, 3}; _ -> {3, 2} end,
                    ?assertEqual(Modules, modules(Checked)),
                    ?assertEqual(Modules * Tabs, length(Cuts)),
                    [?assertEqual(?TAB, maps:get(length, Cu)) || Cu <- Cuts]
            end} || {Name, R} <- demo()].
-endif.
