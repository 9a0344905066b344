%% A device task for the panel's tests, driven by its test: each step waits for a
%% command `{Ref, Command}' (Ref is the task's `ref' argument) and does it:
%% `{event, Fun}' (a cell_task event function of arity 1), `{error, Solutions}' (an
%% error for the operator), `{warning, Id, Caption}', `{product, Serial | undefined}',
%% `{log, Text}', `{retain, Key, Value}' and `{forget_retained, Key}' (retained data),
%% `{offer, Link}' (connects to the link as its upstream end and offers its product).
%% The answers its errors receive are sent to `notify' as
%% `{cell_web_demo_task, Id, answered, Solution}'.
-module(cell_web_demo_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).
-export([spec/4, command/3]).

%% A spec for a task of this module.
-spec spec(atom(), binary(), binary(), pid()) -> cell_task:spec().
spec(Id, Zone, Lane, Notify) ->
    #{id => Id, module => ?MODULE, zone => Zone, lane => Lane,
      args => #{ref => make_ref(), notify => Notify}}.

%% Sends a command to a running task of this module.
-spec command(cell_task:spec(), atom(), term()) -> ok.
command(#{args := #{ref := Ref}}, Id, Command) ->
    case cell_task_proc:whereis(Id) of
        undefined -> erlang:error({no_such_task, Id});
        Pid -> Pid ! {Ref, Command}, ok
    end.

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, T}.

%% No machine behind it: nothing to hold the record against.
-spec reconcile(cell_task:held(), cell_task:task()) -> {ok, cell_task:task()}.
reconcile(_Held, T) ->
    {ok, T}.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    Ref = cell_task:arg(T, ref, undefined),
    case cell_task:woken_by(T) of
        {reply, Ref, Command} ->
            do(Command, T, Ref);
        {answer, Answer} ->
            cell_task:arg(T, notify, self()) ! {?MODULE, cell_task:id(T), answered, Answer},
            {wait, {reply, Ref}, T};
        _ ->
            {wait, {reply, Ref}, T}
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    T.

do({event, Fun}, T, Ref) when is_atom(Fun) ->
    {wait, {reply, Ref}, cell_task:Fun(T)};
do({error, Solutions}, T, _Ref) ->
    {error, cell_task:error_spec(<<"jam">>, "Board jammed",
                                 "The board is stuck at the stopper.\nFree it, then select "
                                 "RETRY to check the sensor again.", Solutions), T};
do({retain, Key, Value}, T, Ref) ->
    {wait, {reply, Ref}, cell_task:retain(T, Key, Value)};
do({forget_retained, Key}, T, Ref) ->
    {wait, {reply, Ref}, cell_task:forget_retained(T, Key)};
do({warning, Id, Caption}, T, Ref) ->
    {wait, {reply, Ref}, cell_task:warning(T, Id, Caption, "Refill soon.")};
%% A product comes and goes as the seed says (§2.3.4): taken, then ItemTransferIn;
%% ItemTransferOut, then released.
do({product, undefined}, T, Ref) ->
    case cell_task:product(T) of
        undefined -> {wait, {reply, Ref}, T};
        #{serial := S} -> {wait, {reply, Ref}, cell_task:clear_product(cell_task:transfer_out(T, S))}
    end;
do({product, Serial}, T, Ref) ->
    T1 = cell_task:set_product(T, cell_product:new(Serial, <<"demo">>)),
    {wait, {reply, Ref}, cell_task:transfer_in(T1, Serial)};
do({offer, Link}, T, Ref) ->
    {ok, T1} = cell_handshake:connect(T, Link, up),
    {wait, {reply, Ref}, cell_handshake:offer(T1, Link)};
do({log, Text}, T, Ref) ->
    ok = cell_task:log(T, brief, "~ts", [Text]),
    {wait, {reply, Ref}, T}.
