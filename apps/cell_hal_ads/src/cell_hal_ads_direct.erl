%% @doc Reads that skip the connection's process: the caller writes its own request on
%% the connection's socket and the connection hands it the answer.
%%
%% A read through the client's process costs the caller a call to that process and the
%% process a reply, on top of the round trip to the PLC. Here the connection publishes
%% in ETS what a read needs — its socket, the AMS addresses, and a read item (index
%% group, offset, size) for every resolved variable — and a caller of
%% {@link cell_hal_ads_client:read_vars/3} builds the frame, registers its invoke id
%% with a reply alias, and writes the frame to the socket itself. The connection still
%% owns the socket and reads every frame: it takes the registration of an answer's
%% invoke id and sends the answer to that alias: one message between processes
%% instead of two, and the connection's process is woken once a read, not twice.
%% Everything else a call guarantees stays:
%%
%% <ul>
%% <li>Invoke ids: the connection's own requests use odd ids, direct reads even ones
%%     from a counter of the socket's, registered with `ets:insert_new' so that an id
%%     is never in flight twice; an answer whose id is not registered (one that came
%%     after its caller gave up) is dropped.</li>
%% <li>`max_in_flight' bounds every request on the socket, direct or not: both sides
%%     take a slot from one shared counter before they send, and whoever removes a
%%     registration gives its slot back (the connection when it takes the answer, the
%%     caller when it gives up); a caller that finds no slot goes through the
%%     connection's process, which queues it.</li>
%% <li>Handles stay right: the connection withdraws what it published before it gives
%%     handles back or loses the connection, and moves to a new epoch. A registration
%%     carries the epoch the caller read; an answer to a registration of an older
%%     epoch may have been read through a handle that meanwhile meant something else,
%%     so it is not used: the caller goes through the connection's process, which
%%     waits for the variables to be resolved again.</li>
%% <li>Timeouts: the caller waits for its own timeout. If its registration is still
%%     there it removes it and the answer can no longer come; if the connection took it
%%     first, the answer is on its way and the caller takes it. Either way no message
%%     is left behind. A timeout is reported to the connection, which closes itself if
%%     nothing at all came from the PLC since the request was sent (the same test as
%%     for its own requests).</li>
%% <li>A caller that exits leaves its registration behind; the answer, when it comes,
%%     goes to an alias nobody holds, and the connection's periodic link check removes
%%     what callers that are gone left without an answer.</li>
%% <li>The caller never waits for room on the socket: it writes only to a socket whose
%%     queue is empty (so its frame goes straight to the kernel), without suspending
%%     (`nosuspend'); otherwise the read goes through the connection's process. Should
%%     the connection fill the queue in the instant between the two, the caller waits
%%     for the socket like any sender, at most the socket's send timeout (the client's
%%     `request_timeout'), and no longer than the socket lives.</li>
%% <li>A lost connection answers every registration `{error, disconnected}'; a client
%%     that exits is seen through the caller's monitor, as in a call.</li>
%% </ul>
%%
%% Only reads that go out as one request take this way (one variable, or a group in
%% one sum command). Anything the tables cannot answer at once (a variable not
%% resolved or failed, the connection not ready, a read that needs several requests)
%% goes through the connection's process as before, and so does a caller with more
%% than a hundred messages waiting (the socket's reply is looked for among them, as
%% gen_tcp:send does, where a call looks only at what came after it). Writes always
%% go through the process: they keep their order.
%%
%% A process's direct read does not wait for requests it started with
%% {@link cell_hal_ads_client:send_request/5} and has not seen answered: those are
%% still in flight, and the read may reach the PLC before them.
%%
%% The tables are found from the client's pid through one persistent term per client,
%% written when its first connection is ready and erased when it ends (or, for a
%% client killed without ending, when the next client announces itself).
-module(cell_hal_ads_direct).

-include("cell_hal_ads.hrl").

%% The connection's side
-export([new/0, announce/2, retract/1, counters/0, take_slot/2, free_slots/2, in_flight/1,
         open/3, add/2, drop/3, close/1, answer/7, fail_all/2, sweep/2]).
%% The caller's side
-export([read_vars/3]).

-ifdef(TEST).
%% The two halves of answer/7, for tests of a timeout that comes between them; the
%% wait for the socket, for tests of a full one.
-export([claim/3, settle/5, sent/1]).
-endif.

