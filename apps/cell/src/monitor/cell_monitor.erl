%% @doc The background monitor (seed 000 §2.4): the process that connects the HAL of the
%% cell, watches the general IO, the drives, every connection and hardware object, and
%% drives the beacon. Its decisions are made by {@link cell_monitor_core}; this process
%% only observes and carries them out.
%%
%% <b>Creation</b> (§2.4.1): one registered process in `cell_controller_sup', after
%% the tasks and before the controller. It adds the connections, groups and hardware
%% objects of the cell spec's `hal' key ({@link cell_monitor_spec}) itself, from its
%% first event (`init/1' does no I/O); a piece the HAL refuses is an alarm naming it,
%% and the rest runs on. Connections and objects already there (left by a monitor that
%% crashed) are taken over as they are, so a restart of the monitor costs the tasks
%% no IO.
%%
%% <b>Watching</b> (§2.4.2): everything is a message — HAL subscriptions to the
%% inputs, connection status (`{cell_hal_conn, C, up | down}'), hardware status
%% (`{cell_hal_hw, Id, up | down}'), the cell's events, settings changes, answers to
%% its errors and its own timers (blink, reset pulses, start-up grace, retries). An
%% input's message is only a cue: its value is read fresh from the HAL, so messages
%% that cross a read never take the monitor back to an older value.
%%
%% Commands to the controller (`estop/2', `service_mode/2') are sent as they are
%% decided; while the controller is not running (it starts after the monitor, and
%% restarts on its own) the latest of each is kept and tried again, 10 ms after the
%% first failure and up to 1 s apart. The emergency-stop flag is set by
%% `cell_controller:estop/2' in this process before it calls the controller, so no
%% task starts a step meanwhile.
%%
%% A hardware object whose process goes away (restarted by the HAL, or lost with its
%% supervisor) is attached again: subscribed to, or created again from the spec, 100 ms
%% after it went and up to 5 s apart until it is back.
%%
%% What the HAL's server cannot take while it is away (restarting: `{error,
%% disconnected}') — a connection or group to add, a connection or input to subscribe
%% to — waits, in order, for the HAL's `{cell_hal_back, Ref}' ({@link
%% cell_hal:notify_back/0}); meanwhile the connection is down for the core and its
%% inputs unknown.
%%
%% <b>Termination</b> (§2.4.3): when the cell application stops (any shutdown by the
%% supervisor), the monitor sets the beacon dark and the drives' reset outputs off,
%% then removes the hardware objects, groups and connections it added: the HAL is
%% disconnected by the process that connected it. A crash leaves the HAL connected for
%% the monitor's restart.
-module(cell_monitor).
-behaviour(gen_statem).

-export([start_link/1, child_spec/1, info/0]).
-export([callback_mode/0, init/1, handle_event/4, terminate/3]).

-type spec() :: #{hal := cell_monitor_spec:hal(), monitor := cell_monitor_spec:monitor()}.
-type state() :: starting | watching.

-define(RETRY_MIN, 10).
-define(RETRY_MAX, 1000).
-define(ATTACH_MIN, 100).
-define(ATTACH_MAX, 5000).
-define(TASK, cell).
-define(LOG, monitor).
-define(SAFE_WRITE_MS, 500).
%% Who the controller is told raised or released an emergency stop of the circuit.
-define(CIRCUIT, <<"emergency stop circuit">>).
-define(EVENTS, [cell_state, alarm_raised, alarm_cleared, estop, service_mode]).

-record(data, {spec :: spec(),
               core :: cell_monitor_core:core() | undefined,
               inputs = #{} :: #{atom() => [cell_monitor_spec:point()]}, %% per connection
               added = [] :: [{connection | group | hardware, atom()}],  %% newest first
               pending = [] :: [{estop | service_mode, boolean()}],    %% for the controller
               retry_ms = ?RETRY_MIN :: pos_integer(),
               attach = #{} :: #{atom() => pos_integer()},            %% hardware: backoff
               hw = #{} :: #{reference() => atom()},                  %% hardware: monitors
               %% what the HAL's server, away, could not take: done again, in order,
               %% when it says it is back (`back')
               away = [] :: [{add, connection | group, map()} | {connection, atom()}
                             | {input, cell_monitor_spec:point()}],
               back :: reference() | undefined}).

%%====================================================================
%% API
%%====================================================================

%% @doc Starts the monitor and returns once it has connected the HAL and attached to
%% everything it watches: the controller, started next, finds the cell's IO in place.
-spec start_link(spec()) -> gen_statem:start_ret().
start_link(Spec) ->
    case gen_statem:start_link({local, ?MODULE}, ?MODULE, Spec, []) of
        {ok, Pid} ->
            %% attach is the first event the monitor handles; a call is answered after it.
            ok = gen_statem:call(Pid, sync, infinity),
            {ok, Pid};
        Other ->
            Other
    end.

%% @doc The child spec for `cell_controller_sup', from the cell spec. Shutdown leaves
%% time to set the outputs safe and take the HAL down.
-spec child_spec(map()) -> supervisor:child_spec().
child_spec(CellSpec) ->
    Spec = #{hal => maps:get(hal, CellSpec, cell_monitor_spec:empty_hal()),
             monitor => maps:get(monitor, CellSpec, cell_monitor_spec:empty_monitor())},
    #{id => ?MODULE, start => {?MODULE, start_link, [Spec]}, shutdown => 10000}.

%% @doc What the monitor sees and does: the beacon's lamps, the inputs, the outputs
%% as commanded, devices, drives, the speed override in force, what it added to the
%% HAL.
-spec info() -> map().
info() ->
    gen_statem:call(?MODULE, info).

%%====================================================================
%% gen_statem
%%====================================================================

%% @private
-spec callback_mode() -> handle_event_function.
callback_mode() -> handle_event_function.

%% @private
-spec init(spec()) -> {ok, starting, #data{}, [{next_event, internal, attach}]}.
init(Spec) ->
    %% terminate/3 runs at shutdown: the HAL is taken down by this process.
    process_flag(trap_exit, true),
    {ok, starting, #data{spec = Spec}, [{next_event, internal, attach}]}.

%% @private
-spec handle_event(gen_statem:event_type(), term(), state(), #data{}) ->
          gen_statem:event_handler_result(state()).

%%--------------------------------------------------------------------
%% starting: the HAL is connected and everything is subscribed to, once.
%%--------------------------------------------------------------------
handle_event(internal, attach, starting, #data{spec = #{hal := Hal, monitor := Mon}} = D) ->
    case cell_monitor_spec:is_empty(Hal, Mon) of
        true -> {next_state, watching, D};
        false -> attach(D)
    end;
handle_event({call, _}, _Request, starting, _D) ->
    {keep_state_and_data, [postpone]};

%%--------------------------------------------------------------------
%% watching: observations go to the core, its effects are carried out.
%%--------------------------------------------------------------------
handle_event(info, {cell_hal, {_, _} = P, _Cue}, watching, D) ->
    core({point, P, read(P)}, D);
handle_event(info, {cell_hal_fault, {_, _} = P, _WhyOrCleared}, watching, D) ->
    %% The PLC refuses the point (or serves it again): unknown while it cannot be read.
    core({point, P, read(P)}, D);
handle_event(info, {cell_hal_conn, Conn, _Cue}, watching, D) ->
    connection(Conn, D);
handle_event(info, {cell_hal_back, Ref}, watching, #data{back = Ref} = D) ->
    again(D);
handle_event(info, {cell_hal_hw, Id, up}, watching, D) ->
    core({device, {hardware, Id}, up}, D);
handle_event(info, {cell_hal_hw, Id, down}, watching, D) ->
    core({device, {hardware, Id}, {down, <<>>}}, D);
handle_event(info, {'DOWN', MRef, process, _, Why}, watching, #data{hw = Hw} = D)
  when is_map_key(MRef, Hw) ->
    %% The object's process ended (the HAL restarts it, or lost it): its successor is
    %% looked for at once, and the object created again if there is none.
    {Id, Hw1} = maps:take(MRef, Hw),
    cell_log:info(?LOG, "~ts: its process ended (~tp); attaching again", [Id, Why]),
    attach_hardware(Id, D#data{hw = Hw1});
handle_event(info, {cell_event, _}, watching, D) ->
    core({cell, cell_controller:flags()}, D);
handle_event(info, {cell_settings, changed, machine}, watching, D) ->
    core({speed, cell_settings:get(machine, speed_override)}, D);
handle_event(info, {cell_settings, changed, monitor}, watching, D) ->
    core({settings, cell_settings:get(monitor)}, D);
handle_event(info, {cell_settings, changed, _Other}, watching, _D) ->
    keep_state_and_data;
handle_event(info, {cell_alarm, answer, Id, Solution, _Who}, watching, D) ->
    Prefix = <<(atom_to_binary(?TASK))/binary, ":">>,
    case Id of
        <<Prefix:(byte_size(Prefix))/binary, Local/binary>> -> core({answer, Local, Solution}, D);
        _ -> keep_state_and_data
    end;
handle_event({timeout, controller}, controller, watching, D) ->
    controller(D);
handle_event({timeout, {attach, Id}}, {attach, Id}, watching, D) ->
    attach_hardware(Id, D);
handle_event({timeout, _}, Timer, watching, D) ->
    core({timeout, Timer}, D);
handle_event({call, From}, sync, watching, _D) ->
    {keep_state_and_data, [{reply, From, ok}]};
handle_event({call, From}, info, watching, #data{core = Core, added = Added}) ->
    Info = case Core of
               undefined -> #{};
               _ -> cell_monitor_core:info(Core)
           end,
    {keep_state_and_data, [{reply, From, Info#{hal => lists:reverse(Added)}}]};

%%--------------------------------------------------------------------
%% Every state
%%--------------------------------------------------------------------
handle_event(info, Msg, _State, _D) ->
    %% Late answers and monitors of what is gone: noted for the programmer only.
    cell_log:trace(?LOG, "unexpected message ~tp", [Msg]),
    keep_state_and_data.

%% @private
-spec terminate(term(), state(), #data{}) -> ok.
terminate(Reason, _State, #data{added = Added} = D) when Reason =:= normal;
                                                          Reason =:= shutdown ->
    safe_outputs(D),
    lists:foreach(fun remove/1, Added),
    _ = Added =/= [] andalso cell_log:notice(?LOG, "HAL disconnected: ~ts", [summary(Added)]),
    ok;
terminate(Reason, _State, _D) ->
    cell_log:error(?LOG, "monitor stopped (~tp); the HAL stays connected for its restart",
                   [Reason]),
    ok.

%%====================================================================
%% Attaching
%%====================================================================

attach(#data{spec = #{hal := Hal, monitor := Mon} = Spec} = D0) ->
    ok = cell_settings:register(cell_monitor_settings),
    ok = cell_settings:subscribe(),
    ok = cell_events:subscribe(?EVENTS),
    #{connections := Conns, groups := Groups, hardware := Hw} = Hal,
    D1 = lists:foldl(fun(C, Di) -> add(connection, C, fun cell_hal:add_connection/1, Di) end,
                     D0, Conns),
    D2 = lists:foldl(fun(G, Di) -> add(group, G, fun cell_hal:add_group/1, Di) end, D1, Groups),
    D3 = lists:foldl(fun(#{type := none}, Di) -> Di;
                        (H, Di) -> add(hardware, H, fun hw_add/1, Di)
                     end, D2, Hw),
    Info = cell_monitor_spec:points(Hal, Mon),
    Inputs = maps:groups_from_list(fun(P) -> maps:get(connection, maps:get(P, Info)) end,
                                   [P || {P, #{dir := in}} <- lists:sort(maps:to_list(Info))]),
    %% An emergency stop the circuit raised before this monitor (its predecessor's, or
    %% one whose call to the controller was still pending when it was replaced) is
    %% this monitor's to release when the circuit is closed.
    {Core, Effects} = cell_monitor_core:new(Spec, #{settings => cell_settings:get(monitor),
                                                    speed => speed(),
                                                    cell => cell_controller:flags(),
                                                    estop_raised => cell_controller:estop_by()
                                                                    =:= ?CIRCUIT}),
    {D4, A4} = effects(Effects, D3#data{core = Core, inputs = Inputs}, []),
    %% Devices, then inputs: each subscribed to first, read after, so a change in
    %% between is seen in a message or in the read, never in neither.
    Steps = [fun(Di) -> connection_subscribe(Id, Di) end || #{id := Id} <- Conns]
        ++ [fun(Di) -> step(attach_hardware(Id, Di)) end
            || #{id := Id} <- Hw, added(hardware, Id, D4)]
        ++ [fun(Di) -> input_subscribe(P, Di) end || P <- lists:append(maps:values(Inputs))]
        ++ [fun(Di) -> core_step(start, Di) end],
    {D5, A5} = lists:foldl(fun(Step, {Di, Ai}) ->
                                   {Dj, Aj} = Step(Di),
                                   {Dj, Ai ++ Aj}
                           end, {D4, A4}, Steps),
    {next_state, watching, D5, A5}.

added(Kind, Id, #data{added = Added}) ->
    lists:member({Kind, Id}, Added).

%% Adds one piece of the HAL; one already there is taken over; one refused is an alarm.
add(Kind, #{id := Id} = Spec, Add, #data{added = Added} = D) ->
    AlarmId = <<"hal.", (atom_to_binary(Id))/binary>>,
    case Add(Spec) of
        ok ->
            ok = cell_alarms:clear_alarm(?TASK, AlarmId),
            D#data{added = [{Kind, Id} | Added]};
        {error, {already_exists, Id}} ->
            ok = cell_alarms:clear_alarm(?TASK, AlarmId),
            cell_log:info(?LOG, "~ts ~ts is already in the HAL: taken over as it is",
                          [kind_name(Kind), Id]),
            D#data{added = [{Kind, Id} | Added]};
        {error, disconnected} when Kind =:= hardware ->
            %% Attached as one whose process went away: created again from the spec,
            %% with its backoff, once the HAL's supervisor of hardware objects is back.
            cell_log:warning(?LOG, "the HAL is restarting: the ~ts ~ts is created when it "
                             "is back", [kind_name(Kind), Id]),
            D#data{added = [{Kind, Id} | Added]};
        {error, disconnected} ->
            cell_log:warning(?LOG, "the HAL is restarting: the ~ts ~ts is added when it is "
                             "back", [kind_name(Kind), Id]),
            away({add, Kind, Spec}, D);
        {error, Why} ->
            Text = io_lib:format("The HAL refused the ~ts ~ts of the cell spec: ~tp. "
                                 "Correct the cell's configuration and restart the cell.",
                                 [kind_name(Kind), Id, Why]),
            ok = cell_alarms:alarm(?TASK, AlarmId, "IO configuration refused", Text),
            cell_log:error(?LOG, "~ts", [Text]),
            D
    end.

kind_name(connection) -> "connection";
kind_name(group) -> "IO group";
kind_name(hardware) -> "hardware object".

connection_subscribe(Conn, D) ->
    case cell_hal:subscribe_connection(Conn) of
        {ok, _} -> step(connection(Conn, D));
        {error, unknown_connection} -> {D, []};
        {error, disconnected} -> step(hal_away(Conn, away({connection, Conn}, D)))
    end.

input_subscribe({G, P} = Point, D) ->
    case cell_hal:subscribe(G, P) of
        ok -> core_step({point, Point, read(Point)}, D);
        {error, unknown_point} -> {D, []};
        {error, disconnected} -> core_step({point, Point, unknown}, away({input, Point}, D))
    end.

%% The HAL's server is away (it restarts): what could not be done then is done when
%% it says it is back, one message asked for however much waits.
away(Step, #data{away = Away, back = Back} = D) ->
    D#data{away = Away ++ [Step],
           back = case Back of
                      undefined -> cell_hal:notify_back();
                      _ -> Back
                  end}.

%% The HAL's server is back: what waited is done again, in the order it came (pieces
%% added before what is subscribed to in them); what finds it away again waits again.
again(#data{away = Away} = D0) ->
    cell_log:info(?LOG, "the HAL is back: what waited for it is done again", []),
    Steps = [fun(Di) -> redo(Step, Di) end || Step <- Away],
    {D, A} = lists:foldl(fun(Step, {Di, Ai}) ->
                                 {Dj, Aj} = Step(Di),
                                 {Dj, Ai ++ Aj}
                         end, {D0#data{away = [], back = undefined}, []}, Steps),
    {keep_state, D, A}.

redo({add, connection, Spec}, D) -> {add(connection, Spec, fun cell_hal:add_connection/1, D), []};
redo({add, group, Spec}, D) -> {add(group, Spec, fun cell_hal:add_group/1, D), []};
redo({connection, Conn}, D) -> connection_subscribe(Conn, D);
redo({input, Point}, D) -> input_subscribe(Point, D).

%% A connection the monitor cannot follow while the HAL's server is away: down, its
%% inputs unknown, as for a lost connection (what the core does with a connection
%% that is down: an alarm after its grace, the beacon, nothing taken from its inputs).
hal_away(Conn, #data{inputs = Inputs} = D) ->
    Events = [{point, P, unknown} || P <- maps:get(Conn, Inputs, [])]
        ++ [{device, {connection, Conn}, {down, <<"the HAL is restarting">>}}],
    lists:foldl(fun(E, {keep_state, Di, Ai}) ->
                        {keep_state, Dj, Aj} = core(E, Di),
                        {keep_state, Dj, Ai ++ Aj}
                end, {keep_state, D, []}, Events).

core_step(Event, D) ->
    step(core(Event, D)).

step({keep_state, D, Actions}) -> {D, Actions}.

%% A connection's status as it is now, then its inputs as they are now.
connection(Conn, #data{inputs = Inputs} = D) ->
    Points = maps:get(Conn, Inputs, []),
    Events = case cell_hal:status(Conn) of
                 up ->
                     [{device, {connection, Conn}, up}]
                         ++ [{point, P, read(P)} || P <- Points];
                 _ ->
                     [{point, P, unknown} || P <- Points]
                         ++ [{device, {connection, Conn}, {down, down_detail(Conn)}}]
             end,
    lists:foldl(fun(E, {keep_state, Di, Ai}) ->
                        {keep_state, Dj, Aj} = core(E, Di),
                        {keep_state, Dj, Ai ++ Aj}
                end, {keep_state, D, []}, Events).

down_detail(Conn) ->
    case cell_hal:info(Conn) of
        {ok, #{endpoint := Ep, reason := <<>>}} -> Ep;
        {ok, #{endpoint := Ep, reason := Why}} -> <<Why/binary, " (", Ep/binary, ")">>;
        {error, _} -> <<>>
    end.

%% Subscribes to a hardware object and monitors its process, creating it again from
%% the spec if it is gone; tried again with a backoff while it cannot be found.
attach_hardware(Id, #data{spec = #{hal := #{hardware := Hw}}, attach = Backoff} = D) ->
    [Spec] = [H || #{id := I} = H <- Hw, I =:= Id],
    Found = case subscribe_hardware(Id) of
                {error, not_present} ->
                    _ = hw_add(Spec),
                    subscribe_hardware(Id);
                Status ->
                    Status
            end,
    case Found of
        {ok, Status1, Pid} ->
            MRef = erlang:monitor(process, Pid),
            %% An object may start down (one that must reach its device first): as its
            %% message `down' says it.
            Device = case Status1 of
                         up -> up;
                         down -> {down, <<>>}
                     end,
            core({device, {hardware, Id}, Device},
                 D#data{attach = maps:remove(Id, Backoff), hw = (D#data.hw)#{MRef => Id}});
        {error, not_present} ->
            Wait = maps:get(Id, Backoff, ?ATTACH_MIN),
            {keep_state, D1, A1} = core({device, {hardware, Id}, {down, <<>>}}, D),
            {keep_state, D1#data{attach = Backoff#{Id => min(2 * Wait, ?ATTACH_MAX)}},
             A1 ++ [{{timeout, {attach, Id}}, Wait, {attach, Id}}]}
    end.

%% The object's status and process. The HAL's supervisor of hardware objects names
%% each child by the object's id; the process may end between finding it and calling
%% it.
subscribe_hardware(Id) ->
    case [Pid || {I, Pid, _, _} <- hw_children(), I =:= Id, is_pid(Pid)] of
        [Pid] ->
            try cell_hal_hw:subscribe(Id) of
                {ok, Status} -> {ok, Status, Pid};
                {error, not_present} -> {error, not_present}
            catch
                exit:{_, {gen_server, call, _}} -> {error, not_present}
            end;
        [] ->
            {error, not_present}
    end.

%% The HAL's supervisor of hardware objects restarts with its server: while it is
%% away there is no object to find, and none can be created (`disconnected', as the
%% HAL's own calls say).
hw_children() ->
    try supervisor:which_children(cell_hal_hw_sup)
    catch exit:{_, {gen_server, call, [cell_hal_hw_sup | _]}} -> []
    end.

hw_add(Spec) ->
    try cell_hal_hw:add(Spec)
    catch exit:{_, {gen_server, call, [cell_hal_hw_sup | _]}} -> {error, disconnected}
    end.

read({G, P}) ->
    case cell_hal:read(G, P) of
        {ok, V} -> V;
        {error, _} -> unknown
    end.

speed() ->
    cell_settings:get(machine, speed_override).

%%====================================================================
%% Effects
%%====================================================================

core(Event, #data{core = Core} = D) ->
    {Core1, Effects} = cell_monitor_core:handle(Event, Core),
    {D1, Actions} = effects(Effects, D#data{core = Core1}, []),
    {keep_state, D1, Actions}.

effects([], D, Actions) ->
    {D, lists:reverse(Actions)};
effects([{estop, On} | Rest], D, A) ->
    {D1, A1} = command({estop, On}, D),
    effects(Rest, D1, lists:reverse(A1, A));
effects([{service_mode, On} | Rest], D, A) ->
    {D1, A1} = command({service_mode, On}, D),
    effects(Rest, D1, lists:reverse(A1, A));
effects([{warning, Id, Caption, Text} | Rest], D, A) ->
    ok = cell_alarms:warning(?TASK, Id, Caption, Text),
    effects(Rest, D, A);
effects([{reset_warning, Id} | Rest], D, A) ->
    ok = cell_alarms:reset_warning(?TASK, Id),
    effects(Rest, D, A);
effects([{error, Id, Caption, Text} | Rest], D, A) ->
    {ok, _} = cell_alarms:raise_error(?TASK, #{id => Id, caption => Caption,
                                               description => Text, solutions => [retry]},
                                      self()),
    effects(Rest, D, A);
effects([{withdraw, Id} | Rest], D, A) ->
    ok = cell_alarms:withdraw(<<(atom_to_binary(?TASK))/binary, ":", Id/binary>>),
    effects(Rest, D, A);
effects([{write, {G, P}, V} | Rest], D, A) ->
    %% A group the HAL refused has its alarm already: its outputs are not written.
    _ = added(group, G, D) andalso write(G, P, V),
    effects(Rest, D, A);
effects([{timer, T, Ms} | Rest], D, A) ->
    effects(Rest, D, [{{timeout, T}, Ms, T} | A]);
effects([{cancel, T} | Rest], D, A) ->
    effects(Rest, D, [{{timeout, T}, cancel} | A]);
effects([{log, Level, Format, Args} | Rest], D, A) ->
    cell_log:log(Level, ?LOG, Format, Args),
    effects(Rest, D, A);
effects([{override, Kind, Id, Pct} | Rest], D, A) ->
    Set = case Kind of
              axis -> cell_hal_axis:set_override(Id, Pct);
              channel -> cell_hal_channel:set_override(Id, Pct)
          end,
    _ = case Set of
            ok -> ok;
            %% Not added yet, or down: it is told when it comes (up again).
            {error, Away} when Away =:= not_present; Away =:= not_connected -> ok;
            {error, Why} -> cell_log:warning(?LOG, "cannot set the speed override of ~ts: ~tp",
                                             [Id, Why])
        end,
    effects(Rest, D, A).

write(G, P, V) ->
    case cell_hal:write(G, P, V) of
        ok -> ok;
        %% Written again when the connection is back.
        {error, disconnected} -> ok;
        {error, Why} -> cell_log:error(?LOG, "cannot write ~ts.~ts: ~tp", [G, P, Why])
    end.

%% A command for the controller: the latest of each kind is kept until it is taken.
command({Kind, _} = Cmd, #data{pending = Pending} = D) ->
    step(controller(D#data{pending = lists:keydelete(Kind, 1, Pending) ++ [Cmd]})).

controller(#data{pending = Pending} = D) ->
    Left = [Cmd || Cmd <- Pending, send(Cmd) =:= not_running],
    case Left of
        [] ->
            {keep_state, D#data{pending = [], retry_ms = ?RETRY_MIN},
             [{{timeout, controller}, cancel}]};
        _ ->
            Wait = D#data.retry_ms,
            {keep_state, D#data{pending = Left, retry_ms = min(2 * Wait, ?RETRY_MAX)},
             [{{timeout, controller}, Wait, controller}]}
    end.

send({Kind, On}) ->
    Who = case Kind of
              estop -> ?CIRCUIT;
              service_mode -> <<"service key">>
          end,
    try cell_controller:Kind(On, Who)
    catch
        exit:{Why, {gen_server, call, _}} when Why =:= noproc; Why =:= normal;
                                                Why =:= shutdown;
                                                element(1, Why) =:= shutdown ->
            not_running
    end.

%%====================================================================
%% Termination
%%====================================================================

%% The beacon dark, the drives' reset outputs off, each confirmed by the device or
%% given up after a short wait (a connection that is down refuses at once).
safe_outputs(#data{spec = #{monitor := #{io := Io, drives := Drives}}}) ->
    Lamps = [P || {Role, P} <- maps:to_list(Io), lists:member(Role, cell_monitor_spec:outputs())],
    Resets = [P || #{reset := P} <- Drives],
    lists:foreach(fun({G, P}) ->
                          Write = fun() -> cell_hal:write_sync(G, P, false, ?SAFE_WRITE_MS) end,
                          _ = catch_exit(Write)
                  end, lists:usort(Lamps ++ Resets)).

remove({Kind, Id}) ->
    Remove = case Kind of
                 connection -> fun() -> cell_hal:remove_connection(Id) end;
                 group -> fun() -> cell_hal:remove_group(Id) end;
                 hardware -> fun() -> cell_hal_hw:remove(Id) end
             end,
    log_removal(Kind, Id, catch_exit(Remove)).

log_removal(_Kind, _Id, ok) ->
    ok;
log_removal(Kind, Id, Other) ->
    cell_log:warning(?LOG, "~ts ~ts not removed from the HAL: ~tp", [kind_name(Kind), Id, Other]).

%% At termination the HAL may itself be stopping: a call that finds nobody is noted.
catch_exit(Fun) ->
    try Fun()
    catch exit:{Why, {gen_server, call, _}} -> {error, Why};
          exit:{Why, {gen_statem, call, _}} -> {error, Why}
    end.

summary(Added) ->
    Count = fun(K) -> length([x || {Kind, _} <- Added, Kind =:= K]) end,
    io_lib:format("~b connections, ~b IO groups, ~b hardware objects removed",
                  [Count(connection), Count(group), Count(hardware)]).
