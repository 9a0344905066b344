%% The cell's database: mnesia started in Databases/ of the cell root, tables created
%% once and kept, records that survive a restart, clear errors for a folder that
%% cannot be used, and the traceability queries of the inspection block.
-module(cell_db_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2, end_per_testcase/2]).
-export([fresh_folder/1, records_survive_a_restart/1, callers_at_once/1, table_differs/1,
         unusable_folder/1, other_folder/1, overrides_find_their_inspection/1]).

all() ->
    [fresh_folder, records_survive_a_restart, callers_at_once, table_differs, unusable_folder,
     other_folder, overrides_find_their_inspection].

init_per_suite(Config) ->
    _ = application:stop(mnesia),
    _ = application:load(cell_base),
    Config.

end_per_suite(_Config) ->
    _ = application:stop(mnesia),
    ok.

init_per_testcase(Case, Config) ->
    _ = application:stop(mnesia),
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
    ok = application:set_env(cell_base, root, Root),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:stop(mnesia),
    ok.

fresh_folder(Config) ->
    ok = cell_inspect_db:start(),
    Dir = filename:join(?config(root, Config), "Databases"),
    ?assertEqual(Dir, mnesia:system_info(directory)),
    ?assert(filelib:is_regular(filename:join(Dir, "schema.DAT"))),
    ?assertEqual(disc_copies, mnesia:table_info(cell_inspect_inspection, storage_type)),
    %% Again: nothing to do.
    ok = cell_inspect_db:start().

records_survive_a_restart(_Config) ->
    ok = cell_inspect_db:start(),
    {ok, _} = cell_inspect_db:record_inspection(#{block => b1, point => <<"P">>,
                                                  serial => <<"S-1">>, result => pass,
                                                  text => <<"ok">>, image => <<"img">>}),
    stopped = mnesia:stop(),
    ok = cell_inspect_db:start(),
    {ok, #{inspections := [#{point := <<"P">>, result := pass, text := <<"ok">>,
                             image := <<"img">>}]}} = cell_inspect_db:by_serial(<<"S-1">>).

%% Several apps start the database at once: one creates the schema, all succeed.
callers_at_once(_Config) ->
    Self = self(),
    Pids = [spawn(fun() -> Self ! {self(), cell_inspect_db:start()} end) || _ <- lists:seq(1, 6)],
    [receive {P, R} -> ?assertEqual(ok, R) after 60000 -> ct:fail(timeout) end || P <- Pids],
    ok = cell_db:ensure_tables([{other_app_table, [{attributes, [k, v]}]}], 10000),
    ok = cell_db:ensure_tables([{other_app_table, [{attributes, [k, v]}]}], 10000).

table_differs(_Config) ->
    ok = cell_db:start(),
    ok = cell_db:ensure_tables([{t1, [{attributes, [a, b]}]}], 10000),
    {error, {table_differs, t1, [a, c], [a, b]} = E} =
        cell_db:ensure_tables([{t1, [{attributes, [a, c]}]}], 10000),
    ?assertMatch({match, _}, re:run(cell_db:format_error(E), "fields \\[a,b\\]")).

%% Databases/ is a file: a clear error, mnesia not started.
unusable_folder(Config) ->
    Root = ?config(root, Config),
    ok = filelib:ensure_dir(filename:join(Root, "x")),
    ok = file:write_file(filename:join(Root, "Databases"), <<"not a folder">>),
    {error, {unusable_folder, _, _} = E} = cell_db:start(),
    ?assertEqual(no, mnesia:system_info(is_running)),
    ?assertMatch({match, _}, re:run(cell_db:format_error(E), "cannot be written")).

%% mnesia runs already in another folder: refused, not silently used.
other_folder(Config) ->
    ok = cell_db:start(),
    ok = application:set_env(cell_base, root, ?config(root, Config) ++ "-other"),
    {error, {other_folder, _, _}} = cell_db:start().

%% An override is logged against the latest result of its block for its point and
%% serial; never without a serial, never against another block's or an error.
overrides_find_their_inspection(_Config) ->
    ok = cell_inspect_db:start(),
    R = fun(B, P, S, Res) ->
                {ok, _} = cell_inspect_db:record_inspection(#{block => B, point => P,
                                                              serial => S, result => Res})
        end,
    R(b1, <<"P1">>, <<"S">>, fail),
    R(b2, <<"P2">>, <<"S">>, pass),
    R(b1, <<"P3">>, <<"S">>, error),
    Ov = fun(B, P, S) -> cell_inspect_db:log_override(#{block => B, point => P, serial => S,
                                                        employee => <<"E">>}) end,
    ?assertMatch({ok, _}, Ov(b1, <<"P1">>, <<"S">>)),
    ?assertEqual(not_found, Ov(b1, <<"P2">>, <<"S">>)),
    ?assertEqual(not_found, Ov(b1, <<"P3">>, <<"S">>)),
    ?assertEqual(not_found, Ov(b1, <<"P1">>, <<>>)),
    {ok, #{inspections := Is, overrides := [#{point := <<"P1">>, inspection := Of}]}} =
        cell_inspect_db:by_serial(<<"S">>),
    [#{id := Of}] = [I || #{point := <<"P1">>} = I <- Is].
