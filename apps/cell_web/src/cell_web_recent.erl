%% @doc The latest lines of the task log, kept in memory for the panel: a page that
%% connects shows them at once, without reading the day's log file.
%%
%% Subscribed to `cell_log'; the lines sit in an ETS table that websockets read
%% directly. If the log server restarts, this process restarts with it and subscribes
%% again.
-module(cell_web_recent).
-behaviour(gen_server).

-export([start_link/0, lines/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(TAB, cell_web_recent_lines).
-define(KEEP, 200).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The latest lines, oldest first.
-spec lines() -> [cell_log:line()].
lines() ->
    [L || {_, L} <- ets:tab2list(?TAB)].

-spec init([]) -> {ok, reference()}.
init([]) ->
    ?TAB = ets:new(?TAB, [named_table, ordered_set, protected, {read_concurrency, true}]),
    ok = cell_log:subscribe(),
    {ok, monitor(process, cell_log_server)}.

-spec handle_call(term(), gen_server:from(), reference()) -> no_return().
handle_call(Msg, _From, _State) ->
    erlang:error({unexpected_call, Msg}).

-spec handle_cast(term(), reference()) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), reference()) -> {noreply, reference()} | {stop, term(), reference()}.
handle_info({cell_log, Line}, Ref) ->
    true = ets:insert(?TAB, {erlang:unique_integer([monotonic]), Line}),
    case ets:info(?TAB, size) > ?KEEP of
        true -> true = ets:delete(?TAB, ets:first(?TAB));
        false -> ok
    end,
    {noreply, Ref};
handle_info({'DOWN', Ref, process, _, Reason}, Ref) ->
    {stop, {log_server_down, Reason}, Ref}.
