%% @doc The servo drives of the router, as the cell's monitor ({@link cell_monitor})
%% watches them: the conveyor drive of each lane (its three belts), the lower routing
%% robot's and the upper manipulator robot's. Each has a `ready' and a `fault' status
%% bit, a fault code and a reset output, pulsed to clear a fault.
%%
%% The group's `lanes' option (default `[front]') says which conveyor drives there are.
-module(router_drives_io).
-behaviour(cell_hal_group).

-export([points/1, drives/1, point/2, caption/1]).

-type drive() :: conveyor_front | conveyor_rear | lower | upper.
-export_type([drive/0]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    Drives = drives(maps:get(lanes, Opts, [front])),
    router_io:points(maps:get(base, Opts, 0),
                     lists:append([defs(D, N) || {D, N} <- lists:zip(Drives, lists:seq(1, length(Drives)))])).

defs(D, N) ->
    Caption = <<(caption(D))/binary, " drive">>,
    Addr = fun(Kind, I) -> iolist_to_binary(io_lib:format("A5.~s.~2..0b", [Kind, N * 10 + I])) end,
    [{point(D, ready), in, bool, Addr("01", 1), <<Caption/binary, ": ready">>},
     {point(D, fault), in, bool, Addr("01", 2), <<Caption/binary, ": fault">>},
     {point(D, code), in, int16, Addr("30", 1), <<Caption/binary, ": fault code">>},
     {point(D, reset), out, bool, Addr("20", 1), <<Caption/binary, ": reset fault">>}].

%% @doc The drives of a router with these lanes.
-spec drives([front | rear]) -> [drive()].
drives(Lanes) ->
    [conveyor(L) || L <- [front, rear], lists:member(L, Lanes)] ++ [lower, upper].

conveyor(front) -> conveyor_front;
conveyor(rear) -> conveyor_rear.

%% @doc The name of a drive's point.
-spec point(drive(), ready | fault | code | reset) -> atom().
point(conveyor_front, ready) -> conveyor_front_ready;
point(conveyor_front, fault) -> conveyor_front_fault;
point(conveyor_front, code) -> conveyor_front_fault_code;
point(conveyor_front, reset) -> conveyor_front_reset;
point(conveyor_rear, ready) -> conveyor_rear_ready;
point(conveyor_rear, fault) -> conveyor_rear_fault;
point(conveyor_rear, code) -> conveyor_rear_fault_code;
point(conveyor_rear, reset) -> conveyor_rear_reset;
point(lower, ready) -> lower_ready;
point(lower, fault) -> lower_fault;
point(lower, code) -> lower_fault_code;
point(lower, reset) -> lower_reset;
point(upper, ready) -> upper_ready;
point(upper, fault) -> upper_fault;
point(upper, code) -> upper_fault_code;
point(upper, reset) -> upper_reset.

%% @doc How the operator knows a drive.
-spec caption(drive()) -> binary().
caption(conveyor_front) -> <<"Conveyors front">>;
caption(conveyor_rear) -> <<"Conveyors rear">>;
caption(lower) -> <<"Lower robot">>;
caption(upper) -> <<"Upper robot">>.
