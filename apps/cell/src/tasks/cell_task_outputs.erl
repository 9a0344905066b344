%% @doc The outputs a device task commanded, and what to write again when a connection
%% it lost is back (pure: no process, no IO).
%%
%% A task's outputs are written through without waiting for the device. A write still
%% queued or in flight when the connection drops may never reach the PLC, and a PLC
%% may take its outputs to safe values while its link is down; after a reconnect the
%% HAL reads the outputs back from the device. The engine keeps, per task, the last
%% value the task commanded for each output (its image); when the operator retries
%% after the connection was lost, every output of the lost connection's groups that
%% the HAL now reads differently from the image (or cannot read) is written again, so
%% the task goes on with its outputs as it last commanded them.
%%
%% The writes go in the order the task last commanded those outputs, as the task's own
%% writes did: a robot's target before the command that starts the move to it, so that
%% a PLC that lost both does not start a move to a stale target.
%%
%% The image holds only what the task wrote itself; securing (uninit: Stop, Reset,
%% emergency stop) clears it, so a secured output is never set again by this path.
-module(cell_task_outputs).

-export([new/0, command/4, writes/3, text/1]).
-export_type([image/0, write/0]).

%% Each output's last commanded value, with the rank of that command among the task's.
-type image() :: #{{atom(), atom()} => {pos_integer(), cell_hal_type:value()}}.
-type write() :: {atom(), atom(), cell_hal_type:value()}.

%% @doc An empty image: the task has commanded nothing yet.
-spec new() -> image().
new() ->
    #{}.

%% @doc The image after the task commanded `Point' of `Group' to `Value'.
-spec command(image(), atom(), atom(), cell_hal_type:value()) -> image().
command(Image, Group, Point, Value) ->
    Last = maps:fold(fun(_, {Rank, _}, Max) -> max(Rank, Max) end, 0, Image),
    maps:put({Group, Point}, {Last + 1, Value}, Image).

%% @doc The writes that bring the outputs of `Groups' back to the image: each output of
%% those groups the task commanded whose value now (`Now', as the HAL reads it; an
%% output missing there could not be read) differs from what the task commanded, in
%% the order the task last commanded them.
-spec writes(image(), [atom()], #{{atom(), atom()} => cell_hal_type:value()}) -> [write()].
writes(Image, Groups, Now) ->
    Ranked = lists:sort([{Rank, Key, V} || {Key, {Rank, V}} <- maps:to_list(Image)]),
    [{G, P, V} || {_Rank, {G, P} = Key, V} <- Ranked,
                  lists:member(G, Groups),
                  not same(maps:find(Key, Now), V)].

same({ok, Now}, Commanded) -> Now == Commanded;
same(error, _Commanded) -> false.

%% @doc The writes in an operator's words: `conv.motor := true, conv.speed := 12.5'.
-spec text([write()]) -> iodata().
text(Writes) ->
    lists:join(", ", [io_lib:format("~ts.~ts := ~ts", [G, P, value_text(V)])
                      || {G, P, V} <- Writes]).

value_text(V) when is_binary(V) -> [$", V, $"];
value_text(V) -> io_lib:format("~tp", [V]).
