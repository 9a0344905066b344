%% @doc A simulated code reader: a read takes the decode time and returns the code a
%% simulation placed in front of it, or `no_read' at the end of its read window when
%% there is none.
%%
%% Options: `decode_ms' (default 30), `read_window_ms' (300). Simulation controls:
%% {@link present/2}, {@link fail_next/2}, {@link set_link/2}.
-module(cell_hal_code_reader_sim).
-behaviour(cell_hal_code_reader).

-export([present/2, fail_next/2, set_link/2]).
-export([check_opts/1, init/2, read/2, handle_call/3, handle_info/2]).

-record(s, {decode_ms :: non_neg_integer(),
            window_ms :: non_neg_integer(),
            code :: binary() | none,
            fail :: term(),
            reading :: cell_hal_hw:from() | undefined}).

%% @doc Places a code in front of the reader (`none': nothing readable).
-spec present(atom(), binary() | none) -> ok | {error, term()}.
present(Id, Code) when is_binary(Code); Code =:= none ->
    cell_hal_hw:call(Id, {impl, {present, Code}}, 5000).

%% @doc The next read fails with `Reason'.
-spec fail_next(atom(), term()) -> ok | {error, term()}.
fail_next(Id, Reason) ->
    cell_hal_hw:call(Id, {impl, {fail_next, Reason}}, 5000).

%% @doc Unplugs (`down') or plugs (`up') the simulated reader.
-spec set_link(atom(), up | down) -> ok | {error, term()}.
set_link(Id, Link) when Link =:= up; Link =:= down ->
    cell_hal_hw:call(Id, {impl, {link, Link}}, 5000).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    Ms = fun(V) -> is_integer(V) andalso V >= 0 end,
    cell_hal_hw:check_opts(Opts, #{decode_ms => {30, Ms}, read_window_ms => {300, Ms}}).

%% @private
-spec init(atom(), map()) -> {ok, #s{}}.
init(_Id, #{decode_ms := D, read_window_ms := W}) ->
    {ok, #s{decode_ms = D, window_ms = W, code = none}}.

%% @private
-spec read(cell_hal_hw:from(), #s{}) -> {reply, {error, term()}, #s{}} | {noreply, #s{}}.
read(_From, #s{reading = Busy} = S) when Busy =/= undefined ->
    {reply, {error, busy}, S};
read(_From, #s{fail = Why} = S) when Why =/= undefined ->
    {reply, {error, Why}, S#s{fail = undefined}};
read(From, #s{code = none, window_ms = W} = S) ->
    _ = erlang:send_after(W, self(), {?MODULE, done, {error, no_read}}),
    {noreply, S#s{reading = From}};
read(From, #s{code = Code, decode_ms = D} = S) ->
    _ = erlang:send_after(D, self(), {?MODULE, done, {ok, Code}}),
    {noreply, S#s{reading = From}}.

%% @private
-spec handle_call(term(), cell_hal_hw:from(), #s{}) -> {reply, ok, #s{}}.
handle_call({present, Code}, _From, S) ->
    {reply, ok, S#s{code = Code}};
handle_call({fail_next, Why}, _From, S) ->
    {reply, ok, S#s{fail = Why}};
handle_call({link, Link}, _From, S) ->
    ok = cell_hal_hw:set_status(Link),
    {reply, ok, S}.

%% @private
-spec handle_info(term(), #s{}) -> {noreply, #s{}}.
handle_info({?MODULE, done, Result}, #s{reading = From} = S) ->
    cell_hal_hw:reply(From, Result),
    {noreply, S#s{reading = undefined}}.
