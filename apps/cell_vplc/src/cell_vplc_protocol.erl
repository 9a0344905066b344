%% @doc One client of the virtual PLC (a ranch protocol): takes Modbus TCP frames off
%% the stream, answers each from the register map ({@link cell_vplc_image}) with the
%% simulation's point values, and hands the values a write sets to the simulated PLC,
%% whose rules move the machine's physics as the HAL's writes do in simulation mode.
%%
%% A stream that is not Modbus TCP (a protocol id other than 0, a length outside
%% 2..254, an empty PDU) closes this connection, said in the log; the PLC and its
%% other clients go on.
-module(cell_vplc_protocol).
-behaviour(ranch_protocol).
-behaviour(gen_server).

-export([start_link/3]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-record(conn, {socket :: inet:socket(),
               transport :: module(),
               peer :: string(),
               image :: cell_vplc_image:image(),
               buf = <<>> :: binary()}).

%% @private
-spec start_link(ranch:ref(), module(), #{image := cell_vplc_image:image()}) -> {ok, pid()}.
start_link(Ref, Transport, Opts) ->
    {ok, proc_lib:spawn_link(fun() -> enter(Ref, Transport, Opts) end)}.

enter(Ref, Transport, #{image := Image}) ->
    {ok, Socket} = ranch:handshake(Ref),
    Peer = case Transport:peername(Socket) of
               {ok, {Ip, Port}} -> inet:ntoa(Ip) ++ ":" ++ integer_to_list(Port);
               {error, _} -> "a client"
           end,
    cell_log:info(vplc, "virtual PLC: ~s connected", [Peer]),
    ok = Transport:setopts(Socket, [{active, once}]),
    gen_server:enter_loop(?MODULE, [], #conn{socket = Socket, transport = Transport,
                                             peer = Peer, image = Image}).

%% @private
-spec init(term()) -> no_return().
init(_) ->
    %% Started by ranch through start_link/3 and gen_server:enter_loop/3 only.
    erlang:error(not_started_by_ranch).

%% @private
-spec handle_call(term(), gen_server:from(), #conn{}) -> no_return().
handle_call(Request, _From, _C) ->
    erlang:error({unexpected_call, Request}).

%% @private
-spec handle_cast(term(), #conn{}) -> no_return().
handle_cast(Msg, _C) ->
    erlang:error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #conn{}) -> {noreply, #conn{}} | {stop, normal, #conn{}}.
handle_info({tcp, S, Data}, #conn{socket = S, buf = Buf} = C) ->
    case frames(<<Buf/binary, Data/binary>>, C) of
        {ok, C1} ->
            ok = (C1#conn.transport):setopts(S, [{active, once}]),
            {noreply, C1};
        {close, Why} ->
            cell_log:warning(vplc, "virtual PLC: ~s sent ~s; its connection is closed",
                             [C#conn.peer, Why]),
            {stop, normal, C}
    end;
handle_info({tcp_closed, S}, #conn{socket = S, peer = Peer} = C) ->
    cell_log:info(vplc, "virtual PLC: ~s disconnected", [Peer]),
    {stop, normal, C};
handle_info({tcp_error, S, _}, #conn{socket = S, peer = Peer} = C) ->
    cell_log:info(vplc, "virtual PLC: ~s disconnected", [Peer]),
    {stop, normal, C}.

%% Every complete frame of the buffer answered, the rest kept for the next data.
frames(Buf, #conn{socket = S, transport = T, image = Image} = C) ->
    case cell_hal_modbus_codec:frame(Buf) of
        more ->
            {ok, C#conn{buf = Buf}};
        {error, Why} ->
            {close, ["something that is not Modbus TCP (",
                     cell_hal_modbus_codec:format_error(Why), ")"]};
        {ok, Tid, Unit, Pdu, Rest} ->
            case cell_vplc_image:answer(Unit, Pdu, {Image, fun read/1}) of
                {reply, Reply, Writes} ->
                    ok = lists:foreach(fun write/1, Writes),
                    case T:send(S, cell_hal_modbus_codec:adu(Tid, Unit, Reply)) of
                        ok -> frames(Rest, C);
                        {error, _} -> {close, "a request but is gone before the answer"}
                    end;
                close ->
                    {close, "an empty request"}
            end
    end.

read(Key) ->
    case cell_hal_sim:get(Key) of
        {ok, V} -> V;
        {error, not_set} -> undefined
    end.

%% The image's map checked the value against the point's type.
write({Key, V}) ->
    ok = cell_hal_sim:set(Key, V).
