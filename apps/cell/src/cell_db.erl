%% @doc The cell's database: mnesia on this node, in the `Databases/' folder of the
%% cell root (seed 000 §3), shared by every part of the runtime that keeps records
%% there: the statistics and traceability ({@link cell_stats}), the inspection
%% results of `cell_inspect', and any cell's own tables.
%%
%% A user calls {@link start/0}, then {@link ensure_tables/2} with its own tables.
%% Both are idempotent and safe to call from several processes at once: the first
%% caller sets mnesia's folder, creates the schema if the folder has none and starts
%% mnesia; later callers find it running in the right folder. A table that exists is
%% checked (same fields), never recreated, so records survive restarts of the app and
%% of the node. Tables live on disc on this node: `disc_copies' (in memory too, for
%% tables read often) unless a table asks for `{storage, disc_only_copies}' (tables
%% that grow with the products, which memory must not).
%%
%% mnesia is not started by the release's boot script (it is loaded only): its folder
%% must be set first, and that folder comes from `cell_config'. An app using this
%% module does not list mnesia among its applications for the same reason.
%%
%% Errors say what is wrong in words ({@link format_error/1}): a folder that cannot be
%% written, a database made by a node of another name, a table of the same name with
%% other fields, mnesia already running in another folder. A database of another node
%% is left alone and mnesia stopped again, so once the folder is moved aside the next
%% {@link start/0} starts an empty database.
-module(cell_db).

-export([start/0, ensure_tables/2, dir/0, sync_transaction/1, format_error/1, unclosed/1]).

-export_type([table/0, error/0]).

-type table() :: {atom(), [{attributes, [atom()]} | {record_name, atom()}
                           | {index, [atom() | pos_integer()]}
                           | {type, set | ordered_set | bag}
                           | {storage, disc_copies | disc_only_copies}]}.
-type error() :: {unusable_folder, file:filename(), term()}
               | {other_folder, file:filename(), file:filename()}
               | {schema, term()}
               | {other_node, node(), [node()]}
               | {mnesia, term()}
               | {table_differs, atom(), [atom()], [atom()]}
               | {create_table, atom(), term()}
               | {tables_not_loaded, [atom()]}.

%% @doc The folder mnesia uses: `Databases/' of the cell root.
-spec dir() -> file:filename().
dir() ->
    filename:absname(cell_config:dir(databases)).

%% @doc Starts mnesia in `Databases/' with a disc schema of this node, if it does not
%% run already.
-spec start() -> ok | {error, error()}.
start() ->
    %% One caller at a time: creating a schema and starting mnesia must not interleave.
    global:trans({?MODULE, self()}, fun start_locked/0, [node()]).

start_locked() ->
    Dir = dir(),
    case mnesia:system_info(is_running) of
        yes -> check_running(Dir);
        _ -> start_stopped(Dir)
    end.

check_running(Dir) ->
    case filename:absname(mnesia:system_info(directory)) of
        Dir -> check_schema();
        Other -> {error, {other_folder, Other, Dir}}
    end.

start_stopped(Dir) ->
    case usable(Dir) of
        ok ->
            report_unclosed(Dir),
            _ = application:load(mnesia),
            ok = application:set_env(mnesia, dir, Dir),
            case mnesia:create_schema([node()]) of
                ok ->
                    cell_log:notice(cell, "a new database was created in ~ts", [Dir]),
                    start_mnesia();
                {error, {_, {already_exists, _}}} ->
                    start_mnesia();
                {error, Why} ->
                    {error, {schema, Why}}
            end;
        {error, _} = E ->
            E
    end.

start_mnesia() ->
    case application:ensure_started(mnesia) of
        ok ->
            case check_schema() of
                ok ->
                    ok;
                {error, _} = E ->
                    %% Not this node's database: leave it as it is.
                    _ = application:stop(mnesia),
                    E
            end;
        {error, Why} ->
            {error, {mnesia, Why}}
    end.

%% The schema must be on disc on this node: a folder made by a node of another name
%% holds tables this node cannot load.
check_schema() ->
    Disc = mnesia:table_info(schema, disc_copies),
    case lists:member(node(), Disc) of
        true -> ok;
        false when Disc =:= [] ->
            case mnesia:change_table_copy_type(schema, node(), disc_copies) of
                {atomic, ok} -> ok;
                {aborted, Why} -> {error, {schema, Why}}
            end;
        false -> {error, {other_node, node(), Disc}}
    end.

%% mnesia repairs a table file on disc only that was not closed (the node stopped
%% without shutting down) as it loads it, and says so on the console only: the log
%% says it here, before.
report_unclosed(Dir) ->
    lists:foreach(fun(File) ->
                          cell_log:warning(cell, "database: the table file ~ts was not "
                                           "closed properly (the node stopped without "
                                           "shutting down); it is repaired as it loads, "
                                           "and what it may have lost of the product "
                                           "histories is taken again from the trace "
                                           "journal", [File])
                  end, unclosed(Dir)).

%% @doc The table files of the folder that were not closed properly.
-spec unclosed(file:filename()) -> [file:filename()].
unclosed(Dir) ->
    [F || F <- lists:sort(filelib:wildcard(filename:join(Dir, "*.DAT"))), needs_repair(F)].

needs_repair(File) ->
    Name = {?MODULE, File},
    case dets:open_file(Name, [{file, File}, {repair, false}, {access, read}]) of
        {ok, _} -> ok = dets:close(Name), false;
        {error, {needs_repair, _}} -> true;
        %% Anything else is for mnesia to say as it loads the table.
        {error, _} -> false
    end.

