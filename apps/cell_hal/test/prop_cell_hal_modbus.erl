%% A PropEr property of the Modbus driver on a real socket: whatever bytes a device
%% sends back (random garbage, or valid answers with a byte changed, cut or repeated),
%% the driver never crashes, answers each request at most once, ends the connection
%% with a reason when the stream stops making sense, and never hands over a value that
%% was not on the wire as a well-formed answer to that very request.
-module(prop_cell_hal_modbus).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(C, cell_hal_modbus_codec).
-define(WAIT, 5000).

property_test_() ->
    {setup,
     fun() ->
             {ok, L} = gen_tcp:listen(0, [binary, {active, false}, {ip, loopback},
                                          {reuseaddr, true}]),
             L
     end,
     fun(L) -> gen_tcp:close(L) end,
     fun(L) ->
             [{timeout, 300, ?_assert(proper:quickcheck(prop_device_bytes(L),
                                                        [{to_file, user}, {numtests, 300}]))}]
     end}.

%% Requests the driver sends at once (no more than it keeps in flight, so the device
%% sees them all before it answers): register reads of 1..4 registers.
requests() ->
    ?LET(K, integer(1, 16), vector(K, ?LET({A, N}, {integer(0, 100), integer(1, 4)},
                                          {read_holding_registers, A, N}))).

%% What the device sends back.
answer(Reqs) ->
    Valid = [?C:adu(Tid, 1, ?C:response_pdu(R, << <<(Tid * 7 + I):16>> || I <- lists:seq(1, N) >>))
             || {Tid, {_, _, N} = R} <- lists:zip(lists:seq(0, length(Reqs) - 1), Reqs)],
    Stream = iolist_to_binary(Valid),
    oneof([binary(),
           Stream,
           ?LET({Pos, Byte}, {integer(0, byte_size(Stream) - 1), byte()}, mutate(Stream, Pos, Byte)),
           ?LET(Pos, integer(0, byte_size(Stream) - 1), binary:part(Stream, 0, Pos)),
           ?LET(Extra, binary(), <<Stream/binary, Extra/binary>>),
           <<Stream/binary, Stream/binary>>]).

mutate(Bin, Pos, Byte) ->
    <<Head:Pos/binary, _, Tail/binary>> = Bin,
    <<Head/binary, Byte, Tail/binary>>.

prop_device_bytes(L) ->
    {ok, Port} = inet:port(L),
    ?FORALL(Reqs, requests(),
            ?FORALL(Bytes, answer(Reqs),
                    begin
                        Events = exchange(L, Port, Reqs, Bytes),
                        ?WHENFAIL(io:format("requests ~p~nbytes ~p~nevents ~p~n",
                                            [Reqs, Bytes, Events]),
                                  sound(Reqs, Bytes, Events))
                    end)).

%% The driver connects and sends the requests (tags 1..N: transaction ids 0..N-1 on a
%% fresh connection); the device, a process of its own, answers with `Bytes' and
%% closes. Every event until the connection is lost.
exchange(L, Port, Reqs, Bytes) ->
    Sent = iolist_size([?C:adu(0, 1, ?C:request_pdu(R)) || R <- Reqs]),
    Device = spawn_link(fun() ->
                                {ok, Dev} = gen_tcp:accept(L, ?WAIT),
                                {ok, _} = gen_tcp:recv(Dev, Sent, ?WAIT),
                                ok = gen_tcp:send(Dev, Bytes),
                                ok = gen_tcp:close(Dev)
                        end),
    {ok, Opts} = cell_hal_modbus:check_opts(#{host => "127.0.0.1", port => Port,
                                              max_in_flight => 16, timeout_ms => ?WAIT}),
    {ok, S0} = cell_hal_modbus:connect(cell_hal_modbus:init(prop, Opts)),
    {[connected], S1} = next_events(S0),
    S2 = lists:foldl(fun({Tag, R}, S) ->
                             {ok, Si} = cell_hal_modbus:request(Tag, R, ?WAIT, S),
                             Si
                     end, S1, lists:zip(lists:seq(1, length(Reqs)), Reqs)),
    Events = until_lost(S2, []),
    unlink(Device),
    Events.

until_lost(S, Acc) ->
    {Events, S1} = next_events(S),
    Acc1 = Acc ++ Events,
    case lists:keymember(lost, 1, Events) of
        true ->
            _ = cell_hal_modbus:disconnect(S1),
            flush(),
            Acc1;
        false ->
            until_lost(S1, Acc1)
    end.

next_events(S) ->
    receive
        Msg ->
            case cell_hal_modbus:handle_info(Msg, S) of
                {ok, [], S1} -> next_events(S1);
                {ok, Events, S1} -> {Events, S1}
            end
    after ?WAIT ->
            error(driver_silent)
    end.

flush() ->
    receive _ -> flush() after 0 -> ok end.

%% The events are exactly the answers at the start of the stream that are well-formed
%% answers to requests asked and not yet answered, in order, then the loss.
sound(Reqs, Bytes, Events) ->
    Expected = [{reply, Tid + 1, Result} || {Tid, Result} <- well_formed(Bytes, Reqs, #{})],
    {Replies, Rest} = lists:splitwith(fun(E) -> element(1, E) =:= reply end, Events),
    Replies =:= Expected andalso match([{lost, '_'}], Rest).

match([{lost, _}], [{lost, _}]) -> true;
match(_, _) -> false.

well_formed(Bytes, Reqs, Answered) ->
    case ?C:frame(Bytes) of
        {ok, Tid, 1, Pdu, Rest} when Tid < length(Reqs), not is_map_key(Tid, Answered) ->
            case ?C:decode_response(lists:nth(Tid + 1, Reqs), Pdu) of
                {ok, Regs} ->
                    [{Tid, {ok, Regs}} | well_formed(Rest, Reqs, Answered#{Tid => true})];
                {exception, Code} ->
                    Exc = {modbus_exception, Code, ?C:exception_name(Code)},
                    [{Tid, {error, Exc}} | well_formed(Rest, Reqs, Answered#{Tid => true})];
                {error, _} ->
                    []
            end;
        _ ->
            []
    end.
