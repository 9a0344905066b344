%% Unit tests and properties of the SHDR codec. The reader these lines are written for
%% is modelled here from the reference agent's tokenizer as documented in seed 003
%% and read in its source: fields split at `|'; a field starting with `"' runs to the
%% closing `"' before a `|' or the end, `\' taking the next character as it is;
%% blanks around fields are dropped.
-module(cell_shdr_codec_tests).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-define(T0, 1781933503512).   %% 2026-06-20T05:31:43.512Z

%% -------------------------------------------------------------------------------------
%% Timestamps
%% -------------------------------------------------------------------------------------

timestamp_test_() ->
    [?_assertEqual(<<"1970-01-01T00:00:00.000Z">>, cell_shdr_codec:timestamp(0)),
     ?_assertEqual(<<"1970-01-01T00:00:00.999Z">>, cell_shdr_codec:timestamp(999)),
     ?_assertEqual(<<"1970-01-01T00:00:01.000Z">>, cell_shdr_codec:timestamp(1000)),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z">>, cell_shdr_codec:timestamp(?T0)),
     %% a leap day, and the last millisecond of a year
     ?_assertEqual(<<"2024-02-29T23:59:59.999Z">>,
                   cell_shdr_codec:timestamp(ms({{2024, 2, 29}, {23, 59, 59}}) + 999)),
     ?_assertEqual(<<"2025-12-31T23:59:59.999Z">>,
                   cell_shdr_codec:timestamp(ms({{2025, 12, 31}, {23, 59, 59}}) + 999)),
     ?_assertEqual(<<"2026-01-01T00:00:00.000Z">>,
                   cell_shdr_codec:timestamp(ms({{2026, 1, 1}, {0, 0, 0}}))),
     ?_assertEqual(<<"0">>, cell_shdr_codec:relative(0)),
     ?_assertEqual(<<"1456">>, cell_shdr_codec:relative(1456))].

ms(DateTime) ->
    (calendar:datetime_to_gregorian_seconds(DateTime)
     - calendar:datetime_to_gregorian_seconds({{1970, 1, 1}, {0, 0, 0}})) * 1000.

prop_timestamp_matches_calendar() ->
    ?FORALL(Ms, range(0, 4102444800000),
            begin
                B = cell_shdr_codec:timestamp(Ms),
                {ok, RE} = re:compile(<<"^\\d{4}-\\d\\d-\\d\\dT\\d\\d:\\d\\d:\\d\\d\\.\\d{3}Z$">>),
                Expected = list_to_binary(
                             calendar:system_time_to_rfc3339(Ms, [{unit, millisecond},
                                                                  {offset, "Z"}])),
                re:run(B, RE) =/= nomatch andalso B =:= Expected
            end).

%% -------------------------------------------------------------------------------------
%% Data lines, escaping
%% -------------------------------------------------------------------------------------

data_line_test_() ->
    L = fun(Pairs) -> iolist_to_binary(cell_shdr_codec:data_line({utc, ?T0}, Pairs)) end,
    [?_assertEqual(<<"2026-06-20T05:31:43.512Z|avail|AVAILABLE|execution|ACTIVE\n">>,
                   L([{<<"avail">>, <<"AVAILABLE">>}, {<<"execution">>, <<"ACTIVE">>}])),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|x|UNAVAILABLE\n">>, L([{<<"x">>, unavailable}])),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|n|42|f|0.1|g|-2.5e-7\n">>,
                   L([{<<"n">>, 42}, {<<"f">>, 0.1}, {<<"g">>, -2.5e-7}])),
     ?_assertEqual(<<"1456|m|5\n">>,
                   iolist_to_binary(cell_shdr_codec:data_line({relative, 1456},
                                                              [{<<"m">>, 5}])))].

escape_test_() ->
    E = fun cell_shdr_codec:escape/1,
    [?_assertEqual(<<"plain text">>, E(<<"plain text">>)),
     ?_assertEqual(<<"back\\slash">>, E(<<"back\\slash">>)),
     ?_assertEqual(<<"\"a\\|b\"">>, E(<<"a|b">>)),
     ?_assertEqual(<<"\"\\\"quoted\\\"\"">>, E(<<"\"quoted\"">>)),
     ?_assertEqual(<<"\"\\|\\\\\\|\"">>, E(<<"|\\|">>)),
     ?_assertEqual(<<"two lines">>, E(<<"two\nlines">>)),
     ?_assertEqual(<<"crlf too">>, E(<<"crlf\r\ntoo">>)),
     ?_assertEqual(<<"say \"hi\"">>, E(<<"say \"hi\"">>)),
     %% the reference agent would take these letters for a multiline asset and stop
     ?_assertEqual(<<"see --multi-line--X">>, E(<<"see --multiline--X">>)),
     ?_assertEqual(<<"\"a\\|--multi-line----multi-line--\"">>,
                   E(<<"a|--multiline----multiline--">>)),
     ?_assertEqual(<<>>, E(<<>>))].

