%% @doc Forced IO points: a value a service technician imposes on a point, whatever the
%% cell's tasks command, until it is released.
%%
%% <ul>
%% <li>An output is forced by writing the value to the device (confirmed, or the
%%   force is refused); while it is forced, a task's writes to it are not sent: the
%%   last one is kept, and written when the force is released, so the output goes
%%   back to what the cell wants (or, if no task wrote meanwhile, to the value it had
%%   before the force).</li>
%% <li>An input can only be forced on a simulated PLC (`cell_hal_sim'): the simulated
%%   PLC answers the forced value for it, whatever its image and rules say, and its
%%   own value again once released. A real PLC's input is what the machine says; the
%%   HAL never pretends otherwise.</li>
%% </ul>
%%
%% Who may force, and when forces end, is the caller's decision (the panel's,
%% `cell_web_forces'); this module only keeps them, with one exception: a force lasts
%% as long as the HAL's server it was set under. When that server restarts (and with
%% it, `rest_for_one', every connection's worker) the forces end: none is reported
%% any more, and each connection's new worker, once up, writes every output of its
%% own that was forced back to the value the cell wants ({@link take_ended/1}),
%% before any read back or task write, and logs it. A worker's own restart, alone,
%% keeps the forces: they stay visible and releasable. One row a forced point in a
%% table owned by `cell_hal_sup' (so the restart of a HAL process loses no row): forces
%% are added and released by one process, the panel's; a task's write to a forced
%% output only updates the value kept in its row (an atomic update of one element).
%% A release writes the kept value and removes the row only if no task wrote since
%% (it compares the whole row), trying again otherwise, so the device ends with the
%% task's last write in every interleaving.
-module(cell_hal_force).

-include("cell_hal.hrl").

-export([create_table/0, force/3, release/1, forces/0, forced/2, forceable/2, held/2,
         input_value/1, take_ended/1, forget_ended_inputs/0]).

-export_type([force/0]).

-type key() :: {atom(), atom()}.
-type force() :: #{group := atom(), point := atom(), dir := in | out,
                   value := cell_hal_type:value(), who := binary(), since := integer()}.

-define(TAB, cell_hal_forces).
-define(WRITE_TIMEOUT, 5000).
%% {Key, Dir, Value, Who, Since, Kept, Server}: Kept is the value the cell wants the
%% output to have once released ({ok, V}), or none; Server the HAL's server the force
%% was set under, the force active only while that process lives.
-define(KEPT, 6).

