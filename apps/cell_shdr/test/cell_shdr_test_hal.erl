%% A scripted HAL for the adapter's tests, following the HAL contract of
%% docs/architecture.md: `read(Group, Point)' answers `{ok, Value}' or `{error,
%% unknown_point}'; `subscribe(Group, Point)' makes the caller receive `{cell_hal,
%% {Group, Point}, Value}' on every change. A point may be a counter, which reads
%% 1, 2, 3 ... (one more at each read), so a time series shows every sample it took.
%% Its groups belong to no connection (`connection_of/1' knows none).
-module(cell_shdr_test_hal).

-export([start/0, stop/0, set/3, counter/2, read/2, subscribe/2, connection_of/1,
         subscribe_connection/1]).

-define(TAB, cell_shdr_test_hal).

%% Starts the table's owner; returns once the table exists.
start() ->
    Self = self(),
    Pid = spawn(fun() ->
                        ?TAB = ets:new(?TAB, [named_table, public]),
                        Self ! {self(), ready},
                        receive stop -> ok end
                end),
    receive {Pid, ready} -> {ok, Pid} end.

stop() ->
    case ets:info(?TAB, owner) of
        undefined -> ok;
        Pid -> Pid ! stop, ok
    end.

set(Group, Point, Value) ->
    true = ets:insert(?TAB, {{Group, Point}, value, Value}),
    _ = [Pid ! {cell_hal, {Group, Point}, Value}
         || [Pid] <- ets:match(?TAB, {{sub, Group, Point, '$1'}})],
    ok.

counter(Group, Point) ->
    true = ets:insert(?TAB, {{Group, Point}, counter, 0}),
    ok.

read(Group, Point) ->
    case ets:lookup(?TAB, {Group, Point}) of
        [{_, value, V}] -> {ok, V};
        [{_, counter, _}] -> {ok, ets:update_counter(?TAB, {Group, Point}, {3, 1})};
        [] -> {error, unknown_point}
    end.

subscribe(Group, Point) ->
    true = ets:insert(?TAB, {{sub, Group, Point, self()}}),
    ok.

connection_of(_Group) ->
    {error, unknown_group}.

subscribe_connection(_Conn) ->
    {error, unknown_connection}.
