%% @doc The process of one AMS/TCP connection to a Beckhoff TwinCAT ADS server (a
%% gen_statem), started and called through {@link cell_hal_ads_client}, which documents
%% the calls and the messages it sends.
%%
%% == States ==
%% <table>
%% <tr><th>state</th><th>what happens</th><th>next</th></tr>
%% <tr><td>`connecting'</td><td>a connector process opens the TCP connection, so the client
%%   never blocks; calls get `{error, disconnected}'</td>
%%   <td>`{connected, restoring}', or the end on failure</td></tr>
%% <tr><td>`{connected, restoring}'</td><td>device info, ADS state and symbol version are
%%   read, the symbol version is watched; after a program change every variable in
%%   use is resolved again (new handles), every subscription added again; calls wait
%%   (postponed) until this is done or their timeout passes</td>
%%   <td>`{connected, ready}', or the end</td></tr>
%% <tr><td>`{connected, ready}'</td><td>calls are served, several requests in flight;
%%   a change of the symbol version (program download or online change) goes back to
%%   restoring</td><td>`{connected, restoring}', or the end</td></tr>
%% </table>
%%
%% A client is one connection and no more: when the connection cannot be made or is
%% lost, callers waiting are answered `{error, disconnected}', processes that called
%% `subscribe_status' get `{down, Reason}' if it had been up, and the process stops
%% with `{shutdown, Reason}', logging nothing of its own. Connecting again, with a
%% back-off, and saying in words what happened are its owner's (the HAL's worker,
%% through {@link cell_hal_ads}), which starts a new client: a second way of
%% reconnecting inside the client would only be a second set of states to keep right.
%%
%% The connection is given up when the PLC closes it, sends a frame that cannot be
%% read, or stops answering (a request timed out with nothing at all received since it
%% was sent; when the connection is idle a ReadState is sent every `link_check' ms to
%% find this out). A bad frame never takes more than the connection down: the process
%% ends with the reason, nothing else.
%%
%% == Modules ==
%% This module is the connection's process: the socket, the frames in and out, the
%% states above. What it decides with is pure and kept apart:
%% <ul>
%% <li>{@link cell_hal_ads_jobs}: the requests queued and in flight, in groups answered
%%     together, and their deadlines;</li>
%% <li>{@link cell_hal_ads_opts} and {@link cell_hal_ads_args}: options and call
%%     arguments, checked (arguments in the caller);</li>
%% <li>{@link cell_hal_ads_resolve}, {@link cell_hal_ads_vars} and
%%     {@link cell_hal_ads_symbols}: resolving variables against the PLC's symbols and
%%     the cache of their handles;</li>
%% <li>{@link cell_hal_ads_batch}: reads and writes of many variables as sum
%%     commands;</li>
%% <li>{@link cell_hal_ads_subs}: subscriptions, their notifications and the samples
%%     they bring;</li>
%% <li>{@link cell_hal_ads_errors}: reasons in words.</li>
%% </ul>
-module(cell_hal_ads_conn).
-behaviour(gen_statem).

-include("cell_hal_ads.hrl").

-export([callback_mode/0, init/1, handle_event/4, terminate/3, code_change/4]).

-type state() :: connecting | {connected, restoring | ready}.

%% Frames the socket delivers before it asks to be read on: the connection keeps up
%% with its PLC without a setopts call on every frame.
-define(ACTIVE, 64).

-record(data, {opts :: map(),
               log :: binary(),
               target :: cell_hal_ads_codec:ams_addr(),
               source :: cell_hal_ads_codec:ams_addr() | undefined,
               socket :: gen_tcp:socket() | undefined,
               connector :: pid() | undefined,
               buffer = <<>> :: binary(),
               %% the requests queued and in flight, in jobs
               jobs = cell_hal_ads_jobs:new() :: cell_hal_ads_jobs:jobs(),
               generation = 0 :: non_neg_integer(),
               vars = cell_hal_ads_vars:new() :: cell_hal_ads_vars:vars(),
               subs = cell_hal_ads_subs:new() :: cell_hal_ads_subs:subs(),
               monitors = #{} :: #{pid() => reference()},
               watchers = #{} :: #{pid() => true},
               version :: byte() | undefined,
               checking_version = false :: boolean(),
               refresh_again = false :: false | byte(),
               table :: {byte() | undefined, cell_hal_ads_symbols:table()} | undefined,
               device = #{} :: map(),
               was_up = false :: boolean(),
               down :: term(),
               %% native monotonic time of the last bytes from the PLC
               last_rx = 0 :: integer(),
               %% what callers need to read without calling (cell_hal_ads_direct), and
               %% its epoch: it moves on whenever published handles are withdrawn
               direct :: cell_hal_ads_direct:tables(),
               epoch = 0 :: non_neg_integer(),
               announced = false :: boolean(),
               %% the socket's requests in flight, direct reads included, and the
               %% direct reads' invoke ids
               counters :: cell_hal_ads_direct:counters() | undefined,
               %% packets received on the connection
               received = 0 :: non_neg_integer()}).

%%====================================================================
%% gen_statem
%%====================================================================

-spec callback_mode() -> gen_statem:callback_mode_result().
callback_mode() ->
    [handle_event_function, state_enter].

-spec init(map()) -> gen_statem:init_result(state()).
init(Opts) ->
    process_flag(trap_exit, true),
    #{host := Host, port := Port, target_net_id := Net, target_port := TPort} = Opts,
    Peer = iolist_to_binary([host_text(Host), ":", integer_to_list(Port)]),
    Log = case Opts of
              #{name := Name} -> Name;
              _ -> <<"ads/", Peer/binary>>
          end,
    {ok, connecting, #data{opts = Opts#{peer => Peer}, log = Log, target = {Net, TPort},
                           down = starting,
                           direct = cell_hal_ads_direct:new()}}.

host_text(H) when is_tuple(H) -> inet:ntoa(H);
host_text(H) -> H.

