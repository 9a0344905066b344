%% Settings schemas: defaults, validation (both sides of every limit, wrong types,
%% unknown keys), JSON round trips and differences; PropEr properties over random
%% objects and random values in and out of range.
-module(cell_settings_schema_tests).

-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(R, cell_test_robot_settings).
-define(A, cell_test_axis_settings).
-define(S, cell_settings_schema).

%%====================================================================
%% Examples
%%====================================================================

defaults_test() ->
    D = ?S:defaults(?R),
    ?assertMatch(#{enabled := true, speed := 100.0, retries := 3, tool := none,
                   waypoints := [], axes := [], camera := undefined, offset := undefined},
                 D),
    %% A nested object's declared default overrides some of its fields only.
    ?assertEqual(#{id => z, speed => 10, low => -100.0, high => 100.0}, maps:get(home, D)),
    ?assertEqual(ok, ?S:check_schema(?R)),
    ?assertEqual(ok, ?S:check_schema(cell_machine_settings)).

machine_defaults_test() ->
    ?assertMatch(#{simulation_mode := true, dual_lane := false, log_level := brief,
                   speed_override := 50, cell_name := <<"cell">>, ads_ams_net_id := <<>>},
                 ?S:defaults(cell_machine_settings)).

limits_test_() ->
    V = fun(In) -> ?S:validate(?R, In) end,
    Err = fun(Path, Why) -> {error, {invalid, Path, Why}} end,
    [%% both sides of an integer range
     ?_assertMatch({ok, #{retries := 0}}, V(#{retries => 0})),
     ?_assertMatch({ok, #{retries := 10}}, V(#{retries => 10})),
     ?_assertEqual(Err([retries], {out_of_range, -1, 0, 10}), V(#{retries => -1})),
     ?_assertEqual(Err([retries], {out_of_range, 11, 0, 10}), V(#{retries => 11})),
     ?_assertEqual(Err([retries], {wrong_type, integer, 1.0}), V(#{retries => 1.0})),
     %% floats: integers are taken as floats; bounds inclusive
     ?_assertMatch({ok, #{speed := 2500.0}}, V(#{speed => 2500})),
     ?_assertMatch({ok, #{speed := 0.5}}, V(#{speed => 0.5})),
     ?_assertEqual(Err([speed], {out_of_range, 0.49, 0.5, 2500.0}), V(#{speed => 0.49})),
     ?_assertEqual(Err([speed], {out_of_range, 2500.5, 0.5, 2500.0}), V(#{speed => 2500.5})),
     ?_assertEqual(Err([speed], {wrong_type, float, <<"fast">>}), V(#{speed => <<"fast">>})),
     %% strings: length in characters, not bytes
     ?_assertMatch({ok, #{label := <<"ÄÖÜäöüßé"/utf8>>}}, V(#{label => <<"ÄÖÜäöüßé"/utf8>>})),
     ?_assertEqual(Err([label], {too_long, 8}), V(#{label => <<"123456789">>})),
     ?_assertEqual(Err([label], not_utf8), V(#{label => <<255, 0>>})),
     ?_assertEqual(Err([label], {wrong_type, string, "R2"}), V(#{label => "R2"})),
     ?_assertEqual(Err([note], {too_long, 1024}), V(#{note => binary:copy(<<"x">>, 1025)})),
     %% enums: atoms from code, binaries from files, never new atoms
     ?_assertMatch({ok, #{tool := vacuum}}, V(#{tool => vacuum})),
     ?_assertMatch({ok, #{tool := gripper}}, V(#{<<"tool">> => <<"gripper">>})),
     ?_assertEqual(Err([tool], {not_one_of, <<"laser">>, [gripper, vacuum, none]}),
                   V(#{tool => <<"laser">>})),
     ?_assertEqual(Err([tool], {wrong_type, enum, 3}), V(#{tool => 3})),
     %% lists: element limits name the position (1-based), length limit
     ?_assertMatch({ok, #{waypoints := [1, 2, 3, 4, 5]}}, V(#{waypoints => [1, 2, 3, 4, 5]})),
     ?_assertEqual(Err([waypoints], {too_long, 5}), V(#{waypoints => [1, 2, 3, 4, 5, 6]})),
     ?_assertEqual(Err([waypoints, 2], {out_of_range, 1001, -1000, 1000}),
                   V(#{waypoints => [1, 1001]})),
     ?_assertEqual(Err([axes, 2, speed], {out_of_range, 0, 1, 100}),
                   V(#{axes => [#{}, #{speed => 0}]})),
     %% nested objects, unknown and duplicate keys, cross-field checks
     ?_assertEqual(Err([home, <<"sped">>], unknown_field), V(#{home => #{<<"sped">> => 1}})),
     ?_assertEqual(Err([<<"colour">>], unknown_field), V(#{<<"colour">> => 1})),
     ?_assertEqual(Err([retries], duplicate_field), V(#{retries => 1, <<"retries">> => 2})),
     ?_assertEqual(Err([home, high], {below_low, 0.0, 1.0}),
                   V(#{home => #{low => 1.0, high => 0.0}})),
     ?_assertEqual(Err([], {wrong_type, object, [1]}), V([1])),
     ?_assertEqual(Err([home], {wrong_type, object, 7}), V(#{home => 7})),
     %% optional values
     ?_assertMatch({ok, #{offset := undefined}}, V(#{offset => null})),
     ?_assertMatch({ok, #{offset := -10.0}}, V(#{offset => -10})),
     ?_assertMatch({ok, #{camera := #{id := y, speed := 10}}}, V(#{camera => #{id => y}})),
     %% a retired field is accepted and dropped
     ?_assertEqual(V(#{}), V(#{<<"old_mode">> => <<"fast">>}))].

machine_check_test_() ->
    V = fun(Id) -> ?S:validate(cell_machine_settings, #{ads_ams_net_id => Id}) end,
    [?_assertMatch({ok, _}, V(<<"5.18.40.112.1.1">>)),
     ?_assertMatch({ok, _}, V(<<"255.255.255.255.255.255">>)),
     ?_assertMatch({error, {invalid, [ads_ams_net_id], {not_an_ams_net_id, _}}},
                   V(<<"256.1.1.1.1.1">>)),
     ?_assertMatch({error, {invalid, [ads_ams_net_id], _}}, V(<<"5.18.40.112.1">>)),
     ?_assertMatch({error, {invalid, [ads_ams_net_id], _}}, V(<<"a.b.c.d.e.f">>)),
     ?_assertMatch({error, {invalid, [speed_override], {out_of_range, 101, 1, 100}}},
                   ?S:validate(cell_machine_settings, #{speed_override => 101})),
     ?_assertMatch({error, {invalid, [log_level], {not_one_of, <<"loud">>, _}}},
                   ?S:validate(cell_machine_settings, #{<<"log_level">> => <<"loud">>}))].

merge_test() ->
    {ok, Base} = ?S:validate(?R, #{retries => 7, home => #{speed => 50}}),
    {ok, M} = ?S:validate(?R, #{home => #{id => x}}, Base),
    ?assertEqual(7, maps:get(retries, M)),
    ?assertEqual(#{id => x, speed => 50, low => -100.0, high => 100.0}, maps:get(home, M)).

json_test() ->
    {ok, Obj} = ?S:validate(?R, #{note => <<"a \"quoted\" line\nand ünïcode"/utf8>>,
                                  axes => [#{id => y}], offset => 2.5}),
    Json = ?S:to_json(?R, Obj),
    %% one field a line, in declaration order, final newline
    Keys = [K || {match, [K]} <- [re:run(L, "^  \"([a-z_]+)\":", [{capture, all_but_first, binary}])
                                  || L <- binary:split(Json, <<"\n">>, [global])]],
    ?assertEqual([atom_to_binary(N, utf8) || #{name := N} <- ?R:fields()], Keys),
    ?assertEqual($\n, binary:last(Json)),
    ?assertEqual({ok, Obj}, ?S:from_json(?R, Json)),
    %% a file written before a field existed loads with its default
    ?assertMatch({ok, #{retries := 3, tool := vacuum}},
                 ?S:from_json(?R, <<"{\"tool\": \"vacuum\"}">>)),
    ?assertEqual({error, not_json}, ?S:from_json(?R, <<"{\"tool\": ">>)),
    ?assertEqual({error, not_json}, ?S:from_json(?R, <<>>)),
    ?assertEqual({error, {invalid, [<<"tool">>], duplicate_field}},
                 ?S:from_json(?R, <<"{\"tool\": \"none\", \"tool\": \"vacuum\"}">>)),
    ?assertEqual({error, {invalid, [], {wrong_type, object, [1, 2]}}},
                 ?S:from_json(?R, <<"[1, 2]">>)).

diff_and_messages_test() ->
    {ok, A} = ?S:validate(?R, #{axes => [#{}, #{}], tool => vacuum}),
    {ok, B} = ?S:validate(?R, #{axes => [#{}, #{speed => 20}], tool => gripper, retries => 4}),
    Changes = ?S:diff(?R, A, B),
    ?assertEqual([#{path => [retries], from => 3, to => 4},
                  #{path => [tool], from => vacuum, to => gripper},
                  #{path => [axes, 2, speed], from => 10, to => 20}], Changes),
    ?assertEqual([<<"retries: 3 -> 4">>, <<"tool: vacuum -> gripper">>,
                  <<"axes[2].speed: 10 -> 20">>], [?S:format_change(C) || C <- Changes]),
    ?assertEqual([], ?S:diff(?R, A, A)),
    ?assertEqual(<<"speed_override: 150 is out of range 1..100">>,
                 ?S:format_error({invalid, [speed_override], {out_of_range, 150, 1, 100}})),
    ?assertEqual(<<"home.sped: unknown field">>,
                 ?S:format_error({invalid, [home, <<"sped">>], unknown_field})),
    ?assertEqual({ok, 10}, ?S:get_path(A, [axes, 2, speed])),
    ?assertEqual(error, ?S:get_path(A, [axes, 3, speed])).

%% A secret field's change is listed, never its values (they go to the log and panel).
secret_fields_are_hidden_test() ->
    V = cell_test_secret_settings,
    ?assertEqual(ok, ?S:check_schema(V)),
    {ok, A} = ?S:validate(V, #{key => <<"s3cr3t-one">>}),
    {ok, B} = ?S:validate(V, #{key => <<"s3cr3t-two">>, label => <<"gate">>}),
    Changes = ?S:diff(V, A, B),
    ?assertEqual([#{path => [label], from => <<"door">>, to => <<"gate">>},
                  #{path => [key], from => <<"(hidden)">>, to => <<"(hidden)">>}], Changes),
    Text = iolist_to_binary([?S:format_change(C) || C <- Changes]),
    ?assertEqual(nomatch, binary:match(Text, <<"s3cr3t">>)),
    %% Unchanged, it is not listed at all.
    ?assertEqual([], ?S:diff(V, B, B)).

bad_schema_test_() ->
    [?_assertMatch({error, {bad_schema, cell_test_bad_settings, _}},
                   ?S:check_schema(cell_test_bad_settings)),
     ?_assertMatch({error, {bad_schema, no_such_module, {no_fields, no_such_module}}},
                   ?S:check_schema(no_such_module))].

%%====================================================================
%% Properties
%%====================================================================

roundtrip_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_json_roundtrip(),
                                              [{to_file, user}, {numtests, 300}]))}.

field_validation_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_field_validation(),
                                              [{to_file, user}, {numtests, 1000}]))}.

unknown_key_test_() ->
    {timeout, 120, ?_assert(proper:quickcheck(prop_unknown_key(),
                                              [{to_file, user}, {numtests, 200}]))}.

%% Any valid object survives the file: written, read back, equal.
prop_json_roundtrip() ->
    ?FORALL(Obj, cell_settings_gen:object(?R),
            begin
                {ok, Valid} = ?S:validate(?R, Obj),
                ?S:from_json(?R, ?S:to_json(?R, Valid)) =:= {ok, Valid}
            end).

%% A value for one field is accepted exactly when it is of the field's type and in
%% its limits; when refused, the error names the field and what is wrong; when
%% accepted, only that field changed.
prop_field_validation() ->
    Scalars = [F || #{type := T} = F <- ?R:fields(), scalar(T)],
    ?FORALL({#{name := N, type := T}, KeyAsBinary}, {elements(Scalars), boolean()},
            ?FORALL({Verdict, V}, cell_settings_gen:value_case(T),
                    begin
                        Key = case KeyAsBinary of
                                  true -> atom_to_binary(N, utf8);
                                  false -> N
                              end,
                        Result = ?S:validate(?R, #{Key => V}),
                        Defaults = ?S:defaults(?R),
                        ?WHENFAIL(io:format(user, "~p ~p -> ~p~n", [N, V, Result]),
                                  case {Verdict, Result} of
                                      {ok, {ok, M}} ->
                                          maps:remove(N, M) =:= maps:remove(N, Defaults)
                                              andalso same_value(maps:get(N, M), V);
                                      {Tag, {error, {invalid, [N], Why}}} ->
                                          Tag =:= why_tag(Why);
                                      _ ->
                                          false
                                  end)
                    end)).

%% A key the schema does not declare is refused wherever it appears, by its name.
prop_unknown_key() ->
    Names = [atom_to_binary(N, utf8) || #{name := N} <- ?R:fields() ++ ?A:fields()]
        ++ [<<"old_mode">>],
    ?FORALL({Key, Where}, {?SUCHTHAT(K, proper_unicode:utf8(12), not lists:member(K, Names)),
                           elements([top, home, axis])},
            begin
                {In, Path} = case Where of
                                 top -> {#{Key => 1}, [Key]};
                                 home -> {#{home => #{Key => true}}, [home, Key]};
                                 axis -> {#{axes => [#{}, #{}, #{Key => <<"x">>}]},
                                          [axes, 3, Key]}
                             end,
                ?S:validate(?R, In) =:= {error, {invalid, Path, unknown_field}}
            end).

scalar({list, _, _}) -> false;
scalar({list, _}) -> false;
scalar({object, _}) -> false;
scalar({optional, {object, _}}) -> false;
scalar(_) -> true.

same_value(Got, V) when is_float(Got), is_number(V) -> Got == V;
same_value(Got, V) when is_atom(Got), is_binary(V) -> atom_to_binary(Got, utf8) =:= V;
same_value(undefined, null) -> true;
same_value(Got, V) -> Got =:= V.

why_tag(W) when is_atom(W) -> W;
why_tag(W) when is_tuple(W) -> element(1, W).
