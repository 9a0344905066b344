%% Keeps the feed and out tables of a node's line segment alive for the node suite.
-module(cell_handshake_nodes_SUITE_keeper).

-export([start/0]).

-spec start() -> ok.
start() ->
    Self = self(),
    Pid = spawn(fun() ->
                        _ = ets:new(line_feed, [named_table, public, ordered_set]),
                        _ = ets:new(line_out, [named_table, public, set]),
                        Self ! {self(), ready},
                        receive stop -> ok end
                end),
    receive {Pid, ready} -> ok end.
