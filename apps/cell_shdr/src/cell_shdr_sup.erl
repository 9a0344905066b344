%% @doc The adapter's supervisor, rest_for_one in dependency order: the cache (the
%% values and the log every client reads), the sampler (feeds time series into the
%% cache), the axes' watcher (feeds the cell's axes into it), the listener (its clients register with the cache). A cache that restarts
%% takes the listener and every client with it: agents reconnect and start from a
%% fresh snapshot, never from a log that no longer matches.
%%
%% The cache watches the cell's services and attaches again when one restarts, so a
%% burst of restarts in the cell never reaches this supervisor. Ten restarts a minute
%% of the adapter's own processes is a fault that will not go away by itself; beyond
%% that the adapter gives up and the cell runs on without it (the application is
%% temporary in the release: an adapter's bug must never stop the machine).
-module(cell_shdr_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% Only the adapter's own faults count here: a restart of the cell's services is
    %% met by the cache attaching again, not by a crash (see the module doc).
    Flags = #{strategy => rest_for_one, intensity => 10, period => 60},
    Children = [#{id => cell_shdr_cache, start => {cell_shdr_cache, start_link, []}},
                #{id => cell_shdr_sampler, start => {cell_shdr_sampler, start_link, []}},
                #{id => cell_shdr_axes, start => {cell_shdr_axes, start_link, []}},
                #{id => cell_shdr_listener, start => {cell_shdr_listener, start_link, []}}],
    {ok, {Flags, Children}}.
