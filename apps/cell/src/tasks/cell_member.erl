%% @doc The membership protocol of the cell's engines: what a device task's engine
%% ({@link cell_task_proc}) and a unit's engine ({@link cell_unit_proc}) do alike as
%% members of the cell, so that both follow one protocol and a fix lands once.
%%
%% <ul>
%% <li>Joining: the member's row in the registry (module, zone, lane, settings key,
%%     whether it does work), whether a predecessor of the same id crashed, and the
%%     controller's commands as they stand when it joins ({@link join/2}).</li>
%% <li>A predecessor that crashed: said in the log in an operator's words and
%%     published as a `task_crashed' event ({@link crashed/4}); {@link crash_text/1}
%%     says what ended it.</li>
%% <li>The controller's commands: `{control, Key, Value}' messages
%%     ({@link control/3}), and the bookkeeping every member does with them
%%     ({@link controlled/3}).</li>
%% <li>The emergency stop's barrier ({@link estop_secured/1}): each member marks its
%%     slot once its outputs are secured; the last one tells the controller.</li>
%% <li>Messages every member treats alike ({@link exit_signal/1},
%%     {@link unexpected/2}), and leaving the cell ({@link leave/2}).</li>
%% </ul>
-module(cell_member).

-export([entry/2, join/2, controls/0, control/3, controlled/3, estop_secured/1,
         crashed/4, crash_text/1, settings_key/1, exit_signal/1, unexpected/2, leave/2]).

-export_type([estop_barrier/0, controls/0, previous/0]).

%% The controller's emergency stop: an atomics array with a slot per member of the
%% fan-out and a count after them, the member's slot, the number of members, and whom
%% the last to secure its outputs tells.
-type estop_barrier() :: {atomics:atomics_ref(), pos_integer(), pos_integer(), pid()}.
%% The controller's commands as a member keeps them.
-type controls() :: #{request := start | pause | stop, estop := boolean(),
                      service_mode := boolean()}.
-type previous() :: fresh | clean | {crashed, term()}.

%% @doc The member's row in the registry as it joins: OFF, holding nothing, with
%% `Extra' (a unit's kind and lifecycle state) over it.
-spec entry(cell_task:spec(), map()) -> map().
entry(#{module := Mod, zone := Zone, lane := Lane} = Spec, Extra) ->
    maps:merge(#{module => Mod, zone => Zone, lane => Lane, state => off,
                 serial => undefined, settings_key => settings_key(Spec),
                 work => maps:get(work, Spec, true)},
               Extra).

%% @doc Registers the member with the cell (see {@link entry/2}): how its predecessor
%% of the same id ended, and the controller's commands as they stand now (read after
%% registering, so none sent meanwhile is missed: each comes as a message too).
-spec join(cell_task:spec(), map()) -> {previous(), controls()}.
join(#{id := Id} = Spec, Extra) ->
    Previous = cell_registry:register_task(Id, entry(Spec, Extra)),
    {Previous, controls()}.

%% @doc The controller's commands as the registry holds them.
-spec controls() -> controls().
controls() ->
    #{request => cell_registry:control(request), estop => cell_registry:control(estop),
      service_mode => cell_registry:control(service_mode)}.

%% @doc Sends a command of the controller to a member: `request' (start | pause |
%% stop), `estop' (`{true, Barrier}', see {@link estop_barrier()}, or `false'),
%% `estop_settled' (the barrier's atomics: every member secured its outputs),
%% `service_mode' (boolean), `settings' (the snapshot for the next start).
-spec control(pid(), request | estop | estop_settled | service_mode | settings, term()) -> ok.
control(Pid, Key, Value) ->
    Pid ! {control, Key, Value},
    ok.

%% @doc The bookkeeping of a command every member does alike: the request, the
%% emergency stop (which is a Stop too) and service mode as the member keeps them.
%% `estop_settled' and `settings' change none of them.
-spec controlled(atom(), term(), controls()) -> controls().
controlled(request, Request, C) when Request =:= start; Request =:= pause; Request =:= stop ->
    C#{request := Request};
controlled(estop, {true, _Barrier}, C) ->
    C#{estop := true, request := stop};
controlled(estop, false, C) ->
    C#{estop := false};
controlled(service_mode, On, C) when is_boolean(On) ->
    C#{service_mode := On};
controlled(estop_settled, _, C) ->
    C;
controlled(settings, Settings, C) when is_map(Settings) ->
    C.

%% @doc Marks the caller's slot of the emergency stop's barrier: its outputs are
%% secured. The last of the fan-out tells the controller.
-spec estop_secured(estop_barrier()) -> ok.
estop_secured({Ref, Slot, Total, Controller}) ->
    ok = atomics:put(Ref, Slot, 1),
    case atomics:add_get(Ref, Total + 1, 1) of
        Total -> Controller ! {estop_secured, Ref}, ok;
        _ -> ok
    end.

