%% @doc A supervisor of a test's own for one HAL connection's worker, with the child
%% spec cell_hal_conn_sup gives it: a model that kills the worker hundreds of times a
%% minute would exhaust the product's restart intensity (ten a minute, on purpose), and
%% raising that would hide a real crash loop. `adopt/1' moves a connection's worker
%% from the product's supervisor to a fresh one of these.
-module(cell_hal_test_worker_sup).
-behaviour(supervisor).

-export([adopt/1, release/1, worker/1, init/1]).

%% The connection's worker, stopped under the product's supervisor (it closes its
%% connection and is marked down) and started again under a new supervisor of the
%% test's own, linked to the caller.
-spec adopt(atom()) -> pid().
adopt(Conn) ->
    ok = cell_hal_conn_sup:stop_worker(Conn),
    {ok, Sup} = supervisor:start_link(?MODULE, Conn),
    Sup.

%% Stops the supervisor and its worker (it closes its connection).
-spec release(pid()) -> ok.
release(Sup) ->
    unlink(Sup),
    Ref = monitor(process, Sup),
    exit(Sup, shutdown),
    receive {'DOWN', Ref, process, Sup, _} -> ok end.

-spec worker(pid()) -> pid() | restarting | undefined.
worker(Sup) ->
    case supervisor:which_children(Sup) of
        [{_, Pid, _, _}] -> Pid;
        [] -> undefined
    end.

-spec init(atom()) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(Conn) ->
    %% Each kill of a model is a restart: far more than the product allows, on purpose.
    {ok, {#{strategy => one_for_one, intensity => 1000, period => 1},
          [cell_hal_conn_sup:child_spec(Conn)]}}.
