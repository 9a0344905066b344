%% A virtual PLC in an OS process of its own (scripts/vplc), as the suites that run the
%% cell against one start it: its listening line awaited, and its process killed
%% outright.
-module(cell_vplc_os).

-export([await_listening/2, kill/2]).

%% The TCP port the virtual PLC on port `P' listens on, once it says so, by `Deadline'
%% (monotonic ms); its other lines logged.
-spec await_listening(port(), integer()) -> inet:port_number().
await_listening(P, Deadline) ->
    receive
        {P, {data, {eol, <<"virtual PLC of router_cell listening on ", Rest/binary>>}}} ->
            [_, PortText] = binary:split(Rest, <<" port ">>),
            binary_to_integer(PortText);
        {P, {data, {_, Line}}} ->
            ct:log("vplc: ~s", [Line]),
            await_listening(P, Deadline);
        {P, {exit_status, S}} ->
            ct:fail({vplc_exited, S})
    after max(0, Deadline - erlang:monotonic_time(millisecond)) ->
        ct:fail(vplc_not_listening)
    end.

%% Kills the virtual PLC's OS process outright and waits for its end, within `Timeout'
%% ms.
-spec kill(port(), timeout()) -> ok.
kill(P, Timeout) ->
    case erlang:port_info(P, os_pid) of
        {os_pid, Pid} ->
            _ = os:cmd("kill -KILL " ++ integer_to_list(Pid)),
            await_exit(P, Timeout);
        undefined ->
            ok
    end.

await_exit(P, Timeout) ->
    receive
        {P, {exit_status, _}} -> ok;
        {P, {data, _}} -> await_exit(P, Timeout)
    after Timeout ->
        ct:fail(vplc_not_killed)
    end.
