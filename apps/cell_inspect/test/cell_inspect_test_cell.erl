%% The cell an inspection suite runs its blocks in, and what the suites wait for from
%% the simulated cameras.
-module(cell_inspect_test_cell).
-include_lib("common_test/include/ct.hrl").
-include("cell_inspect_suite.hrl").

-export([start/3, stop/1, block_settings/1, await_cam/2, request_seen/1, message_seen/1]).

%% @doc Starts the cell (without tasks, logging quietly) on a root folder of the
%% suite's own (suites of one test folder share their priv_dir in a run, and the
%% database lives in the root), with `Env' (`[{App, Key, Value}]') set first;
%% registers the inspection settings. Returns the applications started, for stop/1.
start(Config, Suite, Env) ->
    Root = filename:join(?config(priv_dir, Config), atom_to_list(Suite) ++ ".root"),
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    %% Other suites of the same run may have left apps running on their own root.
    _ = [application:stop(A) || A <- [cell_inspect, cell_web, cell_shdr, cell, cell_hal,
                                      cell_base, mnesia]],
    _ = [application:load(A) || A <- [cell_base, cell, cell_inspect]],
    ok = application:set_env(cell_base, root, Root),
    ok = application:set_env(cell, cell_spec, #{name => atom_to_binary(Suite), tasks => []}),
    [ok = application:set_env(A, K, V) || {A, K, V} <- Env],
    {ok, Apps} = application:ensure_all_started(cell),
    ok = cell_inspect_settings:register(),
    Apps.

stop(Apps) ->
    _ = application:stop(cell_inspect),
    _ = [application:stop(A) || A <- lists:reverse(Apps)],
    _ = application:stop(mnesia),
    ok = application:unset_env(cell, cell_spec).

%% @doc A block's settings as the suites start them: the heartbeat every 300 ms, the
%% point STATION1 (simulated processing), messages 7 (Yes / No), 8 (a text) and 9 (a
%% number), and the simulated camera `cam1', shooting when told.
block_settings(Id) ->
    #{id => atom_to_binary(Id), heartbeat_ms => 300, processing_timeout_ms => 5000,
      panel_messages => false,
      points => [#{id => <<"STATION1">>, processing => <<"sim">>, workspace => <<"ws1">>}],
      messages => [#{id => 7, text => <<"Part OK?">>, kind => yes_no},
                   #{id => 8, text => <<"Batch number">>, kind => text},
                   #{id => 9, text => <<"Count">>, kind => number}],
      clients => [#{id => ?CAM, type => <<"sim">>, manual => true}]}.

%% @doc The next event of a simulated camera (cell_inspect_camera_sim:subscribe/1)
%% that `Match' accepts; the test fails after the deadline.
await_cam(Id, Match) ->
    receive
        {cell_inspect_camera_sim, Id, Event} ->
            case Match(Event) of
                true -> Event;
                false -> await_cam(Id, Match)
            end
    after ?WAIT -> ct:fail({camera_event_missing, Id})
    end.

request_seen(Id) ->
    await_cam(Id, fun({request, _}) -> true; (_) -> false end).

message_seen(Id) ->
    await_cam(Id, fun({message, _}) -> true; (_) -> false end).
