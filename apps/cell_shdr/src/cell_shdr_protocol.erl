%% @doc One MTConnect agent (or any SHDR client) connected to the adapter: a ranch
%% protocol process that owns the socket.
%%
%% At connect it registers with {@link cell_shdr_cache}, sends the snapshot (the
%% adapter's `* name: value' announcements, every current value, every condition,
%% every asset), then copies the cache's log to the socket from the position the
%% snapshot stands for: changed values only, each once.
%%
%% <b>Slow clients.</b> The log is shared and bounded; this process reads it at its
%% own pace, in batches, and tells the cache through a flag when it has caught up and
%% waits. A client that falls more than `max_client_buffer' bytes behind is dropped
%% with a log line, and one that reads nothing for the socket's send timeout (5 s) is
%% dropped too, so neither the cache nor another client ever waits for it.
%%
%% <b>Admission and life.</b> The cache admits at most `max_clients' clients (one
%% count for the whole listener, whatever ranch's acceptors); a client beyond it is
%% closed at once with a log line, never left in the kernel's queue. A client must show
%% life with a `* PING' within `life_timeout' of its connect, or it is closed: TCP
%% cannot tell the adapter whether a client reads the little it is sent, and every
%% MTConnect agent PINGs at connect. Until then it holds its place only until a new
%% client needs it: when every place is taken, the newcomer takes the place of the
%% oldest client that has not PINGed, so idle connections can never lock an agent out.
%%
%% <b>Input.</b> The socket is in `{active, once}'. `* PING' is answered `* PONG
%% <period>' at once; after the first PING, a client silent for two periods is
%% disconnected (seed 003: "if the agent becomes unresponsive, the adapter can
%% disconnect"). Other lines are ignored, with one log line per connection; a line
%% longer than 1024 bytes ends the connection. Nothing a client sends is turned into
%% an atom or reaches another process.
-module(cell_shdr_protocol).
-behaviour(gen_server).
-behaviour(ranch_protocol).

-export([start_link/3]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-define(SOURCE, shdr).
-define(MAX_LINE, 1024).
-define(BATCH_ENTRIES, 512).
-define(SEND_TIMEOUT, 5000).
-define(SNDBUF, 262144).

-record(c, {socket :: inet:socket(),
            transport :: module(),
            peer :: binary(),
            flag :: atomics:atomics_ref(),
            head :: atomics:atomics_ref(),
            log :: ets:tid() | atom(),
            pos :: non_neg_integer(),
            sent :: non_neg_integer(),            %% log offset sent so far
            limit :: pos_integer(),
            ping_period :: pos_integer(),
            heard :: integer(),                   %% monotonic ms of the last input
            heartbeat :: reference() | undefined, %% armed after the first PING
            life :: reference() | alive,          %% the life check, until the first PING
            life_timeout :: pos_integer(),
            buffer = <<>> :: binary(),
            warned = false :: boolean()}).

%% @doc Called by ranch for each accepted connection.
-spec start_link(ranch:ref(), module(), map()) -> {ok, pid()}.
start_link(Ref, Transport, Opts) ->
    {ok, proc_lib:spawn_link(?MODULE, init, [{Ref, Transport, Opts}])}.

%% @private
-spec init({ranch:ref(), module(), map()}) -> no_return().
init({Ref, Transport, _Opts}) ->
    {ok, Socket} = ranch:handshake(Ref),
    %% A fixed kernel send buffer bounds what a client that stopped reading holds in
    %% the kernel too; past it, a send waits, and the send timeout ends the wait.
    ok = Transport:setopts(Socket, [{send_timeout, ?SEND_TIMEOUT}, {send_timeout_close, true},
                                    {nodelay, true}, {sndbuf, ?SNDBUF}]),
    Peer = peer(Transport, Socket),
    Flag = atomics:new(1, []),
    case cell_shdr_cache:register_client(Flag) of
        {ok, Reg} ->
            start(Reg, Socket, Transport, Peer, Flag);
        {error, {full, Max}} ->
            cell_log:warning(?SOURCE, "MTConnect client ~ts refused: ~p clients are connected, "
                             "the limit (max_clients), and each has shown life", [Peer, Max]),
            refuse(Transport, Socket);
        {error, closing} ->
            refuse(Transport, Socket)
    end.

%% The end of the stream first, so the client reads a plain end even when what it sent
%% (its PING) is still unread here and the close itself resets the connection.
-spec refuse(module(), inet:socket()) -> no_return().
refuse(Transport, Socket) ->
    _ = Transport:shutdown(Socket, write),
    _ = Transport:close(Socket),
    exit(normal).

start(#{preamble := Preamble, seq := Seq, offset := Off, head := Head, log := Log,
        limit := Limit, ping_period := Period, life_timeout := Life},
      Socket, Transport, Peer, Flag) ->
    cell_log:info(?SOURCE, "MTConnect client ~ts connected", [Peer]),
    C = #c{socket = Socket, transport = Transport, peer = Peer, flag = Flag, head = Head,
           log = Log, pos = Seq, sent = Off, limit = Limit, ping_period = Period,
           heard = now_ms(), life = erlang:start_timer(Life, self(), life),
           life_timeout = Life},
    case send(Preamble, C) of
        ok ->
            ok = active_once(C),
            case pump(C) of
                {ok, C1} -> gen_server:enter_loop(?MODULE, [], C1);
                {stop, Why, _} -> exit(Why)
            end;
        {stop, Why, _} ->
            exit(Why)
    end.

