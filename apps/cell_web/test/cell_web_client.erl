%% An HTTP and websocket client of the panel for the suites: httpc for the API (with
%% the session cookie and CSRF token of a login), a small websocket client on gen_tcp.
-module(cell_web_client).

-export([new/1, login/3, req/3, req/4, req/5, ws_connect/2, ws_connect/3, ws_next/2,
         ws_send/2, ws_close/1]).

new(Port) ->
    #{port => Port, cookie => undefined, csrf => undefined}.

%% Logs in; the client carries the session from then on.
login(C, User, Password) ->
    case req(C, post, "/api/session", #{user => iolist_to_binary(User),
                                          password => iolist_to_binary(Password)}) of
        {200, #{<<"csrf">> := Csrf}, Headers} ->
            {ok, C#{cookie => cookie(Headers), csrf => Csrf}};
        {Status, Body, _} ->
            {error, Status, Body}
    end.

cookie(Headers) ->
    [Cookie | _] = [hd(string:split(V, ";")) || {"set-cookie", V} <- Headers],
    Cookie.

req(C, Method, Path) ->
    req(C, Method, Path, none, []).

req(C, Method, Path, Body) ->
    req(C, Method, Path, Body, []).

%% Body: none | a map (JSON) | {ContentType, Binary}. Extra: more headers, or
%% `no_csrf' to leave the token out.
req(#{port := Port} = C, Method, Path, Body, Extra) ->
    Url = "http://127.0.0.1:" ++ integer_to_list(Port) ++ Path,
    Headers = [H || H <- Extra, is_tuple(H)]
        ++ [{"cookie", maps:get(cookie, C)} || maps:get(cookie, C) =/= undefined]
        ++ [{"x-csrf-token", binary_to_list(maps:get(csrf, C))}
            || maps:get(csrf, C) =/= undefined, not lists:member(no_csrf, Extra)],
    Request = case Body of
                  none when Method =:= post; Method =:= put ->
                      {Url, Headers, "application/json", <<>>};
                  none -> {Url, Headers};
                  {Type, Bin} -> {Url, Headers, Type, Bin};
                  Map -> {Url, Headers, "application/json", jsx:encode(Map)}
              end,
    {ok, {{_, Status, _}, RespHeaders, RespBody}} =
        httpc:request(Method, Request, [{timeout, 30000}, {autoredirect, false}],
                      [{body_format, binary}]),
    Decoded = case lists:keyfind("content-type", 1, RespHeaders) of
                  {_, "application/json" ++ _} -> jsx:decode(RespBody, [return_maps]);
                  _ -> RespBody
              end,
    {Status, Decoded, RespHeaders}.

%% Opens the websocket; answers the socket and the messages of the first frame (the
%% snapshot), or the HTTP status when the upgrade is refused.
ws_connect(C, Origin) ->
    ws_connect(C, Origin, "/api/ws").

ws_connect(#{port := Port} = C, Origin, Path) ->
    {ok, S} = gen_tcp:connect({127, 0, 0, 1}, Port, [binary, {active, false}, {packet, raw}]),
    Key = base64:encode(crypto:strong_rand_bytes(16)),
    Req = ["GET ", Path, " HTTP/1.1\r\nHost: 127.0.0.1:", integer_to_list(Port),
           "\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n",
           "Sec-WebSocket-Key: ", Key, "\r\n",
           [["Origin: ", Origin, "\r\n"] || Origin =/= none],
           [["Cookie: ", maps:get(cookie, C), "\r\n"] || maps:get(cookie, C) =/= undefined],
           "\r\n"],
    ok = gen_tcp:send(S, Req),
    {Head, Rest} = read_head(S, <<>>),
    case Head of
        <<"HTTP/1.1 101", _/binary>> ->
            {ok, {S, Rest}};
        <<"HTTP/1.1 ", Code:3/binary, _/binary>> ->
            gen_tcp:close(S),
            {error, binary_to_integer(Code)}
    end.

read_head(S, Acc) ->
    case binary:split(Acc, <<"\r\n\r\n">>) of
        [Head, Rest] -> {Head, Rest};
        [_] ->
            {ok, More} = gen_tcp:recv(S, 0, 10000),
            read_head(S, <<Acc/binary, More/binary>>)
    end.

%% The next text frame's messages (pings skipped), `{close, Code}', or `timeout'.
ws_next({S, Buf}, Timeout) ->
    Deadline = erlang:monotonic_time(millisecond) + Timeout,
    next(S, Buf, Deadline).

next(S, Buf, Deadline) ->
    case frame(Buf) of
        {text, Payload, Rest} -> {jsx:decode(Payload, [return_maps]), {S, Rest}};
        {close, <<Code:16, _/binary>>, _} -> {{close, Code}, {S, <<>>}};
        {close, _, _} -> {{close, 1005}, {S, <<>>}};
        {_Other, _, Rest} -> next(S, Rest, Deadline);
        more ->
            Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
            case gen_tcp:recv(S, 0, Left) of
                {ok, Data} -> next(S, <<Buf/binary, Data/binary>>, Deadline);
                {error, timeout} -> {timeout, {S, Buf}};
                {error, closed} -> {{close, closed}, {S, <<>>}}
            end
    end.

frame(<<_Fin:1, _:3, Op:4, 0:1, 127:7, Len:64, Payload:Len/binary, Rest/binary>>) ->
    {opcode(Op), Payload, Rest};
frame(<<_Fin:1, _:3, Op:4, 0:1, 126:7, Len:16, Payload:Len/binary, Rest/binary>>) ->
    {opcode(Op), Payload, Rest};
frame(<<_Fin:1, _:3, Op:4, 0:1, Len:7, Payload:Len/binary, Rest/binary>>) when Len < 126 ->
    {opcode(Op), Payload, Rest};
frame(_) ->
    more.

opcode(1) -> text;
opcode(8) -> close;
opcode(9) -> ping;
opcode(10) -> pong;
opcode(_) -> other.

%% A masked text frame, as a client must send.
ws_send({S, _}, Text) ->
    Mask = crypto:strong_rand_bytes(4),
    Len = byte_size(Text),
    true = Len < 126,
    ok = gen_tcp:send(S, [<<1:1, 0:3, 1:4, 1:1, Len:7>>, Mask, mask(Text, Mask)]).

mask(Data, <<M:32>>) ->
    mask(Data, M, <<>>).

mask(<<D:32, Rest/binary>>, M, Acc) -> mask(Rest, M, <<Acc/binary, (D bxor M):32>>);
mask(<<D:24>>, M, Acc) -> <<Acc/binary, (D bxor (M bsr 8)):24>>;
mask(<<D:16>>, M, Acc) -> <<Acc/binary, (D bxor (M bsr 16)):16>>;
mask(<<D:8>>, M, Acc) -> <<Acc/binary, (D bxor (M bsr 24)):8>>;
mask(<<>>, _, Acc) -> Acc.

ws_close({S, _}) ->
    gen_tcp:close(S).
