%% @doc The cell's database: mnesia in the cell root's `Databases/' folder (seed 000
%% §3), shared by every part of the runtime that keeps records there (statistics,
%% traceability, inspection results).
%%
%% {@link start/0} is idempotent: it starts mnesia in `Databases/' with a schema on
%% disk, creating the schema the first time, and answers `ok' at once when mnesia
%% already runs there. Each user then declares its own tables with {@link
%% ensure_tables/2}, which creates those that are missing, leaves existing ones as they
%% are and waits until they are loaded. Errors say what is wrong with the folder:
%%
%% <ul>
%% <li>`{databases_folder, Dir, Why}' — the folder cannot be created or written;</li>
%% <li>`{database_of_another_node, Dir, Nodes}' — the database there was made by a node
%%   of another name (the node name is part of an mnesia database: start the cell
%%   with that name, or move the folder away);</li>
%% <li>`{mnesia, Why}' — mnesia itself refused to start.</li>
%% </ul>
%%
%% mnesia is started by this module, not as a dependency of the `cell' application,
%% because its folder is only known once the cell root is. If the root changes while
%% the node runs (tests do that), mnesia is stopped and started again in the new
%% folder.
-module(cell_db).

-export([start/0, ensure_tables/2, dir/0, format_error/1]).

-export_type([table_def/0]).

%% A table: its name and mnesia's create_table options without the storage type,
%% which is given as `storage' (default disc_copies) and placed on this node.
-type table_def() :: {atom(), [{atom(), term()}]}.

-define(WAIT_MS, 60000).

%% @doc The folder of the database: `Databases/' in the cell root.
-spec dir() -> file:filename().
dir() ->
    cell_config:dir(databases).

%% @doc Starts mnesia in `Databases/' if it is not running there yet.
-spec start() -> ok | {error, term()}.
start() ->
    Dir = filename:absname(dir()),
    case usable(Dir) of
        ok -> start(Dir);
        {error, Why} -> {error, {databases_folder, Dir, Why}}
    end.

start(Dir) ->
    case running_in() of
        {yes, Dir} ->
            on_disc(Dir);
        {yes, Other} ->
            cell_log:notice(cell, "the database moves from ~ts to ~ts", [Other, Dir]),
            _ = application:stop(mnesia),
            start_in(Dir);
        no ->
            start_in(Dir)
    end.

start_in(Dir) ->
    _ = application:load(mnesia),
    ok = application:set_env(mnesia, dir, Dir),
    Created = case mnesia:create_schema([node()]) of
                  ok -> true;
                  {error, {_, {already_exists, _}}} -> false;
                  {error, Why} -> {error, Why}
              end,
    case Created of
        {error, W} ->
            {error, {mnesia, W}};
        _ ->
            case application:ensure_all_started(mnesia) of
                {ok, _} ->
                    Created andalso cell_log:notice(cell, "a new database was created in ~ts",
                                                    [Dir]),
                    on_disc(Dir);
                {error, W} ->
                    {error, {mnesia, W}}
            end
    end.

%% The schema must be on disc on this node, or nothing would survive a restart.
on_disc(Dir) ->
    case lists:member(node(), mnesia:table_info(schema, disc_copies)) of
        true ->
            ok;
        false ->
            case mnesia:table_info(schema, disc_copies) of
                [] ->
                    %% Started elsewhere without a disc schema: put it on disc here.
                    case mnesia:change_table_copy_type(schema, node(), disc_copies) of
                        {atomic, ok} -> ok;
                        {aborted, Why} -> {error, {mnesia, Why}}
                    end;
                Nodes ->
                    {error, {database_of_another_node, Dir, Nodes}}
            end
    end.

running_in() ->
    case mnesia:system_info(is_running) of
        yes -> {yes, filename:absname(mnesia:system_info(directory))};
        _ -> no
    end.

usable(Dir) ->
    Probe = filename:join(Dir, ".probe"),
    case filelib:ensure_dir(Probe) of
        ok ->
            case file:write_file(Probe, <<>>) of
                ok -> _ = file:delete(Probe), ok;
                {error, Why} -> {error, Why}
            end;
        {error, Why} ->
            {error, Why}
    end.

%% @doc Creates the tables of one user of the database that do not exist yet, and
%% waits until all of them are loaded. `Owner' names the user in log lines.
-spec ensure_tables(atom(), [table_def()]) -> ok | {error, term()}.
ensure_tables(Owner, Defs) ->
    Existing = mnesia:system_info(tables),
    Created = lists:foldl(fun(_, {error, _} = E) -> E;
                             ({Name, Opts}, Acc) ->
                                  case lists:member(Name, Existing) of
                                      true -> Acc;
                                      false -> create(Owner, Name, Opts, Acc)
                                  end
                          end, [], Defs),
    case Created of
        {error, _} = E ->
            E;
        _ ->
            Names = [N || {N, _} <- Defs],
            case mnesia:wait_for_tables(Names, ?WAIT_MS) of
                ok -> ok;
                {timeout, Bad} -> {error, {tables_not_loaded, Bad}};
                {error, Why} -> {error, {mnesia, Why}}
            end
    end.

create(Owner, Name, Opts, Acc) ->
    Storage = proplists:get_value(storage, Opts, disc_copies),
    Options = [{Storage, [node()]} | proplists:delete(storage, Opts)],
    case mnesia:create_table(Name, Options) of
        {atomic, ok} ->
            cell_log:info(cell, "~ts: table ~ts created", [Owner, Name]),
            [Name | Acc];
        {aborted, {already_exists, Name}} ->
            Acc;
        {aborted, Why} ->
            {error, {create_table, Name, Why}}
    end.

%% @doc An error of this module in words.
-spec format_error(term()) -> iolist().
format_error({databases_folder, Dir, Why}) ->
    io_lib:format("the database folder ~ts cannot be used: ~ts", [Dir, file:format_error(Why)]);
format_error({database_of_another_node, Dir, Nodes}) ->
    io_lib:format("the database in ~ts belongs to the node ~ts, not to this node ~ts: "
                  "start the cell with that node name, or move the folder away",
                  [Dir, lists:join(", ", [atom_to_list(N) || N <- Nodes]), node()]);
format_error({tables_not_loaded, Tabs}) ->
    io_lib:format("the tables ~tp could not be loaded", [Tabs]);
format_error({create_table, Name, Why}) ->
    io_lib:format("the table ~ts could not be created: ~tp", [Name, Why]);
format_error({mnesia, Why}) ->
    io_lib:format("mnesia: ~ts", [mnesia:error_description(Why)]);
format_error(Other) ->
    io_lib:format("~tp", [Other]).
