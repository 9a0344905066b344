%% The PLC, played by a test, in either form of the block:
%%
%% - `s7': a Modbus server (plc_server.py on Debian's pymodbus, started on 127.0.0.1
%%   with a port the OS picks) holding one inspection block in the S7 UDT layout from
%%   a base register;
%% - `ads': the fake TwinCAT PLC of the ADS tests (cell_hal_ads' test/peers/fake_plc.py,
%%   proven against Beckhoff's AdsLib) holding the structure MVSCAMERA with the members
%%   of seed 004's Allen-Bradley table, declared here from the seed, not from the code
%%   under test.
%%
%% The test writes what the PLC writes (tags by name: S7 strings with their length
%% bytes, bits in their register, INTs; ADS members by symbol) and waits, with a
%% deadline, for what the block answers: every write the block makes is reported by
%% the server and kept in order, so a test can check the sequence of codes the PLC
%% saw, not only the last one. The PLC's side of the seed's handshakes (values and
%% their echoes, a command raised until its echo follows) is here too.
-module(cell_inspect_plc).

-export([start/2, start/3, start_ads/0, stop/1, port/1, set/3, pulse/2, await/3, await/4,
         await_written/3, tag/2, tags/1, written/2, log/1, forget/1, bytes/1, raw/2, peer/1,
         silent/2, registers/3, set_registers/3]).
-export([values/2, command/2, trigger/3, send_message/2, before/3]).
-export([program_without/2, program_with/2]).

-define(WAIT, 20000).
-define(FILETIME_UNIX_EPOCH, 116444736000000000).

%% Seed 004's Allen-Bradley tag structure as TwinCAT declares it: Boolean a BOOL,
%% Short an INT, String `.DATA/N' a STRING(N).
-define(MVSCAMERA,
        [{cancel_inspection, "CANCELINSPECTION", bool},
         {cancel_inspection_echo, "CANCELINSPECTION_ECHO", bool},
         {clear_results, "CLEARRESULTS", bool},
         {clear_results_echo, "CLEARRESULTS_ECHO", bool},
         {employee_override_echo, "EMPLOYEEOVERRIDE_ECHO", {string, 32}},
         {error_code, "ERRORCODE", short},
         {heartbeat, "HEARTBEAT", bool},
         {inspection_fail, "INSPECTION_FAIL", bool},
         {inspection_pass, "INSPECTION_PASS", bool},
         {inspection_string, "INSPECTION_STRING", {string, 32}},
         {inspection_point_id, "INSPECTIONPOINTID", {string, 16}},
         {inspection_point_id_echo, "INSPECTIONPOINTID_ECHO", {string, 16}},
         {inspection_status, "INSPECTIONSTATUS", short},
         {log_override, "LOGOVERRIDE", bool},
         {log_override_echo, "LOGOVERRIDE_ECHO", bool},
         {override_employee_id, "OVERRIDEEMPLOYEEID", {string, 32}},
         {part_serial, "PARTSERIAL", {string, 32}},
         {part_serial_echo, "PARTSERIAL_ECHO", {string, 32}},
         {trigger_inspection, "TRIGGERINSPECTION", bool},
         {trigger_inspection_echo, "TRIGGERINSPECTION_ECHO", bool},
         {message_id, "MESSAGEID", short},
         {message_id_echo, "MESSAGEID_ECHO", short},
         {send_message, "SENDMESSAGE", bool},
         {send_message_echo, "SENDMESSAGE_ECHO", bool},
         {message_result, "MESSAGERESULT", {string, 32}},
         {message_status, "MESSAGESTATUS", short}]).

-record(plc, {port :: port() | undefined,         %% s7: the Modbus server
              peer :: pid() | undefined,          %% ads: the fake TwinCAT PLC
              tcp :: inet:port_number(),
              base = 0 :: non_neg_integer(),
              layout = [] :: [cell_inspect_udt:element()],
              %% s7: the UDT's bytes as the server holds them; ads: each member's
              image :: binary() | #{cell_inspect_tags:tag() => binary()},
              log = [] :: [{cell_inspect_tags:tag(), term()}],   %% the block's writes, newest first
              waiters = [] :: list()}).

%% @doc Starts the Modbus server and its owner; the UDT at `Base' with the seed's lengths.
start(DataDir, LogFile) ->
    start(DataDir, LogFile, 0).

start(DataDir, LogFile, Base) ->
    spawn_plc(fun() -> init_s7(DataDir, LogFile, Base) end).

%% @doc Starts the fake TwinCAT PLC holding MVSCAMERA, and its owner.
start_ads() ->
    spawn_plc(fun init_ads/0).

