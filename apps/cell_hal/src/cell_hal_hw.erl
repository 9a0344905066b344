%% @doc Hardware objects (seed 000 §4.2): wrappers of the machine's cameras, code
%% readers, laser markers, axes and interpolation channels behind one interface per kind
%% ({@link cell_hal_camera}, {@link cell_hal_code_reader}, {@link
%% cell_hal_laser_marker}, {@link cell_hal_axis}, {@link cell_hal_channel}), created
%% from settings
%% by a factory, so a cell is configured rather than coded for its hardware.
%%
%% Settings name the implementation of each object by type, as the seed's
%% `Settings.CameraType' does:
%% ```
%% ok = cell_hal_hw:from_settings(#{camera => #{type => sim, opts => #{width => 320}},
%%                                  code_reader => #{type => sim},
%%                                  laser_marker => #{type => none}}).
%% '''
%% Each key is the object's id; `kind' may be given when the id is not itself a kind
%% (`#{top_camera => #{kind => camera, type => sim}}'). `type => none' means the
%% machine has no such hardware (the seed's `null'): nothing starts, and `present/1'
%% says so. Type `sim' is built in for every kind, `io' for code readers (one wired
%% through the PLC's IO, {@link cell_hal_code_reader_io}) and `ads' for axes (TwinCAT
%% NC, cell_hal_ads_axis in the cell_hal_ads application); a cell adds its own under the
%% application variable `hardware_types' of `cell_hal':
%% `#{{camera, ueye} => my_ueye_camera}'.
%%
%% Every object runs in its own process under `cell_hal_hw_sup'; its implementation
%% module is a callback module of its kind's behaviour, called by this generic server.
%% Operations (grab, read, mark) run one at a time, in the order asked, as a device
%% does them (an axis or a channel answers each command at once and tells of its job's
%% end by a message of its own, so a halt or a stop never waits behind a move): an implementation answers at once (`{reply, R, State}') or starts the
%% work and answers later from `handle_info/2', and never sees two at once. It reports
%% its connectivity with {@link set_status/1}: subscribers get `{cell_hal_hw, Id, up |
%% down}', and operations asked while it is down fail with `not_connected'. An
%% implementation starts up unless its `init' says `{ok, State, down}' (a device it
%% must reach first).
%%
%% An operation is asked and waited for ({@link call/3}), or asked without waiting
%% ({@link call_async/2}): the answer then comes as a message `{Ref, Answer}', which a
%% device task waits for with `{wait, [{reply, Ref}, {timer, Ms}], T}' (the timer for
%% an object that went away with the question).
-module(cell_hal_hw).
-behaviour(gen_server).

-export([add/1, from_settings/1, remove/1, list/0, present/1, status/1, subscribe/1,
         unsubscribe/1, watch/1]).
-export([call/3, call_async/2, set_status/1, check_opts/2]).
-export([start_link/4]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2, terminate/2]).

-export_type([kind/0, spec/0]).

-type kind() :: camera | code_reader | laser_marker | axis | channel.
-type spec() :: #{id := atom(), kind := kind(), type := atom(), opts => map()}.

-define(TAB, cell_hal_hw_objects).

%% Who asked: a caller waiting in gen_server:call, or one told by a message.
-type from() :: gen_server:from() | {async, pid(), reference()}.
-define(BUILT_IN, #{{camera, sim} => cell_hal_camera_sim,
                    {code_reader, sim} => cell_hal_code_reader_sim,
                    {code_reader, io} => cell_hal_code_reader_io,
                    {laser_marker, sim} => cell_hal_laser_marker_sim,
                    {axis, sim} => cell_hal_axis_sim,
                    %% TwinCAT NC over ADS, where the cell_hal_ads application is
                    %% in the release (else the type is refused as unknown).
                    {axis, ads} => cell_hal_ads_axis,
                    {channel, sim} => cell_hal_channel_sim,
                    {channel, ads} => cell_hal_ads_channel}).

-record(state, {id :: atom(),
                kind :: kind(),
                mod :: module(),
                impl :: term(),
                status = up :: up | down,
                busy :: from() | undefined,                %% the operation in progress
                waiting = queue:new() :: queue:queue({from(), term()}),
                subs = #{} :: #{pid() => reference()},
                %% Told `{cell_hal_hw_changed, Id}' when the object may have changed.
                watchers = #{} :: #{pid() => reference()}}).

%%====================================================================
%% Factory
%%====================================================================

%% @doc Creates one hardware object from its spec.
-spec add(spec()) -> ok | {error, {bad_option, atom()} | {already_exists, atom()} | term()}.
add(#{id := Id, kind := Kind, type := Type} = Spec) when is_atom(Id) ->
    Opts = maps:get(opts, Spec, #{}),
    case {is_kind(Kind), implementation(Kind, Type), is_map(Opts)} of
        {false, _, _} -> {error, {bad_option, kind}};
        {_, error, _} -> {error, {bad_option, type}};
        {_, _, false} -> {error, {bad_option, opts}};
        {true, none, true} -> ok;
        {true, {ok, Mod}, true} ->
            case Mod:check_opts(Opts) of
                {ok, Opts1} -> cell_hal_hw_sup:start_object(Id, Kind, Mod, Opts1);
                {error, _} = Error -> Error
            end
    end;
add(#{id := _, kind := _, type := _}) ->
    {error, {bad_option, id}};
add(Spec) when is_map(Spec) ->
    {error, {bad_option, hd([K || K <- [id, kind, type], not maps:is_key(K, Spec)])}};
add(_) ->
    {error, {bad_option, spec}}.

%% @doc Creates every hardware object the settings name (see the module's doc); stops
%% at the first that cannot be created, naming it.
-spec from_settings(#{atom() => #{type := atom(), kind => kind(), opts => map()}}) ->
          ok | {error, {atom(), term()}}.
from_settings(Settings) when is_map(Settings) ->
    add_all(lists:sort(maps:to_list(Settings))).

add_all([]) ->
    ok;
add_all([{Id, Object} | Rest]) when is_map(Object) ->
    case add(maps:merge(#{id => Id, kind => Id}, Object)) of
        ok -> add_all(Rest);
        {error, Why} -> {error, {Id, Why}}
    end;
add_all([{Id, _} | _]) ->
    {error, {Id, {bad_option, spec}}}.

%% @doc Stops and forgets a hardware object.
-spec remove(atom()) -> ok | {error, not_present}.
remove(Id) ->
    cell_hal_hw_sup:stop_object(Id).

%% @doc Every hardware object: id, kind and implementation module.
-spec list() -> [{atom(), kind(), module()}].
list() ->
    lists:sort([{Id, Kind, Mod} || {Id, _, Kind, Mod} <- ets:tab2list(?TAB)]).

%% @doc Whether the machine has this hardware object.
-spec present(atom()) -> boolean().
present(Id) ->
    ets:member(?TAB, Id).

%% @doc Whether a hardware object can be talked to now.
-spec status(atom()) -> up | down | {error, not_present}.
status(Id) ->
    case whereis_object(Id) of
        {ok, Pid} -> gen_server:call(Pid, status);
        error -> {error, not_present}
    end.

%% @doc Sends `{cell_hal_hw, Id, up | down}' to the caller on every change, and
%% returns the status now.
-spec subscribe(atom()) -> {ok, up | down} | {error, not_present}.
subscribe(Id) ->
    case whereis_object(Id) of
        {ok, Pid} -> gen_server:call(Pid, {subscribe, self()});
        error -> {error, not_present}
    end.

%% @doc Sends `{cell_hal_hw_changed, Id}' to the caller whenever the object may have
%% changed: a command or operation it took (not a question of its status), the end of
%% a job, anything its implementation handled (an axis publishing its position as it
%% moves, a fault) unless the implementation says nothing it shows changed (its
%% `handle_info/2' answers `{noreply, State, unchanged}': an axis whose poll at rest
%% read what it had), its connection. The caller reads what it shows (an axis's {@link
%% cell_hal_axis:status/1}) when it is ready to: a panel shows a moving axis at its own
%% pace, never falling behind. Answers the object's process, for the caller to monitor
%% (a restarted object has watchers no more).
-spec watch(atom()) -> {ok, pid()} | {error, not_present}.
watch(Id) ->
    case whereis_object(Id) of
        {ok, Pid} -> gen_server:call(Pid, {watch, self()});
        error -> {error, not_present}
    end.

%% @doc Ends the caller's subscription to an object's status (see {@link subscribe/1}).
-spec unsubscribe(atom()) -> ok.
unsubscribe(Id) ->
    case whereis_object(Id) of
        {ok, Pid} -> gen_server:call(Pid, {unsubscribe, self()});
        error -> ok
    end.

is_kind(K) -> lists:member(K, [camera, code_reader, laser_marker, axis, channel]).

implementation(_, none) ->
    none;
implementation(Kind, Type) ->
    Types = maps:merge(?BUILT_IN, application:get_env(cell_hal, hardware_types, #{})),
    case maps:find({Kind, Type}, Types) of
        {ok, Mod} when is_atom(Mod) ->
            case code:ensure_loaded(Mod) of
                {module, Mod} -> {ok, Mod};
                _ -> error
            end;
        _ ->
            error
    end.

%%====================================================================
%% For kind modules and implementations
%%====================================================================

%% @doc A request to a hardware object, answered within `Timeout' ms. An object of
%% another kind, or none, answers `{error, not_present}'.
-spec call(atom(), {kind(), term()} | {impl, term()}, timeout()) -> term().
call(Id, Request, Timeout) ->
    case whereis_object(Id) of
        {ok, Pid} ->
            try
                gen_server:call(Pid, Request, Timeout)
            catch
                exit:{timeout, _} -> {error, timeout};
                exit:{_, {gen_server, call, _}} -> {error, not_present}
            end;
        error ->
            {error, not_present}
    end.

%% @doc A request to a hardware object without waiting: the answer comes as
%% `{Ref, Answer}' to the caller, `{Ref, {error, not_present}}' at once when there is
%% no such object. An object that goes away with the question never answers: wait with
%% a deadline.
-spec call_async(atom(), {kind(), term()}) -> reference().
call_async(Id, Request) ->
    Ref = make_ref(),
    _ = case whereis_object(Id) of
            {ok, Pid} -> gen_server:cast(Pid, {async, self(), Ref, Request});
            error -> self() ! {Ref, {error, not_present}}
        end,
    Ref.

%% @doc Called by an implementation (in its own process) when the device comes and
%% goes; subscribers are told once the callback returns.
-spec set_status(up | down) -> ok.
set_status(Status) when Status =:= up; Status =:= down ->
    self() ! {'$cell_hal_hw_status', Status},
    ok.

%% @doc Checks an implementation's options against `#{Key => {Default, IsValid}}' and
%% fills in the defaults.
-spec check_opts(map(), #{atom() => {term(), fun((term()) -> boolean())}}) ->
          {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts, Known) ->
    case [K || {K, V} <- maps:to_list(Opts),
               not (maps:is_key(K, Known) andalso (element(2, maps:get(K, Known)))(V))] of
        [] -> {ok, maps:merge(maps:map(fun(_, {Default, _}) -> Default end, Known), Opts)};
        [K | _] -> {error, {bad_option, K}}
    end.

whereis_object(Id) ->
    case ets:lookup(?TAB, Id) of
        [{_, Pid, _, _}] when is_pid(Pid) -> {ok, Pid};
        _ -> error
    end.

%%====================================================================
%% gen_server
%%====================================================================

%% @private
-spec start_link(atom(), kind(), module(), map()) -> {ok, pid()} | {error, term()}.
start_link(Id, Kind, Mod, Opts) ->
    gen_server:start_link(?MODULE, {Id, Kind, Mod, Opts}, []).

%% @private
-spec init({atom(), kind(), module(), map()}) -> {ok, #state{}} | {stop, term()}.
init({Id, Kind, Mod, Opts}) ->
    process_flag(trap_exit, true),
    case Mod:init(Id, Opts) of
        {ok, Impl} ->
            true = ets:insert(?TAB, {Id, self(), Kind, Mod}),
            {ok, #state{id = Id, kind = Kind, mod = Mod, impl = Impl}};
        {ok, Impl, Status} when Status =:= up; Status =:= down ->
            true = ets:insert(?TAB, {Id, self(), Kind, Mod}),
            {ok, #state{id = Id, kind = Kind, mod = Mod, impl = Impl, status = Status}};
        {error, Why} ->
            {stop, Why}
    end.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) ->
          {reply, term(), #state{}} | {noreply, #state{}}.
handle_call(status, _From, #state{status = Status} = S) ->
    {reply, Status, S};
handle_call({subscribe, Pid}, _From, #state{subs = Subs, status = Status} = S) ->
    {reply, {ok, Status}, S#state{subs = monitored(Pid, Subs)}};
handle_call({unsubscribe, Pid}, _From, #state{subs = Subs} = S) ->
    case maps:take(Pid, Subs) of
        {MRef, Rest} ->
            erlang:demonitor(MRef, [flush]),
            {reply, ok, S#state{subs = Rest}};
        error ->
            {reply, ok, S}
    end;
handle_call({watch, Pid}, _From, #state{watchers = Ws} = S) ->
    {reply, {ok, self()}, S#state{watchers = monitored(Pid, Ws)}};
handle_call({impl, Request}, _From, #state{mod = Mod, impl = Impl} = S) ->
    {reply, Reply, Impl1} = Mod:handle_call(Request, Impl),
    {reply, Reply, changed(S#state{impl = Impl1})};
handle_call({_, _} = Request, From, S) ->
    operation(Request, From, S).

%% An operation of the object's kind, asked by a call or without waiting.
operation({Kind, _}, From, #state{kind = Other} = S) when Kind =/= Other ->
    reply(From, {error, not_present}),
    {noreply, S};
operation({_, _}, From, #state{status = down} = S) ->
    reply(From, {error, not_connected}),
    {noreply, S};
operation({_, Op}, From, #state{busy = undefined} = S) ->
    start(From, Op, S);
operation({_, Op}, From, #state{waiting = W} = S) ->
    {noreply, S#state{waiting = queue:in({From, Op}, W)}}.

reply({async, Pid, Ref}, Reply) ->
    Pid ! {Ref, Reply},
    ok;
reply(From, Reply) ->
    gen_server:reply(From, Reply).

%% Starts an operation; one that finishes at once lets the next waiting one start.
%% Watchers hear of every operation but a question of the status (their own).
start(From, Op, #state{kind = Kind, mod = Mod, impl = Impl} = S) ->
    Told = case Op of
               status -> fun(S1) -> S1 end;
               _ -> fun changed/1
           end,
    case dispatch(Kind, Op, Mod, Impl) of
        {reply, Reply, Impl1} ->
            reply(From, Reply),
            next(Told(S#state{impl = Impl1}));
        {noreply, Impl1} ->
            {noreply, Told(S#state{impl = Impl1, busy = From})}
    end.

%% Subscribers and watchers, each monitored once.
monitored(Pid, Pids) when is_map_key(Pid, Pids) -> Pids;
monitored(Pid, Pids) -> Pids#{Pid => erlang:monitor(process, Pid)}.

changed(#state{id = Id, watchers = Ws} = S) ->
    maps:foreach(fun(Pid, _) -> Pid ! {cell_hal_hw_changed, Id} end, Ws),
    S.

next(#state{waiting = W, status = Status} = S) ->
    case queue:out(W) of
        {{value, {From, _}}, W1} when Status =:= down ->
            reply(From, {error, not_connected}),
            next(S#state{waiting = W1});
        {{value, {From, Op}}, W1} ->
            start(From, Op, S#state{waiting = W1, busy = undefined});
        {empty, _} ->
            {noreply, S#state{busy = undefined}}
    end.

%% The operations of each kind's behaviour.
dispatch(camera, {grab, Opts}, Mod, Impl) -> Mod:grab(Opts, Impl);
dispatch(code_reader, read, Mod, Impl) -> Mod:read(Impl);
dispatch(laser_marker, {mark, Job}, Mod, Impl) -> Mod:mark(Job, Impl);
dispatch(axis, {command, Owner, Command}, Mod, Impl) -> Mod:command(Owner, Command, Impl);
dispatch(axis, {override, Pct}, Mod, Impl) -> Mod:set_override(Pct, Impl);
dispatch(axis, status, Mod, Impl) -> Mod:status(Impl);
dispatch(channel, {follow, Owner, Path, Params}, Mod, Impl) -> Mod:follow(Owner, Path, Params, Impl);
dispatch(channel, {halt, Owner, Dec}, Mod, Impl) -> Mod:halt(Owner, Dec, Impl);
dispatch(channel, {override, Pct}, Mod, Impl) -> Mod:set_override(Pct, Impl);
dispatch(channel, status, Mod, Impl) -> Mod:status(Impl).

%% @private
-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({async, Pid, Ref, {_, _} = Request}, S) when is_pid(Pid), is_reference(Ref) ->
    operation(Request, {async, Pid, Ref}, S);
handle_cast(Msg, _S) ->
    error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'$cell_hal_hw_status', Status}, #state{status = Status} = S) ->
    {noreply, S};
handle_info({'$cell_hal_hw_status', Status}, #state{id = Id, subs = Subs} = S) ->
    cell_log:notice(Id, "~s is ~s", [Id, case Status of up -> "connected";
                                                         down -> "disconnected" end]),
    maps:foreach(fun(Pid, _) -> Pid ! {cell_hal_hw, Id, Status} end, Subs),
    {noreply, changed(S#state{status = Status})};
handle_info({'DOWN', MRef, process, Pid, _}, #state{subs = Subs, watchers = Ws} = S)
  when is_map_key(Pid, Subs); is_map_key(Pid, Ws) ->
    Drop = fun(M) -> case M of
                         #{Pid := MRef} -> maps:remove(Pid, M);
                         #{} -> M
                     end
           end,
    {noreply, S#state{subs = Drop(Subs), watchers = Drop(Ws)}};
handle_info({'EXIT', _, _}, S) ->
    {noreply, S};
handle_info(Msg, #state{mod = Mod, impl = Impl, busy = Busy} = S) ->
    case Mod:handle_info(Msg, Impl) of
        {noreply, Impl1} ->
            {noreply, changed(S#state{impl = Impl1})};
        {noreply, Impl1, unchanged} ->
            {noreply, S#state{impl = Impl1}};
        {reply, Reply, Impl1} when Busy =/= undefined ->
            reply(Busy, Reply),
            next(changed(S#state{impl = Impl1}))
    end.

%% @private
-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, #state{id = Id, subs = Subs, busy = Busy, waiting = W}) ->
    true = ets:match_delete(?TAB, {Id, self(), '_', '_'}),
    %% Whoever asked is answered rather than left waiting for a deadline.
    _ = [reply(From, {error, not_present}) || From <- [Busy || Busy =/= undefined]
                                                  ++ [F || {F, _} <- queue:to_list(W)]],
    maps:foreach(fun(Pid, _) -> Pid ! {cell_hal_hw, Id, down} end, Subs),
    ok.
