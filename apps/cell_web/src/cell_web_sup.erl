%% @doc The panel's supervisor.
%%
%% rest_for_one, in dependency order: the sessions table and the audit trail are used
%% by every request; the password hasher by logins; the listener serves the requests;
%% the recent log lines feed new websockets, the feed every connected one, the IO
%% watcher and the forces keeper send through the feed (last: a fault of theirs
%% restarts nothing else). The feed and
%% the recent lines stay when the cell's services restart: they attach again (see
%% {@link cell_attach}), so a burst of restarts in the cell costs this supervisor
%% nothing. Ten restarts a minute of the panel's own processes is a fault that will not
%% heal: beyond that the panel stops and says so, and the cell runs on (the release
%% starts this application as temporary: a panel's bug must never stop the machine).
-module(cell_web_sup).
-behaviour(supervisor).

-export([start_link/0]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% Only the panel's own faults count here: the feed and the recent lines attach
    %% again when the cell's events or the log server restart (see the module doc).
    Flags = #{strategy => rest_for_one, intensity => 10, period => 60},
    Children = [#{id => cell_web_sessions, start => {cell_web_sessions, start_link, []}},
                #{id => cell_web_audit, start => {cell_web_audit, start_link, []}},
                #{id => cell_web_hasher, start => {cell_web_hasher, start_link, []}},
                #{id => cell_web_listener, start => {cell_web_listener, start_link, []}},
                #{id => cell_web_recent, start => {cell_web_recent, start_link, []}},
                #{id => cell_web_feed, start => {cell_web_feed, start_link, []}},
                #{id => cell_web_io, start => {cell_web_io, start_link, []}},
                #{id => cell_web_forces, start => {cell_web_forces, start_link, []}}],
    {ok, {Flags, Children}}.
