%% The statistics when their database cannot be used (here: a database of another
%% node name in Databases/): the cell runs all the same, the log says why in words,
%% what happens is counted and recorded in memory, and once the folder is moved aside
%% the statistics start an empty database and write what they kept.
-module(cell_stats_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_testcase/2, end_per_testcase/2]).
-export([database_unusable_then_back/1]).

-define(RETRY_WAIT_MS, 30000).

all() ->
    [database_unusable_then_back].

init_per_testcase(_Case, Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    %% The suites of an app share a priv_dir: a root of its own.
    Root = filename:join(?config(priv_dir, Config), "cell_stats_root"),
    _ = application:load(cell_base),
    _ = application:load(cell),
    ok = application:set_env(cell_base, root, Root),
    {ok, _} = application:ensure_all_started(cell_base),
    ok = application:set_env(cell, cell_spec, #{name => <<"stats suite">>, tasks => []}),
    [{root, Root} | Config].

end_per_testcase(_Case, _Config) ->
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    ok = application:unset_env(cell, cell_spec),
    ok.

database_unusable_then_back(Config) ->
    Databases = filename:join(?config(root, Config), "Databases"),
    Peer = cell_test_db:foreign(Databases),
    ok = cell_log:subscribe(),
    {ok, _} = application:ensure_all_started(cell),
    Why = await_log(<<"statistics: the database cannot be opened">>),
    ?assertNotEqual(nomatch, binary:match(Why, atom_to_binary(Peer))),
    ?assertNotEqual(nomatch, binary:match(Why, <<"move the folder aside">>)),
    ?assertNotEqual(nomatch, binary:match(Why, <<"counting goes on in memory">>)),
    ?assertEqual({error, database_closed}, cell_stats:flush()),
    %% A record made meanwhile is kept for the database.
    ok = cell_stats:record(<<"S-1">>, measured, #{width => 12}),
    %% The folder moved aside: the statistics start a new database at their next try.
    ok = file:rename(Databases, Databases ++ ".old"),
    _ = await_log(<<"database table cell_trace_event created">>),
    ok = cell_stats:flush(),
    {ok, #{events := [#{event := measured, detail := #{width := 12}}]}} =
        cell_stats:product(<<"S-1">>).

%% The text of the first task log line that begins with `Prefix'.
await_log(Prefix) ->
    receive
        {cell_log, #{text := Text}} ->
            case binary:longest_common_prefix([Text, Prefix]) =:= byte_size(Prefix) of
                true -> Text;
                false -> await_log(Prefix)
            end
    after ?RETRY_WAIT_MS ->
        ct:fail({no_log_line, Prefix})
    end.
