%% The property of prop_cell_line_nodes: a line of three cells on three nodes, each in
%% a network namespace of its own, with partitions, kills and heals as commands. Every
%% serial leaves exactly once, none is held after the line is whole again, nothing
%% waits forever, no task crashes. The nodes speak the distribution over TLS.
%%
%% CELLRT_LINE_PROP_RUNS (default 3) sets the number of runs; the cuts made in all are
%% printed.
%%
%% Needs root (namespaces, tc); without it the suite fails, saying what is missing.
-module(cell_line_nodes_prop_SUITE).
-include_lib("common_test/include/ct.hrl").

-export([all/0, suite/0, init_per_suite/1, end_per_suite/1]).
-export([line_of_three/1]).

suite() ->
    [{timetrap, {minutes, 5 + 2 * runs()}}].

all() ->
    [line_of_three].

init_per_suite(Config) ->
    ok = cell_netns:required(),
    Config.

end_per_suite(_Config) ->
    ok.

%% The line's nodes speak the distribution over TLS, as a line across PCs does.
line_of_three(Config) ->
    ok = prop_cell_line_nodes:setup(filename:join(?config(priv_dir, Config), "line"),
                                    #{tls => true}),
    try
        Result = proper:quickcheck(prop_cell_line_nodes:prop_line(),
                                   [{numtests, runs()}, {start_size, 80}, {max_size, 80}, noshrink,
                                    {to_file, user}]),
        ct:pal("~b runs, ~b cuts", [runs(), prop_cell_line_nodes:cuts()]),
        true = Result,
        [tls] = prop_cell_line_nodes:protocols()
    after
        prop_cell_line_nodes:teardown()
    end.

runs() ->
    list_to_integer(os:getenv("CELLRT_LINE_PROP_RUNS", "3")).