%% No line the codec writes outside an asset document holds `--multiline--', since the
%% reference agent reads everything after such a line as an asset.
no_multiline_start_test_() ->
    T = <<"x --multiline--TAG y">>,
    Lines = [cell_shdr_codec:data_line({utc, ?T0}, [{<<"k">>, T}]),
             cell_shdr_codec:condition_line({utc, ?T0}, <<"c">>,
                                            #{level => fault, code => T, severity => T,
                                              qualifier => T, text => T}),
             cell_shdr_codec:message_line({utc, ?T0}, <<"m">>, T, T),
             cell_shdr_codec:command(<<"station">>, T),
             cell_shdr_codec:remove_asset_line({utc, ?T0}, T),
             cell_shdr_codec:remove_all_assets_line({utc, ?T0}, T)],
    [?_assertEqual(nomatch, binary:match(iolist_to_binary(L), <<"--multiline--">>))
     || L <- Lines].

%% Any text, as a value between other fields, reads back as itself: no character can
%% break the line (line breaks become blanks, and blanks at the ends are the agent's
%% to drop).
prop_values_read_back() ->
    ?FORALL(Values, non_empty(list(text())),
            begin
                Pairs = [{<<"k", (integer_to_binary(I))/binary>>, V}
                         || {I, V} <- lists:zip(lists:seq(1, length(Values)), Values)],
                Line = iolist_to_binary(cell_shdr_codec:data_line({utc, ?T0}, Pairs)),
                [Body] = binary:split(Line, <<"\n">>, [trim]) -- [<<>>],
                [_Ts | Fields] = agent_tokens(Body),
                Expected = lists:append([[K, agent_view(V)] || {K, V} <- Pairs]),
                byte_size(Line) - 1 =:= byte_size(Body) andalso
                    binary:last(Line) =:= $\n andalso Fields =:= Expected
            end).

text() ->
    ?LET(Chars, list(oneof([$|, $", $\\, $\s, $\n, $\r, $a, $Z, $0, $-, $:, 16#e9,
                            range(32, 126)])),
         unicode:characters_to_binary(Chars)).

%% What the agent keeps of a value: line breaks as blanks, blanks at the ends gone.
agent_view(V) ->
    string:trim(binary:replace(binary:replace(V, <<"\r\n">>, <<" ">>, [global]),
                               [<<"\r">>, <<"\n">>], <<" ">>, [global]),
                both, " \t").

%% -------------------------------------------------------------------------------------
%% Conditions, messages, time series
%% -------------------------------------------------------------------------------------

condition_test_() ->
    C = fun(Cond) -> iolist_to_binary(cell_shdr_codec:condition_line({utc, ?T0}, <<"htemp">>,
                                                                     Cond)) end,
    %% The seed's own example line, field for field.
    [?_assertEqual(<<"2026-06-20T05:31:43.512Z|htemp|WARNING|HTEMP|1|HIGH|Oil Temperature High\n">>,
                   C(#{level => warning, code => <<"HTEMP">>, severity => <<"1">>,
                       qualifier => <<"HIGH">>, text => <<"Oil Temperature High">>})),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|htemp|NORMAL|912|||\n">>,
                   C(#{level => normal, code => <<"912">>})),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|htemp|NORMAL||||\n">>, C(#{level => normal})),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|htemp|FAULT|214|||Gen Fault 4\n">>,
                   C(#{level => fault, code => <<"214">>, text => <<"Gen Fault 4">>})),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|htemp|FAULT|a.b|error||\"x\\|y\"\n">>,
                   C(#{level => fault, code => <<"a.b">>, severity => <<"error">>,
                       text => <<"x|y">>})),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|htemp|UNAVAILABLE||||\n">>,
                   C(#{level => unavailable}))].

prop_condition_fields() ->
    ?FORALL({Level, Code, Sev, Text}, {oneof([normal, warning, fault]), text(), text(), text()},
            begin
                Line = iolist_to_binary(cell_shdr_codec:condition_line(
                                          {utc, ?T0}, <<"c">>,
                                          #{level => Level, code => Code, severity => Sev,
                                            text => Text})),
                [Body, <<>>] = binary:split(Line, <<"\n">>),
                [_, <<"c">>, L, C, S, <<>>, T] = agent_tokens(Body),
                L =:= string:uppercase(atom_to_binary(Level, utf8)) andalso
                    C =:= agent_view(Code) andalso S =:= agent_view(Sev) andalso
                    T =:= agent_view(Text)
            end).

message_test() ->
    ?assertEqual(<<"2026-06-20T05:31:43.512Z|msg|CODE1|hello\n">>,
                 iolist_to_binary(cell_shdr_codec:message_line({utc, ?T0}, <<"msg">>,
                                                               <<"CODE1">>, <<"hello">>))).

time_series_test_() ->
    TS = fun(S, Rate, Vs) ->
                 iolist_to_binary(cell_shdr_codec:time_series_line(S, <<"ia">>, length(Vs),
                                                                   Rate, Vs))
         end,
    %% The seed's example: five samples at 10 Hz, stamped with the last.
    [?_assertEqual(<<"2026-06-20T05:31:43.512Z|ia|5|10|16.0 24.0 12.0 66.0 18.0\n">>,
                   TS({utc, ?T0}, 10, [16.0, 24.0, 12.0, 66.0, 18.0])),
     %% Relative time, the rate left to the data item's declaration.
     ?_assertEqual(<<"1456|m|5||1 2 2 4 5\n">>,
                   iolist_to_binary(cell_shdr_codec:time_series_line({relative, 1456}, <<"m">>,
                                                                     5, undefined,
                                                                     [1, 2, 2, 4, 5]))),
     ?_assertEqual(<<"1556|m|1|2.5|7\n">>,
                   iolist_to_binary(cell_shdr_codec:time_series_line({relative, 1556}, <<"m">>,
                                                                     1, 2.5, [7]))),
     ?_assertEqual(<<"10">>, cell_shdr_codec:format_rate(10.0)),
     ?_assertEqual(<<"0.5">>, cell_shdr_codec:format_rate(0.5)),
     %% a count that is not the number of values is a bug of the caller
     ?_assertError(function_clause,
                   cell_shdr_codec:time_series_line({utc, 0}, <<"x">>, 3, 1, [1]))].

%% -------------------------------------------------------------------------------------
%% Assets
%% -------------------------------------------------------------------------------------

asset_one_line_test() ->
    Line = iolist_to_binary(cell_shdr_codec:asset_line({utc, ?T0}, <<"AAA123">>,
                                                       <<"CuttingTool">>, <<"<CuttingTool/>">>)),
    ?assertEqual(<<"2026-06-20T05:31:43.512Z|@ASSET@|AAA123|CuttingTool|<CuttingTool/>\n">>,
                 Line).

asset_multiline_test() ->
    Doc = <<"<File a=\"1\">\n  <X>one</X>\n\n  <Y>two</Y>\n</File>">>,
    Out = iolist_to_binary(cell_shdr_codec:asset_line({utc, ?T0}, <<"R1">>, <<"File">>, Doc)),
    [First | Rest] = binary:split(Out, <<"\n">>, [global, trim]),
    {match, [Tag]} = re:run(First, <<"\\|(--multiline--[0-9A-F]+)$">>,
                            [{capture, all_but_first, binary}]),
    ?assertMatch(<<"2026-06-20T05:31:43.512Z|@ASSET@|R1|File|--multiline--", _/binary>>, First),
    ?assertEqual(Tag, lists:last(Rest)),
    ?assertEqual([<<"<File a=\"1\">">>, <<"  <X>one</X>">>, <<"  <Y>two</Y>">>, <<"</File>">>],
                 lists:droplast(Rest)).

%% A document holding the letters goes in the multiline form (there only a whole line
%% equal to the tag ends it), its id and type defused like any text.
asset_multiline_letters_test() ->
    Doc = <<"<File d=\"--multiline--X\"/>">>,
    Out = iolist_to_binary(cell_shdr_codec:asset_line({utc, ?T0}, <<"R--multiline--1">>,
                                                      <<"File">>, Doc)),
    {Head, Body} = agent_multiline(binary:split(Out, <<"\n">>, [global, trim])),
    ?assertEqual(<<"2026-06-20T05:31:43.512Z|@ASSET@|R--multi-line--1|File|">>, Head),
    ?assertEqual([Doc], Body).

%% A document line starting `* PONG' would be taken for a heartbeat by the agent.
asset_star_line_test() ->
    Doc = <<"<File>\n* PONG 5\n*x\n</File>">>,
    Out = iolist_to_binary(cell_shdr_codec:asset_line({utc, ?T0}, <<"R1">>, <<"File">>, Doc)),
    {_, Body} = agent_multiline(binary:split(Out, <<"\n">>, [global, trim])),
    ?assertEqual([<<"<File>">>, <<"&#42; PONG 5">>, <<"&#42;x">>, <<"</File>">>], Body).

