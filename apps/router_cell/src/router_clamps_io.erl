%% @doc The IO of a routing fixture's clamps (one instance per lane): two pneumatic
%% clamps, `a' (loading side) and `b' (unloading side), each a cylinder on a bistable
%% valve with two coils (close, open: the valve holds its last position with both
%% off) and a sensor at each end. {@link router_clamps_unit} drives them.
-module(router_clamps_io).
-behaviour(cell_hal_group).

-export([points/1, clamps/0]).

-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    router_io:points(maps:get(base, Opts, 0), [
        {a_is_closed, in, bool, <<"A2.02.01">>, <<"Clamp A closed (extended)">>},
        {a_is_open, in, bool, <<"A2.02.02">>, <<"Clamp A open (retracted)">>},
        {b_is_closed, in, bool, <<"A2.02.03">>, <<"Clamp B closed (extended)">>},
        {b_is_open, in, bool, <<"A2.02.04">>, <<"Clamp B open (retracted)">>},
        {a_close, out, bool, <<"A2.21.01">>, <<"Clamp A valve: close">>},
        {a_open, out, bool, <<"A2.21.02">>, <<"Clamp A valve: open">>},
        {b_close, out, bool, <<"A2.21.03">>, <<"Clamp B valve: close">>},
        {b_open, out, bool, <<"A2.21.04">>, <<"Clamp B valve: open">>}]).

%% @doc The clamps of a fixture, each with its valve's coils and end sensors.
-spec clamps() -> [#{name := a | b, close := atom(), open := atom(), is_closed := atom(),
                     is_open := atom()}].
clamps() ->
    [#{name => a, close => a_close, open => a_open, is_closed => a_is_closed,
       is_open => a_is_open},
     #{name => b, close => b_close, open => b_open, is_closed => b_is_closed,
       is_open => b_is_open}].
