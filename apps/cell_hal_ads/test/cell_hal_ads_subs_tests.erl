%% Unit tests of the subscription table: notifications attached and forgotten as the
%% connection comes and goes, and device notifications decoded for their subscribers.
-module(cell_hal_ads_subs_tests).
-include_lib("eunit/include/eunit.hrl").

-define(S, cell_hal_ads_subs).
-define(FILETIME_UNIX_EPOCH, 116444736000000000).

sub(Pid, Name, Type) ->
    #{pid => Pid, var => {Name, Type}, key => cell_hal_ads_vars:key(Name, Type),
      opts => #{mode => on_change, cycle => 100000, max_delay => 0}}.

%% A notification payload: stamps of `{FileTime, [{Note, Bytes}]}'.
payload(Stamps) ->
    Body = iolist_to_binary(
             [<<(length(Stamps)):32/little>>
              | [[<<T:64/little, (length(Ss)):32/little>>
                  | [<<N:32/little, (byte_size(B)):32/little, B/binary>> || {N, B} <- Ss]]
                 || {T, Ss} <- Stamps]]),
    <<(byte_size(Body)):32/little, Body/binary>>.

life_test() ->
    P = self(),
    Q = spawn(fun() -> ok end),
    R1 = make_ref(), R2 = make_ref(), R3 = make_ref(),
    T0 = ?S:watch_version(1, ?S:new()),
    T1 = ?S:add(R1, sub(P, <<"MAIN.a">>, int32), 10, T0),
    T2 = ?S:add(R2, sub(P, <<"MAIN.b">>, bool), 11, T1),
    T3 = ?S:add(R3, sub(Q, <<"MAIN.a">>, int32), 12, T2),
    ?assertEqual(3, ?S:count(T3)),
    ?assertEqual([1, 10, 11, 12], lists:sort(?S:notes(T3))),
    ?assertEqual([R1], ?S:owned([R1, R3, make_ref()], P, T3)),
    ?assertEqual([R3], ?S:of_pid(Q, T3)),
    %% ended: its notification is the caller's to delete
    {#{pid := P}, [11], T4} = ?S:take(R2, T3),
    ?assertEqual([1, 10, 12], lists:sort(?S:notes(T4))),
    %% a program change: the subscriptions' notifications go, the version's stays
    {Gone, T5} = ?S:refresh(T4),
    ?assertEqual([10, 12], lists:sort(Gone)),
    ?assertEqual([1], ?S:notes(T5)),
    ?assertEqual(2, ?S:count(T5)),
    %% served again; one that ended meanwhile is gone
    {ok, T6} = ?S:attach(R1, 20, T5),
    ?assertEqual(gone, ?S:attach(R2, 21, T6)),
    {_, [], T7} = ?S:take(R3, T6),
    ?assertEqual([1, 20], lists:sort(?S:notes(T7))),
    ?assertEqual([R1], [R || {R, _} <- ?S:to_list(T7)]).

note_request_test() ->
    K = cell_hal_ads_vars:key(<<"MAIN.a">>, int32),
    Sym = #{name => <<"MAIN.a">>, type => <<"DINT">>, data_type => 3, size => 4,
            comment => <<>>, group => 16#4040, offset => 8, flags => 0},
    Vars = cell_hal_ads_vars:resolved(K, Sym, {handle, 7},
                                      cell_hal_ads_vars:declare(<<"MAIN.a">>, int32,
                                                                cell_hal_ads_vars:new())),
    Sub = (sub(self(), <<"MAIN.a">>, int32))#{opts => #{mode => cyclic, cycle => 5,
                                                         max_delay => 3}},
    ?assertEqual({add_notification, 16#F005, 7, 4, cyclic, 3, 5},
                 ?S:note_request(Sub, Vars)).

samples_test() ->
    P = self(),
    R1 = make_ref(), R2 = make_ref(),
    T = ?S:add(R2, sub(P, <<"MAIN.b">>, bool), 11,
               ?S:add(R1, sub(P, <<"MAIN.a">>, int32), 10, ?S:watch_version(1, ?S:new()))),
    T1 = ?FILETIME_UNIX_EPOCH + 10, T2 = ?FILETIME_UNIX_EPOCH + 20,
    Payload = payload([{T1, [{10, <<5:32/little>>}, {11, <<1>>}, {99, <<0>>}]},
                       {T2, [{10, <<6:32/little>>}, {1, <<7>>}, {11, <<1, 2, 3>>}]}]),
    {ok, Deliveries, Versions, Dropped} = ?S:samples(Payload, T),
    %% in the PLC's order, stamps in ns; a deleted notification's sample ignored
    ?assertEqual(2, length(Deliveries)),
    ?assertEqual({P, R1, [{1000, 5}, {2000, 6}]}, lists:keyfind(R1, 2, Deliveries)),
    ?assertEqual({P, R2, [{1000, true}]}, lists:keyfind(R2, 2, Deliveries)),
    ?assertEqual([7], Versions),
    ?assertMatch([{<<"MAIN.b">>, _}], Dropped),
    ?assertMatch({error, _}, ?S:samples(<<1, 2>>, T)).
