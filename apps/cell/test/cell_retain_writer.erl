%% A node that makes serial numbers from a task's retained counter, for
%% cell_retain_SUITE, which kills it with SIGKILL at random moments. It builds the task
%% as the engine does (cell_task:new/1), loads its retained data as the engine does when
%% a task starts (cell_task:load_retained/1), prints "start N" with the counter found,
%% then takes serial after serial with cell_task:retain_update/4 and prints "made N"
%% for each once it is durable, without pause, until it is killed.
-module(cell_retain_writer).

-export([main/0, spec/0]).

-spec main() -> no_return().
main() ->
    %% The registry the task's row lives in, as in a cell.
    {ok, _} = cell_registry:start_link(),
    case cell_task:load_retained(cell_task:new(spec())) of
        {ok, T} ->
            io:format("pid ~s start ~b~n", [os:getpid(), cell_task:retained(T, serial, 0)]),
            loop(T);
        {error, Reason} ->
            io:format("pid ~s unreadable ~0tp~n", [os:getpid(), Reason]),
            halt(3)
    end.

%% The task of the node (its files are named by its zone and lane).
-spec spec() -> cell_task:spec().
spec() ->
    #{id => serials, module => ?MODULE, zone => <<"Serials">>, lane => <<"1">>,
      settings => #{}}.

loop(T) ->
    {N, T1} = cell_task:retain_update(T, serial, fun(S) -> S + 1 end, 0),
    io:format("made ~b~n", [N]),
    loop(T1).
