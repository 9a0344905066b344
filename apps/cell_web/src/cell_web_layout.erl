%% @doc The picture of the machine the panel draws, derived from the cell spec alone,
%% so that any cell gets it without drawing anything: zones are columns in the order
%% products flow through them, lanes are rows, links are arrows between tasks.
%%
%% The flow order comes from the links: a task's rank is the length of the longest
%% chain of links leading to it (a cycle is cut where it closes), a zone's column is
%% the smallest rank of its tasks (ties keep the spec's order). Lanes are rows in the
%% order the spec names them; a lane whose tasks are linked to tasks of two or more
%% other lanes (the robots a dual-lane machine shares) is drawn across all rows, and
%% its tasks are marked `shared'. Tasks of one zone and row sit side by side
%% (`slot' of `slots'). The beacon is the spec's monitor's lamp outputs.
%%
%% Pure: {@link cell_web_layout_h} adds what is live (states, phases, counters).
-module(cell_web_layout).

-export([layout/1]).

-export_type([layout/0]).

-type layout() :: #{name := binary(), zones := [map()], lanes := [map()],
                    rows := pos_integer(), tasks := [map()], links := [map()],
                    beacon := [map()]}.

%% @doc The layout of a (validated) cell spec.
-spec layout(map()) -> layout().
layout(Spec) ->
    Tasks = maps:get(tasks, Spec, []),
    Links = [L || #{from := _, to := _} = L <- maps:get(links, Spec, [])],
    Ids = [Id || #{id := Id} <- Tasks],
    Edges = [{F, T} || #{from := F, to := T} <- Links,
                       lists:member(F, Ids), lists:member(T, Ids)],
    Rank = ranks(Ids, Edges),
    Zones = order([{maps:get(zone, T), maps:get(maps:get(id, T), Rank)} || T <- Tasks]),
    Lanes = unique([maps:get(lane, T) || T <- Tasks]),
    LaneOf = maps:from_list([{Id, L} || #{id := Id, lane := L} <- Tasks]),
    Shared = [L || L <- Lanes, length(neighbour_lanes(L, LaneOf, Edges)) >= 2],
    Rows = [L || L <- Lanes, not lists:member(L, Shared)],
    RowOf = fun(L) -> case index(L, Rows) of
                          0 -> 0;            %% a shared lane starts at the first row
                          I -> I - 1
                      end
            end,
    Cells = lists:foldl(fun(#{id := Id, zone := Z, lane := L}, Acc) ->
                                maps:update_with({Z, L}, fun(Is) -> Is ++ [Id] end, [Id], Acc)
                        end, #{}, Tasks),
    TaskViews =
        [begin
             InCell = maps:get({Z, L}, Cells),
             IsShared = lists:member(L, Shared),
             #{id => Id, zone => Z, lane => L, column => index(Z, Zones) - 1,
               row => RowOf(L),
               rows => case IsShared of
                           true -> max(length(Rows), 1);
                           false -> 1
                       end,
               slot => index(Id, InCell) - 1, slots => length(InCell), shared => IsShared}
         end || #{id := Id, zone := Z, lane := L} <- Tasks],
    #{name => maps:get(name, Spec, <<"cell">>),
      zones => [#{name => Z, column => I - 1} || {Z, I} <- numbered(Zones)],
      lanes => [#{name => L, row => RowOf(L), shared => lists:member(L, Shared)}
                || L <- Lanes],
      rows => max(length(Rows), 1),
      tasks => TaskViews,
      links => [#{id => Id, from => local(F, Ids), to => local(T, Ids)}
                || #{id := Id, from := F, to := T} <- Links],
      beacon => beacon(Spec)}.

%% Longest chain of links to each task; a link closing a cycle is not followed again.
ranks(Ids, Edges) ->
    Start = maps:from_list([{Id, 0} || Id <- Ids]),
    relax(Start, Edges, length(Ids)).

relax(Rank, _Edges, 0) ->
    Rank;
relax(Rank, Edges, N) ->
    Next = lists:foldl(fun({F, T}, Acc) ->
                               R = maps:get(F, Acc) + 1,
                               case R > maps:get(T, Acc) of
                                   true -> Acc#{T := R};
                                   false -> Acc
                               end
                       end, Rank, Edges),
    case Next =:= Rank of
        true -> Rank;
        false -> relax(Next, Edges, N - 1)
    end.

%% Zones by the smallest rank of their tasks, ties in the order first named.
order(ZoneRanks) ->
    Named = unique([Z || {Z, _} <- ZoneRanks]),
    Best = lists:foldl(fun({Z, R}, Acc) -> maps:update_with(Z, fun(O) -> min(O, R) end, R, Acc)
                       end, #{}, ZoneRanks),
    Keyed = [{maps:get(Z, Best), index(Z, Named), Z} || Z <- Named],
    [Z || {_, _, Z} <- lists:sort(Keyed)].

neighbour_lanes(Lane, LaneOf, Edges) ->
    unique([maps:get(B, LaneOf) || {A, B} <- Edges ++ [{T, F} || {F, T} <- Edges],
                                   maps:get(A, LaneOf) =:= Lane,
                                   maps:get(B, LaneOf) =/= Lane]).

local(End, Ids) when is_atom(End) ->
    case lists:member(End, Ids) of
        true -> End;
        false -> null
    end;
local(_Remote, _Ids) ->
    null.

beacon(Spec) ->
    Io = maps:get(io, maps:get(monitor, Spec, #{}), #{}),
    [#{lamp => Role, group => G, point => P}
     || Role <- [beacon_red, beacon_yellow, beacon_green, beacon_blue],
        {G, P} <- [maps:get(Role, Io, none)]].

unique(List) ->
    lists:reverse(lists:foldl(fun(X, Acc) ->
                                      case lists:member(X, Acc) of
                                          true -> Acc;
                                          false -> [X | Acc]
                                      end
                              end, [], List)).

index(X, List) -> index(X, List, 1).
index(_, [], _) -> 0;
index(X, [X | _], I) -> I;
index(X, [_ | T], I) -> index(X, T, I + 1).

numbered(List) -> lists:zip(List, lists:seq(1, length(List))).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

task(Id, Zone, Lane) -> #{id => Id, zone => Zone, lane => Lane, module => m}.

router(Lanes) ->
    LaneTasks = lists:append(
                  [[task(list_to_atom("unload_" ++ L), <<"Unloading">>, list_to_binary(L)),
                    task(list_to_atom("load_" ++ L), <<"Loading">>, list_to_binary(L)),
                    task(list_to_atom("work_" ++ L), <<"Work">>, list_to_binary(L))]
                   || L <- Lanes]),
    Links = lists:append(
              [[#{id => list_to_atom("lw_" ++ L), from => list_to_atom("load_" ++ L),
                  to => list_to_atom("work_" ++ L)},
                #{id => list_to_atom("wr_" ++ L), from => list_to_atom("work_" ++ L), to => lower},
                #{id => list_to_atom("pu_" ++ L), from => upper,
                  to => list_to_atom("unload_" ++ L)}] || L <- Lanes]),
    #{name => <<"r">>,
      tasks => LaneTasks ++ [task(lower, <<"Lower robot">>, <<"Shared">>),
                             task(upper, <<"Upper robot">>, <<"Shared">>)],
      links => Links ++ [#{id => rp, from => lower, to => upper}]}.

zones(L) -> [Z || #{name := Z} <- maps:get(zones, L)].
find(Id, L) -> hd([T || #{id := I} = T <- maps:get(tasks, L), I =:= Id]).

flow_order_test() ->
    L = layout(router(["front"])),
    %% The spec names unloading first; the links put it last.
    ?assertEqual([<<"Loading">>, <<"Work">>, <<"Lower robot">>, <<"Upper robot">>,
                  <<"Unloading">>], zones(L)),
    ?assertEqual(2, maps:get(rows, L)),
    ?assertMatch(#{column := 4, row := 0, rows := 1, shared := false}, find(unload_front, L)),
    %% One lane: the robots' lane is a row of its own, not shared.
    ?assertMatch(#{row := 1, shared := false}, find(lower, L)).

shared_lane_test() ->
    L = layout(router(["front", "rear"])),
    ?assertEqual(2, maps:get(rows, L)),
    ?assertMatch(#{row := 0, rows := 2, shared := true}, find(lower, L)),
    ?assertMatch(#{row := 1, shared := false}, find(work_rear, L)),
    ?assertEqual([#{name => <<"front">>, row => 0, shared => false},
                  #{name => <<"rear">>, row => 1, shared => false},
                  #{name => <<"Shared">>, row => 0, shared => true}], maps:get(lanes, L)).

slots_and_no_links_test() ->
    L = layout(#{name => <<"c">>, tasks => [task(a, <<"Z">>, <<"L">>), task(b, <<"Z">>, <<"L">>),
                                            task(c, <<"Y">>, <<"L">>)]}),
    ?assertEqual([<<"Z">>, <<"Y">>], zones(L)),
    ?assertMatch(#{slot := 1, slots := 2, column := 0}, find(b, L)),
    ?assertEqual([], maps:get(links, L)),
    ?assertEqual([], maps:get(beacon, L)).

cycle_and_remote_test() ->
    L = layout(#{name => <<"c">>,
                 tasks => [task(a, <<"A">>, <<"L">>), task(b, <<"B">>, <<"L">>)],
                 links => [#{id => ab, from => a, to => b}, #{id => ba, from => b, to => a},
                           #{id => feed, from => undefined, to => a},
                           #{id => out, from => b, to => {c, 'n@h'}}],
                 monitor => #{io => #{beacon_red => {general, red}}}}),
    ?assertEqual(2, length(zones(L))),
    ?assertMatch([_, _, #{id := feed, from := null, to := a}, #{id := out, to := null}],
                 maps:get(links, L)),
    ?assertEqual([#{lamp => beacon_red, group => general, point => red}], maps:get(beacon, L)).

empty_test() ->
    ?assertMatch(#{zones := [], tasks := [], rows := 1}, layout(#{name => <<"e">>, tasks => []})).
-endif.
