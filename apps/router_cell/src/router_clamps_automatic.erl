%% @doc The fixture clamps' Automatic sequence ({@link router_clamps_unit}): the clamps
%% follow the work segment's standing order `clamp' (`cell_unit:order/3'): `true' →
%% both closed, `false' → both open, none yet → they stay as GoHome left them.
%%
%% <pre>
%%  step     waits for                                   then
%%  follow   an order (none given yet)                   close or open
%%  close    both clamps closed (unstarved: a panel)     closed
%%  closed   the order to change                         follow
%%  open     both clamps open                            opened
%%  opened   the order to change (starved: no panel)     follow
%% </pre>
%%
%% A clamp that does not reach its end in time aborts the sequence (the unit's
%% fault). Halt (the cell's Pause, service mode) holds the sequence before its next
%% move, never in the middle of one.
-module(router_clamps_automatic).
-behaviour(cell_sequence).

-export([init/2, step/2, target/1]).

-define(CLAMPS, [clamp_a, clamp_b]).

-spec init(map(), cell_sequence:seq()) -> {ok, follow, cell_sequence:seq()}.
init(_Args, Seq) -> {ok, follow, Seq}.

-spec step(term(), cell_sequence:seq()) -> cell_sequence:result().
step(follow, Seq) ->
    case target(cell_sequence:order(Seq, clamp, undefined)) of
        closed -> cell_sequence:next(Seq, close);
        open -> cell_sequence:next(Seq, open);
        none -> cell_sequence:await(Seq, {order, clamp, {ne, undefined}}, follow)
    end;
step(close, Seq0) ->
    Seq = cell_sequence:on_entry(
            Seq0, fun(S) -> move(cell_sequence:unstarved(S), closed) end),
    cell_sequence:await(Seq, ?CLAMPS, closed);
step(closed, Seq) ->
    cell_sequence:await(Seq, {order, clamp, {ne, true}}, follow);
step(open, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun(S) -> move(S, open) end),
    cell_sequence:await(Seq, ?CLAMPS, opened);
step(opened, Seq0) ->
    Seq = cell_sequence:on_entry(Seq0, fun cell_sequence:starved/1),
    cell_sequence:await(Seq, {order, clamp, {ne, false}}, follow);
step(Other, Seq) ->
    cell_sequence:abort(Seq, {unhandled_step, Other}).

%% @doc Where the order `clamp' sends the clamps; `none' before the first order.
-spec target(term()) -> closed | open | none.
target(true) -> closed;
target(false) -> open;
target(_) -> none.

move(Seq, End) ->
    lists:foldl(fun(C, S) -> cell_cylinder:move(S, C, End) end, Seq, ?CLAMPS).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

target_test_() ->
    [?_assertEqual(closed, target(true)),
     ?_assertEqual(open, target(false)),
     ?_assertEqual(none, target(undefined))].
-endif.
