%% @doc Supervises the log server. The log server owns the per-source level table
%% and installs the log file handlers; nothing else here keeps state.
-module(cell_base_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% A log server that keeps crashing points at a broken disk; give up after a few
    %% tries a minute rather than spin, so the node reports it.
    Flags = #{strategy => one_for_one, intensity => 5, period => 60},
    Children = [#{id => cell_log_server, start => {cell_log_server, start_link, []}}],
    {ok, {Flags, Children}}.