spawn_plc(Init) ->
    Self = self(),
    Pid = spawn(fun() -> S = Init(), Self ! {self(), started}, loop(S) end),
    receive {Pid, started} -> {ok, Pid}
    after ?WAIT -> erlang:error(plc_did_not_start)
    end.

stop(Plc) ->
    Ref = monitor(process, Plc),
    Plc ! stop,
    receive {'DOWN', Ref, process, _, _} -> ok after ?WAIT -> ok end.

port(Plc) -> call(Plc, port).

%% @doc ADS: a program change takes a member out of the structure (a download of a
%% program that lacks it).
program_without(Plc, Tag) -> call(Plc, {program_without, Tag}).

%% @doc ADS: a program change puts the member back, zeroed.
program_with(Plc, Tag) -> call(Plc, {program_with, Tag}).

%% @doc The PLC writes a tag.
set(Plc, Tag, Value) -> call(Plc, {set, Tag, Value}).

%% @doc ADS: the PLC raises a command bit and drops it again before the next
%% notification goes out: the PLC's notification brings both, stamped one PLC cycle
%% apart, in one frame.
pulse(Plc, Tag) -> call(Plc, {pulse, Tag}).

%% @doc Every tag as the server holds it now.
tags(Plc) -> call(Plc, tags).

tag(Plc, Tag) -> maps:get(Tag, tags(Plc)).

%% @doc Waits until the block has written `Tag' := `Value' (or the PLC holds it
%% already); fails the test after the deadline.
await(Plc, Tag, Value) ->
    await(Plc, Tag, Value, ?WAIT).

await(Plc, Tag, Value, Timeout) ->
    case call(Plc, {await, fun(Tags, _) -> maps:get(Tag, Tags) =:= Value end, Timeout}) of
        ok -> ok;
        {timeout, Tags, _} -> erlang:error({not_written, Tag, Value, maps:get(Tag, Tags)})
    end.

%% @doc Waits until the values the block wrote to `Tag' since the last {@link forget/1}
%% are `Values', oldest first (a value that came and went already counts).
await_written(Plc, Tag, Values) ->
    case call(Plc, {await, fun(_, Log) -> written_in(Log, Tag) =:= Values end, ?WAIT}) of
        ok -> ok;
        {timeout, _, Log} -> erlang:error({not_written, Tag, Values, written_in(Log, Tag)})
    end.

%% @doc The values the block wrote to a tag, oldest first.
written(Plc, Tag) ->
    written_in(call(Plc, log), Tag).

written_in(Log, Tag) ->
    [V || {T, V} <- lists:reverse(Log), T =:= Tag].

%% @doc Every change the block's writes made, `{Tag, Value}', oldest first.
log(Plc) -> lists:reverse(call(Plc, log)).

%% @doc Forgets the writes seen so far.
forget(Plc) -> call(Plc, forget).

%% @doc S7: the whole UDT, byte for byte, as the server holds it.
bytes(Plc) -> call(Plc, bytes).

%% @doc ADS: a member's bytes as the PLC holds them (asked of the PLC itself).
raw(Plc, Tag) -> call(Plc, {raw, Tag}).

%% @doc ADS: the fake PLC, for its own commands (cell_hal_ads_peer:cmd/2).
peer(Plc) -> call(Plc, peer).

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
%% The PLC's side of the handshakes
%%--------------------------------------------------------------------

%% @doc The PLC sets values and waits for their echoes (Trigger steps 2 to 4).
values(Plc, Pairs) ->
    [ok = set(Plc, T, V) || {T, V} <- Pairs],
    [ok = await(Plc, cell_inspect_tags:echo(T), V) || {T, V} <- Pairs],
    ok.

%% @doc The PLC raises a command, waits for its echo, drops it, waits for the echo to
%% follow: the four-phase handshake the block expects. Returns the tags as the PLC
%% read them when the echo came.
command(Plc, Cmd) ->
    ok = set(Plc, Cmd, true),
    ok = await(Plc, cell_inspect_tags:echo(Cmd), true),
    Seen = tags(Plc),
    ok = set(Plc, Cmd, false),
    ok = await(Plc, cell_inspect_tags:echo(Cmd), false),
    Seen.

%% @doc Trigger steps 2 to 6, the writes seen before forgotten.
trigger(Plc, Point, Serial) ->
    ok = values(Plc, [{inspection_point_id, Point}, {part_serial, Serial}]),
    ok = forget(Plc),
    command(Plc, trigger_inspection).