asset_pipe_test() ->
    Out = iolist_to_binary(cell_shdr_codec:asset_line({utc, ?T0}, <<"R|1">>, <<"File">>,
                                                      <<"<File d=\"a|b\"/>">>)),
    ?assertEqual(<<"2026-06-20T05:31:43.512Z|@ASSET@|\"R\\|1\"|File|<File d=\"a&#124;b\"/>\n">>,
                 Out).

%% The agent's multiline reading (seed 003; the reference agent collects lines after
%% a line holding --multiline--TAG until a line equal to the tag) gives back the
%% document line for line, whatever its lines hold (a `|' as its XML character
%% reference, since the agent would split its tokens there).
prop_multiline_reads_back() ->
    ?FORALL(Lines, non_empty(list(non_empty_line())),
            begin
                Doc = iolist_to_binary(lists:join($\n, Lines ++ [<<"</end>">>])),
                Out = iolist_to_binary(cell_shdr_codec:asset_line({utc, ?T0}, <<"id">>,
                                                                  <<"File">>, Doc)),
                {Head, Body} = agent_multiline(binary:split(Out, <<"\n">>, [global, trim])),
                Head =:= <<"2026-06-20T05:31:43.512Z|@ASSET@|id|File|">> andalso
                    Body =:= [star(binary:replace(L, <<"|">>, <<"&#124;">>, [global]))
                              || L <- binary:split(Doc, <<"\n">>, [global]),
                                 string:trim(L) =/= <<>>]
            end).

star(<<$*, Rest/binary>>) -> <<"&#42;", Rest/binary>>;
star(L) -> L.

non_empty_line() ->
    ?LET(Chars, list(oneof([$a, $<, $>, $-, $\s, $m, $=, $", $*, range(33, 126)])),
         list_to_binary(Chars)).

%% The reference agent's reading: a line starting `* PONG' is a heartbeat wherever it
%% comes; after a line holding --multiline--TAG, lines up to one equal to the tag.
agent_multiline(Lines) ->
    [First | Rest] = [L || L <- Lines, binary:longest_common_prefix([L, <<"* PONG">>]) < 6],
    {Pos, _} = binary:match(First, <<"--multiline--">>),
    Tag = binary:part(First, Pos, byte_size(First) - Pos),
    {Body, [Tag]} = lists:splitwith(fun(L) -> L =/= Tag end, Rest),
    {binary:part(First, 0, Pos), Body}.

remove_asset_test_() ->
    [?_assertEqual(<<"2026-06-20T05:31:43.512Z|@REMOVE_ASSET@|R1\n">>,
                   iolist_to_binary(cell_shdr_codec:remove_asset_line({utc, ?T0}, <<"R1">>))),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|@REMOVE_ALL_ASSETS@|File\n">>,
                   iolist_to_binary(cell_shdr_codec:remove_all_assets_line({utc, ?T0},
                                                                           <<"File">>))),
     ?_assertEqual(<<"2026-06-20T05:31:43.512Z|@REMOVE_ALL_ASSETS@\n">>,
                   iolist_to_binary(cell_shdr_codec:remove_all_assets_line({utc, ?T0}, all)))].

