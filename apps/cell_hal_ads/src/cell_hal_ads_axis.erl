%% @doc An axis of TwinCAT NC over ADS (type `ads' of kind `axis', see {@link
%% cell_hal_axis}): PLCopen's states kept by {@link cell_hal_axis_fsm} as for the
%% simulated axis, each command and its effects written to the NC's ADS interface
%% (AMS port 500) as {@link cell_hal_ads_nc} maps them, and the NC's online state read
%% back to learn of each job's end and of faults.
%%
%% ```
%% #{id => x, kind => axis, type => ads,
%%   opts => #{host => "10.0.0.5", target_net_id => "10.0.0.5.1.1", axis => 1,
%%             limits => {0.0, 1200.0}}}
%% '''
%%
%% == How the end of a job is learnt ==
%% The online state is polled: one ADS Read of the online structure every `poll_ms'
%% (default 20) while a job runs, every `idle_poll_ms' (default 200) at rest, so a
%% fault of a standing axis is seen too. Device notifications would spare the polls,
%% but the ADS client subscribes to PLC symbols by name, and the NC's axis state is an
%% index group of port 500 without symbols; a notification by index group and offset
%% is not in the client yet. A poll is sent without waiting ({@link
%% cell_hal_ads_client:send_request/5}): the object answers status and commands
%% meanwhile. The object's watchers ({@link cell_hal_hw:watch/1}) hear of a poll only
%% when what the status shows changed, as of the simulated axis: an axis at rest tells
%% them nothing.
%%
%% == The connection ==
%% The axis holds its own ADS client to the NC's port 500 (`host', `target_net_id',
%% `port', `source_net_id', `source_port', `timeout_ms' as for {@link cell_hal_ads}).
%% It starts down and is up once connected and the NC's state has been read: its
%% PLCopen state is then rebuilt from the NC's (powered if the controller is enabled,
%% homed if referenced, ErrorStop with the NC's error). A lost connection makes the
%% object down: commands and status are refused with `{error, not_connected}', the
%% job that ran ends with `{Ref, {error, not_connected}}' (nobody knows what the NC
%% does with it), and the client is started again after `reconnect_ms', doubling up to
%% `max_reconnect_ms' while it fails.
%%
%% == What is written ==
%% Power: the controller and both feed enables of the NC's cyclic axis interface.
%% Home: the NC's reference (homing) function, then, once referenced, the actual
%% position set to the position asked. Moves: an absolute start with velocity,
%% acceleration, deceleration and `jerk' (a relative move is made absolute by the state
%% machine). Halt and stop: the NC's stop with the deceleration given. Reset: the NC's
%% reset. Override: the velocity override of the cyclic interface (percent times
%% 10000). Coupled motion (an interpolation channel's `follow') is not offered.
-module(cell_hal_ads_axis).
-behaviour(cell_hal_axis).

-export([check_opts/1, init/2, command/3, set_override/2, status/1, handle_call/2,
         handle_info/2]).

