%% Product files under a real SIGKILL of a whole VM that is writing them, many times
%% in a row: each file is always readable (never torn) and holds the last acknowledged
%% product or the one being written when the VM died (never lost). A file written by
%% one VM is read by a fresh one that has loaded nothing but what reading needs.
-module(cell_product_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("stdlib/include/assert.hrl").

-export([all/0]).
-export([sigkill_while_writing/1, in_transit_read_by_fresh_vm/1]).

-define(ROUNDS, 60).
-define(FILES, 4).

all() ->
    [sigkill_while_writing, in_transit_read_by_fresh_vm].

%% A product marked in transit, read by a VM that has just started, in which the
%% handshake (whose code writes the marker) was never loaded: the file is read, never
%% reported damaged because the marker's atoms are not known yet.
in_transit_read_by_fresh_vm(Config) ->
    Dir = filename:join(?config(priv_dir, Config), "Fresh"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Path = filename:join(Dir, cell_product:file_name(<<"Z">>, <<"L">>)),
    Stored = cell_product:stored(cell_product:new(<<"S1">>, <<"r">>), 3,
                                 #{link => fresh_vm_link, from => upstream,
                                   phase => in_transit}),
    ok = cell_product:save(Path, Stored),
    %% The reader names the link, as the task's spec does in a cell.
    Eval = "io:format(\"handshake ~p~n\", [code:is_loaded(cell_handshake)]), "
           "Link = fresh_vm_link, "
           "io:format(\"read ~0tp ~p~n\", [cell_product:load(os:getenv(\"PRODUCT\")), Link]), "
           "halt().",
    Erl = os:find_executable("erl"),
    Paths = lists:usort([filename:dirname(code:which(M))
                         || M <- [cell_product, cell_file, cell_config]]),
    Args = lists:append([["-pa", P] || P <- Paths]) ++ ["-noshell", "-noinput", "-eval", Eval],
    Port = open_port({spawn_executable, Erl},
                     [{args, Args}, {line, 4096}, exit_status, use_stdio, stderr_to_stdout,
                      {env, [{"PRODUCT", Path}]}]),
    Lines = port_lines(Port, []),
    ?assert(lists:member("handshake false", Lines), Lines),
    Expected = lists:flatten(io_lib:format("read ~0tp fresh_vm_link", [{ok, Stored}])),
    ?assert(lists:member(Expected, Lines), Lines).

port_lines(Port, Acc) ->
    receive
        {Port, {data, {eol, Line}}} -> port_lines(Port, [Line | Acc]);
        {Port, {data, {noeol, Line}}} -> port_lines(Port, [Line | Acc]);
        {Port, {exit_status, 0}} -> lists:reverse(Acc);
        {Port, {exit_status, S}} -> ct:fail({reader_failed, S, lists:reverse(Acc)})
    after 60000 ->
        ct:fail({reader_silent, lists:reverse(Acc)})
    end.

sigkill_while_writing(Config) ->
    Dir = filename:join(?config(priv_dir, Config), "Data"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    rand:seed(exsss, erlang:phash2(make_ref())),
    Acked = lists:foldl(fun(Round, Last) -> round(Dir, Round, Last) end, 0,
                        lists:seq(1, ?ROUNDS)),
    ct:comment("~p rounds, ~p operations acknowledged", [?ROUNDS, Acked]),
    ?assert(Acked > ?ROUNDS).

%% One VM: it goes on from operation Last + 1, is killed somewhere in its work, and
%% the files are checked.
round(Dir, Round, Last) ->
    Port = writer(Dir, Last + 1),
    OsPid = receive {Port, {data, {eol, "pid " ++ P}}} -> P
            after 30000 -> ct:fail(writer_did_not_start)
            end,
    Acked = drive(Port, Last, Last + rand:uniform(12)),
    %% Kill it while it is writing the next one: at once, or after up to 12 ms.
    true = port_command(Port, "go\n"),
    Delay = rand:uniform(13) - 1,
    erlang:send_after(Delay, self(), kill),
    receive kill -> os:cmd("kill -9 " ++ OsPid) end,
    await_exit(Port),
    check(Dir, Acked, Round),
    Acked.

drive(_Port, Acked, Acked) ->
    Acked;
drive(Port, Acked, Target) ->
    true = port_command(Port, "go\n"),
    receive
        {Port, {data, {eol, "ack " ++ M}}} ->
            N = list_to_integer(M),
            ?assertEqual(Acked + 1, N),
            drive(Port, N, Target);
        {Port, {exit_status, S}} ->
            ct:fail({writer_exited, S})
    after 30000 ->
        ct:fail(writer_silent)
    end.

await_exit(Port) ->
    receive
        {Port, {exit_status, _}} -> ok;
        {Port, _} -> await_exit(Port)
    after 30000 ->
        ct:fail(writer_not_killed)
    end.

%% Every file decodes; it holds the state the last acknowledged operation on it left,
%% or the state of operation Acked + 1 if that one targets it.
check(Dir, Acked, Round) ->
    Leftovers = cell_file:cleanup(Dir),
    lists:foreach(
      fun(F) ->
              Path = filename:join(Dir, "task" ++ integer_to_list(F) ++ "@Lane.product"),
              Allowed = [state_after(Acked, F)]
                  ++ [P || {File, P} <- [cell_product_writer:op(Acked + 1, ?FILES)],
                           File =:= filename:basename(Path)],
              case cell_product:load(Path) of
                  {ok, Stored} ->
                      Product = case Stored of
                                    undefined -> undefined;
                                    #{product := P} -> P
                                end,
                      case lists:member(Product, Allowed) of
                          true -> ok;
                          false -> ct:fail({lost, Round, F, Acked, got, summary(Product),
                                            allowed, [summary(A) || A <- Allowed]})
                      end;
                  {error, Reason} ->
                      ct:fail({torn, Round, F, Reason, leftovers, Leftovers})
              end
      end, lists:seq(0, ?FILES - 1)).

%% The product file F holds after operations 1..M.
state_after(M, F) ->
    case [N || N <- lists:seq(M, 1, -1), N rem ?FILES =:= F] of
        [] -> undefined;
        [Last | _] -> element(2, cell_product_writer:op(Last, ?FILES))
    end.

summary(undefined) -> none;
summary(#{op := M}) -> M.

writer(Dir, First) ->
    Erl = os:find_executable("erl"),
    Paths = [filename:dirname(code:which(M)) || M <- [cell_file, cell_product, cell_config,
                                                      cell_product_writer]],
    Args = lists:append([["-pa", P] || P <- lists:usort(Paths)])
        ++ ["-noshell", "-s", "cell_product_writer", "main", "-extra", Dir,
            integer_to_list(?FILES), integer_to_list(First)],
    open_port({spawn_executable, Erl}, [{args, Args}, {line, 1024}, exit_status, use_stdio,
                                        stderr_to_stdout]).
