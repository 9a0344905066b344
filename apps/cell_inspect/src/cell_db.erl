%% @doc The cell's database: mnesia on this node, its folder `Databases/' of the cell
%% root (seed 000 §3), tables on disc (`disc_copies').
%%
%% Any app that keeps tables calls {@link start/0}, then {@link ensure_tables/2} with
%% its own tables. Both are idempotent and safe to call from several apps at once: the
%% first caller sets mnesia's folder, creates the schema if the folder has none and
%% starts mnesia; later callers find it running in the right folder. A table that
%% exists is checked (same attributes), never recreated, so data survives restarts of
%% the app and of the node.
%%
%% mnesia is not started by the release's boot script (it is loaded only): its folder
%% must be set first, and that folder comes from `cell_config'. An app using this
%% module does not list mnesia among its applications for the same reason.
%%
%% Errors say what is wrong in words ({@link format_error/1}): a folder that cannot be
%% written, a database made by another node name, a table of the same name with other
%% fields, mnesia already running elsewhere.
-module(cell_db).

-export([start/0, ensure_tables/2, dir/0, sync_transaction/1, format_error/1]).

-export_type([table/0, error/0]).

-type table() :: {atom(), [{attributes, [atom()]} | {record_name, atom()}
                           | {index, [atom()]} | {type, set | ordered_set | bag}]}.
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
    cell_config:dir(databases).

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
    case same_dir(mnesia:system_info(directory), Dir) of
        true -> check_schema();
        false -> {error, {other_folder, mnesia:system_info(directory), Dir}}
    end.

start_stopped(Dir) ->
    case usable(Dir) of
        ok ->
            _ = application:load(mnesia),
            ok = application:set_env(mnesia, dir, Dir),
            case mnesia:create_schema([node()]) of
                ok -> start_mnesia();
                {error, {_, {already_exists, _}}} -> start_mnesia();
                {error, Why} -> {error, {schema, Why}}
            end;
        {error, _} = E ->
            E
    end.

start_mnesia() ->
    case application:ensure_started(mnesia) of
        ok -> check_schema();
        {error, Why} -> {error, {mnesia, Why}}
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

same_dir(A, B) ->
    filename:absname(A) =:= filename:absname(B).

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
                 exit:{aborted, {no_exists, _, _}} ->
                     case mnesia:create_table(Name, [{disc_copies, [node()]} | Opts]) of
                         {atomic, ok} -> ok;
                         {aborted, {already_exists, Name}} -> ok;
                         {aborted, Why} -> {error, {create_table, Name, Why}}
                     end
             end,
    case Result of
        ok -> ensure(Rest);
        E -> E
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
    io_lib:format("the database in Databases/ belongs to node ~ts, this node is ~ts: "
                  "start the cell with that node name, or move the folder aside to start "
                  "an empty database", [lists:join(", ", [atom_to_list(N) || N <- Owners]),
                                         Node]);
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
