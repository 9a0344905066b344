%% @doc Supervises the handshake links this node runs, one gen_server each,
%% one_for_one: a link that crashes comes back empty and greets its partners, who
%% attach again; the transfer it held ends as interrupted on both sides, never as a
%% deadlock. Links crashing in a loop point at a bug: beyond ten a minute the
%% controller's tree is restarted and the tasks come back stopped.
-module(cell_handshake_sup).
-behaviour(supervisor).

-export([start_link/1]).
-export([init/1]).

-spec start_link([cell_handshake_link:spec()]) -> {ok, pid()} | ignore | {error, term()}.
start_link(Links) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, Links).

-spec init([cell_handshake_link:spec()]) ->
          {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(Links) ->
    %% One link's crash is its own (its partners attach again); ten a minute is a bug
    %% that escalates to the controller (see the module doc).
    Flags = #{strategy => one_for_one, intensity => 10, period => 60},
    {ok, {Flags, [cell_handshake_link:child_spec(L) || L <- Links]}}.