-record(s, {id :: atom(),
            opts :: map(),
            ctx :: cell_hal_ads_nc:ctx(),
            fsm :: cell_hal_axis_fsm:axis(),
            watch :: cell_hal_ads_nc:watch(),
            online :: cell_hal_ads_nc:online() | undefined,
            client :: pid() | undefined,
            monitor :: reference() | undefined,
            up = false :: boolean(),
            %% Polls sent without waiting, labelled with their client: one may still
            %% be answered (or its client's end told) after that client was given up.
            reqs = gen_statem:reqids_new() :: cell_hal_ads_client:request_ids(),
            polling = false :: boolean(),         % a poll of the present client is out
            %% That poll went out before a command's writes were answered: what it
            %% reads may predate the command, and is dropped.
            stale = false :: boolean(),
            poll_timer :: reference() | undefined,
            backoff :: pos_integer(),
            %% Who is told of each job's end: {Pid, Ref} by job id.
            owners = #{} :: #{pos_integer() => {pid(), reference()}}}).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    cell_hal_ads_nc_conn:check_opts(
      Opts, #{axis => {undefined, fun(A) -> is_integer(A) andalso A >= 1 andalso A =< 255 end},
              limits => {none, fun limits/1},
              jerk => {100000, fun positive/1},
              in_position => {0.01, fun(V) -> is_number(V) andalso V >= 0 end},
              rotary => {false, fun erlang:is_boolean/1}},
      [axis]).

positive(V) -> is_number(V) andalso V > 0.
limits(none) -> true;
limits({Min, Max}) -> is_number(Min) andalso is_number(Max) andalso Min < Max;
limits(_) -> false.

%% @private
-spec init(atom(), map()) -> {ok, #s{}, down}.
init(Id, #{axis := Axis, jerk := Jerk, in_position := Tol, limits := Limits,
           reconnect_ms := Backoff} = Opts) ->
    self() ! {?MODULE, connect},
    {ok, #s{id = Id, opts = Opts, ctx = #{axis => Axis, jerk => Jerk, in_position => Tol},
            fsm = cell_hal_axis_fsm:new(#{limits => Limits}),
            watch = cell_hal_ads_nc:watch(undefined), backoff = Backoff}, down}.

%% @private
-spec command(pid(), cell_hal_axis_fsm:command(), #s{}) ->
          {reply, {ok, reference()} | {error, term()}, #s{}}.
command(_Owner, {follow, _}, S) ->
    {reply, {error, {unsupported, follow}}, S};
command(_Owner, _Command, #s{up = false} = S) ->
    {reply, {error, not_connected}, S};
command(Owner, Command, #s{fsm = Fsm, ctx = Ctx, watch = W} = S) ->
    case cell_hal_axis_fsm:command(Command, position(S), Fsm) of
        {ok, Fsm1, Effects} ->
            Extra = cell_hal_ads_nc:command_writes(Command, cell_hal_axis_fsm:state(Fsm), Ctx),
            {Writes, W1} = cell_hal_ads_nc:effect_writes(Effects, W, Ctx),
            case write(Extra ++ Writes, S) of
                ok ->
                    Ref = make_ref(),
                    S1 = case [J || {run, #{id := J}} <- Effects] of
                             [JobId] -> S#s{owners = (S#s.owners)#{JobId => {Owner, Ref}}};
                             [] -> Owner ! {Ref, done}, S
                         end,
                    S2 = tell_all(Effects, S1#s{fsm = Fsm1, watch = W1,
                                                stale = S1#s.polling}),
                    {reply, {ok, Ref}, poll_soon(S2)};
                {error, Why} ->
                    {reply, {error, {nc_refused, Why}}, S}
            end;
        {error, _} = Error ->
            {reply, Error, S}
    end.

%% @private
-spec set_override(number(), #s{}) -> {reply, ok | {error, term()}, #s{}}.
set_override(Pct, #s{fsm = Fsm, ctx = Ctx, watch = W} = S) ->
    case cell_hal_axis_fsm:set_override(Pct, Fsm) of
        {ok, Fsm1, Effects} ->
            {Writes, W1} = cell_hal_ads_nc:effect_writes(Effects, W, Ctx),
            case write(Writes, S) of
                ok -> {reply, ok, S#s{fsm = Fsm1, watch = W1}};
                {error, Why} -> {reply, {error, {nc_refused, Why}}, S}
            end;
        {error, _} = Error ->
            {reply, Error, S}
    end.

%% @private
-spec status(#s{}) -> {reply, cell_hal_axis:status(), #s{}}.
status(#s{fsm = Fsm, online = Online} = S) ->
    V = case Online of
            #{velocity := Vel} -> Vel;
            undefined -> 0.0
        end,
    {reply, #{state => cell_hal_axis_fsm:state(Fsm), position => position(S),
              velocity => V, error => cell_hal_axis_fsm:error_code(Fsm),
              homed => cell_hal_axis_fsm:homed(Fsm),
              powered => cell_hal_axis_fsm:powered(Fsm),
              override => cell_hal_axis_fsm:override(Fsm)}, S}.

%% @private
-spec handle_call(term(), #s{}) -> no_return().
handle_call(Request, _S) ->
    error({unknown_call, Request}).

%% @private
%% Watchers hear only of what shows: a poll that reads the axis as it was (an axis at
%% rest, polled every `idle_poll_ms') tells them nothing.
-spec handle_info(term(), #s{}) -> {noreply, #s{}} | {noreply, #s{}, unchanged}.
handle_info(Msg, S) ->
    S1 = info(Msg, S),
    case shown(S1) =:= shown(S) of
        true -> {noreply, S1, unchanged};
        false -> {noreply, S1}
    end.

shown(S) ->
    {reply, Status, _} = status(S),
    Status.

info({?MODULE, connect}, #s{opts = Opts} = S) ->
    {Client, Mon} = cell_hal_ads_nc_conn:connect(Opts, 500),
    S#s{client = Client, monitor = Mon};
info({cell_hal_ads, Client, up}, #s{client = Client} = S) ->
    came_up(S);
info({cell_hal_ads, Client, {down, Reason}}, #s{client = Client, up = true} = S) ->
    lost(Reason, S);
info({cell_hal_ads, _Client, _}, S) ->
    %% A client of an earlier connection, the present state told on subscribing (down
    %% while it connects: its end, if it fails, comes by the monitor), or news the
    %% axis has no use for.
    S;
info({'DOWN', Mon, process, _, Reason}, #s{monitor = Mon} = S) ->
    lost(Reason, S#s{client = undefined, monitor = undefined});
info({timeout, Ref, poll}, #s{poll_timer = Ref} = S) ->
    poll(S#s{poll_timer = undefined});
info({timeout, _Stale, poll}, S) ->
    S;
info(Msg, #s{reqs = Reqs, client = Client} = S) ->
    case cell_hal_ads_client:check_response(Msg, Reqs) of
        {_Early, {poll, Client}, Rest} when S#s.stale ->
            poll(S#s{reqs = Rest, polling = false, stale = false});
        {Result, {poll, Client}, Rest} ->
            polled(Result, S#s{reqs = Rest, polling = false});
        {_Stale, {poll, _Earlier}, Rest} ->
            S#s{reqs = Rest};
        _ ->
            error({unexpected_message, Msg})
    end.

%%--------------------------------------------------------------------
%% The connection
%%--------------------------------------------------------------------

%% Connected: the NC's state read, the axis's state rebuilt from it, the override
%% written, then up.
came_up(#s{ctx = Ctx, fsm = Fsm, opts = #{limits := Limits} = Opts} = S) ->
    Override = cell_hal_axis_fsm:override(Fsm),
    case decoded(read_online(S)) of
        {ok, Online} ->
            Fresh = cell_hal_axis_fsm:new(#{limits => Limits}),
            S1 = S#s{online = Online, fsm = cell_hal_ads_nc:resync(Online, Fresh, Override),
                     watch = cell_hal_ads_nc:watch(undefined), up = true,
                     backoff = maps:get(reconnect_ms, Opts)},
            case write(cell_hal_ads_nc:request({override, Override}, Ctx), S1) of
                ok ->
                    ok = cell_hal_hw:set_status(up),
                    poll_soon(S1);
                {error, Why} ->
                    restart(Why, S1)
            end;
        {error, Why} ->
            restart(Why, S)
    end.

%% The connection failed or is lost: down, the job's owner told, the client started
%% again later.
lost(Reason, #s{id = Id, up = Up} = S) ->
    [cell_log:warning(Id, "axis ~s lost its NC: ~ts",
                      [Id, cell_hal_ads_client:format_error(Reason)]) || Up],
    ok = cell_hal_hw:set_status(down),
    S1 = cancel_poll(stop_client(S)),
    maps:foreach(fun(_, {Pid, Ref}) -> Pid ! {Ref, {error, not_connected}} end, S1#s.owners),
    Backoff = S1#s.backoff,
    _ = erlang:send_after(Backoff, self(), {?MODULE, connect}),
    S1#s{up = false, owners = #{}, watch = cell_hal_ads_nc:watch(undefined),
         polling = false, stale = false,
         backoff = min(Backoff * 2, maps:get(max_reconnect_ms, S1#s.opts))}.

%% A connection that answers wrongly is given up like a lost one.
restart(Why, S) ->
    lost(Why, S).

stop_client(#s{client = undefined} = S) ->
    S;
stop_client(#s{client = C, monitor = Mon} = S) ->
    ok = cell_hal_ads_nc_conn:disconnect(C, Mon),
    S#s{client = undefined, monitor = undefined}.

%%--------------------------------------------------------------------
%% Polling the online state
%%--------------------------------------------------------------------

poll(#s{up = false} = S) ->
    S;
poll(#s{polling = true} = S) ->
    %% One poll at a time; its answer schedules the next.
    S;
poll(#s{client = C, ctx = Ctx, reqs = Reqs, opts = #{timeout_ms := T}} = S) ->
    {read, G, O, N} = cell_hal_ads_nc:request(online, Ctx),
    {ok, Reqs1} = cell_hal_ads_client:send_request(C, {read, G, O, N}, T, {poll, C}, Reqs),
    S#s{reqs = Reqs1, polling = true}.

polled(Result, #s{up = false} = S) ->
    _ = Result,
    S;
polled(Result, #s{fsm = Fsm, watch = W, ctx = Ctx} = S) ->
    case decoded(Result) of
        {ok, Online} ->
            Context = #{state => cell_hal_axis_fsm:state(Fsm), ctx => Ctx},
            {Events, W1} = cell_hal_ads_nc:news(Online, W, Context),
            S1 = lists:foldl(fun event/2, S#s{online = Online, watch = W1}, Events),
            schedule(S1);
        {error, Why} ->
            restart(Why, S)
    end.

event(Event, #s{fsm = Fsm, watch = W, ctx = Ctx} = S) ->
    {Fsm1, Effects} = cell_hal_axis_fsm:event(Event, Fsm),
    {Writes, W1} = cell_hal_ads_nc:effect_writes(Effects, W, Ctx),
    S1 = S#s{fsm = Fsm1, watch = W1},
    case write(Writes, S1) of
        ok when Writes =:= [] ->
            tell_all(Effects, S1);
        ok ->
            %% What was written (the position a homing sets) is read back before
            %% the owner hears of the end: a status then shows it.
            case decoded(read_online(S1)) of
                {ok, Online} -> tell_all(Effects, S1#s{online = Online});
                {error, Why} -> restart(Why, S1)
            end;
        {error, Why} ->
            restart(Why, S1)
    end.

read_online(#s{client = C, ctx = Ctx, opts = #{timeout_ms := T}}) ->
    {read, G, O, N} = cell_hal_ads_nc:request(online, Ctx),
    cell_hal_ads_client:read(C, G, O, N, T).

decoded({ok, Bin}) -> cell_hal_ads_nc:decode_online(Bin);
decoded({error, _} = Error) -> Error.

poll_soon(#s{poll_timer = T, opts = Opts} = S) ->
    S#s{poll_timer = cell_hal_ads_nc_conn:rearm_poll(T, now, Opts)}.

schedule(#s{watch = #{job := Job}, poll_timer = T, opts = Opts} = S) ->
    When = case Job of undefined -> idle; _ -> running end,
    S#s{poll_timer = cell_hal_ads_nc_conn:rearm_poll(T, When, Opts)}.

cancel_poll(#s{poll_timer = T} = S) ->
    S#s{poll_timer = cell_hal_ads_nc_conn:cancel_poll(T)}.

%%--------------------------------------------------------------------

%% The writes one after the other, each answered before the next goes: the NC takes
%% them in that order.
write([], _S) ->
    ok;
write([{write, G, O, Data} | Rest], #s{client = C, opts = #{timeout_ms := T}} = S) ->
    case cell_hal_ads_client:write(C, G, O, Data, T) of
        ok -> write(Rest, S);
        {error, _} = Error -> Error
    end.

tell_all(Effects, S) ->
    lists:foldl(fun({done, #{id := Id}}, Sx) -> tell(Id, done, Sx);
                   ({aborted, #{id := Id}}, Sx) -> tell(Id, aborted, Sx);
                   ({failed, #{id := Id}, Code}, Sx) -> tell(Id, {error, Code}, Sx);
                   (_, Sx) -> Sx
                end, S, Effects).

tell(Id, What, #s{owners = Owners} = S) ->
    case maps:take(Id, Owners) of
        {{Pid, Ref}, Rest} -> Pid ! {Ref, What}, S#s{owners = Rest};
        error -> S
    end.

position(#s{online = #{position := X}}) -> X;
position(#s{online = undefined}) -> 0.0.
