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
%% `cell_web_forces'); this module only keeps them. One row a forced point in a
%% table owned by `cell_hal_sup' (so a restart of a HAL process keeps them): forces
%% are added and released by one process, the panel's; a task's write to a forced
%% output only updates the value kept in its row (an atomic update of one element).
%% A release writes the kept value and removes the row only if no task wrote since
%% (it compares the whole row), trying again otherwise, so the device ends with the
%% task's last write in every interleaving.
-module(cell_hal_force).

-include("cell_hal.hrl").

-export([create_table/0, force/3, release/1, forces/0, forced/2, forceable/2, held/2,
         input_value/1]).

-export_type([force/0]).

-type key() :: {atom(), atom()}.
-type force() :: #{group := atom(), point := atom(), dir := in | out,
                   value := cell_hal_type:value(), who := binary(), since := integer()}.

-define(TAB, cell_hal_forces).
-define(WRITE_TIMEOUT, 5000).
%% {Key, Dir, Value, Who, Since, Kept}: Kept is the value the cell wants the output to
%% have once released ({ok, V}), or none.
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
                {ok, {ok, V}} -> put_force(Key, Dir, Conn, V, Who, Now)
            end;
        error ->
            {error, unknown_point}
    end.

put_force(Key, in, _Conn, V, Who, _Now) ->
    true = ets:insert(?TAB, {Key, in, V, Who, os:system_time(millisecond), none}),
    ok;
put_force(Key, out, Conn, V, Who, Now) ->
    Row = case ets:lookup(?TAB, Key) of
              [{Key, out, _, _, Since, Kept}] -> {Key, out, V, Who, Since, Kept};
              [] -> {Key, out, V, Who, os:system_time(millisecond), Now}
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
        [{Key, in, _, _, _, _}] -> true = ets:delete(?TAB, Key), ok;
        [{Key, out, _, _, _, _}] -> restore(Key)
    end.

restore(Key) ->
    case ets:lookup(?TAB, Key) of
        [] ->
            ok;
        [{Key, out, _, _, _, Kept} = Row] ->
            _ = case {Kept, cell_hal_store:value(Key)} of
                    {{ok, V}, {ok, #hal_value{conn = Conn}}} -> write(Conn, Key, V);
                    _ -> ok
                end,
            %% Removed only if no task wrote meanwhile; else its value is written too.
            true = ets:delete_object(?TAB, Row),
            restore(Key)
    end.

%% @doc Every force now, oldest first.
-spec forces() -> [force()].
forces() ->
    Rows = try ets:tab2list(?TAB) catch error:badarg -> [] end,
    [#{group => G, point => P, dir => Dir, value => V, who => Who, since => Since}
     || {{G, P}, Dir, V, Who, Since, _} <- lists:keysort(5, Rows)].

%% @doc Whether a point is forced.
-spec forced(atom(), atom()) -> boolean().
forced(Group, Point) ->
    try ets:member(?TAB, {Group, Point}) catch error:badarg -> false end.

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
        [{Key, in, V, _, _, _}] -> {ok, V};
        _ -> none
    catch
        error:badarg -> none
    end.

write(Conn, Key, V) ->
    case cell_hal_store:conn(Conn) of
        {ok, #hal_conn{status = up, pid = Pid}} when is_pid(Pid) ->
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
-endif.