%% -------------------------------------------------------------------------------------
%% Protocol commands and input
%% -------------------------------------------------------------------------------------

command_test_() ->
    [?_assertEqual(<<"* PONG 10000\n">>, iolist_to_binary(cell_shdr_codec:pong(10000))),
     ?_assertEqual(<<"* uuid: 7f4e\n">>,
                   iolist_to_binary(cell_shdr_codec:command(<<"uuid">>, <<"7f4e">>))),
     ?_assertEqual(<<"* description: two lines\n">>,
                   iolist_to_binary(cell_shdr_codec:command(<<"description">>,
                                                            <<"two\nlines">>)))].

parse_input_test_() ->
    P = fun(B) -> cell_shdr_codec:parse_input(B, 16) end,
    [?_assertEqual({ok, [ping], <<>>}, P(<<"* PING\n">>)),
     ?_assertEqual({ok, [ping, ping], <<>>}, P(<<"* PING\r\n  *  PING  \n">>)),
     ?_assertEqual({ok, [], <<"* PI">>}, P(<<"* PI">>)),
     ?_assertEqual({ok, [ping], <<"* P">>}, P(<<"\n\n* PING\n* P">>)),
     ?_assertEqual({ok, [{unknown, <<"* PONG 5">>}, {unknown, <<"hello">>}], <<>>},
                   P(<<"* PONG 5\nhello\n">>)),
     ?_assertEqual({ok, [{unknown, <<255, 0, 1>>}], <<>>}, P(<<255, 0, 1, $\n>>)),
     %% both sides of the line limit, with and without the newline
     ?_assertEqual({ok, [{unknown, binary:copy(<<"x">>, 16)}], <<>>},
                   P(<<(binary:copy(<<"x">>, 16))/binary, $\n>>)),
     ?_assertEqual({error, line_too_long}, P(<<(binary:copy(<<"x">>, 17))/binary, $\n>>)),
     ?_assertEqual({ok, [], binary:copy(<<"x">>, 16)}, P(binary:copy(<<"x">>, 16))),
     ?_assertEqual({error, line_too_long}, P(binary:copy(<<"x">>, 17)))].

