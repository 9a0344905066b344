%% A line of two cells on two nodes, as the line suites build it: the upstream cell runs
%% the first segment (`src'), the downstream cell the last (`sink') and the link `x1'
%% between them, each segment a `cell_line_task'.
-module(cell_line_nodes).

-export([spec/4, boot/3]).

%% @doc The cell spec of one side; `Args' are the line task's own (feed, out, ref,
%% notify, delay ...).
-spec spec(up | down, node(), node(), map()) -> map().
spec(up, _UpNode, DownNode, Args) ->
    #{tasks => [task(src, Args#{next => x1})],
      links => [#{id => x1, from => src, to => {sink, DownNode}}]};
spec(down, UpNode, _DownNode, Args) ->
    #{tasks => [task(sink, Args#{prev => x1})],
      links => [#{id => x1, from => {src, UpNode}, to => sink}]}.

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
