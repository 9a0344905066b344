%% @doc The adapter's supervisor, rest_for_one in dependency order: the cache (the
%% values and the log every client reads), the sampler (feeds time series into the
%% cache), the listener (its clients register with the cache). A cache that restarts
%% takes the listener and every client with it: agents reconnect and start from a
%% fresh snapshot, never from a log that no longer matches.
%%
%% Ten restarts a minute is a fault that will not go away by itself; beyond that the
%% adapter gives up and the cell runs on without it (the application is temporary in
%% the release).
-module(cell_shdr_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    Flags = #{strategy => rest_for_one, intensity => 10, period => 60},
    Children = [#{id => cell_shdr_cache, start => {cell_shdr_cache, start_link, []}},
                #{id => cell_shdr_sampler, start => {cell_shdr_sampler, start_link, []}},
                #{id => cell_shdr_listener, start => {cell_shdr_listener, start_link, []}}],
    {ok, {Flags, Children}}.
