%% @doc Databases for tests that a cell must refuse.
-module(cell_test_db).

-export([foreign/1]).

%% The database a node of another name leaves in `Dir': made by such a node, in a VM
%% of its own. Returns that node's name.
foreign(Dir) ->
    Peer = 'cell_test_db_other@localhost',
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Port = open_port({spawn_executable, os:find_executable("erl")},
                     [{args, ["-noshell", "-sname", atom_to_list(Peer), "-mnesia", "dir",
                              "\"" ++ Dir ++ "\"", "-eval",
                              "ok = mnesia:create_schema([node()]), halt()."]},
                      exit_status, stderr_to_stdout]),
    receive {Port, {exit_status, 0}} -> Peer
    after 60000 -> erlang:error(peer_did_not_create_its_database)
    end.