-export_type([tables/0, counters/0, conn/0, readable/0]).

-record(tables, {pub :: ets:tid(),      % the connection and its variables
                 reg :: ets:tid()}).    % invoke id -> caller, for requests in flight

-opaque tables() :: #tables{}.

%% Per socket: requests in flight on it (both sides), and the last direct invoke id.
-opaque counters() :: atomics:atomics_ref().
-define(IN_FLIGHT, 1).
-define(INVOKE, 2).

%% What the connection publishes about itself while it is ready.
-type conn() :: #{pid := pid(), socket := port(),
                  target := cell_hal_ads_codec:ams_addr(),
                  source := cell_hal_ads_codec:ams_addr(),
                  epoch := non_neg_integer(), mode := cell_hal_ads_batch:mode(),
                  counters := counters(), max_in_flight := pos_integer()}.

%% The same, as a row of the `pub' table (key: the atom `conn').
-record(conn, {pid :: pid(),
               socket :: port(),
               addresses :: binary(),
               epoch :: non_neg_integer(),
               mode :: cell_hal_ads_batch:mode(),
               counters :: counters(),
               max :: pos_integer()}).

%% A read in flight, as a row of the `reg' table.
-record(reg, {invoke :: u32(),
              alias :: reference(),
              caller :: pid(),
              epoch :: non_neg_integer(),
              command :: cell_hal_ads_codec:command()}).

%% A variable a caller may read directly, in one of its spellings: the read item.
-type readable() :: {Name :: binary(), cell_hal_ads_types:type(), cell_hal_ads_vars:key(),
                     {Group :: u32(), Offset :: u32(), Size :: non_neg_integer()}}.

-type u32() :: 0..16#FFFFFFFF.

%% The answer a caller gets on its alias.
-type answer() :: {ads, Error :: u32(), Data :: binary()} | retry | {error, term()}.

-type results() :: [{ok, cell_hal_ads_types:value()} | {error, term()}].

-define(KEY(Pid), {?MODULE, Pid}).

%% A direct read looks through the caller's mailbox for the socket's reply (as any
%% gen_tcp:send does), a call does not: a caller with more messages waiting than
%% this goes through the connection's process, where looking would cost more than
%% the call saves.
-define(MAX_WAITING, 100).

%%====================================================================
%% The connection's side
%%====================================================================

%% @doc The tables of a new client, owned by the calling process (the client).
-spec new() -> tables().
new() ->
    #tables{pub = ets:new(?MODULE, [set, protected, {read_concurrency, true}]),
            reg = ets:new(?MODULE, [set, public, {keypos, #reg.invoke},
                                    {write_concurrency, true}])}.

%% @doc Makes the tables findable from the client's pid.
-spec announce(pid(), tables()) -> ok.
announce(Pid, Tables) ->
    %% A client killed without ending could not retract its tables (they went with it).
    _ = [persistent_term:erase(K) || {?KEY(P) = K, _} <- persistent_term:get(),
                                     not is_process_alive(P)],
    persistent_term:put(?KEY(Pid), Tables).

%% @doc The tables are no longer found (the client ends).
-spec retract(pid()) -> ok.
retract(Pid) ->
    _ = persistent_term:erase(?KEY(Pid)),
    ok.

%% @doc The counters of a new socket: nothing in flight.
-spec counters() -> counters().
counters() ->
    atomics:new(2, [{signed, true}]).

%% @doc A slot for one more request on the socket, if fewer than `Max' are in flight.
-spec take_slot(counters(), pos_integer()) -> boolean().
take_slot(Counters, Max) ->
    case atomics:add_get(Counters, ?IN_FLIGHT, 1) =< Max of
        true -> true;
        false -> free_slots(Counters, 1), false
    end.

