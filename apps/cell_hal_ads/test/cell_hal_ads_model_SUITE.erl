%% The state-machine model of an ADS connection (prop_cell_hal_ads_conn) against the
%% suite's fake TwinCAT PLC: 1000 runs one command after the other, 1000 with commands
%% racing in parallel.
-module(cell_hal_ads_model_SUITE).
-include_lib("common_test/include/ct.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1, init_per_testcase/2,
         end_per_testcase/2]).
-export([sequential/1, parallel/1]).

-define(RUNS, 1000).

all() ->
    [sequential, parallel].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_base),
    %% a PLC task of 1 ms: a notification brings its first value a millisecond after
    %% it is added, not ten
    case cell_hal_ads_peer:start("fake_plc.py", ["--task-ms", "1"]) of
        {ok, Fake, {ready, Port, _}} ->
            [{apps, Apps}, {fake, Fake}, {port, Port} | Config];
        {error, Reason} ->
            ct:fail("the fake PLC did not start: ~tp", [Reason])
    end.

end_per_suite(Config) ->
    ok = cell_hal_ads_peer:stop(?config(fake, Config)),
    Config.

init_per_testcase(_Case, Config) ->
    ok = prop_cell_hal_ads_conn:setup(#{fake => ?config(fake, Config),
                                        port => ?config(port, Config)}),
    Config.

end_per_testcase(_Case, _Config) ->
    prop_cell_hal_ads_conn:teardown().

sequential(_Config) ->
    check(prop_cell_hal_ads_conn:prop_sequential()).

parallel(_Config) ->
    check(prop_cell_hal_ads_conn:prop_parallel()).

check(Property) ->
    Started = erlang:monotonic_time(millisecond),
    Passed = proper:quickcheck(Property, [{to_file, user}, {numtests, ?RUNS}]),
    ct:log("~b runs in ~b ms", [?RUNS, erlang:monotonic_time(millisecond) - Started]),
    true = Passed.
