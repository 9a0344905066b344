%% The PLC, played by a test: a process that owns a Modbus server (plc_server.py on
%% Debian's pymodbus, started on 127.0.0.1 with a port the OS picks) holding one
%% inspection block in the S7 UDT layout from a base register. The test writes what the
%% PLC writes (tags by name: S7 strings with their length bytes, bits in their
%% register, INTs) and waits, with a deadline, for what the block answers: every write
%% the block makes is reported by the server and kept in order, so a test can check
%% the sequence of codes the PLC saw, not only the last one.
-module(cell_inspect_plc).

-export([start/2, start/3, stop/1, port/1, set/3, await/3, await/4, tag/2, tags/1,
         written/2, log/1, forget/1, bytes/1, silent/2, registers/3, set_registers/3]).

-define(WAIT, 20000).

-record(plc, {port :: port(),
              tcp :: inet:port_number(),
              base :: non_neg_integer(),
              layout :: [cell_inspect_udt:element()],
              image :: binary(),                 %% the UDT's bytes as the server holds them
              log = [] :: [{cell_inspect_tags:tag(), term()}],   %% the block's writes, newest first
              waiters = [] :: list()}).

%% @doc Starts the server and its owner; the UDT at `Base' with the seed's lengths.
start(DataDir, LogFile) ->
    start(DataDir, LogFile, 0).

start(DataDir, LogFile, Base) ->
    Self = self(),
    Pid = spawn(fun() -> init(Self, DataDir, LogFile, Base) end),
    receive {Pid, started} -> {ok, Pid}
    after ?WAIT -> erlang:error(plc_did_not_start)
    end.

stop(Plc) ->
    Ref = monitor(process, Plc),
    Plc ! stop,
    receive {'DOWN', Ref, process, _, _} -> ok after ?WAIT -> ok end.

port(Plc) -> call(Plc, port).

%% @doc The PLC writes a tag.
set(Plc, Tag, Value) -> call(Plc, {set, Tag, Value}).

%% @doc Every tag as the server holds it now.
tags(Plc) -> call(Plc, tags).

tag(Plc, Tag) -> maps:get(Tag, tags(Plc)).

%% @doc Waits until the block has written `Tag' := `Value' (or the PLC holds it
%% already); fails the test after the deadline.
await(Plc, Tag, Value) ->
    await(Plc, Tag, Value, ?WAIT).

await(Plc, Tag, Value, Timeout) ->
    case call(Plc, {await, fun(Tags) -> maps:get(Tag, Tags) =:= Value end, Timeout}) of
        ok -> ok;
        {timeout, Tags} -> erlang:error({not_written, Tag, Value, maps:get(Tag, Tags)})
    end.

%% @doc The values the block wrote to a tag, oldest first.
written(Plc, Tag) ->
    [V || {T, V} <- lists:reverse(call(Plc, log)), T =:= Tag].

%% @doc Every change the block's writes made, `{Tag, Value}', oldest first.
log(Plc) -> lists:reverse(call(Plc, log)).

%% @doc Forgets the writes seen so far.
forget(Plc) -> call(Plc, forget).

%% @doc The whole UDT, byte for byte, as the server holds it.
bytes(Plc) -> call(Plc, bytes).

silent(Plc, On) -> call(Plc, {silent, On}).

registers(Plc, Addr, N) -> call(Plc, {get, Addr, N}).

set_registers(Plc, Addr, Values) -> call(Plc, {set_registers, Addr, Values}).

call(Plc, Req) ->
    Ref = monitor(process, Plc),
    Plc ! {call, self(), Ref, Req},
    receive
        {Ref, Reply} -> demonitor(Ref, [flush]), Reply;
        {'DOWN', Ref, process, _, Why} -> erlang:error({plc_gone, Why})
    after ?WAIT + 5000 -> erlang:error({plc_silent, Req})
    end.

%%--------------------------------------------------------------------

init(Parent, DataDir, LogFile, Base) ->
    Script = filename:join(DataDir, "plc_server.py"),
    Port = open_port({spawn_executable, "/bin/sh"},
                     [{args, ["-c", "exec /usr/bin/python3 \"$0\" 0 2>>\"$PLC_LOG\"", Script]},
                      {env, [{"PLC_LOG", LogFile}]}, {line, 1 bsl 16}, exit_status, use_stdio,
                      binary]),
    Tcp = receive
              {Port, {data, {eol, <<"port ", N/binary>>}}} -> binary_to_integer(N)
          after ?WAIT -> erlang:error(plc_server_did_not_start)
          end,
    Layout = cell_inspect_udt:layout(cell_inspect_udt:default_lengths()),
    Size = cell_inspect_udt:size(Layout),
    S = #plc{port = Port, tcp = Tcp, base = Base, layout = Layout, image = <<0:Size/unit:8>>},
    Parent ! {self(), started},
    loop(S).

loop(#plc{port = Port} = S) ->
    receive
        {Port, {data, {eol, <<"w ", Rest/binary>>}}} ->
            loop(check(wrote(Rest, S)));
        {call, From, Ref, Req} ->
            {Reply, S1} = handle(Req, {From, Ref}, S),
            _ = Reply =/= noreply andalso (From ! {Ref, Reply}),
            loop(check(S1));
        {timeout, _, {waiter, WRef}} ->
            loop(expire(WRef, S));
        {Port, {exit_status, Status}} ->
            erlang:error({plc_server_exited, Status});
        stop ->
            catch port_close(Port),
            ok
    end.

handle(port, _, #plc{tcp = T} = S) ->
    {T, S};
handle({set, Tag, Value}, _, S) ->
    {ok, write_tag(Tag, Value, S)};
handle(tags, _, S) ->
    {tags_of(S), S};
handle({await, Cond, Timeout}, From, #plc{waiters = W} = S) ->
    WRef = make_ref(),
    _ = erlang:start_timer(Timeout, self(), {waiter, WRef}),
    {noreply, S#plc{waiters = [{WRef, From, Cond} | W]}};
handle(log, _, #plc{log = L} = S) ->
    {L, S};
handle(forget, _, S) ->
    {ok, S#plc{log = []}};
handle(bytes, _, #plc{image = I} = S) ->
    {I, S};
handle({silent, On}, _, S) ->
    cmd(S, "silent ~b", [case On of true -> 1; false -> 0 end]),
    {ok, S};
handle({get, Addr, N}, _, S) ->
    {cmd(S, "get ~b ~b", [Addr, N]), S};
handle({set_registers, Addr, Values}, _, S) ->
    [] = cmd(S, "set ~b~s", [Addr, [[$\s, integer_to_list(V)] || V <- Values]]),
    {ok, S}.

%% A command and its answer; write reports that come meanwhile are applied first.
cmd(#plc{port = Port}, Fmt, Args) ->
    true = port_command(Port, [io_lib:format(Fmt, Args), $\n]),
    receive
        {Port, {data, {eol, <<"ok", Rest/binary>>}}} ->
            [binary_to_integer(W) || W <- binary:split(Rest, <<" ">>, [global, trim_all])]
    after ?WAIT -> erlang:error({plc_server_silent, Fmt})
    end.

%% The block wrote registers: the image changes; the tags that changed are logged.
wrote(Line, #plc{base = Base, image = I, log = L} = S) ->
    [Addr | Values] = [binary_to_integer(W) || W <- binary:split(Line, <<" ">>, [global, trim_all])],
    Start = (Addr - Base) * 2,
    Bytes = << <<V:16>> || V <- Values >>,
    case Start >= 0 andalso Start + byte_size(Bytes) =< byte_size(I) of
        true ->
            <<Pre:Start/binary, _:(byte_size(Bytes))/binary, Post/binary>> = I,
            I1 = <<Pre/binary, Bytes/binary, Post/binary>>,
            Old = tags_of(S),
            New = tags_of(S#plc{image = I1}),
            Changed = [{T, V} || T <- cell_inspect_tags:all(), (V = maps:get(T, New)) =/= maps:get(T, Old)],
            S#plc{image = I1, log = lists:reverse(Changed) ++ L};
        false ->
            S
    end.

%% The PLC writes one tag: its bytes change in the image, and the registers they lie
%% in are written (the other bytes of those registers as the server holds them).
write_tag(Tag, Value, #plc{layout = Layout, image = I, base = Base} = S) ->
    Plc = maps:map(fun(_, V) when is_binary(V) -> cell_inspect_io:to_plc(V, 254);
                      (_, V) -> V
                   end, maps:put(Tag, Value, tags_of(S))),
    Encoded = cell_inspect_udt:encode(Layout, Plc),
    [E] = [E || #{tag := T} = E <- Layout, T =:= Tag],
    {First, Last} = span(E),
    Len = Last - First + 1,
    <<Pre:First/binary, _:Len/binary, Post/binary>> = I,
    I1 = <<Pre/binary, (binary:part(Encoded, First, Len))/binary, Post/binary>>,
    RFirst = First div 2,
    RLast = Last div 2,
    Regs = [R || <<R:16>> <= binary:part(I1, RFirst * 2, (RLast - RFirst + 1) * 2)],
    [] = cmd(S, "set ~b~s", [Base + RFirst, [[$\s, integer_to_list(R)] || R <- Regs]]),
    S#plc{image = I1}.

span(#{kind := bool, byte := B}) -> {B, B};
span(#{kind := int, byte := B}) -> {B, B + 1};
span(#{kind := {string, N}, byte := B}) -> {B, B + N + 1}.

tags_of(#plc{layout = Layout, image = I}) ->
    Raw = cell_inspect_udt:decode(Layout, I),
    maps:map(fun(T, V) when is_binary(V) -> _ = T, cell_inspect_io:from_plc(V);
                (_, V) -> V
             end, Raw).

check(#plc{waiters = W} = S) ->
    Tags = tags_of(S),
    {Done, Left} = lists:partition(fun({_, _, Cond}) -> Cond(Tags) end, W),
    _ = [From ! {Ref, ok} || {_, {From, Ref}, _} <- Done],
    S#plc{waiters = Left}.

expire(WRef, #plc{waiters = W} = S) ->
    case lists:keytake(WRef, 1, W) of
        {value, {_, {From, Ref}, _}, Left} ->
            From ! {Ref, {timeout, tags_of(S)}},
            S#plc{waiters = Left};
        false ->
            S
    end.
