%% Unit tests of the steps of resolving variables: the requests for the PLC and what
%% its answers mean, then the answers into the handle cache.
-module(cell_hal_ads_resolve_tests).
-include_lib("eunit/include/eunit.hrl").

-define(R, cell_hal_ads_resolve).
-define(MODE, #{sum => true, max_sum => 500}).

sym(Name, Type, Size) ->
    #{name => Name, type => Type, data_type => 3, size => Size, comment => <<>>,
      group => 16#4040, offset => 8, flags => 0}.

item(Name, Type) ->
    {cell_hal_ads_vars:key(Name, Type), Name, Type}.

info_requests_test() ->
    Items = [item(<<"MAIN.a">>, int32)],
    {[{read_write, 16#F009, 0, _, <<"MAIN.a", 0>>}], Assemble} = ?R:info_requests(Items, ?MODE),
    [{error, {ads_error, 16#710, _}} = E] = Assemble([{error, cell_hal_ads_codec:ads_error(16#710)}]),
    ?assertEqual([{hd(Items), {error, {unknown_symbol, <<"MAIN.a">>}}}], ?R:infos(Items, [E])),
    ?assertEqual([{hd(Items), {error, timeout}}], ?R:infos(Items, [{error, timeout}])),
    ?assertMatch([{_, {error, {symbol_error, <<"MAIN.a">>, _}}}],
                 ?R:infos(Items, [{ok, <<1, 2, 3>>}])).

check_test() ->
    I = item(<<"MAIN.a">>, int32),
    ?assertMatch({ok, _}, ?R:check(I, {ok, sym(<<"MAIN.a">>, <<"DINT">>, 4)})),
    ?assertMatch({error, {type_mismatch, <<"MAIN.a">>, _}},
                 ?R:check(I, {ok, sym(<<"MAIN.a">>, <<"BOOL">>, 1)})),
    ?assertEqual({error, x}, ?R:check(I, {error, x})),
    ?assertEqual({error, {symbol_table, timeout}}, ?R:lookup_wild(<<"*a">>, {error, timeout})).

handles_test() ->
    A = item(<<"MAIN.a">>, int32),
    B = item(<<"MAIN.b">>, int32),
    C = item(<<"*c">>, int32),
    SA = sym(<<"MAIN.a">>, <<"DINT">>, 4),
    SC = sym(<<"IO.full.c">>, <<"DINT">>, 4),
    Ok = [{A, SA}, {C, SC}],
    {[{read_write, 16#F082, 2, _, _}], _} = ?R:handle_requests(Ok, ?MODE),
    {[{read_write, 16#F003, 0, 4, NameA}, {read_write, 16#F003, 0, 4, NameC}], Assemble} =
        ?R:handle_requests(Ok, #{sum => false, max_sum => 500}),
    %% a "*" name is asked for by the full name it matched
    ?assertEqual([<<"MAIN.a", 0>>, <<"IO.full.c", 0>>], [iolist_to_binary(N) || N <- [NameA, NameC]]),
    Results = [{ok, <<7:32/little>>}, {ok, <<1>>}],
    Checked = [{A, {ok, SA}}, {B, {error, {unknown_symbol, <<"MAIN.b">>}}}, {C, {ok, SC}}],
    ?assertEqual([{element(1, A), {ok, SA, {handle, 7}}},
                  {element(1, C), {error, {symbol_error, <<"*c">>, {bad_response, handle_size}}}},
                  {element(1, B), {error, {unknown_symbol, <<"MAIN.b">>}}}],
                 ?R:handles(Ok, Assemble(Results), Checked)),
    ?assertEqual([{element(1, A), {ok, SA, {address, 16#4040, 8}}}],
                 ?R:by_address([{A, {ok, SA}}])),
    ?assertEqual([{write, 16#F006, 0, <<7:32/little>>}],
                 ?R:release_requests([{handle, 7}, {address, 1, 2}], ?MODE)).

into_the_cache_test() ->
    P = self(),
    {KA, NA, TA} = item(<<"MAIN.a">>, int32),
    {KB, NB, TB} = item(<<"MAIN.b">>, int32),
    SA = sym(<<"MAIN.a">>, <<"DINT">>, 4),
    Names = #{KA => {NA, TA}, KB => {NB, TB}},
    {V1, [], [{NB, TB, {unknown_symbol, NB}}]} =
        ?R:registered([{KA, {ok, SA, {handle, 7}}}, {KB, {error, {unknown_symbol, NB}}}],
                      Names, cell_hal_ads_vars:new()),
    ?assertEqual({ok, {handle, 7}, 4, int32}, cell_hal_ads_vars:ready(KA, V1)),
    %% registered by another caller meanwhile: the second handle goes back
    {V1, [{handle, 8}], []} = ?R:registered([{KA, {ok, SA, {handle, 8}}}], Names, V1),
    ?assertEqual({not_resolved, NB}, ?R:find_error(KB, [], Names)),
    ?assertEqual(x, ?R:find_error(KB, [{KB, {error, x}}], Names)),
    %% resolved again after a reconnect: a released variable's new handle goes back
    V2 = cell_hal_ads_vars:use(KA, P, V1),
    {V3, [{handle, 9}], [{NA, TA, gone}]} =
        ?R:refreshed([{KA, {error, gone}}, {KB, {ok, SA, {handle, 9}}}],
                     cell_hal_ads_vars:reset(V2)),
    ?assertEqual({error, gone}, cell_hal_ads_vars:ready(KA, V3)).
