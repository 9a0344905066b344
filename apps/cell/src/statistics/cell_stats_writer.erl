%% @doc Writes the history of {@link cell_stats} to the database, in batches, so that
%% the statistics process never waits on a table on the disc.
%%
%% A write to a table on the disc only (dets) waits for its answer with a receive
%% that looks through the whole mailbox of the writing process. The statistics
%% process has thousands of events queued in a burst: writing there, every write
%% looked through them all, and the process spent its time looking instead of
%% counting. This process has only its batches in its mailbox, and one at a time:
%% the statistics process hands it what it collected while the last batch was being
%% written (see `cell_stats:db/2').
%%
%% Each write is a fun run here, in the order given. The first that finds the database
%% gone (`exit:{aborted, Why}') ends the batch: it and the writes after it go back to
%% the statistics process, which keeps them until the database is open again.
-module(cell_stats_writer).
-behaviour(gen_server).

-export([start_link/0, write/3, write_now/2]).
-export([init/1, handle_call/3, handle_cast/2]).

-export_type([result/0]).

-type write() :: fun(() -> term()).
-type result() :: done | {failed, term(), [write()]}.

%% @doc Starts the writer of the calling process, linked to it.
-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    gen_server:start_link(?MODULE, [], []).

%% @doc Writes a batch; `{cell_stats_writer, N, result()}' comes back to the caller
%% when it is done.
-spec write(pid(), non_neg_integer(), [write()]) -> ok.
write(Writer, N, Writes) ->
    gen_server:cast(Writer, {write, self(), N, Writes}).

%% @doc Writes a batch after every batch handed over before, and returns when it is
%% done.
-spec write_now(pid(), [write()]) -> result().
write_now(Writer, Writes) ->
    gen_server:call(Writer, {write, Writes}, infinity).

-spec init([]) -> {ok, undefined}.
init([]) ->
    %% Writing the history never competes with the tasks, as counting does not.
    process_flag(priority, low),
    {ok, undefined}.

-spec handle_call({write, [write()]}, gen_server:from(), undefined) ->
          {reply, result(), undefined}.
handle_call({write, Writes}, _From, State) ->
    {reply, run(Writes), State}.

-spec handle_cast({write, pid(), non_neg_integer(), [write()]}, undefined) ->
          {noreply, undefined}.
handle_cast({write, Owner, N, Writes}, State) ->
    Owner ! {?MODULE, N, run(Writes)},
    {noreply, State}.

run([]) ->
    done;
run([Write | Rest] = Writes) ->
    try Write() of
        _ -> run(Rest)
    catch
        exit:{aborted, Why} -> {failed, Why, Writes}
    end.
