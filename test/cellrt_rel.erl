%% What the system tests of the built release share: where it is, running its start
%% script with a deadline.
-module(cellrt_rel).

-export([top/0, bin/0, run/4, collect/2, boot_apps/0, await_boot/2, await_boot_expr/0,
         await_ping/4, start_dist/1, stop_dist/1]).

%% The project folder: $CELLRT_TOP (set by the Makefile and scripts/test), else derived
%% from this file's path, which rebar3 copies under _build/.
top() ->
    case os:getenv("CELLRT_TOP") of
        false ->
            case string:split(?FILE, "/_build/") of
                [Top, _] -> Top;
                [_] -> filename:dirname(filename:dirname(?FILE))
            end;
        Top -> Top
    end.

%% The start script of the default release.
bin() ->
    filename:join([top(), "_build", "default", "rel", "cellrt", "bin", "cellrt"]).

%% The applications the release's boot starts and how (permanent unless it says
%% otherwise), in its order; those it only loads are left out.
boot_apps() ->
    Rel = filename:dirname(filename:dirname(bin())),
    [File] = filelib:wildcard(filename:join([Rel, "releases", "*", "cellrt.rel"])),
    {ok, [{release, _, _, Apps}]} = file:consult(File),
    [{element(1, A), start_type(A)} || A <- Apps, start_type(A) =/= load].

start_type({_, _, Type}) when is_atom(Type) -> Type;
start_type(_) -> permanent.

%% Returns once the boot of `Node', a node just up, has started every application
%% (see await_boot_expr/0).
await_boot(Node, Timeout) ->
    lists:foreach(fun({App, Type}) ->
                          {ok, _} = erpc:call(Node, application, ensure_all_started,
                                              [App, Type], Timeout)
                  end, boot_apps()).

%% An expression to evaluate in a node just up, which returns `ok' once its boot has
%% started every application. A node answers ping while its boot still starts them,
%% and starting one application waits only for those it needs: asking for each in
%% the boot's own order, the way the boot starts it, waits for the boot (a start under
%% way is waited for, not repeated).
await_boot_expr() ->
    lists:flatten(io_lib:format("lists:foreach(fun({A, T}) -> {ok, _} = "
                                "application:ensure_all_started(A, T) end, ~w).",
                                [boot_apps()])).

%% Runs the start script's `ping' until `Done(Output)' holds, for at most `TimeoutMs';
%% `ok' or `{error, timeout}'. `ping' waits for its answer, so each try is a round trip,
%% not a sleep. A deadline, not a number of tries: a failing ping is quick, and a node
%% that boots slowly on a busy machine (the virtual PLC first, then the cell) must not
%% run out of tries before it is up.
await_ping(Bin, Env, Done, TimeoutMs) ->
    ping_until(Bin, Env, Done, erlang:monotonic_time(millisecond) + TimeoutMs).

ping_until(Bin, Env, Done, Deadline) ->
    {_, Out} = run(Bin, ["ping"], Env, 30000),
    case Done(Out) of
        true -> ok;
        false ->
            case erlang:monotonic_time(millisecond) < Deadline of
                true -> ping_until(Bin, Env, Done, Deadline);
                false -> {error, timeout}
            end
    end.

%% Makes the test's node a distributed one, named from `Prefix' and its OS pid, unless
%% it is already; whether it did (for stop_dist/1).
start_dist(Prefix) ->
    case node() of
        nonode@nohost ->
            Name = list_to_atom(Prefix ++ "_" ++ os:getpid() ++ "@localhost"),
            {ok, _} = net_kernel:start([Name, shortnames]),
            true;
        _ ->
            false
    end.

%% Ends what start_dist/1 started.
stop_dist(true) -> _ = net_kernel:stop(), ok;
stop_dist(false) -> ok.

%% Runs the start script `Bin' with `Args' and `Env'; its exit status and output.
run(Bin, Args, Env, Timeout) ->
    Port = open_port({spawn_executable, Bin},
                     [{args, Args}, {env, Env}, exit_status, stderr_to_stdout, binary]),
    collect(Port, Timeout).

%% The exit status and output of a port, within `Timeout' ms.
collect(Port, Timeout) ->
    collect(Port, [], erlang:monotonic_time(millisecond) + Timeout).

collect(Port, Acc, Deadline) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        {Port, {data, D}} -> collect(Port, [Acc, D], Deadline);
        {Port, {exit_status, S}} -> {S, unicode:characters_to_list(iolist_to_binary(Acc))}
    after Left ->
        catch port_close(Port),
        ct:fail("timed out; output so far: ~s", [Acc])
    end.
