%% @doc Code readers (seed 000 §4.2, `ICodeReader'): barcode and 2D-code readers that
%% identify a product. The behaviour an implementation follows and the API tasks use;
%% an implementation is a callback module run by {@link cell_hal_hw}.
-module(cell_hal_code_reader).

-export([read/2, read_async/1]).

-callback check_opts(Opts :: map()) -> {ok, map()} | {error, {bad_option, atom()}}.
%% `{ok, State, down}': the object starts down (a device it must reach first).
-callback init(Id :: atom(), Opts :: map()) ->
    {ok, State :: term()} | {ok, State :: term(), up | down} | {error, term()}.
%% Triggers one read: the code, or `{error, no_read}' when the reader found none within
%% its read window; answers now, or `noreply' and later from handle_info/2.
-callback read(State :: term()) ->
    {reply, {ok, binary()} | {error, term()}, State :: term()} | {noreply, State :: term()}.
%% Requests particular to the implementation (settings, simulation controls).
-callback handle_call(Request :: term(), State :: term()) -> {reply, term(), State :: term()}.
%% A message to the object's process; `reply' answers the operation in progress.
-callback handle_info(Msg :: term(), State :: term()) ->
    {noreply, State :: term()} | {reply, term(), State :: term()}.

%% @doc Triggers one read.
-spec read(atom(), timeout()) -> {ok, binary()} | {error, term()}.
read(Id, Timeout) ->
    cell_hal_hw:call(Id, {code_reader, read}, Timeout).

%% @doc Triggers one read without waiting: the answer comes as the message `{Ref,
%% {ok, Code} | {error, Why}}' (`no_read', `not_connected', `timeout', `not_present',
%% ...). A device task waits for it with `{wait, [{reply, Ref}, {timer, Ms}], T}', the
%% timer for a reader that went away with the question.
-spec read_async(atom()) -> reference().
read_async(Id) ->
    cell_hal_hw:call_async(Id, {code_reader, read}).
