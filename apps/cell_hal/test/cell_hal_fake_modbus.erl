%% A Modbus TCP device for tests, on the project's codec (cell_hal_modbus_codec): it
%% listens on 127.0.0.1 on a port the OS picks, answers reads and writes from an image
%% kept in an ETS table, and can refuse addresses (an exception for every request that
%% touches one) or every Nth request, as a PLC does.
%%
%% Tables of the image: `co' (coils), `di' (discrete inputs), `hr' (holding registers),
%% `ir' (input registers); a bit is a boolean, a register a word. Unset reads as zero.
-module(cell_hal_fake_modbus).

-export([start/0, stop/1, port/1, set/3, get/2, refuse/4, fail_every/3, requests/1]).

-define(C, cell_hal_modbus_codec).

-record(dev, {pid :: pid(), tab :: ets:tid(), port :: inet:port_number()}).

%% @doc A device listening on a port of its own.
-spec start() -> #dev{}.
start() ->
    Tab = ets:new(fake_modbus, [public, {read_concurrency, true}]),
    true = ets:insert(Tab, [{requests, 0}, {fail_every, 0, 0}]),
    Parent = self(),
    Pid = spawn(fun() ->
                        {ok, L} = gen_tcp:listen(0, [binary, {active, false}, {ip, loopback},
                                                     {reuseaddr, true}]),
                        {ok, Port} = inet:port(L),
                        Parent ! {self(), port, Port},
                        process_flag(trap_exit, true),
                        Acceptor = spawn_link(fun() -> accept(L, Tab) end),
                        receive stop -> exit(Acceptor, kill), gen_tcp:close(L) end
                end),
    receive {Pid, port, Port} -> #dev{pid = Pid, tab = Tab, port = Port}
    after 5000 -> error(fake_modbus_not_listening)
    end.

%% @doc Stops listening and closes every connection.
-spec stop(#dev{}) -> ok.
stop(#dev{pid = Pid, tab = Tab}) ->
    MRef = monitor(process, Pid),
    Pid ! stop,
    receive {'DOWN', MRef, process, Pid, _} -> ok end,
    _ = [exit(C, kill) || {{conn, C}} <- ets:tab2list(Tab)],
    ets:delete(Tab),
    ok.

-spec port(#dev{}) -> inet:port_number().
port(#dev{port = Port}) -> Port.

%% @doc Sets a bit or a register of the image.
-spec set(#dev{}, {co | di | hr | ir, non_neg_integer()}, boolean() | 0..65535) -> ok.
set(#dev{tab = Tab}, Key, V) ->
    true = ets:insert(Tab, {Key, V}),
    ok.

-spec get(#dev{}, {co | di | hr | ir, non_neg_integer()}) -> boolean() | 0..65535.
get(#dev{tab = Tab}, {T, _} = Key) ->
    case ets:lookup(Tab, Key) of
        [{_, V}] -> V;
        [] when T =:= co; T =:= di -> false;
        [] -> 0
    end.

%% @doc Refuses every request that touches an address of a table with the exception
%% `Code' (0: answers it again).
-spec refuse(#dev{}, co | di | hr | ir, non_neg_integer(), 0..255) -> ok.
refuse(#dev{tab = Tab}, T, A, 0) ->
    true = ets:delete(Tab, {refused, T, A}),
    ok;
refuse(#dev{tab = Tab}, T, A, Code) ->
    true = ets:insert(Tab, {{refused, T, A}, Code}),
    ok.

%% @doc Answers every Nth request with the exception `Code' (N = 0: none).
-spec fail_every(#dev{}, non_neg_integer(), 0..255) -> ok.
fail_every(#dev{tab = Tab}, N, Code) ->
    true = ets:insert(Tab, [{fail_every, N, Code}, {requests, 0}]),
    ok.

%% @doc How many requests the device has been asked since it started or since its
%% last fail_every/3.
-spec requests(#dev{}) -> non_neg_integer().
requests(#dev{tab = Tab}) ->
    ets:lookup_element(Tab, requests, 2).

%%--------------------------------------------------------------------

accept(L, Tab) ->
    case gen_tcp:accept(L) of
        {ok, S} ->
            Pid = spawn(fun() -> receive go -> serve(S, Tab, <<>>) end end),
            ok = gen_tcp:controlling_process(S, Pid),
            true = ets:insert(Tab, {{conn, Pid}}),
            Pid ! go,
            accept(L, Tab);
        {error, _} ->
            ok
    end.

serve(S, Tab, Buf) ->
    case gen_tcp:recv(S, 0) of
        {ok, Data} -> serve(S, Tab, answer(S, Tab, <<Buf/binary, Data/binary>>));
        {error, _} -> ets:delete(Tab, {conn, self()})
    end.

answer(S, Tab, Buf) ->
    case ?C:frame(Buf) of
        {ok, Tid, Unit, Pdu, Rest} ->
            {ok, Req} = ?C:decode_request(Pdu),
            ok = gen_tcp:send(S, ?C:adu(Tid, Unit, ?C:response_pdu(Req, reply(Tab, Req)))),
            answer(S, Tab, Rest);
        more ->
            Buf
    end.

reply(Tab, Req) ->
    N = ets:update_counter(Tab, requests, 1),
    [{fail_every, Every, FailCode}] = ets:lookup(Tab, fail_every),
    {T, A, Count} = span(Req),
    Refused = [C || I <- lists:seq(A, A + Count - 1), {_, C} <- ets:lookup(Tab, {refused, T, I})],
    if
        Every > 0, N rem Every =:= 0 -> {exception, FailCode};
        Refused =/= [] -> {exception, hd(Refused)};
        true -> do(Tab, Req)
    end.

span({read_coils, A, N}) -> {co, A, N};
span({read_discrete_inputs, A, N}) -> {di, A, N};
span({read_holding_registers, A, N}) -> {hr, A, N};
span({read_input_registers, A, N}) -> {ir, A, N};
span({write_single_coil, A, _}) -> {co, A, 1};
span({write_single_register, A, _}) -> {hr, A, 1};
span({write_multiple_coils, A, Bits}) -> {co, A, length(Bits)};
span({write_multiple_registers, A, Regs}) -> {hr, A, byte_size(Regs) div 2};
span({mask_write_register, A, _, _}) -> {hr, A, 1}.

do(Tab, {Read, A, N}) when Read =:= read_coils; Read =:= read_discrete_inputs ->
    T = case Read of read_coils -> co; _ -> di end,
    [value(Tab, {T, I}, false) || I <- lists:seq(A, A + N - 1)];
do(Tab, {Read, A, N}) when Read =:= read_holding_registers; Read =:= read_input_registers ->
    T = case Read of read_holding_registers -> hr; _ -> ir end,
    << <<(value(Tab, {T, I}, 0)):16>> || I <- lists:seq(A, A + N - 1) >>;
do(Tab, {write_single_coil, A, V}) ->
    true = ets:insert(Tab, {{co, A}, V}),
    ok;
do(Tab, {write_single_register, A, V}) ->
    true = ets:insert(Tab, {{hr, A}, V}),
    ok;
do(Tab, {write_multiple_coils, A, Bits}) ->
    true = ets:insert(Tab, [{{co, A + I}, B} || {I, B} <- lists:enumerate(0, Bits)]),
    ok;
do(Tab, {write_multiple_registers, A, Regs}) ->
    Words = [W || <<W:16>> <= Regs],
    true = ets:insert(Tab, [{{hr, A + I}, W} || {I, W} <- lists:enumerate(0, Words)]),
    ok;
do(Tab, {mask_write_register, A, And, Or}) ->
    Old = value(Tab, {hr, A}, 0),
    true = ets:insert(Tab, {{hr, A}, (Old band And) bor (Or band (bnot And) band 16#FFFF)}),
    ok.

value(Tab, Key, Zero) ->
    case ets:lookup(Tab, Key) of
        [{_, V}] -> V;
        [] -> Zero
    end.
