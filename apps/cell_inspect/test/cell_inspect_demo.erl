%% A cell with one inspection block on a simulated PLC and the operator panel as its
%% only message client, for the panel's browser tests: started by test/browser/run.sh's
%% tests, driven through its standard input one command a line, each answered
%% `OK ...' (or `ERR ...') on standard output once done.
%%
%% Commands: `send ID' (the PLC sends message ID: MessageID, then SendMessage raised
%% and dropped with the echo handshake) · `await TAG VALUE' (waits, at most 15 s, until
%% the block has written an integer TAG, as `await message_status 5', or
%% `await message_result TEXT') · `quit'.
-module(cell_inspect_demo).

-export([main/0]).

-define(WAIT, 15000).

-spec main() -> no_return().
main() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false),
    _ = [application:load(A) || A <- [cell_base, cell, cell_web, cell_inspect]],
    ok = application:set_env(cell, cell_spec, #{name => <<"demo">>, tasks => []}),
    ok = application:set_env(cell_web, port, 0),
    ok = application:set_env(cell_inspect, connections,
                             [#{id => plc, driver => cell_hal_sim, opts => #{poll_ms => 10}}]),
    ok = application:set_env(cell_inspect, blocks,
                             [#{id => line1, connection => plc, io => #{layout => s7}}]),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = cell_settings:put(machine, #{cell_name => <<"Inspection demo">>}, <<"demo">>),
    ok = cell_inspect_settings:register(),
    ok = cell_settings:put(inspect, #{blocks => [block()]}, <<"demo">>),
    {ok, _} = application:ensure_all_started(cell_inspect),
    io:format("PORT ~p~n", [cell_web:port()]),
    loop().

block() ->
    #{id => <<"line1">>, panel_messages => true,
      points => [#{id => <<"STATION1">>, processing => <<"none">>}],
      messages => [#{id => 7, text => <<"Is the label on the left side?">>, kind => yes_no},
                   #{id => 8, text => <<"Batch number of the glue">>, kind => text}],
      clients => []}.

loop() ->
    case io:get_line("") of
        eof ->
            erlang:halt(0);
        Line when is_list(Line) ->
            Words = string:lexemes(string:trim(unicode:characters_to_binary(Line)), " "),
            case Words of
                [<<"quit">>] ->
                    io:format("OK quit~n"),
                    erlang:halt(0);
                _ ->
                    Reply = try run(Words) of
                                ok -> "OK";
                                {error, Why} -> io_lib:format("ERR ~0tp", [Why])
                            catch
                                C:R -> io_lib:format("ERR ~0tp:~0tp", [C, R])
                            end,
                    io:format("~s ~ts~n", [Reply, lists:join(" ", Words)]),
                    loop()
            end
    end.

run([<<"send">>, Id]) ->
    ok = cell_hal_sim:set({line1, message_id}, binary_to_integer(Id)),
    ok = await(message_id_echo, binary_to_integer(Id)),
    ok = cell_hal_sim:set({line1, send_message}, true),
    ok = await(send_message_echo, true),
    ok = cell_hal_sim:set({line1, send_message}, false),
    await(send_message_echo, false);
run([<<"await">>, <<"message_result">> | Text]) ->
    await(message_result, iolist_to_binary(lists:join(" ", Text)));
run([<<"await">>, Tag, Value]) ->
    case [T || T <- cell_inspect_tags:outputs(), atom_to_binary(T) =:= Tag] of
        [T] -> await(T, binary_to_integer(Value));
        [] -> {error, {unknown_tag, Tag}}
    end;
run(Other) ->
    {error, {unknown_command, Other}}.

%% Waits until the block holds an output at a value: as it is now, then at each value
%% the block writes (the HAL tells subscribers of an output every commanded value).
await(Tag, Value) ->
    {ok, Points} = cell_hal:points(line1),
    Outputs = [N || #{name := N, dir := out} <- Points],
    _ = [ok = cell_hal:subscribe(line1, P) || P <- Outputs],
    Deadline = erlang:monotonic_time(millisecond) + ?WAIT,
    Result = await(Tag, Value, Deadline),
    _ = [ok = cell_hal:unsubscribe(line1, P) || P <- Outputs],
    Result.

await(Tag, Value, Deadline) ->
    case cell_inspect_io:read(io(), line1, Tag) of
        {ok, Value} -> ok;
        _ ->
            Left = Deadline - erlang:monotonic_time(millisecond),
            receive {cell_hal, {line1, _}, _} -> await(Tag, Value, Deadline)
            after max(0, Left) -> {error, {not_written, Tag, cell_inspect_io:read(io(), line1, Tag)}}
            end
    end.

io() ->
    {ok, Io} = cell_inspect_io:check_opts(#{layout => s7}),
    Io.
