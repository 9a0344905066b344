%% The inspection block's traceability in the cell's database: its tables created in
%% Databases/ and kept, records that survive a restart, several blocks starting the
%% database at once, and overrides logged against the inspection they override.
-module(cell_inspect_db_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([fresh_folder/1, records_survive_a_restart/1, callers_at_once/1,
         overrides_find_their_inspection/1]).

all() ->
    [fresh_folder, records_survive_a_restart, callers_at_once,
     overrides_find_their_inspection].

%% One database for the suite, in a root of its own; each case uses serials of its own.
init_per_suite(Config) ->
    _ = application:stop(mnesia),
    _ = application:load(cell_base),
    %% The suites of an app share a priv_dir: a root of its own.
    Root = filename:join(?config(priv_dir, Config), "inspect_db_root"),
    ok = application:set_env(cell_base, root, Root),
    [{root, Root} | Config].

end_per_suite(_Config) ->
    application:stop(mnesia).

fresh_folder(Config) ->
    ok = cell_inspect_db:start(),
    Dir = filename:join(?config(root, Config), "Databases"),
    ?assertEqual(Dir, mnesia:system_info(directory)),
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

%% Several blocks start the database at once, as after a restart: all succeed.
callers_at_once(_Config) ->
    stopped = mnesia:stop(),
    Self = self(),
    Pids = [spawn(fun() -> Self ! {self(), cell_inspect_db:start()} end) || _ <- lists:seq(1, 6)],
    [receive {P, R} -> ?assertEqual(ok, R) after 60000 -> ct:fail(timeout) end || P <- Pids].

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
