%% A device task driven by its test: each step waits for a command sent as
%% `{Ref, Command}' (Ref is the task's `ref' argument) and does it. It counts its
%% steps, inits and uninits in the ETS table given as `tab', and tells the `notify'
%% process about each.
%%
%% Commands: {event, Fun} (a cell_task event function of arity 1), {error, Solutions},
%% reset, crash, {continue, N} (N steps that do not wait), {product, Map | undefined},
%% {timer, Ms}, {stuck, Ms} (a step that does not return for Ms: a task whose code
%% blocks). uninit also notes when it ran (`uninit_at/2'). reconcile records what it
%% was given (`recorded(Tab, Id, held)') and the answers to its question
%% (`recorded(Tab, Id, reconciled)'); `{reconcile_result, Id}' in the table set to
%% `{error, Solutions}' makes it ask until it is answered.
-module(cell_test_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).
-export([spec/3, command/3, counts/2, recorded/3, uninit_at/2]).

%% A spec for a task of this module.
-spec spec(atom(), ets:tid() | atom(), pid()) -> cell_task:spec().
spec(Id, Tab, Notify) ->
    #{id => Id, module => ?MODULE, zone => atom_to_binary(Id, utf8), lane => <<"Test">>,
      args => #{ref => make_ref(), tab => Tab, notify => Notify}}.

%% Sends a command to a running task of this module.
-spec command(atom(), reference(), term()) -> ok.
command(Id, Ref, Command) ->
    cell_task_proc:whereis(Id) ! {Ref, Command},
    ok.

-spec counts(ets:tid() | atom(), atom()) -> #{atom() => non_neg_integer()}.
counts(Tab, Id) ->
    maps:from_list([{K, N} || K <- [init, step, uninit],
                              N <- [case ets:lookup(Tab, {K, Id}) of
                                        [{_, C}] -> C;
                                        [] -> 0
                                    end]]).

-spec init(cell_task:task()) -> {ok, cell_task:task()} | {error, map(), cell_task:task()}.
init(T) ->
    count(T, init),
    case ets:lookup(cell_task:arg(T, tab, undefined), {init_result, cell_task:id(T)}) of
        [{_, {error, Solutions}}] ->
            {error, cell_task:error_spec(<<"init">>, "Init failed", "scripted", Solutions), T};
        _ ->
            {ok, T}
    end.

-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, map(), cell_task:task()}.
reconcile(Held, T) ->
    Tab = cell_task:arg(T, tab, undefined),
    case {cell_task:answer(T), ets:lookup(Tab, {reconcile_result, cell_task:id(T)})} of
        {undefined, [{_, {error, Solutions}}]} ->
            record(T, held, Held),
            {error, cell_task:error_spec(<<"where">>, "Where is it", "scripted", Solutions), T};
        {undefined, _} ->
            record(T, held, Held),
            {ok, T};
        {Answer, _} ->
            record(T, reconciled, {Answer, Held}),
            {ok, T}
    end.

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    count(T, step),
    Ref = cell_task:arg(T, ref, undefined),
    case cell_task:get(T, continue, 0) of
        N when N > 0 ->
            {continue, cell_task:put(T, continue, N - 1)};
        0 ->
            case cell_task:woken_by(T) of
                {reply, Ref, Command} ->
                    do(Command, T, Ref);
                {answer, Answer} ->
                    record(T, answers, Answer),
                    {wait, {reply, Ref}, T};
                _ ->
                    {wait, {reply, Ref}, T}
            end
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    true = ets:insert(cell_task:arg(T, tab, undefined),
                      {{uninit_at, cell_task:id(T)}, erlang:monotonic_time(microsecond)}),
    count(T, uninit),
    T.

%% The monotonic time (microseconds) of the task's last uninit.
-spec uninit_at(ets:tid() | atom(), atom()) -> integer() | undefined.
uninit_at(Tab, Id) ->
    case ets:lookup(Tab, {uninit_at, Id}) of
        [{_, At}] -> At;
        [] -> undefined
    end.

do({event, {identifier_read, Serial}}, T, Ref) ->
    {wait, {reply, Ref}, cell_task:identifier_read(T, Serial, <<"scanner">>)};
do({event, {Fun, Arg}}, T, Ref) -> {wait, {reply, Ref}, cell_task:Fun(T, Arg)};
do({event, Fun}, T, Ref) -> {wait, {reply, Ref}, cell_task:Fun(T)};
do({error, Solutions}, T, _Ref) ->
    {error, cell_task:error_spec(<<"step">>, "Step failed", "scripted", Solutions), T};
do(reset, T, _Ref) -> {reset, T};
do(crash, _T, _Ref) -> erlang:error(scripted_crash);
do({continue, N}, T, _Ref) -> {continue, cell_task:put(T, continue, N)};
do({product, undefined}, T, Ref) -> {wait, {reply, Ref}, cell_task:clear_product(T)};
do({product, P}, T, Ref) -> {wait, {reply, Ref}, cell_task:set_product(T, P)};
do({timer, Ms}, T, _Ref) -> {wait, {timer, Ms}, T};
do({stuck, Ms}, T, Ref) ->
    receive after Ms -> ok end,
    {wait, {reply, Ref}, T}.

%% Values a task recorded (the answers its steps received), oldest first.
-spec recorded(ets:tid() | atom(), atom(), atom()) -> [term()].
recorded(Tab, Id, What) ->
    case ets:lookup(Tab, {What, Id, list}) of
        [{_, L}] -> lists:reverse(L);
        [] -> []
    end.

record(T, What, Value) ->
    Id = cell_task:id(T),
    Tab = cell_task:arg(T, tab, undefined),
    Old = case ets:lookup(Tab, {What, Id, list}) of [{_, L}] -> L; [] -> [] end,
    true = ets:insert(Tab, {{What, Id, list}, [Value | Old]}).

count(T, What) ->
    Id = cell_task:id(T),
    Tab = cell_task:arg(T, tab, undefined),
    N = ets:update_counter(Tab, {What, Id}, 1, {{What, Id}, 0}),
    cell_task:arg(T, notify, self()) ! {cell_test_task, Id, What, N},
    ok.
