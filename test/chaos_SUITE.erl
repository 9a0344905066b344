%% The bounded chaos test of the default cell (see cellrt_chaos, whose full form is
%% `make chaos'): the built release killed with SIGKILL five times at random moments
%% while it produces, thirty single processes killed inside it, errors answered as an
%% operator would; then the line drains and every serial is reconciled against the
%% simulated machine's own ledger. Nothing lost, duplicated, double-held, wedged, or
%% left but recorded scrapped, and the statistics' totals are the machine's.
%%
%% CHAOS_SEED chooses the seed (a fixed one otherwise, so a failure can be repeated),
%% CHAOS_NODE the node's short name.
-module(chaos_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, suite/0, init_per_suite/1, end_per_suite/1]).
-export([books_are_read_right/1, kills_lose_nothing/1]).

all() ->
    [books_are_read_right, kills_lose_nothing].

suite() ->
    [{timetrap, {minutes, 30}}].

init_per_suite(Config) ->
    filelib:is_regular(cellrt_rel:bin()) orelse ct:fail("no release: build it with `rebar3 release`"),
    [{started_dist, cellrt_rel:start_dist("chaos_suite")} | Config].

end_per_suite(Config) ->
    cellrt_rel:stop_dist(?config(started_dist, Config)).

kills_lose_nothing(Config) ->
    Priv = ?config(priv_dir, Config),
    Seed = case os:getenv("CHAOS_SEED") of
               false -> 2300;
               S -> list_to_integer(S)
           end,
    Opts = (cellrt_chaos:default_opts())#{
             node_kills => 5, proc_kills => 30, seed => Seed,
             root => filename:join(Priv, "chaos_SUITE.root"),
             node => case os:getenv("CHAOS_NODE") of
                         false -> "cellrt_ct_chaos_" ++ os:getpid();
                         Name -> Name
                     end,
             web_port => "0", shdr_port => "0",
             out => filename:join(Priv, "chaos_SUITE.out"),
             command => io_lib:format("chaos_SUITE, CHAOS_SEED=~b", [Seed]),
             log => fun(Fmt, Args) -> ct:pal("chaos: " ++ Fmt, Args) end},
    #{counts := Counts, report := Report} = cellrt_chaos:run(Opts),
    ct:log("~ts", [Report]),
    ?assertEqual(#{"lost" => 0, "duplicated" => 0, "double-held" => 0, "wedged" => 0,
                   "left-but-recorded-scrapped" => 0, "books" => 0}, Counts).

%% The harness itself: each way the machine's ledger and the cell's books can agree or
%% disagree lands in its column.
books_are_read_right(_Config) ->
    S = fun(N) -> iolist_to_binary(io_lib:format("P261127-~6..0b", [N])) end,
    Out = #{status => out, lefts => 1, scraps => 0, in_open => false, in_product => true},
    Scrapped = #{status => scrapped, lefts => 0, scraps => 1, in_open => false,
                 in_product => true},
    InCell = #{status => in_cell, lefts => 0, scraps => 0, in_open => true,
               in_product => false},
    World = #{upstream => #{front => [S(10)], rear => []},
              loading => #{front => {S(7), stop}, rear => empty},
              work => #{front => {S(8), frame}, rear => {S(9), full}},
              unloading => #{front => empty, rear => empty},
              gripper => S(8), next => 12,
              ledger => [{S(1), delivered}, {S(2), delivered}, {S(3), delivered},
                         {S(4), scrapped}, {S(5), delivered}, {S(5), delivered},
                         {S(6), delivered}]},
    Products = #{S(1) => Out,                                   %% ok
                 S(2) => Scrapped,                              %% left, recorded scrapped
                 S(3) => InCell,                                %% delivered, still in the cell
                 S(4) => Scrapped,                              %% ok
                 S(5) => Out,                                   %% delivered twice
                 S(6) => Out#{lefts => 2},                      %% left twice in the books
                 S(7) => InCell,                                %% in the machine, held: ok
                 S(8) => InCell,                                %% in the gripper, held by none
                 S(9) => InCell},                               %% in the fixture, held: ok
    %% S(10) waits upstream, unknown to the cell: ok. S(11) is nowhere: vanished.
    Books = cellrt_chaos:reconcile(#{world => World, products => Products,
                                     held => [{S(7), loading_front}, {S(9), work_rear}]}),
    Serials = fun(Col) -> lists:sort([Se || {Se, _} <- maps:get(Col, Books)]) end,
    ?assertEqual([S(3), S(8), <<"no. 11">>], Serials(lost)),
    ?assertEqual([S(5), S(6)], Serials(duplicated)),
    ?assertEqual([S(2)], Serials(left_scrapped)),
    ?assertEqual(5, maps:get(ok, Books)),
    Phys = maps:get(phys, Books),
    ?assertMatch(#{delivered := 6, scrapped := 1, in_machine := 3, waiting := 1, made := 11},
                 Phys),
    %% The totals: in the cell as many as in the machine, in = all that entered it.
    Total = fun(I, O, Sc, C) -> #{cell => #{in => I, out => O, scrapped => Sc}, in_cell => C} end,
    ?assertEqual([], cellrt_chaos:books(Total(10, 6, 1, 3), Phys)),
    %% A panel entered and left but not counted: its in and its out are missing.
    ?assertEqual([{"in", 9, 10}, {"out", 5, 6}],
                 cellrt_chaos:books(Total(9, 5, 1, 3), Phys)),
    %% Counted scrapped though it is still in the machine; counted in twice.
    ?assertEqual([{"in", 11, 10}, {"scrapped", 2, 1}, {"in the cell", 2, 3}],
                 cellrt_chaos:books(Total(11, 6, 2, 2), Phys)),
    %% What the operator's hand took out is scrapped for the cell.
    ?assertEqual([], cellrt_chaos:books(Total(11, 6, 2, 3), Phys#{removed => 1})).
