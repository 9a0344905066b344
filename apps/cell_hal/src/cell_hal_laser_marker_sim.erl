%% @doc A simulated laser marker: a mark takes the set-up time plus a time per
%% character, and is remembered so a simulation or a test can see what was marked.
%%
%% Options: `setup_ms' (default 50), `ms_per_char' (5). Simulation controls: {@link
%% marks/1}, {@link fail_next/2}, {@link set_link/2}.
-module(cell_hal_laser_marker_sim).
-behaviour(cell_hal_laser_marker).

-export([marks/1, fail_next/2, set_link/2]).
-export([check_opts/1, init/2, mark/2, handle_call/2, handle_info/2]).

-record(s, {setup_ms :: non_neg_integer(),
            ms_per_char :: non_neg_integer(),
            marks = [] :: [cell_hal_laser_marker:job()],      %% newest first
            fail :: term()}).

%% @doc Every job marked so far, oldest first.
-spec marks(atom()) -> [cell_hal_laser_marker:job()] | {error, term()}.
marks(Id) ->
    cell_hal_hw:call(Id, {impl, marks}, 5000).

%% @doc The next mark fails with `Reason'.
-spec fail_next(atom(), term()) -> ok | {error, term()}.
fail_next(Id, Reason) ->
    cell_hal_hw:call(Id, {impl, {fail_next, Reason}}, 5000).

%% @doc Unplugs (`down') or plugs (`up') the simulated marker.
-spec set_link(atom(), up | down) -> ok | {error, term()}.
set_link(Id, Link) when Link =:= up; Link =:= down ->
    cell_hal_hw:call(Id, {impl, {link, Link}}, 5000).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    Ms = fun(V) -> is_integer(V) andalso V >= 0 end,
    cell_hal_hw:check_opts(Opts, #{setup_ms => {50, Ms}, ms_per_char => {5, Ms}}).

%% @private
-spec init(atom(), map()) -> {ok, #s{}}.
init(_Id, #{setup_ms := Setup, ms_per_char := PerChar}) ->
    {ok, #s{setup_ms = Setup, ms_per_char = PerChar}}.

%% @private
-spec mark(cell_hal_laser_marker:job(), #s{}) -> {reply, {error, term()}, #s{}} | {noreply, #s{}}.
mark(_Job, #s{fail = Why} = S) when Why =/= undefined ->
    {reply, {error, Why}, S#s{fail = undefined}};
mark(#{text := Text} = Job, #s{setup_ms = Setup, ms_per_char = PerChar} = S) ->
    _ = erlang:send_after(Setup + PerChar * byte_size(Text), self(), {?MODULE, marked, Job}),
    {noreply, S}.

%% @private
-spec handle_call(term(), #s{}) -> {reply, term(), #s{}}.
handle_call(marks, #s{marks = Marks} = S) ->
    {reply, lists:reverse(Marks), S};
handle_call({fail_next, Why}, S) ->
    {reply, ok, S#s{fail = Why}};
handle_call({link, Link}, S) ->
    ok = cell_hal_hw:set_status(Link),
    {reply, ok, S}.

%% @private
-spec handle_info(term(), #s{}) -> {reply, ok, #s{}}.
handle_info({?MODULE, marked, Job}, #s{marks = Marks} = S) ->
    {reply, ok, S#s{marks = [Job | Marks]}}.
