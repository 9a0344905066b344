%% What the system tests of the built release share: where it is, running its start
%% script with a deadline.
-module(cellrt_rel).

-export([top/0, bin/0, run/4, collect/2]).

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
