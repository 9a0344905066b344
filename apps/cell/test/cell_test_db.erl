%% @doc Databases for tests that a cell must refuse.
-module(cell_test_db).

-export([foreign/1]).

%% The database a node of another name leaves in `Dir': made by such a node, in a VM
%% of its own. Returns that node's name.
foreign(Dir) ->
    Name = "cell_test_db_" ++ integer_to_list(erlang:unique_integer([positive])) ++ "_"
        ++ os:getpid(),
    Peer = list_to_atom(Name ++ "@localhost"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Port = open_port({spawn_executable, os:find_executable("erl")},
                     [{args, ["-noshell", "-sname", atom_to_list(Peer), "-mnesia", "dir",
                              "\"" ++ Dir ++ "\"", "-eval",
                              "ok = mnesia:create_schema([node()]), halt()."]},
                      exit_status, stderr_to_stdout, binary]),
    case collect(Port, <<>>) of
        {0, _} -> Peer;
        {Status, Output} -> erlang:error({peer_did_not_create_its_database, Status, Output})
    end.

collect(Port, Acc) ->
    receive
        {Port, {data, D}} -> collect(Port, <<Acc/binary, D/binary>>);
        {Port, {exit_status, S}} -> {S, Acc}
    after 60000 -> {timeout, Acc}
    end.
