%% A unit for the property and the suites: every sequence it has is a
%% cell_test_seq, which waits for its test to complete or abort it. Idle and Stopped
%% run none. User states x and y, actions a and b.
%%
%% Args: `tab' (the table the sequences note themselves in), `modes' (a sequence's
%% mode by its key, default several), `booting' (false: no booting sequence).
-module(cell_test_unit).
-behaviour(cell_unit).

-export([unit/1, keys/0, spec/2]).

%% The states with a sequence.
keys() ->
    [booting, go_home, automatic, stop, fault_reaction, {user, x}, {user, y},
     {action, a}, {action, b}].

%% A spec for a unit of this module.
spec(Id, Args) ->
    #{id => Id, module => ?MODULE, zone => atom_to_binary(Id, utf8), lane => <<"Test">>,
      args => Args}.

unit(#{tab := Tab} = Args) ->
    Modes = maps:get(modes, Args, #{}),
    Keys = case maps:get(booting, Args, true) of
               true -> keys();
               false -> keys() -- [booting]
           end,
    #{sequences => maps:from_list([{K, {cell_test_seq, #{tab => Tab, key => K,
                                                         mode => maps:get(K, Modes, several)}}}
                                   || K <- Keys]),
      user_states => [x, y],
      actions => [a, b]}.