%% @doc A member restarted after its predecessor crashed: the log says so (`What', the
%% kind of member as the operator knows it, and `More', what the member does about it)
%% and a `task_crashed' event carries the reason.
-spec crashed(cell_task:task(), string(), io_lib:chars(), term()) -> ok.
crashed(Task, What, More, Why) ->
    Text = crash_text(Why),
    cell_log:error(cell_task:id(Task), "~ts restarted after a crash: ~ts~ts", [What, Text, More]),
    cell_task:publish(Task, task_crashed, #{reason => Text}).

%% @doc What ended a member's predecessor, in an operator's words.
-spec crash_text(term()) -> io_lib:chars().
crash_text({{product_not_saved, {Path, Reason}}, _}) ->
    io_lib:format("the product could not be saved to ~ts (~tp)", [Path, Reason]);
crash_text({{retained_not_saved, {Path, Reason}}, _}) ->
    io_lib:format("its retained data could not be saved to ~ts (~tp)", [Path, Reason]);
crash_text({{bad_retained, _, _} = Refused, _}) ->
    ["the task's code tried to retain what cannot be retained: ", cell_retain:text(Refused)];
crash_text({{unexpected_message, Msg}, _}) ->
    crash_text({unexpected_message, Msg});
crash_text({unexpected_message, Msg}) ->
    io_lib:format("it received a message it does not expect: ~tP", [Msg, 12]);
crash_text({Reason, Stack}) when is_list(Stack) ->
    io_lib:format("~tP", [Reason, 12]);
crash_text(killed) ->
    "it was killed";
crash_text(Reason) ->
    io_lib:format("~tP", [Reason, 12]).

%% @doc The name of the member's settings in the cell's settings, if its spec names
%% them (rather than giving them as a map).
-spec settings_key(cell_task:spec()) -> atom() | undefined.
settings_key(Spec) ->
    case maps:get(settings, Spec, #{}) of
        Name when is_atom(Name) -> Name;
        _ -> undefined
    end.

%% @doc An exit signal reaching a member (it traps exits): a linked process that ended
%% normally is nothing to it; any other reason ends the member with it.
-spec exit_signal(term()) -> ignore | {stop, term()}.
exit_signal(normal) -> ignore;
exit_signal(Reason) -> {stop, Reason}.

%% @doc A message no clause of the member's engine takes: a bug somewhere, so the
%% member crashes with it (and is restarted as after any crash), never ignores it.
-spec unexpected(atom(), term()) -> no_return().
unexpected(Id, Msg) ->
    cell_log:error(Id, "received a message it does not expect: ~tP", [Msg, 12]),
    erlang:error({unexpected_message, Msg}).

%% @doc The member's row leaves the registry when it ends on purpose (a Stop of the
%% cell, its removal); after a crash it stays, so its restart knows.
-spec leave(atom(), term()) -> ok.
leave(Id, normal) -> cell_registry:unregister_task(Id);
leave(Id, shutdown) -> cell_registry:unregister_task(Id);
leave(Id, {shutdown, _}) -> cell_registry:unregister_task(Id);
leave(_Id, _Reason) -> ok.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

spec() ->
    #{id => t, module => m, zone => <<"z">>, lane => <<"l">>}.

entry_test_() ->
    [?_assertEqual(#{module => m, zone => <<"z">>, lane => <<"l">>, state => off,
                     serial => undefined, settings_key => undefined, work => true},
                   entry(spec(), #{})),
     ?_assertMatch(#{settings_key := robot, work := false, kind := unit},
                   entry((spec())#{settings => robot, work => false}, #{kind => unit})),
     ?_assertMatch(#{settings_key := undefined}, entry((spec())#{settings => #{a => 1}}, #{}))].

controlled_test_() ->
    C = #{request => start, estop => false, service_mode => false},
    [?_assertEqual(C#{request := pause}, controlled(request, pause, C)),
     ?_assertEqual(C#{estop := true, request := stop}, controlled(estop, {true, barrier}, C)),
     ?_assertEqual(C, controlled(estop, false, C#{estop := true})),
     ?_assertEqual(C#{service_mode := true}, controlled(service_mode, true, C)),
     ?_assertEqual(C, controlled(estop_settled, ref, C)),
     ?_assertEqual(C, controlled(settings, #{speed => 1}, C)),
     ?_assertError(function_clause, controlled(request, go, C)),
     ?_assertError(function_clause, controlled(service_mode, yes, C))].

estop_secured_test() ->
    Ref = atomics:new(3, []),
    ok = estop_secured({Ref, 1, 2, self()}),
    receive {estop_secured, Ref} -> error(too_early) after 0 -> ok end,
    ok = estop_secured({Ref, 2, 2, self()}),
    ?assertEqual([1, 1, 2], [atomics:get(Ref, I) || I <- [1, 2, 3]]),
    receive {estop_secured, Ref} -> ok after 0 -> error(not_told) end.

crash_text_test_() ->
    T = fun(W) -> lists:flatten(io_lib:format("~ts", [crash_text(W)])) end,
    [?_assertEqual("it was killed", T(killed)),
     ?_assertEqual("badarith", T({badarith, [{m, f, 1, []}]})),
     ?_assertEqual("the product could not be saved to p (enospc)",
                   T({{product_not_saved, {<<"p">>, enospc}}, []})),
     ?_assertEqual("it received a message it does not expect: hello",
                   T({{unexpected_message, hello}, [{m, f, 1, []}]})),
     ?_assertEqual("{shutdown,x}", T({shutdown, x}))].

exit_signal_test_() ->
    [?_assertEqual(ignore, exit_signal(normal)),
     ?_assertEqual({stop, killed}, exit_signal(killed))].

unexpected_test() ->
    ?assertError({unexpected_message, hello}, unexpected(t, hello)).
-endif.