usable(Dir) ->
    Probe = filename:join(Dir, ".cellrt-write-test"),
    case filelib:ensure_dir(Probe) of
        ok ->
            case file:write_file(Probe, <<>>) of
                ok -> _ = file:delete(Probe), ok;
                {error, Why} -> {error, {unusable_folder, Dir, Why}}
            end;
        {error, Why} ->
            {error, {unusable_folder, Dir, Why}}
    end.

%% @doc Creates the tables that do not exist yet (on disc, on this node), checks those
%% that do, and waits until all are loaded (at most `Timeout' ms).
-spec ensure_tables([table()], timeout()) -> ok | {error, error()}.
ensure_tables(Tables, Timeout) ->
    case ensure(Tables) of
        ok ->
            Names = [N || {N, _} <- Tables],
            case mnesia:wait_for_tables(Names, Timeout) of
                ok -> ok;
                {timeout, Missing} -> {error, {tables_not_loaded, Missing}};
                {error, Why} -> {error, {mnesia, Why}}
            end;
        {error, _} = E ->
            E
    end.

ensure([]) ->
    ok;
ensure([{Name, Opts} | Rest]) ->
    Wanted = proplists:get_value(attributes, Opts),
    Result = try mnesia:table_info(Name, attributes) of
                 Wanted -> ok;
                 Other -> {error, {table_differs, Name, Wanted, Other}}
             catch
                 exit:{aborted, {no_exists, _, _}} -> create(Name, Opts)
             end,
    case Result of
        ok -> ensure(Rest);
        E -> E
    end.

create(Name, Opts) ->
    Storage = proplists:get_value(storage, Opts, disc_copies),
    case mnesia:create_table(Name, [{Storage, [node()]} | proplists:delete(storage, Opts)]) of
        {atomic, ok} ->
            cell_log:info(cell, "database table ~ts created", [Name]),
            ok;
        {aborted, {already_exists, Name}} ->
            ok;
        {aborted, Why} ->
            {error, {create_table, Name, Why}}
    end.

%% @doc Runs a transaction and, once it committed, flushes mnesia's log to the disk,
%% so what it wrote survives a power cut.
-spec sync_transaction(fun(() -> T)) -> {atomic, T} | {aborted, term()}.
sync_transaction(Fun) ->
    case mnesia:sync_transaction(Fun) of
        {atomic, _} = Done ->
            case mnesia:sync_log() of
                ok -> Done;
                {error, Why} -> {aborted, {sync_log, Why}}
            end;
        Aborted ->
            Aborted
    end.

%% @doc An error in words.
-spec format_error(error() | term()) -> iolist().
format_error({unusable_folder, Dir, Why}) ->
    io_lib:format("the database folder ~ts cannot be written (~ts)", [Dir, posix(Why)]);
format_error({other_folder, Running, Wanted}) ->
    io_lib:format("the database runs in ~ts, not in the cell's ~ts", [Running, Wanted]);
format_error({schema, Why}) ->
    io_lib:format("the database schema cannot be created or read: ~0tp", [Why]);
format_error({other_node, Node, Owners}) ->
    io_lib:format("the database in ~ts belongs to node ~ts, this node is ~ts: "
                  "start the cell with that node name, or move the folder aside to start "
                  "an empty database",
                  [dir(), lists:join(", ", [atom_to_list(N) || N <- Owners]), Node]);
format_error({mnesia, Why}) ->
    io_lib:format("the database (mnesia) cannot start: ~0tp", [Why]);
format_error({table_differs, Name, Wanted, Other}) ->
    io_lib:format("the database table ~s has the fields ~0p, this version expects ~0p",
                  [Name, Other, Wanted]);
format_error({create_table, Name, Why}) ->
    io_lib:format("the database table ~s cannot be created: ~0tp", [Name, Why]);
format_error({tables_not_loaded, Names}) ->
    io_lib:format("the database tables ~0p did not load in time", [Names]);
format_error(Other) ->
    io_lib:format("~0tp", [Other]).

posix(Why) when is_atom(Why) -> file:format_error(Why);
posix(Why) -> io_lib:format("~0tp", [Why]).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% A table file whose owner was killed is found; one closed properly is not.
unclosed_test() ->
    Dir = filename:join(["/tmp", "cell_db_unclosed_" ++ os:getpid()]),
    _ = file:del_dir_r(Dir),
    ok = filelib:ensure_dir(filename:join(Dir, ".")),
    Clean = filename:join(Dir, "clean.DAT"),
    Killed = filename:join(Dir, "killed.DAT"),
    {ok, clean} = dets:open_file(clean, [{file, Clean}]),
    ok = dets:insert(clean, {a, 1}),
    ok = dets:close(clean),
    {ok, killed} = dets:open_file(killed, [{file, Killed}]),
    ok = dets:insert(killed, {a, 1}),
    ok = dets:sync(killed),
    %% Written to since its last flush, as a table in use always is.
    ok = dets:insert(killed, {b, 2}),
    Owner = dets:info(killed, pid),
    Ref = monitor(process, Owner),
    exit(Owner, kill),
    receive {'DOWN', Ref, process, Owner, _} -> ok end,
    ?assertEqual([Killed], unclosed(Dir)),
    %% Looking does not repair: the file is still found.
    ?assertEqual([Killed], unclosed(Dir)),
    ok = file:del_dir_r(Dir).

-endif.
