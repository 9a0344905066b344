%% @doc An interpolation channel of TwinCAT NC I over ADS (type `ads' of kind
%% `channel', see {@link cell_hal_channel}): the coupled motion runs in the NC, as on a
%% TwinCAT machine. A path becomes a DIN 66025 part program ({@link cell_hal_ads_nci}),
%% written into the file `program' on the target by the system service, loaded into
%% the channel by name and started; the channel's state read back tells of its end.
%%
%% ```
%% #{id => router, kind => channel, type => ads,
%%   opts => #{host => "10.0.0.5", target_net_id => "10.0.0.5.1.1", channel => 1,
%%             axes => [1, 2], program => "C:\\TwinCAT\\Mc\\Nci\\router.nc"}}
%% '''
%%
%% `axes' are the NC ids of the channel's interpolation group, its X, Y and (for
%% three) Z: their online state gives the position and, from it, the progress along the
%% path (the nearest of the path's sample points ahead of the last one found). The
%% speed override is the channel's path override (its cyclic interface), which the NC
%% applies to the path at once. The axes are the NC's to power and home (or a
%% task's, through `ads' axis objects of the same ids); the channel only follows.
%%
%% == How a path runs ==
%% {@link follow/4}: the program written (FOPEN, FWRITE, FCLOSE on AMS port 10000),
%% the channel reset, the program loaded by name and the interpreter started, each
%% write answered before the next. A refusal on the way is the caller's `{error,
%% {nc_refused, Why}}' and nothing runs. Then the channel's state is polled (every
%% `poll_ms' while a job runs, `idle_poll_ms' at rest; each poll reads the
%% interpreter's state and the channel's error code, then the axes' online state, in
%% turn, each bounded by `timeout_ms'): the NC shows a started program as running at
%% once, so a program read as ready again ran to its end (`{Ref, done}'), an error
%% code fails it (`{Ref, {error, {Id, Code}}}'), and an interpreter found idle was
%% stopped or reset elsewhere (`{Ref, aborted}'). {@link halt/3} stops the channel
%% and resets it (the NC asks for a reset after a stop), and is done once the
%% interpreter no longer runs.
%%
%% == The connection ==
%% Two ADS clients, one to the NC (port 500), one to the system service (port 10000),
%% with `host', `target_net_id', `port', `source_net_id', `source_port' and
%% `timeout_ms' as for {@link cell_hal_ads}. The channel is up once both are connected
%% and its state has been read. A lost connection makes it down: follow and halt are
%% refused with `{error, not_connected}', a running job ends with `{Ref, {error,
%% not_connected}}' (nobody knows what the NC does with it), and the clients are
%% started again after `reconnect_ms', doubling up to `max_reconnect_ms'.
-module(cell_hal_ads_channel).
-behaviour(cell_hal_channel).

-export([check_opts/1, init/2, follow/4, halt/3, set_override/2, status/1, handle_call/2,
         handle_info/2]).

-define(NC_PORT, 500).
-define(SYSTEM_SERVICE_PORT, 10000).
-define(SAMPLES, 2000).

-record(job, {kind :: follow | halt,
              owner :: {pid(), reference()}}).

-record(s, {id :: atom(),
            opts :: map(),
            ctx :: cell_hal_ads_nci:ctx(),
            %% The two clients, by role: {Pid, Monitor, Up}.
            clients = #{} :: #{nc | files => {pid(), reference(), boolean()}},
            up = false :: boolean(),
            job :: #job{} | undefined,
            path :: cell_hal_path:path() | undefined,
            %% The path's sample points, {Along, Point}, in order.
            samples = [] :: [{float(), cell_hal_path:point()}],
            along = 0.0 :: float(),
            itp = idle :: cell_hal_ads_nci:itp_state(),
            positions :: [float()] | undefined,
            override = 100 :: number(),
            poll_timer :: reference() | undefined,
            backoff :: pos_integer()}).

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    cell_hal_ads_nc_conn:check_opts(Opts, #{channel => {undefined, fun id/1},
                                            axes => {undefined, fun axes/1},
                                            program => {undefined, fun program/1}},
                                    [channel, axes, program]).

id(V) -> is_integer(V) andalso V >= 1 andalso V =< 255.
axes(Ids) when is_list(Ids), length(Ids) >= 2, length(Ids) =< 3 ->
    lists:all(fun id/1, Ids) andalso length(lists:usort(Ids)) =:= length(Ids);
axes(_) -> false.
program(P) when is_list(P) -> io_lib:printable_unicode_list(P) andalso P =/= [];
program(P) when is_binary(P) -> byte_size(P) > 0;
program(_) -> false.

%% @private
-spec init(atom(), map()) -> {ok, #s{}, down}.
init(Id, #{channel := C, reconnect_ms := Backoff} = Opts) ->
    self() ! {?MODULE, connect},
    {ok, #s{id = Id, opts = Opts, ctx = #{channel => C}, backoff = Backoff}, down}.

%% @private
-spec follow(pid(), cell_hal_path:path(), cell_hal_axis_fsm:params(), #s{}) ->
          {reply, {ok, reference()} | {error, term()}, #s{}}.
follow(_Owner, _Path, _Params, #s{up = false} = S) ->
    {reply, {error, not_connected}, S};
follow(_Owner, _Path, _Params, #s{job = #job{}} = S) ->
    {reply, {error, busy}, S};
follow(Owner, Path0, #{velocity := V}, #s{opts = #{axes := Axes}} = S)
  when is_number(V), V > 0 ->
    Path = case S#s.positions of
               undefined -> Path0;
               Ps -> cell_hal_path:from(Path0, point(Ps))
           end,
    Program = cell_hal_ads_nci:program(Path, V, length(Axes)),
    case run_program(Program, S) of
        ok ->
            Ref = make_ref(),
            {reply, {ok, Ref},
             poll_soon(S#s{job = #job{kind = follow, owner = {Owner, Ref}}, path = Path,
                           samples = samples(Path), along = 0.0, itp = running})};
        {error, Why} ->
            {reply, {error, {nc_refused, Why}}, S}
    end;
follow(_Owner, _Path, Params, S) ->
    {reply, {error, {bad_params, Params}}, S}.

%% The program on the target and running: written, the channel reset, loaded, started.
run_program(Program, #s{ctx = Ctx, opts = #{program := Name0}} = S) ->
    Name = unicode:characters_to_binary(Name0),
    case write_file(Name, Program, S) of
        ok ->
            requests([cell_hal_ads_nci:request(R, Ctx)
                      || R <- [reset, {load, Name}, start]], S);
        {error, _} = Error ->
            Error
    end.

write_file(Name, Program, #s{ctx = Ctx} = S) ->
    case request(cell_hal_ads_nci:file_writes(open, Name, Ctx), files, S) of
        {ok, <<Handle:32/little>>} ->
            Wrote = request(cell_hal_ads_nci:file_writes({write, Handle, Program}, Name, Ctx),
                            files, S),
            Closed = request(cell_hal_ads_nci:file_writes({close, Handle}, Name, Ctx),
                             files, S),
            case {Wrote, Closed} of
                {{ok, _}, {ok, _}} -> ok;
                {{error, _} = Error, _} -> Error;
                {_, {error, _} = Error} -> Error
            end;
        {ok, Other} ->
            {error, {bad_file_handle, Other}};
        {error, _} = Error ->
            Error
    end.

%% @private
-spec halt(pid(), number(), #s{}) -> {reply, {ok, reference()} | {error, term()}, #s{}}.
halt(_Owner, _Dec, #s{up = false} = S) ->
    {reply, {error, not_connected}, S};
halt(Owner, Dec, #s{ctx = Ctx} = S) when is_number(Dec), Dec > 0 ->
    S1 = end_job(aborted, S),
    case requests([cell_hal_ads_nci:request(R, Ctx) || R <- [stop, reset]], S1) of
        ok ->
            Ref = make_ref(),
            {reply, {ok, Ref}, poll_soon(S1#s{job = #job{kind = halt, owner = {Owner, Ref}}})};
        {error, Why} ->
            {reply, {error, {nc_refused, Why}}, S1}
    end;
halt(_Owner, Dec, S) ->
    {reply, {error, {bad_deceleration, Dec}}, S}.

%% @private
%% The override is the channel's path override (its cyclic interface); kept while
%% down, to be written on connecting.
-spec set_override(number(), #s{}) -> {reply, ok | {error, term()}, #s{}}.
set_override(Pct, S) when is_number(Pct), Pct >= 0, Pct =< 100 ->
    case S#s.up of
        false ->
            {reply, ok, S#s{override = Pct}};
        true ->
            case write_override(Pct, S) of
                ok -> {reply, ok, S#s{override = Pct}};
                {error, Why} -> {reply, {error, {nc_refused, Why}}, S}
            end
    end;
set_override(Pct, S) ->
    {reply, {error, {bad_override, Pct}}, S}.

write_override(Pct, #s{ctx = Ctx} = S) ->
    requests([cell_hal_ads_nci:request({override, Pct}, Ctx)], S).

%% @private
-spec status(#s{}) -> {reply, cell_hal_channel:status(), #s{}}.
status(#s{path = undefined} = S) ->
    {reply, #{state => state(S), along => 0.0, length => 0.0, segment => 0,
              segments => 0, connecting => false, position => position(S)}, S};
status(#s{path = Path, along = Along} = S) ->
    {I, N, Role} = cell_hal_path:segment_at(Path, Along),
    {reply, #{state => state(S), along => Along, length => cell_hal_path:length(Path),
              segment => I, segments => N, connecting => Role =:= connecting,
              position => position(S)}, S}.

state(#s{job = #job{kind = follow}}) -> following;
state(#s{job = #job{kind = halt}}) -> halting;
state(#s{job = undefined}) -> idle.

position(#s{positions = undefined}) -> undefined;
position(#s{positions = Ps}) -> point(Ps).

point(Ps) ->
    list_to_tuple(Ps ++ lists:duplicate(3 - length(Ps), 0.0)).

%% @private
-spec handle_call(term(), #s{}) -> no_return().
handle_call(Request, _S) ->
    error({unknown_call, Request}).

%% @private
%% Watchers hear only of what shows: a poll at rest that reads the channel as it was
%% tells them nothing.
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

info({?MODULE, connect}, S) ->
    lists:foldl(fun connect/2, S, [nc, files]);
info({cell_hal_ads, Client, up}, S) ->
    case role(Client, S) of
        {ok, Role} ->
            {Client, Mon, _} = maps:get(Role, S#s.clients),
            S1 = S#s{clients = (S#s.clients)#{Role => {Client, Mon, true}}},
            case all_up(S1) of
                true -> came_up(S1);
                false -> S1
            end;
        error ->
            S
    end;
info({cell_hal_ads, Client, {down, Reason}}, S) ->
    case role(Client, S) of
        {ok, Role} when element(3, map_get(Role, S#s.clients)) -> lost(Reason, S);
        _ -> S
    end;
info({cell_hal_ads, _Client, _}, S) ->
    %% A client of an earlier connection, the present state told on subscribing (down
    %% while it connects: its end, if it fails, comes by the monitor), or news the
    %% channel has no use for.
    S;
info({'DOWN', Mon, process, _, Reason}, S) ->
    case [R || {R, {_, M, _}} <- maps:to_list(S#s.clients), M =:= Mon] of
        [Role] -> lost(Reason, S#s{clients = maps:remove(Role, S#s.clients)});
        [] -> S
    end;
info({timeout, Ref, poll}, #s{poll_timer = Ref} = S) ->
    schedule(poll(S#s{poll_timer = undefined}));
info({timeout, _Stale, poll}, S) ->
    S;
info(Msg, _S) ->
    error({unexpected_message, Msg}).

connect(Role, #s{opts = Opts, clients = Clients} = S) ->
    Port = case Role of nc -> ?NC_PORT; files -> ?SYSTEM_SERVICE_PORT end,
    {Client, Mon} = cell_hal_ads_nc_conn:connect(Opts, Port),
    S#s{clients = Clients#{Role => {Client, Mon, false}}}.

role(Client, #s{clients = Clients}) ->
    case [R || {R, {C, _, _}} <- maps:to_list(Clients), C =:= Client] of
        [Role] -> {ok, Role};
        [] -> error
    end.

all_up(#s{clients = Clients}) ->
    map_size(Clients) =:= 2 andalso lists:all(fun({_, _, Up}) -> Up end,
                                               maps:values(Clients)).

%% Both connected: the channel's state read, the override written, then up.
came_up(#s{override = Pct, opts = Opts} = S) ->
    S1 = poll(S#s{up = true}),
    case S1#s.up andalso write_override(Pct, S1) of
        false ->
            S1;
        ok ->
            ok = cell_hal_hw:set_status(up),
            schedule(S1#s{backoff = maps:get(reconnect_ms, Opts)});
        {error, Why} ->
            lost(Why, S1)
    end.

%% The connection failed or is lost: down, the job's owner told, the clients started
%% again later.
lost(Reason, #s{id = Id, up = Up} = S) ->
    [cell_log:warning(Id, "channel ~s lost its NC: ~ts",
                      [Id, cell_hal_ads_client:format_error(Reason)]) || Up],
    ok = cell_hal_hw:set_status(down),
    S1 = end_job({error, not_connected}, cancel_poll(stop_clients(S))),
    Backoff = S1#s.backoff,
    _ = erlang:send_after(Backoff, self(), {?MODULE, connect}),
    S1#s{up = false, positions = undefined,
         backoff = min(Backoff * 2, maps:get(max_reconnect_ms, S1#s.opts))}.

stop_clients(#s{clients = Clients} = S) ->
    maps:foreach(fun(_, {C, Mon, _}) -> ok = cell_hal_ads_nc_conn:disconnect(C, Mon) end,
                 Clients),
    S#s{clients = #{}}.

%%--------------------------------------------------------------------
%% Polling the channel
%%--------------------------------------------------------------------

poll(#s{up = false} = S) ->
    S;
poll(#s{ctx = Ctx, opts = #{axes := Axes}} = S) ->
    Reads = [request(cell_hal_ads_nci:request(R, Ctx), nc, S) || R <- [state, error_code]]
        ++ [request(cell_hal_ads_nc:request(online, #{axis => A}), nc, S) || A <- Axes],
    case decoded(Reads) of
        {ok, Itp, Error, Onlines} ->
            Positions = [X || #{position := X} <- Onlines],
            S1 = S#s{itp = Itp, positions = Positions},
            job_news(Error, S1#s{along = along(S1)});
        {error, Why} ->
            lost(Why, S)
    end.

decoded([{ok, St}, {ok, Er} | Axes]) ->
    case {cell_hal_ads_nci:decode_state(St), cell_hal_ads_nci:decode_error(Er),
          onlines(Axes, [])} of
        {{ok, Itp}, {ok, Error}, {ok, Onlines}} -> {ok, Itp, Error, Onlines};
        {{error, _} = E, _, _} -> E;
        {_, {error, _} = E, _} -> E;
        {_, _, {error, _} = E} -> E
    end;
decoded(Results) ->
    hd([E || {error, _} = E <- Results]).

onlines([], Acc) ->
    {ok, lists:reverse(Acc)};
onlines([{ok, Bin} | Rest], Acc) ->
    case cell_hal_ads_nc:decode_online(Bin) of
        {ok, Online} -> onlines(Rest, [Online | Acc]);
        {error, _} = Error -> Error
    end;
onlines([{error, _} = Error | _], _Acc) ->
    Error.

job_news(_Error, #s{job = undefined} = S) ->
    S;
job_news(Error, #s{job = #job{kind = Kind}, itp = Itp} = S) ->
    case cell_hal_ads_nci:news(Kind, Itp, Error) of
        running -> S;
        done -> end_job(done, S);
        aborted -> end_job(aborted, S);
        {error, Code} -> end_job({error, {S#s.id, Code}}, S)
    end.

%% The job ends: its owner told; a path done is at its end.
end_job(_Result, #s{job = undefined} = S) ->
    S;
end_job(Result, #s{job = #job{kind = Kind, owner = {Pid, Ref}}, path = Path} = S) ->
    Pid ! {Ref, Result},
    Along = case {Kind, Result} of
                {follow, done} -> cell_hal_path:length(Path);
                _ -> S#s.along
            end,
    S#s{job = undefined, along = Along}.

%% How far along the path the axes stand: the nearest sample point at or after the
%% last one found (a path may cross itself; its progress only goes on).
along(#s{job = #job{kind = follow}, positions = [_ | _] = Ps, samples = Samples,
         along = Last}) ->
    P = point(Ps),
    Ahead = [Sample || {A, _} = Sample <- Samples, A >= Last],
    case Ahead of
        [] -> Last;
        _ -> element(2, lists:min([{dist2(P, Q), A} || {A, Q} <- Ahead]))
    end;
along(#s{along = Last}) ->
    Last.

samples(Path) ->
    L = cell_hal_path:length(Path),
    [{A, cell_hal_path:at(Path, A)} || K <- lists:seq(0, ?SAMPLES), A <- [L * K / ?SAMPLES]].

dist2({X0, Y0, Z0}, {X1, Y1, Z1}) ->
    (X1 - X0) * (X1 - X0) + (Y1 - Y0) * (Y1 - Y0) + (Z1 - Z0) * (Z1 - Z0).

poll_soon(#s{poll_timer = T, opts = Opts} = S) ->
    S#s{poll_timer = cell_hal_ads_nc_conn:rearm_poll(T, now, Opts)}.

schedule(#s{up = false} = S) ->
    S;
schedule(#s{job = Job, poll_timer = T, opts = Opts} = S) ->
    When = case Job of undefined -> idle; _ -> running end,
    S#s{poll_timer = cell_hal_ads_nc_conn:rearm_poll(T, When, Opts)}.

cancel_poll(#s{poll_timer = T} = S) ->
    S#s{poll_timer = cell_hal_ads_nc_conn:cancel_poll(T)}.

%%--------------------------------------------------------------------

%% The requests one after the other, each answered before the next goes: the NC takes
%% them in that order.
requests([], _S) ->
    ok;
requests([R | Rest], S) ->
    case request(R, nc, S) of
        {ok, _} -> requests(Rest, S);
        {error, _} = Error -> Error
    end.

request(R, Role, #s{clients = Clients, opts = #{timeout_ms := T}}) ->
    case maps:find(Role, Clients) of
        {ok, {C, _, true}} ->
            try
                send(C, R, T)
            catch
                %% The client ended while it was asked (its connection closed): as
                %% lost as an error it answers; its monitor tells the rest.
                exit:{Reason, {gen_statem, call, _}} -> {error, Reason}
            end;
        _ ->
            {error, not_connected}
    end.

send(C, {write, G, O, Data}, T) ->
    case cell_hal_ads_client:write(C, G, O, Data, T) of
        ok -> {ok, <<>>};
        {error, _} = Error -> Error
    end;
send(C, {read, G, O, N}, T) ->
    cell_hal_ads_client:read(C, G, O, N, T);
send(C, {read_write, G, O, N, Data}, T) ->
    cell_hal_ads_client:read_write(C, G, O, N, Data, T).
