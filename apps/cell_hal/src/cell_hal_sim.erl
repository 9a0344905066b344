%% @doc The simulated driver: a connection to a simulated PLC ({@link
%% cell_hal_sim_device}) for simulation and tests, and the API a simulation drives it
%% with. A cell configured with `driver => cell_hal_sim' runs its group modules
%% unchanged, without hardware.
%%
%% Connection options: `device' (the simulated PLC's name, default the connection's
%% id), `timeout_ms' (how long a request may go unanswered before the connection counts
%% as lost, default 1000), `latency_ms' (how long the PLC takes to answer, default 0),
%% `image' (`#{{Group, Point} => Value}': what a PLC started anew holds before the
%% simulation sets anything, e.g. an emergency-stop circuit closed, as a machine at
%% rest has it; default none, every point zero).
%%
%% A simulation sets inputs and reads what the HAL wrote, by point:
%% ```
%% ok = cell_hal_sim:set({feeder, part_present}, true),
%% {ok, true} = cell_hal_sim:get({feeder, clamp_close}),
%% %% the clamp's closed sensor follows the valve 120 ms later:
%% ok = cell_hal_sim:follow({feeder, clamp_closed}, {feeder, clamp_close}, 120),
%% %% the cable is pulled, then plugged back:
%% ok = cell_hal_sim:link(plc1, down),
%% ok = cell_hal_sim:link(plc1, up).
%% '''
-module(cell_hal_sim).
-behaviour(cell_hal_driver).

-include("cell_hal.hrl").

%% Simulation API
-export([set/2, get/1, preset/2, follow/3, follow/4, on_change/2, clear_rules/1, link/2,
         drop/1, clients/1, stop_device/1]).
%% cell_hal_driver
-export([check_opts/1, check_point/4, init/2, endpoint/1, connect/1, plan/2, read/3,
         write/4, request/4, handle_info/2, disconnect/1, format_reason/1]).

-type key() :: {atom(), atom()}.

-record(sim, {id :: atom(),
              device :: atom(),
              device_opts :: map(),
              timeout_ms :: pos_integer(),
              pid :: pid() | undefined,
              mref :: reference() | undefined,
              ref :: reference() | undefined,            %% this connection
              timers = #{} :: #{term() => reference()}}). %% tag => deadline timer

%%====================================================================
%% Simulation API
%%====================================================================

%% @doc Sets a point in the simulated PLC's image: an input, which the HAL sees at its
%% next poll, or an output changed on the PLC's side, which the HAL reads back after
%% its next reconnect (it does not poll outputs).
-spec set(key(), cell_hal_type:value()) ->
          ok | {error, unknown_point | not_simulated | {bad_value, term()}}.
set(Key, V) ->
    with_device(Key, fun(Pid, #hal_point{type = Type}) ->
                             case cell_hal_type:check(Type, V) of
                                 {ok, V1} -> gen_server:call(Pid, {set, Key, V1});
                                 error -> {error, {bad_value, V}}
                             end
                     end).

%% @doc A point's value in the simulated PLC's image: an output as the HAL wrote it,
%% an input as the simulation set it; `not_set' before either happened.
-spec get(key()) -> {ok, cell_hal_type:value()}
                    | {error, unknown_point | not_simulated | not_set}.
get(Key) ->
    with_device(Key, fun(Pid, _) ->
                             case gen_server:call(Pid, {get, Key}) of
                                 {ok, V} -> {ok, V};
                                 error -> {error, not_set}
                             end
                     end).

