%% Unit tests and a model-based property of the variable table: who uses what, and
%% when a handle may go back to the PLC.
-module(cell_hal_ads_vars_tests).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(V, cell_hal_ads_vars).

sym() ->
    #{name => <<"MAIN.x">>, type => <<"DINT">>, data_type => 3, size => 4, comment => <<>>,
      group => 16#4040, offset => 8, flags => 0}.

life_test() ->
    P = self(),
    K = ?V:key(<<"main.X">>, int32),
    ?assertEqual({<<"MAIN.X">>, int32}, K),
    Vs0 = ?V:declare(<<"main.X">>, int32, ?V:new()),
    ?assertEqual(pending, ?V:state(K, Vs0)),
    ?assertEqual({error, {not_resolved, <<"main.X">>}}, ?V:ready(K, Vs0)),
    Vs1 = ?V:resolved(K, sym(), {handle, 7}, ?V:use(K, P, Vs0)),
    ?assertEqual({ok, {handle, 7}, 4, int32}, ?V:ready(K, Vs1)),
    %% declared again in another spelling: the same variable, the spelling remembered
    Vs1b = ?V:declare(<<"MAIN.x">>, int32, Vs1),
    ?assertEqual(?V:find(K, Vs1), ?V:find(K, Vs1b)),
    ?assertEqual(K, ?V:key_of(<<"MAIN.x">>, int32, Vs1b)),
    ?assertEqual(K, ?V:key_of(<<"Main.X">>, int32, Vs1b)),
    Vs2 = ?V:failed(K, {unknown_symbol, <<"main.X">>}, Vs1),
    ?assertEqual({error, {unknown_symbol, <<"main.X">>}}, ?V:ready(K, Vs2)),
    ?assertEqual(failed, ?V:state(K, Vs2)),
    Vs3 = ?V:reset(?V:resolved(K, sym(), {address, 16#4040, 8}, Vs2)),
    ?assertEqual(pending, ?V:state(K, Vs3)),
    ?assertEqual(1, ?V:users(K, Vs3)),
    {Vs4, unused} = ?V:unuse(K, P, Vs3),
    ?assertEqual(0, ?V:users(K, Vs4)),
    ?assertEqual(unknown, ?V:state(K, ?V:remove(K, Vs4))),
    %% its spellings go with it
    ?assertEqual(?V:new(), ?V:remove(K, ?V:remove(K, Vs4))),
    ?assertEqual({?V:new(), unknown}, ?V:unuse(K, P, ?V:new())).

bit_symbol_read_size_test() ->
    K = ?V:key(<<"b">>, bool),
    Vs = ?V:resolved(K, (sym())#{size => 0}, {handle, 1}, ?V:declare(<<"b">>, bool, ?V:new())),
    ?assertEqual({ok, {handle, 1}, 1, bool}, ?V:ready(K, Vs)).

%% The table against a model: for each key, uses per process.
refcount_test_() ->
    {timeout, 60, ?_assert(proper:quickcheck(prop_refcount(), [{to_file, user}, {numtests, 300}]))}.

command() ->
    oneof([{use, key(), user()}, {unuse, key(), user()}, {drop_user, user()}]).

key() -> oneof([{<<"A">>, int32}, {<<"B">>, int32}, {<<"A">>, bool}]).
user() -> oneof([1, 2, 3]).

prop_refcount() ->
    Pids = list_to_tuple([spawn(fun() -> ok end) || _ <- [1, 2, 3]]),
    ?FORALL(Commands, list(command()),
            begin
                Vs0 = lists:foldl(fun({N, T}, Acc) -> ?V:declare(N, T, Acc) end, ?V:new(),
                                  [{<<"A">>, int32}, {<<"B">>, int32}, {<<"A">>, bool}]),
                run(Commands, Pids, Vs0, #{})
            end).

run([], _, _, _) ->
    true;
run([{use, {N, T}, U} | Cs], Pids, Vs, Model) ->
    K = ?V:key(N, T),
    Model1 = maps:update_with({K, U}, fun(C) -> C + 1 end, 1, Model),
    Vs1 = ?V:use(K, element(U, Pids), Vs),
    agree(K, Vs1, Model1) andalso run(Cs, Pids, Vs1, Model1);
run([{unuse, {N, T}, U} | Cs], Pids, Vs, Model) ->
    K = ?V:key(N, T),
    Model1 = case maps:find({K, U}, Model) of
                 {ok, 1} -> maps:remove({K, U}, Model);
                 {ok, C} -> Model#{{K, U} := C - 1};
                 error -> Model
             end,
    {Vs1, Said} = ?V:unuse(K, element(U, Pids), Vs),
    Expected = case total(K, Model1) of 0 -> unused; _ -> used end,
    Said =:= Expected andalso agree(K, Vs1, Model1) andalso run(Cs, Pids, Vs1, Model1);
run([{drop_user, U} | Cs], Pids, Vs, Model) ->
    Had = lists:usort([K || {K, V} <- maps:keys(Model), V =:= U]),
    Model1 = maps:filter(fun({_, V}, _) -> V =/= U end, Model),
    {Vs1, Unused} = ?V:drop_user(element(U, Pids), Vs),
    lists:sort(Unused) =:= [K || K <- Had, total(K, Model1) =:= 0]
        andalso lists:all(fun(K) -> agree(K, Vs1, Model1) end, ?V:keys(Vs1))
        andalso run(Cs, Pids, Vs1, Model1).

total(K, Model) ->
    lists:sum([C || {{K1, _}, C} <- maps:to_list(Model), K1 =:= K]).

agree(K, Vs, Model) ->
    ?V:users(K, Vs) =:= total(K, Model).
