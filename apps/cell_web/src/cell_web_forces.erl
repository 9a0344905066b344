%% @doc The IO points forced from the panel: who may force, and the ends of forces
%% (the rules are {@link cell_web_force_rules}'; the forces themselves are held by the
%% HAL, {@link cell_hal_force}).
%%
%% Forces are added and released through this process, one at a time. It follows the
%% cell's `service_mode' and `estop' events: every force ends when service mode ends
%% and on an emergency stop; {@link user_left/1} ends a user's forces at logout. Each
%% force and release made through the REST API is in the audit trail (as every
%% request is); each release the panel makes on its own is recorded here, with why.
%% Every change is sent to the pages: `{"type": "forces", "forces": [...]}'.
%%
%% If the events restart, this process attaches again (see {@link cell_attach}) and
%% then looks at the cell's flags, since an end may have come meanwhile. When this
%% process starts (again) it ends the forces it finds: nobody watches them any more.
%% It watches the HAL's server too: when that restarts, the HAL ends every force (and
%% its connections write the forced outputs back, see {@link cell_hal_force}); this
%% process records the end of each force it knew of in the audit trail, "the IO
%% service restarted", and tells the pages.
-module(cell_web_forces).
-behaviour(gen_server).

-export([start_link/0, force/3, release/2, release_all/1, user_left/1, json/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(state, {watch = #{} :: cell_attach:watch(),
                retry :: reference() | undefined,
                backoff = cell_attach:first() :: pos_integer(),
                %% the HAL's server watched, and the forces as last set through here
                hal :: reference() | undefined,
                hal_retry :: reference() | undefined,
                known = [] :: [cell_hal_force:force()]}).

-define(CALL_TIMEOUT, 15000).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc Forces a point for a caller of the panel, if the rules let them.
-spec force(cell_web_req:caller(), {atom(), atom()}, cell_hal_type:value()) ->
          ok | {error, cowboy:http_status(), atom(), binary()}.
force(Caller, Key, Value) ->
    gen_server:call(?MODULE, {force, Caller, Key, Value}, ?CALL_TIMEOUT).

%% @doc Releases one forced point (needs the role service or higher).
-spec release(cell_web_req:caller(), {atom(), atom()}) ->
          ok | {error, cowboy:http_status(), atom(), binary()}.
release(Caller, Key) ->
    gen_server:call(?MODULE, {release, Caller, Key}, ?CALL_TIMEOUT).

%% @doc Releases every forced point (needs the role service or higher); how many.
-spec release_all(cell_web_req:caller()) ->
          {ok, non_neg_integer()} | {error, cowboy:http_status(), atom(), binary()}.
release_all(Caller) ->
    gen_server:call(?MODULE, {release_all, Caller}, ?CALL_TIMEOUT).

%% @doc A user logged out: their forces end.
-spec user_left(binary()) -> ok.
user_left(User) ->
    gen_server:call(?MODULE, {ended, {logout, User}}, ?CALL_TIMEOUT).

%% @doc The forces as the pages show them.
-spec json() -> [map()].
json() ->
    [cell_web_json:term(F) || F <- cell_hal_force:forces()].

%%--------------------------------------------------------------------

-spec init([]) -> {ok, #state{}}.
init([]) ->
    State = attach(#state{}),
    ok = ended(restarted),
    {ok, known(watch_hal(State))}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call(Request, From, State) ->
    {reply, Reply, State1} = call(Request, From, State),
    {reply, Reply, known(State1)}.

call({force, #{role := Role} = Caller, Key, Value}, _From, State) ->
    Reply = case may_force(Role) of
                ok ->
                    Who = cell_web_req:who_name(Caller),
                    case cell_hal_force:force(Key, Value, Who) of
                        ok ->
                            {G, P} = Key,
                            cell_log:warning(web, "~s.~s forced to ~ts by ~ts (service mode); "
                                             "the cell's own value is held until it is released",
                                             [G, P, cell_web_json:encode(Value), Who]),
                            ok = changed();
                        {error, Why} -> refused(Why)
                    end;
                {error, _, _, _} = E ->
                    E
            end,
    {reply, Reply, State};
call({release, Caller, Key}, _From, State) ->
    Reply = case may_release(Caller) of
                ok ->
                    case cell_hal_force:release(Key) of
                        ok ->
                            {G, P} = Key,
                            cell_log:notice(web, "~s.~s released by ~ts",
                                            [G, P, cell_web_req:who_name(Caller)]),
                            ok = changed();
                        {error, not_forced} -> {error, 404, not_forced,
                                                <<"this point is not forced">>}
                    end;
                E ->
                    E
            end,
    {reply, Reply, State};
call({release_all, Caller}, _From, State) ->
    Reply = case may_release(Caller) of
                ok ->
                    Forces = cell_hal_force:forces(),
                    _ = [cell_hal_force:release({G, P}) || #{group := G, point := P} <- Forces],
                    cell_log:notice(web, "~b forced IO point(s) released by ~ts",
                                    [length(Forces), cell_web_req:who_name(Caller)]),
                    ok = changed(),
                    {ok, length(Forces)};
                E ->
                    E
            end,
    {reply, Reply, State};
call({ended, Cause}, _From, State) ->
    {reply, ended(Cause), State}.

-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_event, #{type := service_mode, active := On}}, State) ->
    ok = ended({service_mode, On}),
    {noreply, known(State)};
handle_info({cell_event, #{type := estop, active := On}}, State) ->
    ok = ended({estop, On}),
    {noreply, known(State)};
handle_info({'DOWN', Ref, process, _, _}, #state{hal = Ref, known = Known} = State) ->
    %% The HAL ended these forces as its server went (see cell_hal_force).
    ok = lost(Known),
    {noreply, known(watch_hal(State#state{hal = undefined}))};
handle_info({timeout, TRef, cell_attach}, #state{hal_retry = TRef} = State) ->
    {noreply, known(watch_hal(State#state{hal_retry = undefined}))};
handle_info({'DOWN', Ref, process, _, _}, #state{watch = W} = State) when is_map_key(Ref, W) ->
    ok = cell_attach:unwatch(W),
    {noreply, attach(State#state{watch = #{}})};
handle_info({timeout, TRef, cell_attach}, #state{retry = TRef, backoff = B} = State) ->
    {noreply, attach(State#state{retry = undefined, backoff = cell_attach:next(B)})}.

%% Monitors the HAL's server; while it restarts, tried again a moment later.
watch_hal(#state{hal = undefined, hal_retry = undefined} = State) ->
    case whereis(cell_hal_server) of
        undefined -> State#state{hal_retry = cell_attach:retry_after(cell_attach:first())};
        Pid -> State#state{hal = erlang:monitor(process, Pid)}
    end;
watch_hal(State) ->
    State.

%% The forces as they are after a change made here.
known(State) ->
    State#state{known = cell_hal_force:forces()}.

%% Forces the HAL ended on its own: recorded, said, and shown.
lost([]) ->
    ok;
lost(Forces) ->
    {Ending, Why} = cell_web_force_rules:ending(io_restarted, Forces),
    _ = [audit(G, P, Why) || #{group := G, point := P} <- Ending],
    cell_log:warning(web, "~b forced IO point(s) released: the IO service restarted, and its "
                     "connections wrote the outputs back to the values the cell wants",
                     [length(Ending)]),
    changed().

%% Subscribes to the cell's service mode and emergency stop; once attached (again),
%% the flags as they are now end what they would have ended. While the cell's
%% services restart the flags cannot be read: tried again later, as the subscription.
attach(#state{retry = undefined, backoff = B} = State) ->
    Subscribe = fun() -> cell_events:subscribe([service_mode, estop]) end,
    case cell_attach:watch([cell_events], Subscribe) of
        {ok, Watch} ->
            case flags() of
                {ok, Flags} ->
                    ok = ended({estop, maps:get(estop, Flags, false)}),
                    ok = ended({service_mode, maps:get(service_mode, Flags, false)}),
                    State#state{watch = Watch, backoff = cell_attach:first()};
                restarting ->
                    ok = cell_attach:unwatch(Watch),
                    State#state{retry = cell_attach:retry_after(B)}
            end;
        retry ->
            State#state{retry = cell_attach:retry_after(B)}
    end;
attach(State) ->
    State.

%% The cell's flags, unless its services are restarting (their tables gone, the
%% controller not there).
flags() ->
    try {ok, cell_controller:flags()}
    catch
        error:badarg -> restarting;
        exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                           Why =:= killed; element(1, Why) =:= shutdown -> restarting
    end.

may_force(Role) ->
    case flags() of
        {ok, Flags} ->
            cell_web_force_rules:may_force(Role, Flags);
        restarting ->
            {error, 503, cell_restarting,
             <<"the cell's services are starting again; force in a moment">>}
    end.

%% Ends the forces a cause ends, each recorded in the audit trail with why.
ended(Cause) ->
    case cell_web_force_rules:ending(Cause, cell_hal_force:forces()) of
        {[], _} ->
            ok;
        {Ending, Why} ->
            _ = [begin
                     _ = cell_hal_force:release({G, P}),
                     audit(G, P, Why)
                 end || #{group := G, point := P} <- Ending],
            cell_log:warning(web, "~b forced IO point(s) released: ~ts", [length(Ending), Why]),
            changed()
    end.

audit(G, P, Why) ->
    Entry = #{who => <<"cell">>, role => <<"-">>, address => <<"-">>,
              action => <<"RELEASE">>,
              target => iolist_to_binary([<<"/api/forces/">>, atom_to_binary(G, utf8), $/,
                                          atom_to_binary(P, utf8)]),
              outcome => <<"200">>, detail => Why},
    case cell_web_audit:record(Entry) of
        ok -> ok;
        {error, E} -> cell_log:error(web, "the release of ~s.~s could not be written to the "
                                     "audit trail: ~0tp", [G, P, E])
    end.

may_release(#{role := anonymous}) ->
    {error, 401, login_required, <<"log in as a service user to release forced IO">>};
may_release(#{role := Role}) ->
    case cell_web_users:rank(Role) >= cell_web_users:rank(service) of
        true -> ok;
        false -> {error, 403, forbidden, <<"releasing forced IO needs the role service or higher">>}
    end.

refused(unknown_point) -> {error, 404, not_found, <<"no such IO point">>};
refused(not_forceable) ->
    {error, 422, not_forceable,
     <<"an input of a real PLC cannot be forced: only outputs and simulated inputs can">>};
refused({bad_value, _}) -> {error, 400, bad_value, <<"the value does not fit the point's type">>};
refused({unavailable, Why}) -> {error, 409, unavailable, Why};
refused(disconnected) -> {error, 409, disconnected, <<"the point's PLC is not connected">>};
refused(timeout) -> {error, 504, timeout, <<"the PLC did not confirm the forced value in time">>};
refused(Other) -> {error, 502, refused, iolist_to_binary(io_lib:format("the PLC refused it: ~0tp", [Other]))}.

changed() ->
    cell_web_feed:publish([#{<<"type">> => <<"forces">>, <<"forces">> => json()}]).
