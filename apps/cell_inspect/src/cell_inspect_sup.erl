%% @doc The inspection app's top supervisor. It owns the table where each block
%% publishes what it shows (read without a process hop by the API and the panel).
%%
%% `rest_for_one' in dependency order: the pg scope where the blocks' views are
%% published; blocks announce themselves to the panel and keep their clients under the
%% client supervisor, so both come before the blocks.
-module(cell_inspect_sup).
-behaviour(supervisor).

-export([start_link/1]).
-export([init/1]).

-spec start_link([cell_inspect_block:spec()]) -> {ok, pid()} | ignore | {error, term()}.
start_link(Blocks) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, Blocks).

%% @private
-spec init([cell_inspect_block:spec()]) ->
          {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(Blocks) ->
    ok = cell_inspect_block:create_table(),
    %% The blocks attach again to the cell's settings when they restart, so only the
    %% app's own faults count here. Three escalations a minute mean the app cannot run:
    %% it stops (a temporary app: an inspection fault must never stop the cell).
    Flags = #{strategy => rest_for_one, intensity => 3, period => 60},
    {ok, {Flags, [#{id => pg, start => {pg, start_link, [cell_inspect]}},
                  #{id => cell_inspect_panel, start => {cell_inspect_panel, start_link, []}},
                  sup(cell_inspect_client_sup, []),
                  sup(cell_inspect_block_sup, [Blocks])]}}.

sup(Mod, Args) ->
    #{id => Mod, start => {Mod, start_link, Args}, type => supervisor, shutdown => infinity}.
