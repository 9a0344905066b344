%% The cell's database: mnesia started in Databases/ of the cell root, tables created
%% once and kept, records that survive a restart, several callers at once, and clear
%% errors for a folder that cannot be used, a folder of another node name, a table of
%% other fields, mnesia running elsewhere.
-module(cell_db_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2, end_per_testcase/2]).
-export([fresh_folder/1, records_survive_a_restart/1, callers_at_once/1, table_differs/1,
         disc_only_tables/1, unusable_folder/1, other_folder/1, other_node/1]).

-define(TABLES, [{db_suite_a, [{attributes, [k, v]}]},
                 {db_suite_b, [{attributes, [k, v]}, {type, bag}]}]).

all() ->
    [fresh_folder, records_survive_a_restart, callers_at_once, table_differs,
     disc_only_tables, unusable_folder, other_folder, other_node].

init_per_suite(Config) ->
    _ = application:stop(mnesia),
    _ = application:load(cell_base),
    Config.

end_per_suite(_Config) ->
    _ = application:stop(mnesia),
    ok.

init_per_testcase(Case, Config) ->
    _ = application:stop(mnesia),
    %% The suites of an app share a priv_dir: roots of their own.
    Root = filename:join(?config(priv_dir, Config), "cell_db_" ++ atom_to_list(Case)),
    ok = application:set_env(cell_base, root, Root),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:stop(mnesia),
    ok.

fresh_folder(Config) ->
    ok = cell_db:start(),
    Dir = filename:join(?config(root, Config), "Databases"),
    ?assertEqual(Dir, mnesia:system_info(directory)),
    ?assert(filelib:is_regular(filename:join(Dir, "schema.DAT"))),
    ok = cell_db:ensure_tables(?TABLES, 10000),
    ?assertEqual(disc_copies, mnesia:table_info(db_suite_a, storage_type)),
    ?assertEqual(bag, mnesia:table_info(db_suite_b, type)),
    %% Again: nothing to do.
    ok = cell_db:start(),
    ok = cell_db:ensure_tables(?TABLES, 10000).

records_survive_a_restart(_Config) ->
    ok = cell_db:start(),
    ok = cell_db:ensure_tables(?TABLES, 10000),
    {atomic, ok} = cell_db:sync_transaction(fun() -> mnesia:write({db_suite_a, 1, one}) end),
    stopped = mnesia:stop(),
    ok = cell_db:start(),
    ok = cell_db:ensure_tables(?TABLES, 10000),
    ?assertEqual([{db_suite_a, 1, one}], mnesia:dirty_read(db_suite_a, 1)).

%% Several apps start the database at once: one creates the schema, all succeed.
callers_at_once(_Config) ->
    Self = self(),
    Start = fun() -> case cell_db:start() of
                         ok -> cell_db:ensure_tables(?TABLES, 10000);
                         E -> E
                     end
            end,
    Pids = [spawn(fun() -> Self ! {self(), Start()} end) || _ <- lists:seq(1, 6)],
    [receive {P, R} -> ?assertEqual(ok, R) after 60000 -> ct:fail(timeout) end || P <- Pids],
    ok = cell_db:ensure_tables([{other_app_table, [{attributes, [k, v]}]}], 10000),
    ok = cell_db:ensure_tables([{other_app_table, [{attributes, [k, v]}]}], 10000).

table_differs(_Config) ->
    ok = cell_db:start(),
    ok = cell_db:ensure_tables([{t1, [{attributes, [a, b]}]}], 10000),
    {error, {table_differs, t1, [a, c], [a, b]} = E} =
        cell_db:ensure_tables([{t1, [{attributes, [a, c]}]}], 10000),
    ?assertMatch({match, _}, re:run(cell_db:format_error(E), "fields \\[a,b\\]")).

%% A table that grows with the products stays on disc only.
disc_only_tables(_Config) ->
    ok = cell_db:start(),
    ok = cell_db:ensure_tables([{db_suite_big, [{attributes, [k, v]},
                                                {storage, disc_only_copies}]}], 10000),
    ?assertEqual(disc_only_copies, mnesia:table_info(db_suite_big, storage_type)),
    ok = mnesia:dirty_write({db_suite_big, 1, x}),
    ?assertEqual([{db_suite_big, 1, x}], mnesia:dirty_read(db_suite_big, 1)).

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
    {error, {other_folder, _, _} = E} = cell_db:start(),
    ?assertMatch({match, _}, re:run(cell_db:format_error(E), "not in the cell's")).

%% A database made by a node of another name: refused with the name to use, mnesia
%% stopped again; once the folder is moved aside, a new database starts.
other_node(Config) ->
    Dir = filename:join(?config(root, Config), "Databases"),
    Peer = cell_test_db:foreign(Dir),
    {error, {other_node, _, [Peer]} = E} = cell_db:start(),
    ?assertEqual(no, mnesia:system_info(is_running)),
    Text = lists:flatten(cell_db:format_error(E)),
    ?assertNotEqual(nomatch, string:find(Text, atom_to_list(Peer))),
    ?assertNotEqual(nomatch, string:find(Text, "move the folder aside")),
    ok = file:rename(Dir, Dir ++ ".old"),
    ok = cell_db:start(),
    ok = cell_db:ensure_tables(?TABLES, 10000).
