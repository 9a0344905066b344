%% @doc Supervises one {@link cell_inspect_block} per block the cell declares.
-module(cell_inspect_block_sup).
-behaviour(supervisor).

-export([start_link/1]).
-export([init/1]).

-spec start_link([cell_inspect_block:spec()]) -> {ok, pid()} | ignore | {error, term()}.
start_link(Specs) ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, Specs).

%% @private
-spec init([cell_inspect_block:spec()]) ->
          {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init(Specs) ->
    %% A block restarts on its own (the PLC keeps its state); one that keeps crashing
    %% stops the inspection app, which is temporary: the cell runs on, and the PLC sees
    %% the heartbeat stop.
    {ok, {#{strategy => one_for_one, intensity => 5, period => 60},
          [#{id => Id, start => {cell_inspect_block, start_link, [S]}, shutdown => 5000}
           || #{id := Id} = S <- Specs]}}.
