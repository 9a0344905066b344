%% @doc The SHDR text protocol an MTConnect agent reads over TCP (seed 003), as pure
%% functions: no sockets, no processes.
%%
%% A data line is a timestamp and fields joined by `|', ended by a newline:
%%
%% ```
%% 2026-11-21T08:41:43.512Z|avail|AVAILABLE|execution|ACTIVE
%% 2026-11-21T08:41:43.512Z|robot_system|FAULT|robot.lost|error||Product lost: ...
%% 2026-11-21T08:41:43.900Z|spindle_load|5|10|16 24 12 66 18
%% 2026-11-21T08:41:44.000Z|@ASSET@|R1|File|--multiline--0F3A...
%% '''
%%
%% <ul>
%% <li>Timestamps are UTC `YYYY-MM-DDTHH:MM:SS.FFFZ'; in relative-time mode a line
%%     starts with a clock tick in milliseconds instead, and the agent spaces the
%%     samples by it.</li>
%% <li>Plain events and samples share a line (`key|value|key|value'); a condition, a
%%     message, a time series and an asset each take a line of their own, as the seed
%%     says and as agents that read SHDR version 1 require.</li>
%% <li>A value holding `|' (or starting with `"') is written in double quotes with
%%     `\' before every `\', `"' and `|' inside, which is how the reference agent reads
%%     quoted tokens; line breaks become spaces, since nothing can carry them. So no
%%     value can break the line format.</li>
%% <li>An asset document with line breaks goes in the `--multiline--TAG' form, its tag
%%     derived from the document so that no line of the document can end it early.</li>
%% <li>The reference agent takes any line holding `--multiline--' for the start of a
%%     multiline asset and reads every line after it as the asset's until a line equal
%%     to the rest: a value or an announcement holding those letters would stop the
%%     stream for good. So a text never carries them as they are: it says
%%     `--multi-line--' instead; an asset document holding them goes in the multiline
%%     form, where only a whole line equal to the tag ends it.</li>
%% <li>Inside a multiline document the agent still takes a line starting `* PONG' for
%%     a heartbeat: a `*' starting a line of the document is written `&#42;', which
%%     reads the same as XML.</li>
%% <li>Protocol commands: `* PING' from the agent is answered `* PONG <ms>'; the
%%     adapter announces itself with `* name: value' lines.</li>
%% </ul>
-module(cell_shdr_codec).

-export([timestamp/1, relative/1, escape/1, value/1]).
-export([data_line/2, condition_line/3, message_line/4, time_series_line/5,
         asset_line/4, remove_asset_line/2, remove_all_assets_line/2,
         command/2, pong/1]).
-export([parse_input/2, format_rate/1]).

-export_type([stamp/0, value/0, level/0, condition/0, input/0]).

%% A timestamp as the line starts with it: UTC milliseconds, or a relative tick.
-type stamp() :: {utc, integer()} | {relative, non_neg_integer()}.
-type value() :: binary() | number() | unavailable.
-type level() :: normal | warning | fault | unavailable.
%% One condition: its level, native code, native severity, qualifier and text.
-type condition() :: #{level := level(), code => binary(), severity => binary(),
                       qualifier => binary(), text => binary()}.
-type input() :: ping | {unknown, binary()}.

%%====================================================================
%% Timestamps
%%====================================================================

%% @doc `YYYY-MM-DDTHH:MM:SS.FFFZ' for a UTC time in milliseconds since the epoch.
-spec timestamp(integer()) -> binary().
timestamp(Ms) ->
    Secs = Ms div 1000,
    Frac = Ms - Secs * 1000,
    {{Y, Mo, D}, {H, Mi, S}} = calendar:system_time_to_universal_time(Secs, second),
    <<(pad(Y, 4))/binary, $-, (pad(Mo, 2))/binary, $-, (pad(D, 2))/binary, $T,
      (pad(H, 2))/binary, $:, (pad(Mi, 2))/binary, $:, (pad(S, 2))/binary, $.,
      (pad(Frac, 3))/binary, $Z>>.

%% @doc A relative clock tick: whole milliseconds.
-spec relative(non_neg_integer()) -> binary().
relative(Ms) when is_integer(Ms), Ms >= 0 ->
    integer_to_binary(Ms).

pad(N, Width) ->
    B = integer_to_binary(N),
    case Width - byte_size(B) of
        Fill when Fill > 0 -> <<(binary:copy(<<$0>>, Fill))/binary, B/binary>>;
        _ -> B
    end.

stamp({utc, Ms}) -> timestamp(Ms);
stamp({relative, Ms}) -> relative(Ms).

%%====================================================================
%% Values
%%====================================================================

%% @doc A value as a field: numbers in their shortest exact form, `UNAVAILABLE' for
%% an unknown value, text escaped (see {@link escape/1}).
-spec value(value()) -> binary().
value(unavailable) -> <<"UNAVAILABLE">>;
value(I) when is_integer(I) -> integer_to_binary(I);
value(F) when is_float(F) -> float_to_binary(F, [short]);
value(B) when is_binary(B) -> escape(B).

%% @doc Text as one field that no character can break: line breaks become spaces,
%% blanks at both ends go (the agent drops them anyway); a text holding `|' or
%% starting with `"' is quoted, with `\' before each `\', `"' and `|'.
-spec escape(binary()) -> binary().
escape(B) ->
    Flat = defuse(trim_blanks(flatten(B))),
    case needs_quotes(Flat) of
        false -> Flat;
        true -> <<$", (quote(Flat))/binary, $">>
    end.

flatten(B) ->
    case binary:match(B, [<<"\r">>, <<"\n">>]) of
        nomatch -> B;
        _ -> binary:replace(B, [<<"\r\n">>, <<"\r">>, <<"\n">>], <<" ">>, [global])
    end.

trim_blanks(B) ->
    case B of
        <<C, _/binary>> when C =:= $\s; C =:= $\t -> string:trim(B, both, " \t");
        <<>> -> B;
        _ ->
            case binary:last(B) of
                C when C =:= $\s; C =:= $\t -> string:trim(B, both, " \t");
                _ -> B
            end
    end.

%% See the module doc: no text may start a multiline asset in the agent.
defuse(B) ->
    case binary:match(B, <<"--multiline--">>) of
        nomatch -> B;
        _ -> binary:replace(B, <<"--multiline--">>, <<"--multi-line--">>, [global])
    end.

needs_quotes(<<$", _/binary>>) -> true;
needs_quotes(B) -> binary:match(B, <<"|">>) =/= nomatch.

quote(B) ->
    << <<(case C of
              $\\ -> <<"\\\\">>;
              $" -> <<"\\\"">>;
              $| -> <<"\\|">>;
              _ -> <<C>>
          end)/binary>> || <<C>> <= B >>.

%%====================================================================
%% Lines
%%====================================================================

%% @doc A line of plain events and samples sharing one timestamp.
-spec data_line(stamp(), [{binary(), value()}, ...]) -> iodata().
data_line(Stamp, [_ | _] = Pairs) ->
    [stamp(Stamp), [[$|, Key, $|, value(V)] || {Key, V} <- Pairs], $\n].

%% @doc A condition line: `key|LEVEL|code|severity|qualifier|text'. `normal' with no
%% code clears every code of the item (the sweep found nothing active).
-spec condition_line(stamp(), binary(), condition()) -> iodata().
condition_line(Stamp, Key, #{level := Level} = C) ->
    Field = fun(F) -> escape(maps:get(F, C, <<>>)) end,
    [stamp(Stamp), $|, Key, $|, level(Level), $|, Field(code), $|, Field(severity), $|,
     Field(qualifier), $|, Field(text), $\n].

level(normal) -> <<"NORMAL">>;
level(warning) -> <<"WARNING">>;
level(fault) -> <<"FAULT">>;
level(unavailable) -> <<"UNAVAILABLE">>.

%% @doc A message line: `key|native code|text'.
-spec message_line(stamp(), binary(), binary(), value()) -> iodata().
message_line(Stamp, Key, Code, Text) ->
    [stamp(Stamp), $|, Key, $|, escape(Code), $|, value(Text), $\n].

%% @doc A time series: `key|count|rate|v1 v2 ...', stamped with the time of the last
%% sample; the rate (Hz) may be left out when the data item declares it.
-spec time_series_line(stamp(), binary(), non_neg_integer(), number() | undefined,
                       [number()]) -> iodata().
time_series_line(Stamp, Key, Count, Rate, Values) when Count =:= length(Values) ->
    [stamp(Stamp), $|, Key, $|, integer_to_binary(Count), $|, format_rate(Rate), $|,
     lists:join($\s, [value(V) || V <- Values]), $\n].

%% @doc A sample rate in Hz as a field: integral rates without a decimal point.
-spec format_rate(number() | undefined) -> binary().
format_rate(undefined) -> <<>>;
format_rate(R) when is_integer(R) -> integer_to_binary(R);
format_rate(R) when is_float(R), R == trunc(R) -> integer_to_binary(trunc(R));
format_rate(R) when is_float(R) -> float_to_binary(R, [short]).

%% @doc An asset added or changed: one line when the document has no line break (and
%% no `--multiline--'), the multiline form otherwise. A `|' in the document would
%% split the agent's tokens even inside the multiline form, so it is written as the
%% XML character reference `&#124;', which reads the same; so is a `*' starting a
%% line of a multiline document (`&#42;'), which the agent could take for a PONG.
-spec asset_line(stamp(), binary(), binary(), binary()) -> iodata().
asset_line(Stamp, Id, Type, Doc0) ->
    Doc = binary:replace(Doc0, <<"|">>, <<"&#124;">>, [global]),
    Head = [stamp(Stamp), <<"|@ASSET@|">>, escape(Id), $|, escape(Type), $|],
    case binary:match(Doc, [<<"\n">>, <<"\r">>, <<"--multiline--">>]) of
        nomatch ->
            [Head, Doc, $\n];
        _ ->
            Lines = [star(L) || L <- binary:split(Doc, [<<"\r\n">>, <<"\n">>, <<"\r">>],
                                                  [global]),
                                trim(L) =/= <<>>],
            Tag = terminator(Doc),
            [Head, Tag, $\n, lists:join($\n, Lines), $\n, Tag, $\n]
    end.

star(<<$*, Rest/binary>>) -> <<"&#42;", Rest/binary>>;
star(Line) -> Line.

%% The end tag of a multiline document: a hash of the document, so no line of it can
%% equal the tag.
terminator(Doc) ->
    Hash = binary:encode_hex(binary:part(crypto:hash(sha256, Doc), 0, 8)),
    <<"--multiline--", Hash/binary>>.

-spec remove_asset_line(stamp(), binary()) -> iodata().
remove_asset_line(Stamp, Id) ->
    [stamp(Stamp), <<"|@REMOVE_ASSET@|">>, escape(Id), $\n].

%% @doc Removes every asset, or every asset of one type.
-spec remove_all_assets_line(stamp(), binary() | all) -> iodata().
remove_all_assets_line(Stamp, all) ->
    [stamp(Stamp), <<"|@REMOVE_ALL_ASSETS@">>, $\n];
remove_all_assets_line(Stamp, Type) ->
    [stamp(Stamp), <<"|@REMOVE_ALL_ASSETS@|">>, escape(Type), $\n].

%% @doc A protocol command announcing a property: `* uuid: 7f4e...'.
-spec command(binary(), binary()) -> iodata().
command(Name, Value) ->
    [<<"* ">>, Name, <<": ">>, defuse(flatten(Value)), $\n].

%% @doc The answer to `* PING': the heartbeat period the adapter promises.
-spec pong(pos_integer()) -> iodata().
pong(PeriodMs) ->
    [<<"* PONG ">>, integer_to_binary(PeriodMs), $\n].

%%====================================================================
%% Input from the agent
%%====================================================================

%% @doc Splits what the agent sent into complete lines: `* PING' (blanks around it
%% and a CR are forgiven) and anything else as `{unknown, Line}'; blank lines are
%% skipped. The rest of the buffer waits for its newline; a line longer than `Max'
%% bytes is refused.
-spec parse_input(binary(), pos_integer()) ->
          {ok, [input()], binary()} | {error, line_too_long}.
parse_input(Buffer, Max) ->
    parse_input(Buffer, Max, []).

parse_input(Buffer, Max, Acc) ->
    case binary:match(Buffer, <<"\n">>) of
        nomatch when byte_size(Buffer) > Max ->
            {error, line_too_long};
        nomatch ->
            {ok, lists:reverse(Acc), Buffer};
        {Pos, 1} when Pos > Max ->
            {error, line_too_long};
        {Pos, 1} ->
            <<Line:Pos/binary, $\n, Rest/binary>> = Buffer,
            parse_input(Rest, Max, input(trim(Line), Acc))
    end.

input(<<>>, Acc) -> Acc;
input(<<"*", Rest/binary>> = Line, Acc) ->
    case trim(Rest) of
        <<"PING">> -> [ping | Acc];
        _ -> [{unknown, Line} | Acc]
    end;
input(Line, Acc) -> [{unknown, Line} | Acc].

%% Blanks and CR at both ends, byte by byte: input from the network need not be UTF-8.
trim(B) -> trim_tail(trim_head(B)).

trim_head(<<C, Rest/binary>>) when C =:= $\s; C =:= $\t; C =:= $\r -> trim_head(Rest);
trim_head(B) -> B.

trim_tail(<<>>) -> <<>>;
trim_tail(B) ->
    case binary:last(B) of
        C when C =:= $\s; C =:= $\t; C =:= $\r -> trim_tail(binary:part(B, 0, byte_size(B) - 1));
        _ -> B
    end.
