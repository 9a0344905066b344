%% @doc Databases for tests that a cell must refuse.
-module(cell_test_db).

-export([foreign/1]).

%% The database a node of another name leaves in `Dir': made by such a node, in a VM
%% of its own. Returns that node's name.
foreign(Dir) ->
    %% A name of its own: another test run on the machine may make one at the same time.
    Peer = list_to_atom("cell_test_db_other_" ++ os:getpid() ++ "@localhost"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Port = open_port({spawn_executable, os:find_executable("erl")},
                     [{args, ["-noshell", "-sname", atom_to_list(Peer), "-mnesia", "dir",
                              "\"" ++ Dir ++ "\"", "-eval",
                              "ok = mnesia:create_schema([node()]), halt()."]},
                      exit_status, stderr_to_stdout]),
    receive
        {Port, {exit_status, 0}} -> Peer;
        {Port, {exit_status, Status}} -> erlang:error({peer_failed, Status, output(Port)})
    after 60000 -> erlang:error(peer_did_not_create_its_database)
    end.

output(Port) ->
    receive {Port, {data, D}} -> D ++ output(Port) after 0 -> [] end.
