%% @doc Supervises the HAL workers, one child per configured connection, keyed by the
%% connection's id. After a restart it starts a worker for every connection the
%% tables still hold.
-module(cell_hal_conn_sup).
-behaviour(supervisor).

-include("cell_hal.hrl").

-export([start_link/0, start_worker/1, stop_worker/1, child_spec/1]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

%% @doc Starts the worker of a configured connection.
-spec start_worker(atom()) -> ok | {error, term()}.
start_worker(Id) ->
    case supervisor:start_child(?MODULE, spec(Id)) of
        {ok, _} -> ok;
        {error, _} = Error -> Error
    end.

%% @doc Stops a connection's worker (it closes the connection).
-spec stop_worker(atom()) -> ok.
stop_worker(Id) ->
    _ = supervisor:terminate_child(?MODULE, Id),
    _ = supervisor:delete_child(?MODULE, Id),
    ok.

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% A worker handles every failure of its device itself (it reconnects with
    %% backoff); one that still crashes is a bug. Ten crashes a minute across all
    %% connections means something is badly wrong: escalate so the node reports it.
    Flags = #{strategy => one_for_one, intensity => 10, period => 60},
    {ok, {Flags, [spec(Id) || #hal_conn{id = Id} <- cell_hal_store:conns()]}}.

%% @doc The child spec of a connection's worker, as this supervisor runs it: for a
%% supervisor of a test's own that kills workers more often than ten a minute.
-spec child_spec(atom()) -> supervisor:child_spec().
child_spec(Id) ->
    spec(Id).

spec(Id) ->
    %% A worker closes its connection in terminate/3; give it time to say goodbye.
    #{id => Id, start => {cell_hal_worker, start_link, [Id]}, shutdown => 5000}.