%% @doc `N' requests are no longer in flight.
-spec free_slots(counters(), non_neg_integer()) -> ok.
free_slots(_, 0) ->
    ok;
free_slots(Counters, N) ->
    atomics:sub(Counters, ?IN_FLIGHT, N).

%% @doc How many requests are in flight on the socket, direct reads included.
-spec in_flight(counters()) -> non_neg_integer().
in_flight(Counters) ->
    atomics:get(Counters, ?IN_FLIGHT).

%% @doc The connection is ready: its variables first, then itself, so that a caller
%% that finds the connection finds every variable too.
-spec open(tables(), conn(), [readable()]) -> ok.
open(#tables{pub = Pub} = T, Conn, Readable) ->
    ok = add(T, Readable),
    #{pid := Pid, socket := Socket, target := Target, source := Source, epoch := Epoch,
      mode := Mode, counters := Counters, max_in_flight := Max} = Conn,
    true = ets:insert(Pub, #conn{pid = Pid, socket = Socket,
                                 addresses = cell_hal_ads_codec:addresses(Target, Source),
                                 epoch = Epoch, mode = Mode, counters = Counters, max = Max}),
    ok.

%% @doc More variables that can be read directly.
-spec add(tables(), [readable()]) -> ok.
add(#tables{pub = Pub}, Readable) ->
    true = ets:insert(Pub, [{{var, N, T}, K, Item} || {N, T, K, Item} <- Readable]),
    ok.

%% @doc A variable's handle goes back: its spellings are withdrawn, then the epoch
%% moves on (in that order, so that no caller reads the new epoch with the old
%% handle).
-spec drop(tables(), cell_hal_ads_vars:key(), non_neg_integer()) -> ok.
drop(#tables{pub = Pub}, Key, Epoch) ->
    true = ets:match_delete(Pub, {{var, '_', '_'}, Key, '_'}),
    _ = ets:update_element(Pub, conn, {#conn.epoch, Epoch}),
    ok.

%% @doc The connection is no longer ready: nothing is read directly until it is
%% opened again.
-spec close(tables()) -> ok.
close(#tables{pub = Pub}) ->
    true = ets:delete_all_objects(Pub),
    ok.

%% @doc An answer whose invoke id the connection does not know itself: to the caller
%% that registered it, whose slot is free again. `unknown' when nobody waits for it
%% any more; `{unexpected, Expected}' when it answers another command than the one
%% asked (the caller goes through the connection's process; the connection is not to
%% be trusted).
-spec answer(tables(), counters(), u32(),
             cell_hal_ads_codec:command() | {unknown, 0..65535}, u32(), binary(),
             non_neg_integer()) ->
          ok | unknown | {unexpected, cell_hal_ads_codec:command()}.
answer(T, Counters, Invoke, Cmd, Error, Data, Epoch) ->
    settle(claim(T, Counters, Invoke), Cmd, Error, Data, Epoch).

%% The registration is taken: from now on its caller waits for this answer.
claim(#tables{reg = Reg}, Counters, Invoke) ->
    case ets:take(Reg, Invoke) of
        [_] = Taken -> ok = free_slots(Counters, 1), Taken;
        [] -> []
    end.

settle([#reg{alias = Alias, epoch = Epoch, command = Cmd}], Cmd, Error, Data, Epoch) ->
    reply(Alias, {ads, Error, Data});
settle([#reg{alias = Alias, epoch = Epoch, command = Expected}], _, _, _, Epoch) ->
    ok = reply(Alias, retry),
    {unexpected, Expected};
settle([#reg{alias = Alias}], _, _, _, _Newer) ->
    reply(Alias, retry);
settle([], _, _, _, _) ->
    unknown.

%% @doc Every read in flight is answered `{error, Reason}' (the socket and its
%% counters are done with).
-spec fail_all(tables(), term()) -> ok.
fail_all(#tables{reg = Reg}, Reason) ->
    lists:foreach(fun(#reg{invoke = Invoke}) ->
                          case ets:take(Reg, Invoke) of
                              [#reg{alias = Alias}] -> reply(Alias, {error, Reason});
                              [] -> ok    % its caller gave up meanwhile
                          end
                  end, ets:tab2list(Reg)).

%% @doc Registrations of callers that exited are removed (their answers never came),
%% and their slots freed: how many.
-spec sweep(tables(), counters()) -> non_neg_integer().
sweep(#tables{reg = Reg}, Counters) ->
    Gone = lists:sum([remove(Reg, R) || #reg{caller = Pid} = R <- ets:tab2list(Reg),
                                        not is_process_alive(Pid)]),
    ok = free_slots(Counters, Gone),
    Gone.

%% A registration removed if it is still there, exactly as it was: 1 or 0.
remove(Reg, #reg{} = R) ->
    ets:select_delete(Reg, [{R, [], [true]}]).

reply(Alias, Answer) ->
    Alias ! {Alias, Answer},
    ok.

%%====================================================================
%% The caller's side
%%====================================================================

%% @doc Reads resolved variables without a call to the client's process, when that
%% can be done in one request: `{ok, Results}' as {@link cell_hal_ads_client:read_vars/3}
%% answers, `{error, timeout | disconnected}', `{down, Reason}' when the client exited
%% meanwhile (the reason its monitor gives, as to a call: `noproc' when the client was
%% already exiting as it took the monitor), or `{slow, Timeout}': go through the
%% client's process, with the time left.
-spec read_vars(cell_hal_ads_client:client(), [cell_hal_ads_client:var()], timeout()) ->
          {ok, results()} | {error, term()} | {down, term()} | {slow, timeout()}.
read_vars(_Client, _Vars, 0) ->
    %% Its time is up before it starts: the connection's process says so, as to a
    %% call.
    {slow, 0};
read_vars(Client, Vars, Timeout) ->
    case process_info(self(), message_queue_len) of
        {message_queue_len, Waiting} when Waiting =< ?MAX_WAITING ->
            case plan(Client, Vars) of
                {ok, T, Conn, Request, Assemble} ->
                    read(T, Conn, Request, Assemble, Vars, Timeout);
                slow ->
                    {slow, Timeout}
            end;
        _ ->
            {slow, Timeout}
    end.

%% The request, if the tables hold all it needs: the connection ready, every variable
%% published, one request for all. Anything else (a bad argument too) goes the slow
%% way, which checks it.
plan(Client, Vars) ->
    case tables(Client) of
        {ok, #tables{pub = Pub} = T} ->
            %% The tables go with a client that exits at this moment.
            try {ets:lookup(Pub, conn), items(Pub, Vars)} of
                {[#conn{mode = Mode} = Conn], {ok, Items}} ->
                    case cell_hal_ads_batch:reads(Items, Mode) of
                        {[Request], Assemble} -> {ok, T, Conn, Request, Assemble};
                        {_, _} -> slow
                    end;
                _ ->
                    slow
            catch
                error:badarg -> slow
            end;
        error ->
            slow
    end.

tables(Pid) when is_pid(Pid) ->
    case persistent_term:get(?KEY(Pid), undefined) of
        undefined -> error;
        T -> {ok, T}
    end;
tables(Name) when is_atom(Name) ->
    case whereis(Name) of
        undefined -> error;
        Pid -> tables(Pid)
    end;
tables(_) ->
    error.

items(_, []) ->
    {ok, []};
items(Pub, [{Name, Type} | Vars]) ->
    case ets:lookup(Pub, {var, Name, Type}) of
        [{_, _, Item}] ->
            case items(Pub, Vars) of
                {ok, Items} -> {ok, [Item | Items]};
                error -> error
            end;
        [] ->
            error
    end;
items(_, _) ->
    error.

read(T, #conn{pid = Pid, socket = Socket} = Conn, Request, Assemble, Vars, Timeout) ->
    Cmd = cell_hal_ads_codec:request_command(Request),
    Sent = erlang:monotonic_time(),
    case exchange(T, Conn, Request, Cmd, Timeout) of
        {ads, Error, Data} ->
            Answer = case Error of
                         0 -> cell_hal_ads_codec:decode_response(Cmd, Data);
                         _ -> {error, cell_hal_ads_codec:ads_error(Error)}
                     end,
            Results = Assemble([Answer]),
            %% as the connection does after its own reads: a handle that fails may
            %% belong to an older program
            case lists:any(fun is_stale/1, Results) of
                true -> gen_statem:cast(Pid, {?MODULE, stale, Socket});
                false -> ok
            end,
            {ok, decode(Vars, Results)};
        retry ->
            {slow, left(Sent, Timeout)};
        timeout ->
            gen_statem:cast(Pid, {?MODULE, expired, Socket, Sent}),
            {error, timeout};
        Other ->
            %% {error, disconnected} or {down, Reason}
            Other
    end.

%% A slot taken, registered, sent, answered.
-spec exchange(tables(), #conn{}, cell_hal_ads_codec:request(), cell_hal_ads_codec:command(),
               timeout()) -> answer() | timeout | {down, term()}.
exchange(#tables{reg = Reg}, Conn, Request, Cmd, Timeout) ->
    #conn{pid = Pid, socket = Socket, addresses = Addresses, epoch = Epoch,
          counters = Counters, max = Max} = Conn,
    case take_slot(Counters, Max) of
        true ->
            Alias = erlang:monitor(process, Pid, [{alias, demonitor}]),
            case enrol(Reg, Counters, Alias, Epoch, Cmd) of
                {ok, #reg{invoke = Invoke} = R} ->
                    Frame = cell_hal_ads_codec:encode_frame(Addresses, Invoke, Request),
                    case send(Socket, Frame) of
                        ok ->
                            case await(Alias, Timeout) of
                                timeout -> withdraw(Reg, Counters, R, timeout);
                                Answer -> Answer
                            end;
                        error ->
                            withdraw(Reg, Counters, R, retry)
                    end;
                gone ->
                    %% its monitor says why
                    await(Alias, infinity)
            end;
        false ->
            retry
    end.

%% Registered under an even invoke id not in flight; `gone' when the client's tables
%% went with it.
enrol(Reg, Counters, Alias, Epoch, Cmd) ->
    R = #reg{invoke = atomics:add_get(Counters, ?INVOKE, 2) band 16#FFFFFFFE, alias = Alias,
             caller = self(), epoch = Epoch, command = Cmd},
    try ets:insert_new(Reg, R) of
        true -> {ok, R};
        false -> enrol(Reg, Counters, Alias, Epoch, Cmd)   % in flight since the counter wrapped
    catch
        error:badarg -> gone
    end.

%% Only to a socket with nothing queued, never suspended: the frame goes straight to
%% the kernel, and the driver's reply is in the mailbox at once, unless the command
%% had to wait for another scheduler's use of the port (then it comes a moment later)
%% or found the queue filled meanwhile (then it comes when the PLC took enough, or
%% with the socket's send timeout); a socket closed meanwhile ends the wait too.
send(Socket, Frame) ->
    case erlang:port_info(Socket, queue_size) of
        {queue_size, 0} ->
            try erlang:port_command(Socket, Frame, [nosuspend]) of
                true -> sent(Socket);
                false -> error                  % busy
            catch
                error:badarg -> error           % closed meanwhile
            end;
        _ ->
            error                               % something queued, or closed
    end.

sent(Socket) ->
    receive
        {inet_reply, Socket, Status} -> status(Status)
    after 0 ->
            Ref = erlang:monitor(port, Socket),
            receive
                {inet_reply, Socket, Status} ->
                    erlang:demonitor(Ref, [flush]),
                    status(Status);
                {'DOWN', Ref, port, _, _} ->
                    error
            end
    end.

status(ok) -> ok;
status({error, _}) -> error.

%% The registration is taken back and its slot freed, and `Instead' given; if the
%% connection took it first, its answer is on the way and is the one given.
withdraw(Reg, Counters, #reg{alias = Alias} = R, Instead) ->
    try remove(Reg, R) of
        1 ->
            ok = free_slots(Counters, 1),
            erlang:demonitor(Alias, [flush]),
            Instead;
        0 ->
            await(Alias, infinity)
    catch
        error:badarg -> await(Alias, infinity)
    end.

%% The answer on the alias, or the client's exit; `timeout' when neither came in time.
await(Alias, Timeout) ->
    receive
        {Alias, Answer} ->
            erlang:demonitor(Alias, [flush]),
            Answer;
        {'DOWN', Alias, process, _, Reason} ->
            {down, Reason}
    after Timeout ->
            timeout
    end.

-spec decode([cell_hal_ads_client:var()], [{ok, binary()} | {error, term()}]) -> results().
decode([], []) -> [];
decode([{_, Type} | Vars], [{ok, Bin} | Results]) ->
    [cell_hal_ads_types:decode(Type, Bin) | decode(Vars, Results)];
decode([_ | Vars], [{error, _} = E | Results]) ->
    [E | decode(Vars, Results)].

is_stale({error, {ads_error, Code, _}}) -> lists:member(Code, ?STALE_HANDLE_ERRORS);
is_stale(_) -> false.

left(_, infinity) ->
    infinity;
left(Since, Timeout) ->
    Spent = erlang:convert_time_unit(erlang:monotonic_time() - Since, native, millisecond),
    max(0, Timeout - Spent).
