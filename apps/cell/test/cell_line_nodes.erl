%% A line of cells on nodes of their own, as the line suites build it, each cell one
%% segment (a `cell_line_task'): of two, the upstream cell runs the first segment
%% (`src'), the downstream cell the last (`sink') and the link `x1' between them; of
%% more, the segments between are `mid2', `mid3' ..., and link `xI' joins cell I to cell
%% I + 1 and runs on the node of cell I + 1, so every cell but the first hosts a link.
-module(cell_line_nodes).

-export([spec/4, line_spec/3, task_of/2, boot/3]).

%% @doc The cell spec of one side; `Args' are the line task's own (feed, out, ref,
%% notify, delay ...).
-spec spec(up | down, node(), node(), map()) -> map().
spec(up, _UpNode, DownNode, Args) ->
    #{tasks => [task(src, Args#{next => x1})],
      links => [#{id => x1, from => src, to => {sink, DownNode}}]};
spec(down, UpNode, _DownNode, Args) ->
    #{tasks => [task(sink, Args#{prev => x1})],
      links => [#{id => x1, from => {src, UpNode}, to => sink}]}.

%% @doc The cell spec of cell `Which' of the line `Line' (its cells in flow order, each
%% with its node); `Args' as for spec/4.
-spec line_spec(atom(), [{atom(), node()}], map()) -> map().
line_spec(Which, Line, Args) ->
    N = length(Line),
    I = index(Which, Line),
    Id = task_of(I, N),
    Prev = [#{id => link_id(I - 1), from => {task_of(I - 1, N), node_at(I - 1, Line)}, to => Id}
            || I > 1],
    Next = [#{id => link_id(I), from => Id, to => {task_of(I + 1, N), node_at(I + 1, Line)}}
            || I < N],
    Own = maps:from_list([{prev, link_id(I - 1)} || I > 1] ++ [{next, link_id(I)} || I < N]),
    #{tasks => [task(Id, maps:merge(Args, Own))], links => Prev ++ Next}.

%% @doc The task of the I-th of N cells.
-spec task_of(pos_integer(), pos_integer()) -> atom().
task_of(1, _N) -> src;
task_of(N, N) -> sink;
task_of(I, _N) -> list_to_atom("mid" ++ integer_to_list(I)).

index(Which, Line) ->
    length(lists:takewhile(fun({W, _}) -> W =/= Which end, Line)) + 1.

node_at(I, Line) ->
    element(2, lists:nth(I, Line)).

link_id(I) ->
    list_to_atom("x" ++ integer_to_list(I)).

%% @doc Starts the cell of `Spec' on a node, its root folder `Root', through `Call' (how
%% the suite calls a function on that node).
-spec boot(fun((module(), atom(), [term()]) -> term()), file:filename(), map()) -> ok.
boot(Call, Root, Spec) ->
    [ok = Call(application, load, [A]) || A <- [lager, cell_base, cell_hal, cell]],
    ok = Call(application, set_env, [lager, handlers,
                                     [{lager_console_backend, [{level, critical}]}]]),
    ok = Call(application, set_env, [cell_base, root, Root]),
    ok = Call(application, set_env, [cell, cell_spec, Spec]),
    {ok, _} = Call(application, ensure_all_started, [cell]),
    ok.

task(Id, Args) ->
    #{id => Id, module => cell_line_task, zone => atom_to_binary(Id, utf8),
      lane => <<"Line">>, args => Args}.
