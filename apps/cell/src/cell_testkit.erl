%% @doc What a cell's common_test suite needs to run the cell in its own node, as the
%% release would, and to wait for it: public API for the tests of a cell (cellrt's
%% default cell and a cell of one's own use it alike).
%%
%% ```
%% init_per_testcase(Case, Config) ->
%%     Root = filename:join(?config(priv_dir, Config), atom_to_list(Case)),
%%     ok = cell_testkit:write_settings(Root, #{machine => #{simulation_mode => true},
%%                                              my_cell => #{sim_time_scale => 0.05}}),
%%     ok = cell_testkit:start(Root, my_cell, my_cell),
%%     ok = cell_testkit:await_connection(my_plc, 60000),
%%     [{root, Root} | Config].
%%
%% end_per_testcase(_Case, _Config) ->
%%     cell_testkit:stop(my_cell, [my_plc]).
%%
%% parts_pass(_Config) ->
%%     ok = cell_events:subscribe([item_transfer_out, alarm_raised, cell_state]),
%%     ok = cell_controller:start(<<"suite">>),
%%     ok = cell_testkit:await_event(fun(#{type := item_transfer_out}) -> true;
%%                                      (_) -> false
%%                                   end, 60000),
%%     ok = cell_testkit:stop_cell(fun(Alarm) -> ct:fail({unexpected, Alarm}) end, 60000).
%% '''
%%
%% Every wait is for a message with a deadline; a deadline passed raises an error that
%% says what the cell was doing (its tasks and alarms), which fails the case.
-module(cell_testkit).

-export([write_settings/2, start/3, stop/2, await_connection/2, stop_cell/2,
         await_event/2, collect/4]).

%% @doc Writes settings objects into a cell root folder before the cell starts there:
%% `Settings/<name>.json' for each `Name => Fields' (fields left out take their
%% defaults when the cell loads the object).
-spec write_settings(file:filename(), #{atom() => map()}) -> ok.
write_settings(Root, Objects) ->
    Dir = filename:join(Root, "Settings"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    maps:foreach(fun(Name, Fields) ->
                         Path = filename:join(Dir, atom_to_list(Name) ++ ".json"),
                         ok = file:write_file(Path, jsx:encode(Fields))
                 end, Objects).

%% @doc Starts the cell of `CellModule' in this node on the cell root `Root', with the
%% application `App' (the cell's own, which starts cellrt's apps it needs) and all it
%% depends on. The cell stops its tasks before it goes down, as the release has it.
-spec start(file:filename(), module(), atom()) -> ok.
start(Root, CellModule, App) ->
    _ = [application:load(A) || A <- [cell_base, cell_hal, cell, App]],
    ok = application:set_env(cell_base, root, Root),
    ok = application:unset_env(cell, cell_spec),
    ok = application:set_env(cell, cell_module, CellModule),
    {ok, _} = application:ensure_all_started(App),
    ok.

%% @doc Stops the cell as the node stops it: the application `App', the cell (its
%% monitor takes the HAL down), the database; and the simulated PLCs of the connections
%% `SimConns', which a new node has anew.
-spec stop(atom(), [atom()]) -> ok.
stop(App, SimConns) ->
    _ = application:stop(App),
    _ = application:stop(cell),
    _ = application:stop(mnesia),
    lists:foreach(fun(C) -> ok = cell_hal_sim_sup:stop_device(C) end, SimConns).

%% @doc Returns once the HAL connection `Conn' is up.
-spec await_connection(atom(), non_neg_integer()) -> ok.
await_connection(Conn, Timeout) ->
    case cell_hal:subscribe_connection(Conn) of
        {ok, up} -> ok;
        {ok, down} ->
            receive {cell_hal_conn, Conn, up} -> ok
            after Timeout -> erlang:error({connection_not_up, Conn})
            end
    end.

%% @doc The operator's Stop; returns once the cell is OFF. An alarm raised meanwhile
%% goes to `Answer', which returns `ok' (having answered it with {@link
%% cell_alarms:answer/3}, or not), or fails the case.
%% The caller subscribed to the cell's events `cell_state' and `alarm_raised' ({@link
%% cell_events:subscribe/1}).
-spec stop_cell(fun((cell_alarms:alarm()) -> ok), non_neg_integer()) -> ok.
stop_cell(Answer, Timeout) ->
    ok = cell_controller:stop(<<"suite">>),
    ok = cell_controller:sync(),
    case cell_controller:state() of
        off -> ok;
        _ -> await_event(fun(#{type := cell_state, state := off}) -> true;
                            (#{type := alarm_raised, alarm := A}) -> ok = Answer(A), false;
                            (_) -> false
                         end, Timeout)
    end.

%% @doc Returns once `Match' says `true' of an event the caller receives (it subscribed
%% with {@link cell_events:subscribe/1}); the events before it are consumed.
-spec await_event(fun((cell_events:event()) -> boolean()), non_neg_integer()) -> ok.
await_event(Match, Timeout) ->
    await_until(Match, erlang:monotonic_time(millisecond) + Timeout).

await_until(Match, Deadline) ->
    receive
        {cell_event, E} ->
            case Match(E) of
                true -> ok;
                false -> await_until(Match, Deadline)
            end
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        erlang:error({no_event, cell_controller:tasks(), cell_alarms:list()})
    end.

%% @doc What `Pick' finds in the next events the caller receives (`{true, Value}'),
%% until it has found `N', in the order found; an alarm raised meanwhile goes to
%% `Answer', as in {@link stop_cell/2}. The serials of the next three parts out:
%% ```
%% collect(3, fun(#{type := item_transfer_out, task := press, item := S}) -> {true, S};
%%               (_) -> false
%%            end, fun(_Alarm) -> ok end, 60000)
%% '''
-spec collect(non_neg_integer(), fun((cell_events:event()) -> {true, term()} | false),
              fun((cell_alarms:alarm()) -> ok), non_neg_integer()) -> [term()].
collect(N, Pick, Answer, Timeout) ->
    collect(N, Pick, Answer, [], erlang:monotonic_time(millisecond) + Timeout).

collect(0, _Pick, _Answer, Acc, _Deadline) ->
    lists:reverse(Acc);
collect(N, Pick, Answer, Acc, Deadline) ->
    receive
        {cell_event, E} ->
            case {Pick(E), E} of
                {{true, V}, _} ->
                    collect(N - 1, Pick, Answer, [V | Acc], Deadline);
                {false, #{type := alarm_raised, alarm := A}} ->
                    ok = Answer(A),
                    collect(N, Pick, Answer, Acc, Deadline);
                {false, _} ->
                    collect(N, Pick, Answer, Acc, Deadline)
            end
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        erlang:error({only, lists:reverse(Acc), cell_controller:tasks(), cell_alarms:list()})
    end.
