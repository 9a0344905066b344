%% @doc Supervises the camera client processes, one per configured client, keyed by
%% the client's id. Each block keeps its own clients matching its settings
%% ({@link reconcile/2}); a client process that crashes is restarted and finds its
%% block again.
-module(cell_inspect_client_sup).
-behaviour(supervisor).

-export([start_link/0, reconcile/2, whereis/1]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

%% @private
-spec init([]) -> {ok, {supervisor:sup_flags(), []}}.
init([]) ->
    %% A client is a device's stand-in: one that keeps crashing is given up on (its
    %% block sees it disconnected) rather than taking the other clients with it.
    {ok, {#{strategy => one_for_one, intensity => 10, period => 60}, []}}.

%% @doc Makes the running clients of `Block' exactly `Specs': starts the missing ones,
%% restarts those whose settings changed, stops those no longer configured. Returns
%% the pid of each client that runs.
-spec reconcile(atom(), [cell_inspect_client:spec()]) -> [{binary(), pid()}].
reconcile(Block, Specs) ->
    Running = [{Id, Pid, spec_of(Id)} || {{client, Id}, Pid, _, _} <- supervisor:which_children(?MODULE)],
    Wanted = maps:from_list([{Id, S} || #{id := Id} = S <- Specs]),
    _ = [stop(Id) || {Id, _, #{block := B}} <- Running, B =:= Block,
                     not maps:is_key(Id, Wanted)],
    lists:append([ensure(S, lists:keyfind(Id, 1, Running)) || #{id := Id} = S <- Specs]).

ensure(#{id := Id} = Spec, {Id, Pid, Spec}) when is_pid(Pid) ->
    [{Id, Pid}];
ensure(#{id := Id} = Spec, Running) ->
    _ = Running =/= false andalso stop(Id),
    case supervisor:start_child(?MODULE, cell_inspect_client:child_spec(Spec)) of
        {ok, Pid} -> [{Id, Pid}];
        {error, Why} ->
            cell_log:error(inspect, "camera client ~ts could not start: ~0tp", [Id, Why]),
            []
    end.

stop(Id) ->
    _ = supervisor:terminate_child(?MODULE, {client, Id}),
    _ = supervisor:delete_child(?MODULE, {client, Id}),
    ok.

spec_of(Id) ->
    case supervisor:get_childspec(?MODULE, {client, Id}) of
        {ok, #{start := {_, _, [Spec]}}} -> Spec;
        {error, _} -> undefined
    end.

%% @doc The process of a client.
-spec whereis(binary()) -> pid() | undefined.
whereis(Id) ->
    case [Pid || {{client, I}, Pid, _, _} <- supervisor:which_children(?MODULE), I =:= Id,
                 is_pid(Pid)] of
        [Pid] -> Pid;
        [] -> undefined
    end.
