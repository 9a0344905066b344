%% @doc What the router's IO group modules share: points declared the way seed 000
%% §4.1 adds them (`AddInput<bool>("A1.01.06", "Start button", ...)'), laid out in the
%% PLC's Modbus image from a base address per group instance, so a module written for
%% the simulated PLC runs unchanged on the real one.
%%
%% Within a group, booleans take consecutive discrete inputs (inputs) or coils
%% (outputs) from `base'; other types take consecutive input or holding registers from
%% `base', as many as their type needs.
-module(router_io).

-export([points/2]).

-type def() :: {atom(), in | out, cell_hal_type:type(), binary(), binary()}.

%% @doc The point definitions of a group from `{Name, Dir, Type, Address, Caption}'.
-spec points(non_neg_integer(), [def()]) -> [cell_hal_group:point_def()].
points(Base, Defs) ->
    {Points, _} = lists:mapfoldl(fun(Def, Next) -> point(Base, Def, Next) end, #{}, Defs),
    Points.

point(Base, {Name, Dir, Type, Address, Caption}, Next) ->
    Kind = kind(Dir, Type),
    At = maps:get(Kind, Next, 0),
    {#{name => Name, dir => Dir, type => Type, address => Address, caption => Caption,
       field => {Kind, Base + At}},
     Next#{Kind => At + registers(Type)}}.

kind(in, bool) -> discrete_input;
kind(out, bool) -> coil;
kind(in, _) -> input_register;
kind(out, _) -> holding_register.

registers(bool) -> 1;
registers(int32) -> 2;
registers(uint32) -> 2;
registers(real) -> 2;
registers(lreal) -> 4;
registers({string, N}) -> (N + 1) div 2;
registers(_) -> 1.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

layout_test() ->
    Ps = points(100, [{a, in, bool, <<"X1">>, <<"A">>}, {b, in, bool, <<"X2">>, <<"B">>},
                      {c, out, bool, <<"Y1">>, <<"C">>}, {d, in, lreal, <<"R1">>, <<"D">>},
                      {e, in, int32, <<"R2">>, <<"E">>}, {f, in, {string, 5}, <<"R3">>, <<"F">>},
                      {g, out, int16, <<"R4">>, <<"G">>}]),
    ?assertEqual([{discrete_input, 100}, {discrete_input, 101}, {coil, 100},
                  {input_register, 100}, {input_register, 104}, {input_register, 106},
                  {holding_register, 100}],
                 [F || #{field := F} <- Ps]),
    ?assertEqual(ok, cell_hal_group:check_points(Ps)).
-endif.