%% @doc Send Message steps 1 and 2: the MessageID echoed, then SendMessage.
send_message(Plc, Id) ->
    ok = values(Plc, [{message_id, Id}]),
    command(Plc, send_message).

%% @doc Fails unless the PLC saw `A' written before `B' (both written).
before(Plc, A, B) ->
    Log = log(Plc),
    Index = fun(X) -> length(lists:takewhile(fun(E) -> E =/= X end, Log)) end,
    case lists:member(A, Log) andalso lists:member(B, Log) andalso Index(A) < Index(B) of
        true -> ok;
        false -> erlang:error({not_before, A, B, Log})
    end.

%%--------------------------------------------------------------------

init_s7(DataDir, LogFile, Base) ->
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
    #plc{port = Port, tcp = Tcp, base = Base, layout = Layout, image = <<0:Size/unit:8>>}.

%% The structure and its members, every value 0; the PLC tells every write of the
%% block (`report on').
init_ads() ->
    {ok, Peer, {ready, Tcp, _}} = cell_hal_ads_peer:start("fake_plc.py", []),
    ok = cell_hal_ads_peer:listen(Peer),
    Members = [{T, "MVSCAMERA." ++ Name, Decl} || {T, Name, Decl} <- ?MVSCAMERA],
    Size = lists:sum([ads_size(Decl) || {_, _, Decl} <- Members]),
    {ok, _, _} = add(Peer, "MVSCAMERA", "ST_MVSCAMERA", 65, Size, ""),
    [{ok, _, _} = add(Peer, Name, ads_type(Decl), ads_id(Decl), ads_size(Decl), " nested")
     || {_, Name, Decl} <- Members],
    ok = cell_hal_ads_peer:cmd(Peer, "report on"),
    #plc{peer = Peer, tcp = Tcp,
         image = maps:from_list([{T, <<0:(ads_size(Decl))/unit:8>>} || {T, _, Decl} <- Members])}.

add(Peer, Name, Type, Id, Size, Extra) ->
    cell_hal_ads_peer:cmd(Peer, ["add ", Name, " ", Type, " ", integer_to_list(Id), " ",
                                 integer_to_list(Size), " ", binary:encode_hex(<<0:Size/unit:8>>),
                                 Extra]).

ads_type(bool) -> "BOOL";
ads_type(short) -> "INT";
ads_type({string, N}) -> "STRING(" ++ integer_to_list(N) ++ ")".

ads_id(bool) -> 33;
ads_id(short) -> 2;
ads_id({string, _}) -> 30.

ads_size(bool) -> 1;
ads_size(short) -> 2;
ads_size({string, N}) -> N + 1.

loop(#plc{port = Port, peer = Peer} = S) ->
    receive
        {Port, {data, {eol, <<"w ", Rest/binary>>}}} ->
            loop(check(wrote(Rest, S)));
        {peer_event, Peer, {notification, written, Name, Bytes}} ->
            loop(check(wrote_member(Name, Bytes, S)));
        {call, From, Ref, Req} ->
            {Reply, S1} = handle(Req, {From, Ref}, S),
            _ = Reply =/= noreply andalso (From ! {Ref, Reply}),
            loop(check(S1));
        {timeout, _, {waiter, WRef}} ->
            loop(expire(WRef, S));
        {Port, {exit_status, Status}} ->
            erlang:error({plc_server_exited, Status});
        stop when is_pid(Peer) ->
            ok = cell_hal_ads_peer:stop(Peer);
        stop ->
            catch port_close(Port),
            ok
    end.

handle(port, _, #plc{tcp = T} = S) ->
    {T, S};
handle({program_without, Tag}, _, #plc{peer = Peer} = S) ->
    {Name, _} = member(Tag),
    {cell_hal_ads_peer:cmd(Peer, ["remove ", Name]), S};
handle({program_with, Tag}, _, #plc{peer = Peer, image = I} = S) ->
    {Name, Decl} = member(Tag),
    {ok, _, _} = add(Peer, Name, ads_type(Decl), ads_id(Decl), ads_size(Decl), " nested"),
    ok = cell_hal_ads_peer:cmd(Peer, "bump"),
    {ok, S#plc{image = I#{Tag := <<0:(ads_size(Decl))/unit:8>>}}};
handle({set, Tag, Value}, _, #plc{peer = undefined} = S) ->
    {ok, write_tag(Tag, Value, S)};
handle({set, Tag, Value}, _, #plc{peer = Peer, image = I} = S) ->
    {Name, Decl} = member(Tag),
    Bytes = encode(Decl, Value),
    ok = cell_hal_ads_peer:cmd(Peer, ["set ", Name, " ", binary:encode_hex(Bytes)]),
    {ok, S#plc{image = I#{Tag := Bytes}}};
handle({pulse, Tag}, _, #plc{peer = Peer, image = I} = S) ->
    {Name, bool} = member(Tag),
    T0 = ?FILETIME_UNIX_EPOCH + os:system_time(nanosecond) div 100,
    %% One PLC cycle of 1 ms apart, in 100 ns.
    ok = cell_hal_ads_peer:cmd(Peer, ["burst ", integer_to_list(T0), " ", Name, " 01 ; ",
                                      integer_to_list(T0 + 10000), " ", Name, " 00"]),
    {ok, S#plc{image = I#{Tag := <<0>>}}};
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
handle({raw, Tag}, _, #plc{peer = Peer} = S) ->
    {Name, _} = member(Tag),
    {ok, Bytes} = cell_hal_ads_peer:cmd(Peer, ["get ", Name]),
    {Bytes, S};
handle(peer, _, #plc{peer = Peer} = S) ->
    {Peer, S};
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
wrote(Line, #plc{base = Base, image = I} = S) ->
    [Addr | Values] = [binary_to_integer(W) || W <- binary:split(Line, <<" ">>, [global, trim_all])],
    Start = (Addr - Base) * 2,
    Bytes = << <<V:16>> || V <- Values >>,
    case Start >= 0 andalso Start + byte_size(Bytes) =< byte_size(I) of
        true ->
            <<Pre:Start/binary, _:(byte_size(Bytes))/binary, Post/binary>> = I,
            changed(S, S#plc{image = <<Pre/binary, Bytes/binary, Post/binary>>});
        false ->
            S
    end.

%% The block wrote a member of MVSCAMERA.
wrote_member(Name, Bytes, #plc{image = I} = S) ->
    [Tag] = [T || {T, N, _} <- ?MVSCAMERA, list_to_binary("MVSCAMERA." ++ N) =:= Name],
    changed(S, S#plc{image = I#{Tag := Bytes}}).

%% The tags a write changed are logged, in the order of the seed's tags.
changed(Old, #plc{log = L} = New) ->
    {Before, After} = {tags_of(Old), tags_of(New)},
    Changed = [{T, V} || T <- cell_inspect_tags:all(),
                         (V = maps:get(T, After)) =/= maps:get(T, Before)],
    New#plc{log = lists:reverse(Changed) ++ L}.

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

tags_of(#plc{peer = undefined, layout = Layout, image = I}) ->
    Raw = cell_inspect_udt:decode(Layout, I),
    maps:map(fun(T, V) when is_binary(V) -> _ = T, cell_inspect_io:from_plc(V);
                (_, V) -> V
             end, Raw);
tags_of(#plc{image = I}) ->
    maps:map(fun(T, Bytes) -> {_, Decl} = member(T), decode(Decl, Bytes) end, I).

%%--------------------------------------------------------------------
%% MVSCAMERA's members as TwinCAT holds them
%%--------------------------------------------------------------------

member(Tag) ->
    {Tag, Name, Decl} = lists:keyfind(Tag, 1, ?MVSCAMERA),
    {"MVSCAMERA." ++ Name, Decl}.

%% A member's bytes: BOOL one byte, INT little-endian, STRING(N) Latin-1 characters
%% and NULs to N + 1 bytes.
encode(bool, V) -> <<(case V of true -> 1; false -> 0 end)>>;
encode(short, V) -> <<V:16/little-signed>>;
encode({string, N}, V) ->
    Chars = unicode:characters_to_binary(V, utf8, latin1),
    true = byte_size(Chars) =< N,
    <<Chars/binary, 0:((N + 1 - byte_size(Chars)) * 8)>>.

decode(bool, <<B>>) -> B =/= 0;
decode(short, <<V:16/little-signed>>) -> V;
decode({string, _}, Bytes) ->
    [Chars | _] = binary:split(Bytes, <<0>>),
    unicode:characters_to_binary(Chars, latin1, utf8).

check(#plc{waiters = W, log = Log} = S) ->
    Tags = tags_of(S),
    {Done, Left} = lists:partition(fun({_, _, Cond}) -> Cond(Tags, Log) end, W),
    _ = [From ! {Ref, ok} || {_, {From, Ref}, _} <- Done],
    S#plc{waiters = Left}.

expire(WRef, #plc{waiters = W} = S) ->
    case lists:keytake(WRef, 1, W) of
        {value, {_, {From, Ref}, _}, Left} ->
            From ! {Ref, {timeout, tags_of(S), S#plc.log}},
            S#plc{waiters = Left};
        false ->
            S
    end.