%% @private
-spec handle_call(term(), gen_server:from(), #c{}) -> no_return().
handle_call(Msg, _From, _C) ->
    error({unexpected_call, Msg}).

%% @private
-spec handle_cast(term(), #c{}) -> no_return().
handle_cast(Msg, _C) ->
    error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #c{}) -> {noreply, #c{}} | {stop, term(), #c{}}.
handle_info({cell_shdr, wake}, C) ->
    result(pump(C));
handle_info({tcp, Socket, Data}, #c{socket = Socket} = C) ->
    input(Data, C#c{heard = now_ms()});
handle_info({tcp_closed, Socket}, #c{socket = Socket, peer = Peer} = C) ->
    cell_log:info(?SOURCE, "MTConnect client ~ts disconnected (~ts)", [Peer, posix(closed)]),
    {stop, normal, C};
handle_info({timeout, TRef, life}, #c{life = TRef, peer = Peer, life_timeout = Life} = C) ->
    cell_log:warning(?SOURCE, "MTConnect client ~ts sent no PING within ~p ms of its connect "
                     "(life_timeout); disconnected", [Peer, Life]),
    close(C),
    {stop, {shutdown, no_life}, C};
handle_info({cell_shdr, closing}, #c{peer = Peer} = C) ->
    case send_all(C) of
        {ok, C1} ->
            cell_log:info(?SOURCE, "MTConnect client ~ts disconnected: the adapter stops", [Peer]),
            close(C1),
            {stop, normal, C1};
        {stop, _, _} = Stop ->
            Stop
    end;
handle_info({timeout, _, life}, C) ->
    %% Cancelled by the first PING as it fell due.
    {noreply, C};
handle_info({cell_shdr, evicted}, #c{peer = Peer} = C) ->
    cell_log:warning(?SOURCE, "MTConnect client ~ts, which has sent no PING yet, gave its place "
                     "to a new client (max_clients reached); disconnected", [Peer]),
    close(C),
    {stop, {shutdown, evicted}, C};
handle_info({tcp_error, Socket, Reason}, #c{socket = Socket, peer = Peer} = C) ->
    cell_log:info(?SOURCE, "MTConnect client ~ts: connection error ~ts", [Peer, posix(Reason)]),
    {stop, normal, C};
handle_info({timeout, TRef, heartbeat}, #c{heartbeat = TRef, peer = Peer} = C) ->
    Period = C#c.ping_period,
    case now_ms() - C#c.heard > 2 * Period of
        true ->
            cell_log:warning(?SOURCE, "MTConnect client ~ts sent no PING for ~p ms (twice "
                             "its period); disconnected", [Peer, 2 * Period]),
            close(C),
            {stop, {shutdown, silent}, C};
        false ->
            {noreply, C#c{heartbeat = erlang:start_timer(Period, self(), heartbeat)}}
    end.

%%====================================================================
%% Input
%%====================================================================

input(Data, #c{buffer = Buf, peer = Peer} = C) ->
    case cell_shdr_codec:parse_input(<<Buf/binary, Data/binary>>, ?MAX_LINE) of
        {ok, Commands, Rest} ->
            case commands(Commands, C#c{buffer = Rest}) of
                {ok, C1} ->
                    ok = active_once(C1),
                    {noreply, C1};
                {stop, _, _} = Stop ->
                    Stop
            end;
        {error, line_too_long} ->
            cell_log:warning(?SOURCE, "MTConnect client ~ts sent a line longer than ~p bytes; "
                             "disconnected", [Peer, ?MAX_LINE]),
            close(C),
            {stop, {shutdown, line_too_long}, C}
    end.

commands([], C) ->
    {ok, C};
commands([ping | Rest], #c{ping_period = Period} = C0) ->
    C = alive(C0),
    C1 = case C#c.heartbeat of
             undefined -> C#c{heartbeat = erlang:start_timer(Period, self(), heartbeat)};
             _ -> C
         end,
    case send(cell_shdr_codec:pong(Period), C1) of
        ok -> commands(Rest, C1);
        Stop -> Stop
    end;
commands([{unknown, Line} | Rest], #c{warned = false, peer = Peer} = C) ->
    cell_log:info(?SOURCE, "MTConnect client ~ts sent something the adapter does not "
                  "understand; ignored (~ts)", [Peer, printable(Line)]),
    commands(Rest, C#c{warned = true});
commands([{unknown, _} | Rest], C) ->
    commands(Rest, C).

%% The first PING: the client has shown life, and no longer gives its place to a new one.
alive(#c{life = alive} = C) ->
    C;
alive(#c{life = TRef} = C) ->
    _ = erlang:cancel_timer(TRef),
    ok = cell_shdr_cache:alive(),
    C#c{life = alive}.

%% What a log line may show of a client's input: printable ASCII, at most 60 bytes.
printable(Line) ->
    Part = binary:part(Line, 0, min(60, byte_size(Line))),
    << <<(case Ch >= 32 andalso Ch < 127 of true -> Ch; false -> $?end)>> || <<Ch>> <= Part >>.

%%====================================================================
%% Output: the log, read at the client's pace
%%====================================================================

pump(#c{pos = Pos, head = HeadRef} = C) ->
    case atomics:get(HeadRef, 1) of
        Pos -> arm(C);
        Head -> copy(Head, C)
    end.

copy(Head, #c{pos = Pos, log = Log, sent = Sent, limit = Limit, peer = Peer} = C) ->
    case ets:lookup(Log, Head) of
        [{_, _, HeadEnd}] when HeadEnd - Sent =< Limit ->
            Last = min(Head, Pos + ?BATCH_ENTRIES),
            case collect(Pos + 1, Last, Log, []) of
                {ok, Data, End} ->
                    case send(Data, C) of
                        ok when Last < Head ->
                            %% More waits: go on after any input that came meanwhile.
                            self() ! {cell_shdr, wake},
                            {ok, C#c{pos = Last, sent = End}};
                        ok ->
                            pump(C#c{pos = Last, sent = End});
                        Stop ->
                            Stop
                    end;
                behind ->
                    too_slow(C)
            end;
        [{_, _, HeadEnd}] ->
            cell_log:warning(?SOURCE, "MTConnect client ~ts fell ~p bytes behind (the limit "
                             "is ~p); disconnected", [Peer, HeadEnd - Sent, Limit]),
            close(C),
            {stop, {shutdown, too_slow}, C};
        [] ->
            too_slow(C)
    end.

%% Everything the log holds, batch after batch, before the adapter stops.
send_all(#c{pos = Pos, head = HeadRef} = C) ->
    case atomics:get(HeadRef, 1) of
        Pos ->
            {ok, C};
        Head ->
            case copy(Head, C) of
                {ok, C1} -> send_all(C1);
                {stop, _, _} = Stop -> Stop
            end
    end.

too_slow(#c{peer = Peer, limit = Limit} = C) ->
    cell_log:warning(?SOURCE, "MTConnect client ~ts fell more than ~p bytes behind; "
                     "disconnected", [Peer, Limit]),
    close(C),
    {stop, {shutdown, too_slow}, C}.

collect(Seq, Last, _Log, Acc) when Seq > Last ->
    [{_, End} | _] = Acc,
    {ok, lists:reverse([B || {B, _} <- Acc]), End};
collect(Seq, Last, Log, Acc) ->
    case ets:lookup(Log, Seq) of
        [{_, Bin, End}] -> collect(Seq + 1, Last, Log, [{Bin, End} | Acc]);
        [] -> behind
    end.

%% Caught up: say so, then look once more, since the cache may have appended between
%% the read and the flag. Taking the flag back means no wake is coming; finding it
%% gone means one is.
arm(#c{flag = Flag, head = HeadRef, pos = Pos} = C) ->
    ok = atomics:put(Flag, 1, 1),
    case atomics:get(HeadRef, 1) of
        Pos ->
            {ok, C};
        _ ->
            case atomics:compare_exchange(Flag, 1, 1, 0) of
                ok -> pump(C);
                _ -> {ok, C}
            end
    end.

send(Data, #c{transport = T, socket = S, peer = Peer} = C) ->
    case T:send(S, Data) of
        ok ->
            ok;
        {error, timeout} ->
            cell_log:warning(?SOURCE, "MTConnect client ~ts read nothing for ~p ms; "
                             "disconnected", [Peer, ?SEND_TIMEOUT]),
            {stop, {shutdown, not_reading}, C};
        {error, Reason} ->
            cell_log:info(?SOURCE, "MTConnect client ~ts disconnected (~ts)",
                          [Peer, posix(Reason)]),
            {stop, normal, C}
    end.

result({ok, C}) -> {noreply, C};
result({stop, _, _} = Stop) -> Stop.

active_once(#c{transport = T, socket = S}) ->
    case T:setopts(S, [{active, once}]) of
        ok -> ok;
        %% Closed meanwhile: the tcp_closed message ends this process.
        {error, _} -> ok
    end.

close(#c{transport = T, socket = S}) ->
    _ = T:close(S),
    ok.

peer(Transport, Socket) ->
    case Transport:peername(Socket) of
        {ok, {Ip, Port}} -> iolist_to_binary([inet:ntoa(Ip), $:, integer_to_binary(Port)]);
        {error, _} -> <<"(unknown address)">>
    end.

%% inet:format_error/1 knows the POSIX codes only: `closed' is the peer's plain close.
posix(closed) -> "the agent closed the connection";
posix(Reason) when is_atom(Reason) -> inet:format_error(Reason);
posix(Reason) -> io_lib:format("~0tp", [Reason]).

now_ms() ->
    erlang:monotonic_time(millisecond).
