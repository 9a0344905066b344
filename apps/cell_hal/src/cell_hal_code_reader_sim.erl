%% @doc A simulated code reader: a read takes the decode time and returns the code a
%% simulation placed in front of it, or `no_read' at the end of its read window when
%% there is none.
%%
%% Options: `decode_ms' (default 30), `read_window_ms' (300). Simulation controls:
%% {@link present/2}, {@link fail_next/2}, {@link set_link/2}.
-module(cell_hal_code_reader_sim).
-behaviour(cell_hal_code_reader).

-export([present/2, fail_next/2, set_link/2]).
-export([check_opts/1, init/2, read/1, handle_call/2, handle_info/2]).

-record(s, {decode_ms :: non_neg_integer(),
            window_ms :: non_neg_integer(),
            code = none :: binary() | none,
            fail :: term()}).

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
    {ok, #s{decode_ms = D, window_ms = W}}.

%% @private
-spec read(#s{}) -> {reply, {error, term()}, #s{}} | {noreply, #s{}}.
read(#s{fail = Why} = S) when Why =/= undefined ->
    {reply, {error, Why}, S#s{fail = undefined}};
read(#s{code = none, window_ms = W} = S) ->
    _ = erlang:send_after(W, self(), {?MODULE, done, {error, no_read}}),
    {noreply, S};
read(#s{code = Code, decode_ms = D} = S) ->
    _ = erlang:send_after(D, self(), {?MODULE, done, {ok, Code}}),
    {noreply, S}.

%% @private
-spec handle_call(term(), #s{}) -> {reply, ok, #s{}}.
handle_call({present, Code}, S) ->
    {reply, ok, S#s{code = Code}};
handle_call({fail_next, Why}, S) ->
    {reply, ok, S#s{fail = Why}};
handle_call({link, Link}, S) ->
    ok = cell_hal_hw:set_status(Link),
    {reply, ok, S}.

%% @private
-spec handle_info(term(), #s{}) -> {reply, {ok, binary()} | {error, no_read}, #s{}}.
handle_info({?MODULE, done, Result}, S) ->
    {reply, Result, S}.
