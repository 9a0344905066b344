%% The model of prop_cell_shdr for parallel runs: item values and condition codes
%% changed, clients connecting to read a snapshot, and connections killed, all at
%% once. Each change returns once the adapter has taken it, so a session after it (in
%% any linearisation PropEr finds) is told of it; what a session is told up to the
%% PONG to its first PING (the snapshot, then the changes after it, applied in order)
%% is the model's state at one moment, never a mix. A session whose connection a kill
%% ended meanwhile returns `killed', which any state allows.
-module(prop_cell_shdr_par).
-include_lib("proper/include/proper.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([set/2, raise/1, clear/1, kill_all/0, prop_parallel/1]).

-define(KEYS, [<<"prop_a">>, <<"prop_b">>]).
-define(VALUES, [<<"OPEN">>, <<"CLOSED">>, <<"UNLATCHED">>]).
-define(CODES, [<<"c1">>, <<"c2">>, <<"c3">>]).

prop_parallel(NumTests) ->
    proper:quickcheck(
      ?FORALL(Cmds, parallel_commands(?MODULE),
              begin
                  ok = prop_cell_shdr:reset(),
                  Cache = whereis(cell_shdr_cache),
                  {Seq, Par, Result} = run_parallel_commands(?MODULE, Cmds),
                  ?WHENFAIL(io:format(user, "Sequential: ~p~nParallel: ~p~nResult: ~p~n",
                                      [Seq, Par, Result]),
                            aggregate(command_names(Cmds),
                                      Result =:= ok andalso
                                      whereis(cell_shdr_cache) =:= Cache))
              end),
      [{to_file, user}, {numtests, NumTests}, {max_size, 12}]).

initial_state() ->
    prop_cell_shdr:initial_state().

command(_M) ->
    frequency([{4, {call, ?MODULE, set, [oneof(?KEYS), oneof(?VALUES)]}},
               {2, {call, ?MODULE, raise, [oneof(?CODES)]}},
               {2, {call, ?MODULE, clear, [oneof(?CODES)]}},
               {3, {call, prop_cell_shdr, session, []}},
               {1, {call, ?MODULE, kill_all, []}}]).

precondition(_M, _Call) ->
    true.

next_state(M, _Res, {call, _, set, [K, X]}) ->
    prop_cell_shdr:next_state(M, ok, {call, prop_cell_shdr, set, [K, X, []]});
next_state(M, _Res, {call, _, F, [Code]}) when F =:= raise; F =:= clear ->
    prop_cell_shdr:next_state(M, ok, {call, prop_cell_shdr, F, [Code, []]});
next_state(M, _Res, _Call) ->
    M.

postcondition(_M, {call, _, session, []}, killed) ->
    true;
postcondition(M, {call, _, session, []}, #{values := _} = Seen) ->
    prop_cell_shdr:session_matches(M, Seen);
postcondition(_M, {call, _, session, []}, _Other) ->
    false;
postcondition(_M, _Call, Res) ->
    Res =:= ok.

%% Each change returns once the adapter has taken it.
set(K, X) ->
    ok = cell_shdr_test_hal:set(prop, binary_to_atom(K), X),
    ok = cell_shdr_cache:sync().

raise(Code) ->
    ok = cell_alarms:warning(cell, Code, ["Check ", Code], ""),
    sync().

clear(Code) ->
    ok = cell_alarms:reset_warning(cell, Code),
    sync().

sync() ->
    ok = cell_alarms:sync(),
    ok = cell_shdr_cache:sync().

%% Every connection the adapter has now killed on its side.
kill_all() ->
    _ = [exit(P, kill) || P <- cell_shdr_cache:clients()],
    ok.