%% However the bytes are cut into packets, the same commands come out.
prop_input_any_split() ->
    ?FORALL({Lines, Cuts}, {list(oneof([<<"* PING">>, <<"*PING">>, <<"garbage">>, <<>>,
                                        <<"* PING\r">>])), list(range(1, 7))},
            begin
                Stream = iolist_to_binary([[L, $\n] || L <- Lines]),
                Whole = element(2, cell_shdr_codec:parse_input(Stream, 100)),
                Pieces = cut(Stream, Cuts),
                {Got, <<>>} = lists:foldl(
                                fun(Piece, {Acc, Buf}) ->
                                        {ok, Cmds, Rest} =
                                            cell_shdr_codec:parse_input(<<Buf/binary, Piece/binary>>, 100),
                                        {Acc ++ Cmds, Rest}
                                end, {[], <<>>}, Pieces),
                Got =:= Whole andalso length([ping || ping <- Got]) =:=
                    length([L || L <- Lines, lists:member(L, [<<"* PING">>, <<"*PING">>,
                                                              <<"* PING\r">>])])
            end).

cut(<<>>, _) -> [];
cut(B, []) -> [B];
cut(B, [N | Ns]) when N >= byte_size(B) -> [B | cut(<<>>, Ns)];
cut(B, [N | Ns]) -> <<P:N/binary, R/binary>> = B, [P | cut(R, Ns)].

%% -------------------------------------------------------------------------------------
%% The agent's tokenizer, as the model the properties check against
%% -------------------------------------------------------------------------------------

agent_tokens(Line) ->
    tokens(Line, []).

tokens(<<>>, Acc) -> lists:reverse(Acc);
tokens(B, Acc) ->
    Rest0 = skip_blanks(B),
    case Rest0 of
        <<$", Q/binary>> ->
            case quoted(Q, <<>>) of
                {ok, Tok, After} -> next(After, [Tok | Acc]);
                error -> plain(Rest0, Acc)
            end;
        _ -> plain(Rest0, Acc)
    end.

plain(B, Acc) ->
    case binary:split(B, <<"|">>) of
        [Tok] -> lists:reverse([trim_end(Tok) | Acc]);
        [Tok, <<>>] -> lists:reverse([<<>>, trim_end(Tok) | Acc]);
        [Tok, Rest] -> tokens(Rest, [trim_end(Tok) | Acc])
    end.

next(<<>>, Acc) -> lists:reverse(Acc);
next(<<$|>>, Acc) -> lists:reverse([<<>> | Acc]);
next(<<$|, Rest/binary>>, Acc) -> tokens(Rest, Acc).

quoted(<<$\\, C, Rest/binary>>, Tok) -> quoted(Rest, <<Tok/binary, C>>);
quoted(<<$|, _/binary>>, _) -> error;
quoted(<<$", Rest/binary>>, Tok) ->
    case skip_blanks(Rest) of
        <<>> -> {ok, Tok, <<>>};
        <<$|, _/binary>> = After -> {ok, Tok, After};
        _ -> error
    end;
quoted(<<C, Rest/binary>>, Tok) -> quoted(Rest, <<Tok/binary, C>>);
quoted(<<>>, _) -> error.

skip_blanks(<<C, R/binary>>) when C =:= $\s; C =:= $\t -> skip_blanks(R);
skip_blanks(B) -> B.

trim_end(B) -> string:trim(B, trailing, " \t").

%% -------------------------------------------------------------------------------------

properties_test_() ->
    [{timeout, 120, ?_assert(proper:quickcheck(P(), [{to_file, user}, {numtests, 500}]))}
     || P <- [fun prop_timestamp_matches_calendar/0, fun prop_values_read_back/0,
              fun prop_condition_fields/0, fun prop_multiline_reads_back/0,
              fun prop_input_any_split/0]].