%% @doc Creates the table in the calling process (`cell_hal_sup').
-spec create_table() -> ok.
create_table() ->
    ?TAB = ets:new(?TAB, [named_table, public, set, {read_concurrency, true},
                          {write_concurrency, true}]),
    ok.

%% @doc Whether a point of this direction on a connection of this driver may be
%% forced: any output; an input only on a simulated PLC.
-spec forceable(in | out, module()) -> ok | {error, not_forceable}.
forceable(out, _Driver) -> ok;
forceable(in, cell_hal_sim) -> ok;
forceable(in, _Driver) -> {error, not_forceable}.

%% @doc Forces a point to a value (again, with a new value, if it is forced already),
%% `Who' recorded with it. An output's value reaches the device before this returns.
-spec force(key(), cell_hal_type:value(), binary()) ->
          ok | {error, unknown_point | not_forceable | {bad_value, term()} | disconnected
                | {unavailable, binary()} | timeout | term()}.
force(Key, Value, Who) when is_binary(Who) ->
    case cell_hal_store:value(Key) of
        {ok, #hal_value{dir = Dir, type = Type, conn = Conn, value = Now, fault = Fault}} ->
            Driver = case cell_hal_store:conn(Conn) of
                         {ok, #hal_conn{driver = D}} -> D;
                         error -> undefined
                     end,
            case {forceable(Dir, Driver), cell_hal_type:check(Type, Value)} of
                {{error, _} = E, _} -> E;
                {ok, error} -> {error, {bad_value, Value}};
                {ok, {ok, _}} when Dir =:= out, is_binary(Fault) -> {error, {unavailable, Fault}};
                {ok, {ok, V}} ->
                    case whereis(cell_hal_server) of
                        undefined -> {error, disconnected};
                        Server -> put_force(Key, Dir, Conn, V, Who, Now, Server)
                    end
            end;
        error ->
            {error, unknown_point}
    end.

put_force(Key, in, _Conn, V, Who, _Now, Server) ->
    true = ets:insert(?TAB, {Key, in, V, Who, os:system_time(millisecond), none, Server}),
    ok;
put_force(Key, out, Conn, V, Who, Now, Server) ->
    %% A force ended by a restart and not yet written back keeps what the cell wants.
    Row = case ets:lookup(?TAB, Key) of
              [{Key, out, _, _, Since, Kept, Server}] -> {Key, out, V, Who, Since, Kept, Server};
              [{Key, out, _, _, _, Kept, _}] -> {Key, out, V, Who, os:system_time(millisecond),
                                                 Kept, Server};
              _ -> {Key, out, V, Who, os:system_time(millisecond), Now, Server}
          end,
    %% Recorded first: from here a task's write is kept, not sent over the force.
    true = ets:insert(?TAB, Row),
    case write(Conn, Key, V) of
        ok ->
            ok;
        {error, _} = E ->
            ok = restore(Key),
            E
    end.

%% @doc Releases a forced point: an output gets the value the cell wants again (the
%% last a task wrote while it was forced, else the one it had before), an input reads
%% the simulated PLC's own value from its next read.
-spec release(key()) -> ok | {error, not_forced}.
release(Key) ->
    case ets:lookup(?TAB, Key) of
        [] -> {error, not_forced};
        [{Key, in, _, _, _, _, _}] -> true = ets:delete(?TAB, Key), ok;
        [{Key, out, _, _, _, _, _}] -> restore(Key)
    end.

restore(Key) ->
    case ets:lookup(?TAB, Key) of
        [] ->
            ok;
        [{Key, out, _, _, _, Kept, _} = Row] ->
            _ = case {Kept, cell_hal_store:value(Key)} of
                    {{ok, V}, {ok, #hal_value{conn = Conn}}} -> write(Conn, Key, V);
                    _ -> ok
                end,
            %% Removed only if no task wrote meanwhile; else its value is written too.
            true = ets:delete_object(?TAB, Row),
            restore(Key)
    end.

%% @doc Every force now, oldest first (not those a restart of the HAL's server ended).
-spec forces() -> [force()].
forces() ->
    Rows = try ets:tab2list(?TAB) catch error:badarg -> [] end,
    [#{group => G, point => P, dir => Dir, value => V, who => Who, since => Since}
     || {{G, P}, Dir, V, Who, Since, _, Server} <- lists:keysort(5, Rows), active(Server)].

%% @doc Whether a point is forced.
-spec forced(atom(), atom()) -> boolean().
forced(Group, Point) ->
    try ets:lookup(?TAB, {Group, Point}) of
        [{_, _, _, _, _, _, Server}] -> active(Server);
        [] -> false
    catch
        error:badarg -> false
    end.

%% A force is active while the HAL's server it was set under runs.
active(Server) ->
    whereis(cell_hal_server) =:= Server andalso is_process_alive(Server).

%% @doc For a connection's worker coming up: if a restart of the HAL's server ended
%% the force of this output, the row is taken away and the value the cell wants for
%% the output returned (`{ok, Kept}', Kept `none' when no value is known), for the
%% worker to write before anything else. A task's write racing with this is kept in
%% the row, which is then taken again, so the value returned is the task's last.
-spec take_ended(key()) -> {ok, {ok, cell_hal_type:value()} | none} | no.
take_ended(Key) ->
    try ets:lookup(?TAB, Key) of
        [{Key, out, _, _, _, Kept, Server} = Row] ->
            case active(Server) of
                true ->
                    no;
                false ->
                    true = ets:delete_object(?TAB, Row),
                    case ets:lookup(?TAB, Key) of
                        [{Key, out, _, _, _, _, Server}] -> take_ended(Key);
                        _ -> {ok, Kept}
                    end
            end;
        _ ->
            no
    catch
        error:badarg -> no
    end.

%% @doc For the HAL's server starting: the forced inputs of the server before it end
%% (a simulated PLC answers its own value again; nothing to write).
-spec forget_ended_inputs() -> ok.
forget_ended_inputs() ->
    _ = [ets:delete_object(?TAB, Row)
         || {_, in, _, _, _, _, Server} = Row <- ets:tab2list(?TAB), not active(Server)],
    ok.

%% @doc For `cell_hal:write/3': true when the output is forced, the value then kept
%% for its release instead of being written.
-spec held(key(), cell_hal_type:value()) -> boolean().
held(Key, V) ->
    try ets:update_element(?TAB, Key, {?KEPT, {ok, V}})
    catch error:badarg -> false
    end.

%% @doc For the simulated PLC: the value a forced input answers.
-spec input_value(key()) -> {ok, cell_hal_type:value()} | none.
input_value(Key) ->
    try ets:lookup(?TAB, Key) of
        [{Key, in, V, _, _, _, Server}] ->
            case active(Server) of
                true -> {ok, V};
                false -> none
            end;
        _ -> none
    catch
        error:badarg -> none
    end.

write(Conn, Key, V) ->
    case cell_hal_store:up_worker(Conn) of
        {ok, Pid} ->
            try cell_hal_worker:write(Pid, Key, V, {sync, ?WRITE_TIMEOUT})
            catch
                exit:{timeout, _} -> {error, timeout};
                exit:{_, _} -> {error, disconnected}
            end;
        _ ->
            {error, disconnected}
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

forceable_test() ->
    ?assertEqual(ok, forceable(out, cell_hal_modbus)),
    ?assertEqual(ok, forceable(out, cell_hal_sim)),
    ?assertEqual(ok, forceable(in, cell_hal_sim)),
    ?assertEqual({error, not_forceable}, forceable(in, cell_hal_modbus)),
    ?assertEqual({error, not_forceable}, forceable(in, undefined)).

%% A force lives as long as the HAL's server it was set under: the rows of a server
%% gone are not reported, and are taken once, with the value the cell wants.
ended_by_the_server_test() ->
    Old = spawn(fun() -> ok end),
    Ref = monitor(process, Old),
    receive {'DOWN', Ref, process, Old, _} -> ok end,
    true = register(cell_hal_server, self()),
    ok = create_table(),
    try
        true = ets:insert(?TAB, [{{g, out1}, out, 9, <<"ann">>, 1, {ok, 5}, Old},
                                 {{g, out2}, out, 9, <<"ann">>, 2, none, Old},
                                 {{g, in1}, in, true, <<"ann">>, 3, none, Old},
                                 {{g, out3}, out, 7, <<"ben">>, 4, {ok, 1}, self()}]),
        ?assertEqual([{g, out3}], [{G, P} || #{group := G, point := P} <- forces()]),
        ?assertNot(forced(g, out1)),
        ?assert(forced(g, out3)),
        ?assertEqual(none, input_value({g, in1})),
        %% A task's write to an ended force is still kept, for the write back.
        ?assert(held({g, out1}, 6)),
        ?assertEqual({ok, {ok, 6}}, take_ended({g, out1})),
        ?assertEqual(no, take_ended({g, out1})),
        ?assertEqual({ok, none}, take_ended({g, out2})),
        ?assertEqual(no, take_ended({g, out3})),
        ok = forget_ended_inputs(),
        ?assertEqual([{g, out3}], [K || {K, _, _, _, _, _, _} <- ets:tab2list(?TAB)])
    after
        true = ets:delete(?TAB),
        true = unregister(cell_hal_server)
    end.
-endif.