%% @doc Loads values into a connection's simulated PLC for points that may not be
%% configured yet (the image a PLC holds before the cell starts). A value that turns
%% out not to fit its point's type reads as zero, reported.
-spec preset(atom(), #{key() => cell_hal_type:value()}) -> ok | {error, not_simulated}.
preset(Conn, Image) when is_map(Image) ->
    with_conn_device(Conn, fun(Pid) -> gen_server:call(Pid, {preset, Image}) end).

%% @doc `Input' takes every value `Output' takes, `DelayMs' later: a sensor that
%% follows its actuator.
-spec follow(key(), key(), non_neg_integer()) -> ok | {error, term()}.
follow(Input, Output, DelayMs) ->
    follow(Input, Output, DelayMs, fun(V) -> V end).

%% @doc `Input' takes `Fun(V)' `DelayMs' after `Output' takes `V' (a cylinder whose
%% "retracted" sensor is the inverse of its "extend" valve: `fun erlang:not/1').
-spec follow(key(), key(), non_neg_integer(), fun((cell_hal_type:value()) -> cell_hal_type:value())) ->
          ok | {error, term()}.
follow(Input, Output, DelayMs, Fun) when is_integer(DelayMs), DelayMs >= 0,
                                         is_function(Fun, 1) ->
    on_change(Output, fun(V) -> [{DelayMs, Input, Fun(V)}] end).

%% @doc The general rule: whenever `Key' changes in the image, `Fun(NewValue)' returns
%% the changes to make, each `{DelayMs, Point, Value}'.
-spec on_change(key(), fun((cell_hal_type:value()) -> [{non_neg_integer(), key(), cell_hal_type:value()}])) ->
          ok | {error, term()}.
on_change(Key, Fun) when is_function(Fun, 1) ->
    with_device(Key, fun(Pid, _) -> gen_server:call(Pid, {rule, Key, Fun}) end).

%% @doc Forgets every rule of a connection's simulated PLC.
-spec clear_rules(atom()) -> ok | {error, not_simulated}.
clear_rules(Conn) ->
    with_conn_device(Conn, fun(Pid) -> gen_server:call(Pid, clear_rules) end).

%% @doc Breaks or restores the link to a connection's simulated PLC: `down' drops the
%% HAL's connection and refuses new ones; `silent' keeps it but answers nothing, so
%% requests time out; `up' answers again.
-spec link(atom(), up | down | silent) -> ok | {error, not_simulated}.
link(Conn, Link) when Link =:= up; Link =:= down; Link =:= silent ->
    with_conn_device(Conn, fun(Pid) -> gen_server:call(Pid, {link, Link}) end).

%% @doc A momentary loss: the PLC drops its connections and accepts new ones at once.
-spec drop(atom()) -> ok | {error, not_simulated}.
drop(Conn) ->
    with_conn_device(Conn, fun(Pid) -> gen_server:call(Pid, drop) end).

%% @doc How many connections the simulated PLC has.
-spec clients(atom()) -> non_neg_integer() | {error, not_simulated}.
clients(Conn) ->
    with_conn_device(Conn, fun(Pid) -> gen_server:call(Pid, clients) end).

%% @doc Stops a connection's simulated PLC; its image and its rules are forgotten.
-spec stop_device(atom()) -> ok | {error, not_simulated}.
stop_device(Conn) ->
    case device_of(Conn) of
        {ok, Name, _} -> cell_hal_sim_sup:stop_device(Name);
        Error -> Error
    end.

with_device(Key, Fun) ->
    case cell_hal_store:point(Key) of
        {ok, #hal_point{conn = Conn} = P} ->
            with_conn_device(Conn, fun(Pid) -> Fun(Pid, P) end);
        error ->
            {error, unknown_point}
    end.

with_conn_device(Conn, Fun) ->
    case device_of(Conn) of
        {ok, Name, Opts} ->
            try Fun(cell_hal_sim_sup:ensure_device(Name, Opts))
            catch
                exit:{Gone, {gen_server, call, _}} when Gone =:= noproc; Gone =:= killed;
                                                        Gone =:= shutdown ->
                    %% The device died before it answered (its memory is kept): asked
                    %% again of the device its supervisor starts in its place.
                    Fun(cell_hal_sim_sup:ensure_device(Name, Opts))
            end;
        Error ->
            Error
    end.

device_of(Conn) ->
    case cell_hal_store:conn(Conn) of
        {ok, #hal_conn{driver = ?MODULE, opts = Opts}} ->
            {ok, maps:get(device, Opts, Conn), maps:with([latency_ms], Opts)};
        _ ->
            {error, not_simulated}
    end.

%%====================================================================
%% cell_hal_driver
%%====================================================================

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    Defaults = #{timeout_ms => 1000, latency_ms => 0},
    Checks = #{device => fun is_atom/1,
               timeout_ms => fun(V) -> is_integer(V) andalso V > 0 end,
               latency_ms => fun(V) -> is_integer(V) andalso V >= 0 end,
               image => fun(V) -> is_map(V) andalso
                                      lists:all(fun({G, P}) -> is_atom(G) andalso is_atom(P);
                                                   (_) -> false
                                                end, maps:keys(V))
                        end},
    case [K || {K, V} <- maps:to_list(Opts),
               not (maps:is_key(K, Checks) andalso (maps:get(K, Checks))(V))] of
        [] -> {ok, maps:merge(Defaults, Opts)};
        [Bad | _] -> {error, {bad_option, Bad}}
    end.

%% @private
%% Every point is its own cell of the image, by group and name: any field will do.
-spec check_point(map(), atom(), map(), cell_hal_group:point_def()) -> {ok, key()}.
check_point(_Opts, Group, _GroupOpts, #{name := Name}) ->
    {ok, {Group, Name}}.

%% @private
-spec init(atom(), map()) -> #sim{}.
init(Id, Opts) ->
    #sim{id = Id, device = maps:get(device, Opts, Id),
         device_opts = maps:with([latency_ms, image], Opts),
         timeout_ms = maps:get(timeout_ms, Opts, 1000)}.

%% @private
-spec endpoint(#sim{}) -> iodata().
endpoint(#sim{device = Device}) ->
    ["simulated PLC ", atom_to_list(Device)].

%% @private
-spec connect(#sim{}) -> {ok, #sim{}}.
connect(#sim{device = Name, device_opts = DOpts} = S) ->
    Pid = cell_hal_sim_sup:ensure_device(Name, DOpts),
    Ref = make_ref(),
    gen_server:cast(Pid, {connect, self(), Ref}),
    {ok, S#sim{pid = Pid, mref = erlang:monitor(process, Pid), ref = Ref}}.

%% @private
-spec plan([cell_hal_driver:point()], #sim{}) -> {[{key(), cell_hal_type:type()}], #{requests := 1}}.
plan(Points, _S) ->
    {[{K, T} || #{field := K, type := T} <- Points], #{requests => 1}}.

%% @private
-spec read(term(), [{key(), cell_hal_type:type()}], #sim{}) -> {ok, #sim{}}.
read(Tag, Plan, #sim{pid = Pid, ref = Ref} = S) ->
    gen_server:cast(Pid, {read, Ref, Tag, Plan}),
    {ok, deadline(Tag, S)}.

%% @private
-spec write(term(), cell_hal_driver:point(), cell_hal_type:value(), #sim{}) -> {ok, #sim{}}.
write(Tag, #{field := Key}, V, #sim{pid = Pid, ref = Ref} = S) ->
    gen_server:cast(Pid, {write, Ref, Tag, Key, V}),
    {ok, deadline(Tag, S)}.

%% @private
-spec request(term(), term(), pos_integer(), #sim{}) -> {error, not_supported}.
request(_Tag, _Request, _Timeout, _S) ->
    {error, not_supported}.

%% @private
-spec handle_info(term(), #sim{}) -> {ok, [cell_hal_driver:event()], #sim{}} | unknown.
handle_info({cell_hal_sim, Ref, connected}, #sim{ref = Ref} = S) ->
    {ok, [connected], S};
handle_info({cell_hal_sim, Ref, refused}, #sim{ref = Ref} = S) ->
    {ok, [{lost, refused}], disconnect(S)};
handle_info({cell_hal_sim, Ref, closed}, #sim{ref = Ref} = S) ->
    {ok, [{lost, closed}], disconnect(S)};
handle_info({cell_hal_sim, Ref, {reply, Tag, _} = Reply}, #sim{ref = Ref, timers = Ts} = S) ->
    case maps:take(Tag, Ts) of
        {TRef, Rest} ->
            _ = erlang:cancel_timer(TRef),
            {ok, [Reply], S#sim{timers = Rest}};
        error ->
            {ok, [], S}
    end;
handle_info({cell_hal_sim, _OldRef, _}, S) ->
    {ok, [], S};
handle_info({timeout, TRef, {?MODULE, Ref, Tag}}, #sim{ref = Ref, timers = Ts} = S) ->
    case Ts of
        #{Tag := TRef} -> {ok, [{lost, {no_answer, S#sim.timeout_ms}}], disconnect(S)};
        _ -> {ok, [], S}
    end;
handle_info({timeout, _, {?MODULE, _, _}}, S) ->
    {ok, [], S};
handle_info({'DOWN', MRef, process, _, _}, #sim{mref = MRef} = S) ->
    {ok, [{lost, device_stopped}], disconnect(S#sim{mref = undefined})};
handle_info(_, _) ->
    unknown.

%% @private
-spec disconnect(#sim{}) -> #sim{}.
disconnect(#sim{pid = Pid, mref = MRef, ref = Ref, timers = Ts} = S) ->
    maps:foreach(fun(_, T) -> _ = erlang:cancel_timer(T) end, Ts),
    _ = is_reference(MRef) andalso erlang:demonitor(MRef, [flush]),
    _ = is_pid(Pid) andalso is_reference(Ref) andalso gen_server:cast(Pid, {disconnect, Ref}),
    S#sim{pid = undefined, mref = undefined, ref = undefined, timers = #{}}.

%% @private
-spec format_reason(term()) -> iodata().
format_reason(refused) -> "the simulated PLC refused the connection";
format_reason(closed) -> "the simulated PLC dropped the connection";
format_reason(device_stopped) -> "the simulated PLC stopped";
format_reason({no_answer, Ms}) -> io_lib:format("no answer within ~b ms", [Ms]);
format_reason(not_supported) -> "the simulated PLC has no raw requests";
format_reason(Other) -> io_lib:format("~tp", [Other]).

deadline(Tag, #sim{ref = Ref, timeout_ms = Ms, timers = Ts} = S) ->
    S#sim{timers = Ts#{Tag => erlang:start_timer(Ms, self(), {?MODULE, Ref, Tag})}}.