-spec handle_event(gen_statem:event_type(), term(), state(), #data{}) ->
          gen_statem:event_handler_result(state()).

%%--------------------------------------------------------------------
%% connecting: a connector process opens the socket; the client stays responsive.
%%--------------------------------------------------------------------
handle_event(enter, _, connecting, D) ->
    Parent = self(),
    #{host := Host, port := Port, connect_timeout := T} = D#data.opts,
    Pid = spawn_link(fun() -> connector(Parent, Host, Port, T, request_timeout(D)) end),
    {keep_state, D#data{connector = Pid}};
handle_event(info, {connected, Pid, Result}, connecting, #data{connector = Pid} = D) ->
    case Result of
        {ok, Socket} -> connected(Socket, D#data{connector = undefined});
        {error, Reason} -> give_up({connect, Reason}, D#data{connector = undefined}, [])
    end;

%%--------------------------------------------------------------------
%% {connected, restoring}: the connection is being set up again; callers wait.
%%--------------------------------------------------------------------
handle_event(enter, _, {connected, restoring}, _) ->
    keep_state_and_data;
handle_event({call, _}, {req, _, _}, {connected, restoring}, _) ->
    {keep_state_and_data, postpone};
handle_event(internal, restored, {connected, restoring}, D) ->
    case D#data.refresh_again of
        V when is_integer(V), V =/= D#data.version ->
            refresh_version(V, D#data{refresh_again = false});
        _ ->
            {next_state, {connected, ready}, D#data{refresh_again = false}}
    end;

%%--------------------------------------------------------------------
%% {connected, ready}: calls are served.
%%--------------------------------------------------------------------
handle_event(enter, OldState, {connected, ready}, D) ->
    #data{opts = #{link_check := Check}} = D,
    Event = case OldState of
                {connected, restoring} when D#data.was_up -> symbols_changed;
                _ -> up
            end,
    notify_watchers(Event, D),
    D1 = open_direct(D),
    {keep_state, D1#data{was_up = true, down = undefined},
     link_check_timer(Check)};
handle_event({call, From}, {req, Request, Deadline}, {connected, ready}, D) ->
    case expired(Deadline) of
        %% Its time passed while the connection was being set up: a caller that waits
        %% has given up already, one that did not wait is told.
        true -> {keep_state_and_data, [{reply, From, {error, timeout}}]};
        false -> act(serve(Request, From, Deadline, D))
    end;

%%--------------------------------------------------------------------
%% Events common to the connected states.
%%--------------------------------------------------------------------
handle_event(info, {tcp, Socket, Bin}, {connected, _}, #data{socket = Socket} = D0) ->
    D = D0#data{last_rx = erlang:monotonic_time(), received = D0#data.received + 1},
    case D#data.buffer of
        <<>> -> act(incoming(Bin, D));
        Old -> act(frames(D#data{buffer = <<Old/binary, Bin/binary>>}, []))
    end;
handle_event(info, {tcp_passive, Socket}, {connected, _}, #data{socket = Socket}) ->
    %% On a socket the peer just closed this fails; tcp_closed follows and says so.
    _ = inet:setopts(Socket, [{active, ?ACTIVE}]),
    keep_state_and_data;
handle_event(info, {tcp_closed, Socket}, {connected, _}, #data{socket = Socket} = D) ->
    disconnect(closed, D);
handle_event(info, {tcp_error, Socket, Reason}, {connected, _}, #data{socket = Socket} = D) ->
    disconnect({socket, Reason}, D);
handle_event(internal, {fail, Reason}, {connected, _}, D) ->
    disconnect(Reason, D);
handle_event({timeout, deadline}, _, {connected, _}, D) ->
    act(expire(D#data{jobs = cell_hal_ads_jobs:fired(D#data.jobs)}));
handle_event({timeout, link_check}, _, {connected, _}, D) ->
    #data{opts = #{link_check := Check}, last_rx = Last} = D,
    %% slots that callers gone left behind may be what queued requests wait for
    {D1, A1} = case cell_hal_ads_direct:sweep(D#data.direct, D#data.counters) of
                   0 -> {D, []};
                   _ -> pump(D)
               end,
    Quiet = erlang:convert_time_unit(erlang:monotonic_time() - Last, native, millisecond),
    case Quiet >= Check andalso cell_hal_ads_jobs:in_flight(D1#data.jobs) =:= 0 of
        true ->
            {D2, A2} = job([read_state], undefined, deadline(request_timeout(D1)),
                           fun ignore/2, D1),
            {keep_state, D2, link_check_timer(Check) ++ A1 ++ A2};
        false ->
            {keep_state, D1, link_check_timer(Check) ++ A1}
    end;
handle_event(cast, {cell_hal_ads_direct, expired, Socket, Sent}, {connected, _},
             #data{socket = Socket, last_rx = Last}) when Last < Sent ->
    %% A direct read timed out with nothing at all received since it was sent.
    {keep_state_and_data, [{next_event, internal, {fail, no_answer}}]};
handle_event(cast, {cell_hal_ads_direct, expired, Socket, _}, {connected, _},
             #data{socket = Socket} = D) ->
    %% its slot is free: a request may have waited for it
    act(pump(D));
handle_event(cast, {cell_hal_ads_direct, stale, Socket}, {connected, _},
             #data{socket = Socket} = D) ->
    act(check_version(D));
handle_event(internal, {version, V}, {connected, Sub}, D) ->
    case V =:= D#data.version of
        true -> keep_state_and_data;
        false when Sub =:= ready -> refresh_version(V, D);
        false -> {keep_state, D#data{refresh_again = V}}
    end;

%%--------------------------------------------------------------------
%% Events common to all states.
%%--------------------------------------------------------------------
handle_event({call, From}, status, State, D) ->
    {keep_state_and_data, [{reply, From, status_map(State, D)}]};
handle_event({call, {Pid, _} = From}, subscribe_status, State, D) ->
    Present = case State of
                  {connected, ready} -> up;
                  {connected, restoring} when D#data.was_up -> up;   % a program change
                  _ -> {down, D#data.down}
              end,
    Pid ! {cell_hal_ads, self(), Present},
    D1 = monitor_pid(Pid, D),
    {keep_state, D1#data{watchers = (D1#data.watchers)#{Pid => true}}, [{reply, From, ok}]};
handle_event({call, {Pid, _} = From}, unsubscribe_status, _, D) ->
    {keep_state, D#data{watchers = maps:remove(Pid, D#data.watchers)}, [{reply, From, ok}]};
handle_event({call, {Pid, _} = From}, {release, Vars}, _, D) ->
    Keys = [cell_hal_ads_vars:key_of(N, T, D#data.vars) || {N, T} <- Vars],
    {D1, Actions} = unuse_keys(Keys, Pid, D),
    {keep_state, D1, [{reply, From, ok} | Actions]};
handle_event({call, {Pid, _} = From}, {unsubscribe, Refs}, State, D) ->
    {D1, Actions} = drop_subs(cell_hal_ads_subs:owned(Refs, Pid, D#data.subs), State, D),
    {keep_state, D1, [{reply, From, ok} | Actions]};
handle_event({call, From}, {req, _, _}, _, _) ->
    {keep_state_and_data, [{reply, From, {error, disconnected}}]};
handle_event({timeout, {release, K}}, release, State, D) ->
    act(release_idle(K, State, D));
handle_event(info, {'DOWN', _, process, Pid, _}, State, D) ->
    D1 = D#data{monitors = maps:remove(Pid, D#data.monitors),
                watchers = maps:remove(Pid, D#data.watchers)},
    Refs = cell_hal_ads_subs:of_pid(Pid, D1#data.subs),
    {D2, A1} = drop_subs(Refs, State, D1),
    {Vars, Unused} = cell_hal_ads_vars:drop_user(Pid, D2#data.vars),
    {keep_state, D2#data{vars = Vars}, A1 ++ idle_timers(Unused, D2)};
handle_event(info, {'EXIT', _, normal}, _, _) ->
    keep_state_and_data;
handle_event(info, {'EXIT', _, Reason}, _, _) ->
    {stop, Reason}.

-spec terminate(term(), state(), #data{}) -> ok.
terminate(_Reason, {connected, _}, #data{socket = Socket} = D) when Socket =/= undefined ->
    ok = retract_direct(D),
    %% Leave the PLC tidy: its notifications and handles are ours to give back.
    Notes = [{delete_notification, N} || N <- cell_hal_ads_subs:notes(D#data.subs)],
    Handles = [{write, ?IG_SYM_RELEASEHND, 0, <<H:32/little>>}
               || K <- cell_hal_ads_vars:keys(D#data.vars),
                  {ok, {handle, H}, _, _} <- [cell_hal_ads_vars:ready(K, D#data.vars)]],
    Frames = [cell_hal_ads_codec:encode_frame(D#data.target, D#data.source, I, R)
              || {I, R} <- lists:zip(lists:seq(1, length(Notes ++ Handles)), Notes ++ Handles)],
    _ = gen_tcp:send(Socket, Frames),
    %% A shutdown lets the queued frames out before the close.
    _ = gen_tcp:shutdown(Socket, write),
    _ = gen_tcp:close(Socket),
    ok;
terminate(_Reason, _State, D) ->
    %% not connected yet, or the connection given up (its socket closed already)
    retract_direct(D).

-spec code_change(term(), state(), #data{}, term()) -> {ok, state(), #data{}}.
code_change(_Vsn, State, D, _Extra) ->
    {ok, State, D}.

%%====================================================================
%% Connection
%%====================================================================

%% The socket is a port (direct reads write to it with port_command). A PLC that takes
%% none of what is sent to it for a request timeout is given up: without a send
%% timeout, whoever sends next would wait for it for ever.
connector(Parent, Host, Port, Timeout, SendTimeout) ->
    Opts = [{inet_backend, inet}, binary, {active, false}, {nodelay, true}, {keepalive, true},
            {send_timeout, SendTimeout}, {send_timeout_close, true}],
    Result = case gen_tcp:connect(Host, Port, Opts, Timeout) of
                 {ok, S} ->
                     case gen_tcp:controlling_process(S, Parent) of
                         ok -> {ok, S};
                         {error, R} -> _ = gen_tcp:close(S), {error, R}
                     end;
                 {error, R} ->
                     {error, R}
             end,
    Parent ! {connected, self(), Result}.

connected(Socket, D) ->
    #data{opts = #{source_net_id := Configured, source_port := SPort}} = D,
    case source_net_id(Configured, Socket) of
        {ok, NetId} ->
            D1 = D#data{socket = Socket, source = {NetId, SPort}, buffer = <<>>,
                        counters = cell_hal_ads_direct:counters(),
                        last_rx = erlang:monotonic_time(), generation = D#data.generation + 1},
            {D2, Actions} = restore(D1),
            {next_state, {connected, restoring}, D2, Actions};
        {error, Reason} ->
            _ = gen_tcp:close(Socket),
            give_up({socket, Reason}, D, [])
    end.

%% `auto': the usual convention, this machine's address on the PLC's network and ".1.1".
source_net_id(auto, Socket) ->
    case inet:sockname(Socket) of
        {ok, {{A, B, C, E}, _}} -> activate(Socket, {A, B, C, E, 1, 1});
        {ok, _} -> {error, eafnosupport};
        {error, _} = Error -> Error
    end;
source_net_id(NetId, Socket) ->
    activate(Socket, NetId).

activate(Socket, NetId) ->
    case inet:setopts(Socket, [{active, ?ACTIVE}]) of
        ok -> {ok, NetId};
        {error, _} = Error -> Error
    end.

disconnect(Reason, D0) ->
    %% Given up: what is still queued for the PLC is dropped, not waited for (a PLC
    %% that stopped reading would hold a plain close for seconds).
    _ = inet:setopts(D0#data.socket, [{linger, {true, 0}}]),
    _ = gen_tcp:close(D0#data.socket),
    %% Closed first: a direct read that still finds the socket cannot send any more.
    D = close_direct(D0),
    ok = cell_hal_ads_direct:fail_all(D#data.direct, disconnected),
    {Waiting, Jobs} = cell_hal_ads_jobs:abandon(D#data.jobs),
    give_up(Reason, D#data{socket = undefined, counters = undefined, buffer = <<>>,
                           jobs = Jobs}, Waiting).

%% The end of the client: it is one connection. Callers waiting are answered first,
%% then watchers told `{down, Reason}' if it had been up; its owner, told by the exit
%% reason, connects again if it wants to.
give_up(Reason, D, Waiting) ->
    _ = [gen_statem:reply(From, {error, disconnected}) || From <- Waiting],
    D#data.was_up andalso notify_watchers({down, Reason}, D),
    {stop, {shutdown, Reason}, D#data{down = Reason}}.

link_check_timer(infinity) -> [];
link_check_timer(Ms) -> [{{timeout, link_check}, Ms, check}].

request_timeout(#data{opts = #{request_timeout := T}}) -> T.

%%====================================================================
%% Reads without a call (cell_hal_ads_direct)
%%====================================================================

%% Ready: the connection and its resolved variables are published, and made findable
%% from this process the first time.
open_direct(#data{direct = T} = D) ->
    #data{opts = #{max_in_flight := Max}} = D,
    Conn = #{pid => self(), socket => D#data.socket, target => D#data.target,
             source => D#data.source, epoch => D#data.epoch, mode => batch_mode(D),
             counters => D#data.counters, max_in_flight => Max},
    Spellings = [{K, N, Type} || {N, Type, K} <- cell_hal_ads_vars:spellings(D#data.vars)],
    ok = cell_hal_ads_direct:open(T, Conn, readable(Spellings, D#data.vars)),
    case D#data.announced of
        true -> D;
        false -> ok = cell_hal_ads_direct:announce(self(), T), D#data{announced = true}
    end.

%% No longer ready, or handles go back: a new epoch, so that answers read through the
%% old handles are not used.
close_direct(D) ->
    ok = cell_hal_ads_direct:close(D#data.direct),
    D#data{epoch = D#data.epoch + 1}.

drop_direct(K, D) ->
    Epoch = D#data.epoch + 1,
    ok = cell_hal_ads_direct:drop(D#data.direct, K, Epoch),
    D#data{epoch = Epoch}.

retract_direct(#data{announced = true}) -> cell_hal_ads_direct:retract(self());
retract_direct(_) -> ok.

readable(Keyed, Vars) ->
    [{N, T, K, cell_hal_ads_batch:item(Access, Size)} || {K, N, T} <- Keyed,
                                      {ok, Access, Size, _} <- [cell_hal_ads_vars:ready(K, Vars)]].

notify_watchers(Event, D) ->
    maps:foreach(fun(Pid, _) -> Pid ! {cell_hal_ads, self(), Event} end, D#data.watchers).

%%====================================================================
%% Setting the connection up again: after a connect, and after a program change
%%====================================================================

restore(D) ->
    Version = case D#data.opts of
                  #{symbol_version := ignore} -> [];
                  _ -> [{read, ?IG_SYM_VERSION, 0, 1}]
              end,
    job([read_device_info, read_state | Version], undefined,
        deadline(request_timeout(D)), fun restore_info/2, D).

restore_info([Info, State | Version], D) ->
    case {Info, State} of
        {{ok, #{name := Name, version := {Ma, Mi, B}} = Device}, {ok, {AdsState, _}}} ->
            #data{opts = #{peer := Peer}, target = {Net, Port}} = D,
            cell_log:notice(D#data.log, "connected to ~ts, AMS ~ts:~b: ~ts ~b.~b.~b, ~p",
                            [Peer, cell_hal_ads_codec:format_net_id(Net), Port, Name, Ma,
                             Mi, B, AdsState]),
            D1 = D#data{device = Device#{ads_state => AdsState}},
            case Version of
                [] -> restore_vars(D1);
                [{ok, <<V, _/binary>>}] -> watch_version(D1#data{version = V});
                [{error, timeout}] -> fail({restore, timeout}, D1);
                [Other] ->
                    R = case Other of
                            {error, E} -> E;
                            {ok, _} -> {bad_response, symbol_version}
                        end,
                    cell_log:info(D#data.log, "the PLC gives no symbol version (~ts); program "
                                  "changes will show as failing handles",
                                  [format_error(R)]),
                    restore_vars(D1#data{version = undefined})
            end;
        {{error, R}, _} ->
            fail({restore, R}, D);
        {_, {error, R}} ->
            fail({restore, R}, D)
    end.

watch_version(#data{opts = #{symbol_version := watch}} = D) ->
    job([{add_notification, ?IG_SYM_VERSION, 0, 1, on_change, 0, 0}], undefined,
        deadline(request_timeout(D)),
        fun([{ok, Note}], Dx) ->
                restore_vars(Dx#data{subs = cell_hal_ads_subs:watch_version(Note, Dx#data.subs)});
           ([{error, timeout}], Dx) ->
                fail({restore, timeout}, Dx);
           ([{error, R}], Dx) ->
                cell_log:info(Dx#data.log, "the symbol version cannot be watched (~ts); it "
                              "is read again when handles fail", [format_error(R)]),
                restore_vars(Dx)
        end, D);
watch_version(D) ->
    restore_vars(D).

%% Every variable in use is resolved again, then every subscription added again.
restore_vars(D) ->
    Items = [{K, Name, Type} || K <- cell_hal_ads_vars:keys(D#data.vars),
                                {ok, #{name := Name, type := Type}} <-
                                    [cell_hal_ads_vars:find(K, D#data.vars)]],
    resolve_keys(Items, undefined, deadline(request_timeout(D)),
                 fun(Results, Dx) ->
                         case lists:member({error, timeout}, [R || {_, R} <- Results]) of
                             true ->
                                 fail({restore, timeout}, Dx);
                             false ->
                                 {Vars, Gone, Failed} =
                                     cell_hal_ads_resolve:refreshed(Results, Dx#data.vars),
                                 Dy = Dx#data{vars = Vars},
                                 log_variables(error, Failed, Dy),
                                 {Dz, A1} = release_handles(Gone, Dy),
                                 {Dw, A2} = restore_subs(Dz),
                                 {Dw, A1 ++ A2}
                         end
                 end, D).

restore_subs(D) ->
    Subs = cell_hal_ads_subs:to_list(D#data.subs),
    {Ready, Failed} = lists:partition(
                        fun({_, #{key := K}}) ->
                                cell_hal_ads_vars:state(K, D#data.vars) =:= ready
                        end, Subs),
    _ = [Pid ! {cell_hal_ads, Ref, {error, failure(K, D)}}
         || {Ref, #{pid := Pid, key := K}} <- Failed],
    Requests = [cell_hal_ads_subs:note_request(S, D#data.vars) || {_, S} <- Ready],
    job(Requests, undefined, deadline(request_timeout(D)),
        fun(Answers, Dx) ->
                case lists:member({error, timeout}, Answers) of
                    true ->
                        fail({restore, timeout}, Dx);
                    false ->
                        {Dy, Orphans} = lists:foldl(fun add_note/2, {Dx, []},
                                                    lists:zip(Ready, Answers)),
                        {Dz, A} = job(Orphans, undefined, deadline(request_timeout(Dy)),
                                      fun ignore/2, Dy),
                        {Dz, A ++ [{next_event, internal, restored}]}
                end
        end, D).

%% A subscription ended while it was being added again: its new notification goes.
add_note({{Ref, _}, {ok, Note}}, {D, Orphans}) ->
    case cell_hal_ads_subs:attach(Ref, Note, D#data.subs) of
        {ok, Subs} -> {D#data{subs = Subs}, Orphans};
        gone -> {D, [{delete_notification, Note} | Orphans]}
    end;
add_note({{Ref, #{pid := Pid}}, {error, Reason}}, {D, Orphans}) ->
    Pid ! {cell_hal_ads, Ref, {error, Reason}},
    {D, Orphans}.

failure(K, D) ->
    case cell_hal_ads_vars:ready(K, D#data.vars) of
        {error, Reason} -> Reason;
        {ok, _, _, _} -> disconnected
    end.

fail(Reason, D) ->
    {D, [{next_event, internal, {fail, Reason}}]}.

ignore(_Answers, D) ->
    {D, []}.

%% A new symbol version: the program was downloaded or changed online. Old handles
%% and notifications are given back (they may still point somewhere), everything in
%% use is resolved again.
refresh_version(V, D) ->
    cell_log:notice(D#data.log, "the PLC program changed (symbol version ~p -> ~b); "
                    "resolving ~b variables again",
                    [D#data.version, V, length(cell_hal_ads_vars:keys(D#data.vars))]),
    refresh(D#data{version = V}).

refresh(D0) ->
    %% Withdrawn before the handles go back.
    D = close_direct(D0),
    Releases = cell_hal_ads_resolve:release_requests(
                 [A || K <- cell_hal_ads_vars:keys(D#data.vars),
                       {ok, A, _, _} <- [cell_hal_ads_vars:ready(K, D#data.vars)]],
                 batch_mode(D)),
    {Notes, Subs} = cell_hal_ads_subs:refresh(D#data.subs),
    Deletes = [{delete_notification, N} || N <- Notes],
    {D1, A1} = job(Releases ++ Deletes, undefined, deadline(request_timeout(D)), fun ignore/2,
                   D#data{subs = Subs}),
    D2 = D1#data{vars = cell_hal_ads_vars:reset(D1#data.vars),
                 table = undefined, generation = D1#data.generation + 1},
    {D3, A2} = restore_vars(D2),
    {next_state, {connected, restoring}, D3, A1 ++ A2}.

%% After errors that a stale handle gives, the symbol version is read: a program
%% change is then noticed even where notifications on it are not available.
check_version(Results, D) ->
    case [C || {error, {ads_error, C, _}} <- Results, lists:member(C, ?STALE_HANDLE_ERRORS)] of
        [] -> {D, []};
        _ -> check_version(D)
    end.

check_version(D) ->
    case not D#data.checking_version andalso maps:get(symbol_version, D#data.opts) =/= ignore of
        true ->
            job([{read, ?IG_SYM_VERSION, 0, 1}], undefined, deadline(request_timeout(D)),
                fun([{ok, <<V>>}], Dx) ->
                        {Dx#data{checking_version = false},
                         [{next_event, internal, {version, V}}]};
                   (_, Dx) ->
                        {Dx#data{checking_version = false}, []}
                end, D#data{checking_version = true});
        false ->
            {D, []}
    end.

%%====================================================================
%% Serving calls
%%====================================================================

serve({request, Request}, From, Deadline, D) ->
    job([Request], From, Deadline,
        fun([Answer], Dx) -> {Dx, [{reply, From, plain_reply(Request, Answer)}]} end, D);
serve({batch, Kind, Items}, From, Deadline, D) ->
    case cell_hal_ads_args:items(Kind, Items) of
        true ->
            {Requests, Assemble} = batch(Kind, Items, batch_mode(D)),
            job(Requests, From, Deadline,
                fun(Answers, Dx) -> {Dx, [{reply, From, {ok, Assemble(Answers)}}]} end, D);
        false ->
            {D, [{reply, From, {error, {bad_argument, Items}}}]}
    end;
serve(symbols, From, Deadline, D) ->
    with_table(true, From, Deadline,
               fun({ok, Table}, Dx) ->
                       {Dx, [{reply, From, {ok, cell_hal_ads_resolve:table_list(Table)}}]};
                  ({error, R}, Dx) ->
                       {Dx, [{reply, From, {error, R}}]}
               end, D);
serve({resolve, Vars}, {Pid, _} = From, Deadline, D) ->
    resolve_for(Vars, Pid, From, Deadline,
                fun(Results, Dx) -> {Dx, [{reply, From, {ok, Results}}]} end, D);
serve({read_vars, Vars}, From, Deadline, D) ->
    Plan = [cell_hal_ads_batch:plan_read(V, D#data.vars) || V <- Vars],
    Items = [I || {read, I, _} <- Plan],
    {Requests, Assemble} = cell_hal_ads_batch:reads(Items, batch_mode(D)),
    job(Requests, From, Deadline,
        fun(Answers, Dx) ->
                Results = Assemble(Answers),
                Values = cell_hal_ads_batch:merge(Plan, Results,
                                                  fun cell_hal_ads_batch:decode_value/2),
                {Dy, Actions} = check_version(Results, Dx),
                {Dy, [{reply, From, {ok, Values}} | Actions]}
        end, D);
serve({write_vars, Pairs}, From, Deadline, D) ->
    Plan = [cell_hal_ads_batch:plan_write(V, Value, D#data.vars) || {V, Value} <- Pairs],
    Items = [I || {write, I, _} <- Plan],
    {Requests, Assemble} = cell_hal_ads_batch:writes(Items, batch_mode(D)),
    job(Requests, From, Deadline,
        fun(Answers, Dx) ->
                Results = Assemble(Answers),
                {Dy, Actions} = check_version(Results, Dx),
                {Dy, [{reply, From, {ok, cell_hal_ads_batch:merge(Plan, Results,
                                                                  fun(_, R) -> R end)}}
                      | Actions]}
        end, D);
serve({subscribe, Subs}, {Pid, _} = From, Deadline, D) ->
    resolve_for([V || {V, _} <- Subs], Pid, From, Deadline,
                fun(Resolved, Dx) -> add_subs(Subs, Resolved, Pid, From, Deadline, Dx) end, D).

batch(reads, Items, Mode) -> cell_hal_ads_batch:reads(Items, Mode);
batch(writes, Items, Mode) -> cell_hal_ads_batch:writes(Items, Mode);
batch(read_writes, Items, Mode) -> cell_hal_ads_batch:read_writes(Items, Mode).

plain_reply(_, {error, _} = E) -> E;
plain_reply(read_state, {ok, {State, Dev}}) -> {ok, #{ads_state => State, device_state => Dev}};
plain_reply(read_device_info, {ok, Info}) -> {ok, Info};
plain_reply({read, _, _, _}, {ok, Bin}) -> {ok, Bin};
plain_reply({read_write, _, _, _, _}, {ok, Bin}) -> {ok, Bin};
plain_reply(_, {ok, ok}) -> ok.

batch_mode(#data{opts = #{sum_commands := Sum, max_sum := Max}}) ->
    #{sum => Sum, max_sum => Max}.

%%====================================================================
%% Resolving variables
%%====================================================================

%% Resolves variables for a caller: those already resolved are used at once, the others
%% are asked for; only what succeeded counts as used by the caller.
resolve_for(Vars, Pid, From, Deadline, Then, D) ->
    Keyed = [{cell_hal_ads_vars:key_of(N, T, D#data.vars), N, T} || {N, T} <- Vars],
    Missing = lists:ukeysort(1, [I || {K, _, _} = I <- Keyed,
                                      cell_hal_ads_vars:state(K, D#data.vars) =/= ready]),
    Gen = D#data.generation,
    resolve_keys(Missing, From, Deadline,
                 fun(Found, Dx) when Dx#data.generation =/= Gen ->
                         {Dy, A1} = release_found(Found, Dx),
                         {Dz, A2} = Then([{error, symbols_changed} || _ <- Vars], Dy),
                         {Dz, A1 ++ A2};
                    (Found, Dx) ->
                         finish_resolve(Keyed, Found, Pid, Then, Dx)
                 end, D).

finish_resolve(Keyed, Found, Pid, Then, D) ->
    Names = maps:from_list([{K, {N, T}} || {K, N, T} <- Keyed]),
    {Vars, Extra, Failed} = cell_hal_ads_resolve:registered(Found, Names, D#data.vars),
    D1 = D#data{vars = Vars},
    log_variables(warning, Failed, D1),
    {Results, D2} = lists:mapfoldl(
                      fun({K, N, T}, Dx) ->
                              case cell_hal_ads_vars:find(K, Dx#data.vars) of
                                  {ok, #{state := ready, symbol := S}} ->
                                      %% this spelling is remembered for the reads to come
                                      Vs = cell_hal_ads_vars:declare(N, T, Dx#data.vars),
                                      {{ok, cell_hal_ads_resolve:info(S)},
                                       Dx#data{vars = cell_hal_ads_vars:use(K, Pid, Vs)}};
                                  _ ->
                                      {{error, cell_hal_ads_resolve:find_error(K, Found,
                                                                               Names)}, Dx}
                              end
                      end, D1, Keyed),
    D3 = case [ok || {ok, _} <- Results] of
             [] -> D2;
             _ -> monitor_pid(Pid, D2)
         end,
    ok = cell_hal_ads_direct:add(D3#data.direct, readable(Keyed, D3#data.vars)),
    {D4, A1} = release_handles(Extra, D3),
    {D5, A2} = Then(Results, D4),
    {D5, A1 ++ A2}.

%% A host that names the variable in its own words (the HAL names the point) turns
%% these lines off.
log_variables(Level, Failed, #data{opts = #{log_variables := true}} = D) ->
    lists:foreach(fun({Name, Type, Reason}) ->
                          cell_log:log(Level, D#data.log, "variable ~ts (~ts) cannot be used: ~ts",
                                       [Name, cell_hal_ads_types:plc_name(Type),
                                        format_error(Reason)])
                  end, Failed);
log_variables(_, _, _) ->
    ok.

release_found(Found, D) ->
    release_handles([A || {_, {ok, _, A}} <- Found], D).

release_handles(Accesses, D) ->
    Requests = cell_hal_ads_resolve:release_requests(Accesses, batch_mode(D)),
    job(Requests, undefined, deadline(request_timeout(D)), fun ignore/2, D).

%% Resolves `[{Key, Name, Type}]': `Cont([{Key, {ok, Symbol, Access} | {error, Reason}}])'.
%% "*" names are looked up in the uploaded symbol table, the others asked for by name
%% (which also finds structure fields); then the type is checked and a handle taken.
resolve_keys([], _From, _Deadline, Cont, D) ->
    Cont([], D);
resolve_keys(Items, From, Deadline, Cont, D) ->
    {Wild, Plain} = lists:partition(fun({_, N, _}) -> cell_hal_ads_symbols:is_wildcard(N) end,
                                    Items),
    with_table(Wild =/= [], From, Deadline,
               fun(Table, D1) ->
                       FoundWild = [{I, cell_hal_ads_resolve:lookup_wild(N, Table)}
                                    || {_, N, _} = I <- Wild],
                       symbol_infos(Plain, From, Deadline,
                                    fun(FoundPlain, D2) ->
                                            Checked = [{I, cell_hal_ads_resolve:check(I, R)}
                                                       || {I, R} <- FoundWild ++ FoundPlain],
                                            acquire(Checked, From, Deadline, Cont, D2)
                                    end, D1)
               end, D).

%% The symbol table of the present program, uploaded once per symbol version.
with_table(false, _From, _Deadline, Cont, D) ->
    Cont(none, D);
with_table(true, _From, _Deadline, Cont, #data{table = {V, Table}, version = V} = D)
  when V =/= undefined ->
    Cont({ok, Table}, D);
with_table(true, From, Deadline, Cont, D) ->
    job([cell_hal_ads_resolve:upload_info_request()], From, Deadline,
        fun([{ok, InfoBin}], D1) ->
                case cell_hal_ads_resolve:upload_request(InfoBin) of
                    {ok, Upload} ->
                        job([Upload], From, Deadline,
                            fun([{ok, TableBin}], D2) ->
                                    upload_done(cell_hal_ads_resolve:table(TableBin), Cont, D2);
                               ([{error, R}], D2) ->
                                    Cont({error, R}, D2)
                            end, D1);
                    {error, R} ->
                        Cont({error, R}, D1)
                end;
           ([{error, R}], D1) ->
                Cont({error, R}, D1)
        end, D).

upload_done({ok, Table}, Cont, D) ->
    cell_log:debug(D#data.log, "symbol table uploaded: ~b symbols",
                   [cell_hal_ads_symbols:count(Table)]),
    Cont({ok, Table}, D#data{table = {D#data.version, Table}});
upload_done({error, R}, Cont, D) ->
    Cont({error, R}, D).

%% Symbol info by name (0xF009) for each plain name, in one round trip.
symbol_infos([], _From, _Deadline, Cont, D) ->
    Cont([], D);
symbol_infos(Items, From, Deadline, Cont, D) ->
    {Requests, Assemble} = cell_hal_ads_resolve:info_requests(Items, batch_mode(D)),
    job(Requests, From, Deadline,
        fun(Answers, Dx) -> Cont(cell_hal_ads_resolve:infos(Items, Assemble(Answers)), Dx) end,
        D).

%% Handles (0xF003) for the checked symbols, in one round trip; with `access =>
%% address' the symbol's own index group and offset.
acquire(Checked, _From, _Deadline, Cont, #data{opts = #{access := address}} = D) ->
    Cont(cell_hal_ads_resolve:by_address(Checked), D);
acquire(Checked, From, Deadline, Cont, D) ->
    Ok = [{I, S} || {I, {ok, S}} <- Checked],
    {Requests, Assemble} = cell_hal_ads_resolve:handle_requests(Ok, batch_mode(D)),
    job(Requests, From, Deadline,
        fun(Answers, Dx) ->
                Cont(cell_hal_ads_resolve:handles(Ok, Assemble(Answers), Checked), Dx)
        end, D).

%%====================================================================
%% Releasing variables
%%====================================================================

unuse_keys(Keys, Pid, D) ->
    {Vars, Unused} = lists:foldl(fun(K, {V, U}) ->
                                         case cell_hal_ads_vars:unuse(K, Pid, V) of
                                             {V1, unused} -> {V1, [K | U]};
                                             {V1, _} -> {V1, U}
                                         end
                                 end, {D#data.vars, []}, Keys),
    {D#data{vars = Vars}, idle_timers(Unused, D)}.

idle_timers(Keys, #data{opts = #{handle_idle := Idle}}) ->
    [{{timeout, {release, K}}, Idle, release} || K <- lists:usort(Keys)].

%% An idle variable that is still unused goes: its handle back to the PLC.
release_idle(K, State, D) ->
    case cell_hal_ads_vars:users(K, D#data.vars) of
        0 ->
            Access = case cell_hal_ads_vars:ready(K, D#data.vars) of
                         {ok, A, _, _} -> [A];
                         {error, _} -> []
                     end,
            D1 = drop_direct(K, D#data{vars = cell_hal_ads_vars:remove(K, D#data.vars)}),
            case State of
                {connected, _} -> release_handles(Access, D1);
                _ -> {D1, []}
            end;
        _ ->
            {D, []}
    end.

%%====================================================================
%% Subscriptions
%%====================================================================

add_subs(Subs, Resolved, Pid, From, Deadline, D) ->
    Pairs = lists:zip(Subs, Resolved),
    Ready = [{Var, Opts} || {{Var, Opts}, {ok, _}} <- Pairs],
    New = [{make_ref(), #{pid => Pid, var => Var, key => cell_hal_ads_vars:key(N, T),
                          opts => Opts}} || {{N, T} = Var, Opts} <- Ready],
    Requests = [cell_hal_ads_subs:note_request(S, D#data.vars) || {_, S} <- New],
    job(Requests, From, Deadline,
        fun(Answers, Dx) ->
                Added = lists:zip(New, Answers),
                Dy = lists:foldl(fun({{Ref, Sub}, {ok, Note}}, Acc) ->
                                         Acc#data{subs = cell_hal_ads_subs:add(
                                                           Ref, Sub, Note, Acc#data.subs)};
                                    ({{_, #{key := K}}, {error, _}}, Acc) ->
                                         {V, _} = cell_hal_ads_vars:unuse(K, Pid, Acc#data.vars),
                                         Acc#data{vars = V}
                                 end, Dx, Added),
                Results = sub_results(Pairs, Added),
                Unused = [K || {{_, #{key := K}}, {error, _}} <- Added,
                               cell_hal_ads_vars:users(K, Dy#data.vars) =:= 0],
                {Dy, [{reply, From, {ok, Results}} | idle_timers(Unused, Dy)]}
        end, D).

sub_results([], _) ->
    [];
sub_results([{_, {error, _} = E} | Pairs], Added) ->
    [E | sub_results(Pairs, Added)];
sub_results([{_, {ok, _}} | Pairs], [{{Ref, _}, {ok, _}} | Added]) ->
    [{ok, Ref} | sub_results(Pairs, Added)];
sub_results([{_, {ok, _}} | Pairs], [{_, {error, _} = E} | Added]) ->
    [E | sub_results(Pairs, Added)].

%% Ends subscriptions: the PLC's notifications are deleted, the variables released.
drop_subs([], _State, D) ->
    {D, []};
drop_subs(Refs, State, D) ->
    {D1, Notes, Unused} = lists:foldl(fun drop_sub/2, {D, [], []}, Refs),
    {D2, A} = case State of
                  {connected, _} when Notes =/= [] ->
                      job([{delete_notification, N} || N <- Notes], undefined,
                          deadline(request_timeout(D1)), fun ignore/2, D1);
                  _ ->
                      {D1, []}
              end,
    {D2, A ++ idle_timers(Unused, D2)}.

drop_sub(Ref, {D, Notes, Unused}) ->
    {#{pid := Pid, key := K}, Note, Subs} = cell_hal_ads_subs:take(Ref, D#data.subs),
    {Vars, Use} = cell_hal_ads_vars:unuse(K, Pid, D#data.vars),
    {D#data{subs = Subs, vars = Vars}, Note ++ Notes, [K || Use =:= unused] ++ Unused}.

%% A device notification: samples to their subscribers, one message per subscription
%% and frame; a symbol version sample may start a refresh.
notification(Payload, D) ->
    case cell_hal_ads_subs:samples(Payload, D#data.subs) of
        {ok, Deliveries, Versions, Dropped} ->
            lists:foreach(fun({Name, Reason}) ->
                                  cell_log:warning(D#data.log, "sample of ~ts dropped: ~ts",
                                                   [Name, format_error(Reason)])
                          end, Dropped),
            _ = [Pid ! {cell_hal_ads, Ref, {samples, Samples}}
                 || {Pid, Ref, Samples} <- Deliveries],
            {D, [{next_event, internal, {version, V}} || V <- Versions]};
        {error, Reason} ->
            cell_log:warning(D#data.log, "notification dropped: ~ts", [format_error(Reason)]),
            {D, []}
    end.

%%====================================================================
%% Jobs: groups of requests in flight, answered together
%%====================================================================

%% Sends requests (as many at once as `max_in_flight' allows, the rest queued) and
%% calls `Cont(Answers, Data)' when every one is answered or the deadline passed.
job([], _From, _Deadline, Cont, D) ->
    Cont([], D);
job(Requests, From, Deadline, Cont, D) ->
    Jobs = cell_hal_ads_jobs:add(Requests, From, Deadline, Cont, D#data.received, D#data.jobs),
    {D1, Actions} = pump(D#data{jobs = Jobs}),
    arm(Deadline, D1, Actions).

%% The deadline timer fires no later than `Deadline'.
arm(Deadline, D, Actions) ->
    case cell_hal_ads_jobs:arm(Deadline, D#data.jobs) of
        keep -> {D, Actions};
        {set, Jobs} -> {D#data{jobs = Jobs},
                        [{{timeout, deadline}, Deadline, check, [{abs, true}]} | Actions]}
    end.

%% The timer fired: jobs past their deadline end, and it is armed again for the
%% earliest one left.
expire(D) ->
    {D1, Actions} = lists:foldl(fun(Id, {Dx, Ax}) ->
                                        {Dy, Ay} = job_timeout(Id, Dx),
                                        {Dy, Ax ++ Ay}
                                end, {D, []}, cell_hal_ads_jobs:due(now_ms(), D#data.jobs)),
    case cell_hal_ads_jobs:earliest(D1#data.jobs) of
        infinity -> {D1, Actions};
        Earliest -> arm(Earliest, D1, Actions)
    end.

%% Sends queued requests while there is room (a slot of `max_in_flight', which direct
%% reads share), in one write to the socket.
pump(D) ->
    pump(D, []).

pump(#data{opts = #{max_in_flight := Max}, jobs = Jobs} = D, Frames) ->
    case cell_hal_ads_jobs:waiting(Jobs) andalso
        cell_hal_ads_direct:take_slot(D#data.counters, Max) of
        true ->
            {Invoke, Request, Jobs1} = cell_hal_ads_jobs:next(Jobs),
            Frame = cell_hal_ads_codec:encode_frame(D#data.target, D#data.source, Invoke,
                                                    Request),
            pump(D#data{jobs = Jobs1}, [Frame | Frames]);
        false ->
            send(lists:reverse(Frames), D)
    end.

send([], D) ->
    {D, []};
send(Frames, D) ->
    case gen_tcp:send(D#data.socket, Frames) of
        ok -> {D, []};
        {error, Reason} -> {D, [{next_event, internal, {fail, {socket, Reason}}}]}
    end.

%% One answer in; the job completes with its last answer.
deliver(Id, I, Answer, D) ->
    case cell_hal_ads_jobs:deliver(Id, I, Answer, D#data.jobs) of
        {done, Cont, Answers, Jobs} -> Cont(Answers, D#data{jobs = Jobs});
        {pending, Jobs} -> {D#data{jobs = Jobs}, []}
    end.

%% The deadline passed: what is missing is a timeout. If nothing at all came from the
%% PLC since the job was sent, the connection is dead (a pulled cable is noticed here,
%% long before TCP would).
job_timeout(Id, D) ->
    case cell_hal_ads_jobs:time_out(Id, D#data.received, D#data.jobs) of
        {Cont, Answers, Freed, Dead, Jobs} ->
            ok = cell_hal_ads_direct:free_slots(D#data.counters, Freed),
            {D1, A1} = Cont(Answers, D#data{jobs = Jobs}),
            {D2, A2} = pump(D1),
            Fail = [{next_event, internal, {fail, no_answer}} || Dead],
            {D2, A1 ++ A2 ++ Fail};
        none ->
            {D, []}
    end.

%%====================================================================
%% Frames in
%%====================================================================

%% Most often the bytes are one answer to a direct read: read in one match.
incoming(Bin, #data{source = {_, Port}} = D) ->
    case cell_hal_ads_codec:decode_answer(Bin) of
        {answer, Port, Cmd, Err, Invoke, Payload} when Invoke band 1 =:= 0 ->
            direct_answer(Invoke, Cmd, Err, Payload, D);
        _ ->
            frames(D#data{buffer = Bin}, [])
    end.

frames(D, Actions) ->
    #data{buffer = Buffer, opts = #{max_frame := Max}} = D,
    case cell_hal_ads_codec:next_frame(Buffer, Max) of
        more ->
            {D, Actions};
        {ams, Body, Rest} ->
            {D1, A} = frame(Body, D#data{buffer = Rest}),
            case [F || {next_event, internal, {fail, _}} = F <- A] of
                [] -> frames(D1, Actions ++ A);
                _ -> {D1, Actions ++ A}
            end;
        {router, Code, _Body, Rest} ->
            cell_log:debug(D#data.log, "router message 0x~.16B skipped", [Code]),
            frames(D#data{buffer = Rest}, Actions);
        {error, Reason} ->
            {D, Actions ++ [{next_event, internal, {fail, Reason}}]}
    end.

frame(Body, D) ->
    {_, SPort} = D#data.source,
    case cell_hal_ads_codec:decode_ams(Body) of
        {ok, #{target := {_, Port}}, _} when Port =/= SPort ->
            cell_log:debug(D#data.log, "frame for AMS port ~b skipped", [Port]),
            {D, []};
        {ok, #{command := device_notification}, Payload} ->
            notification(Payload, D);
        {ok, #{flags := Flags}, _} when Flags band 1 =:= 0 ->
            cell_log:debug(D#data.log, "request from the PLC skipped", []),
            {D, []};
        {ok, #{invoke := Invoke, command := Cmd, error := Err}, Payload} ->
            case cell_hal_ads_jobs:answered(Invoke, Cmd, D#data.jobs) of
                {ok, Id, I, Jobs} ->
                    ok = cell_hal_ads_direct:free_slots(D#data.counters, 1),
                    Answer = case Err of
                                 0 -> cell_hal_ads_codec:decode_response(Cmd, Payload);
                                 _ -> {error, cell_hal_ads_codec:ads_error(Err)}
                             end,
                    {D1, A1} = deliver(Id, I, Answer, D#data{jobs = Jobs}),
                    {D2, A2} = pump(D1),
                    {D2, A1 ++ A2};
                {unexpected, Expected} ->
                    {D, [{next_event, internal, {fail, {unexpected_answer, Cmd, Expected}}}]};
                unknown ->
                    direct_answer(Invoke, Cmd, Err, Payload, D)
            end;
        {error, Reason} ->
            {D, [{next_event, internal, {fail, Reason}}]}
    end.

%% An answer to a request of a caller's own (cell_hal_ads_direct), or a late one.
direct_answer(Invoke, Cmd, Err, Payload, D) ->
    #data{direct = T, counters = Counters, epoch = Epoch} = D,
    case cell_hal_ads_direct:answer(T, Counters, Invoke, Cmd, Err, Payload, Epoch) of
        ok ->
            %% its slot is free: a request may have waited for it
            pump(D);
        unknown ->
            %% An answer after its deadline: the caller has moved on.
            {D, []};
        {unexpected, Expected} ->
            {D, [{next_event, internal, {fail, {unexpected_answer, Cmd, Expected}}}]}
    end.

%%====================================================================
%% Helpers
%%====================================================================

act({D, Actions}) ->
    {keep_state, D, Actions}.

expired(infinity) -> false;
expired(Deadline) -> now_ms() >= Deadline.

monitor_pid(Pid, D) ->
    case maps:is_key(Pid, D#data.monitors) of
        true -> D;
        false -> D#data{monitors = (D#data.monitors)#{Pid => erlang:monitor(process, Pid)}}
    end.

status_map(State, D) ->
    #data{opts = #{peer := Peer}, target = {Net, Port}} = D,
    Keys = cell_hal_ads_vars:keys(D#data.vars),
    Failed = [Name || K <- Keys, {ok, #{state := failed, name := Name}} <-
                                     [cell_hal_ads_vars:find(K, D#data.vars)]],
    Base = #{state => case State of
                          {connected, ready} -> up;
                          {connected, restoring} -> restoring;
                          connecting -> connecting
                      end,
             name => D#data.log, peer => Peer,
             target => iolist_to_binary([cell_hal_ads_codec:format_net_id(Net), ":",
                                         integer_to_list(Port)]),
             source => case D#data.source of
                           undefined -> undefined;
                           {SNet, SPort} ->
                               iolist_to_binary([cell_hal_ads_codec:format_net_id(SNet), ":",
                                                 integer_to_list(SPort)])
                       end,
             symbol_version => D#data.version,
             variables => length(Keys), failed => lists:sort(Failed),
             subscriptions => cell_hal_ads_subs:count(D#data.subs),
             in_flight => case D#data.counters of
                              undefined -> 0;
                              Counters -> cell_hal_ads_direct:in_flight(Counters)
                          end},
    WithDevice = case D#data.device of
                     #{name := N, version := V, ads_state := S} ->
                         Base#{device => #{name => N, version => V}, ads_state => S};
                     _ ->
                         Base
                 end,
    case D#data.down of
        undefined -> WithDevice;
        Reason -> WithDevice#{reason => format_error(Reason)}
    end.

deadline(infinity) -> infinity;
deadline(Timeout) -> now_ms() + Timeout.

now_ms() ->
    erlang:monotonic_time(millisecond).

format_error(Reason) ->
    cell_hal_ads_errors:format_error(Reason).
