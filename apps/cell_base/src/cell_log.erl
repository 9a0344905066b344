%% @doc The one place every cellrt app logs through (the backend, lager, can change
%% here without touching callers).
%%
%% Seed 000 §5: a device task log for people running the machine and a trace log for
%% programmers. Task messages carry one of the seed's levels, and each source (a task,
%% a connection, the controller) has its own threshold, settable at run time:
%%
%% <table>
%% <tr><th>message level</th><th>shown when the source's level is</th><th>lager</th></tr>
%% <tr><td>`error', `warning'</td><td>always</td><td>error, warning</td></tr>
%% <tr><td>`silent' (mandatory)</td><td>silent, brief, verbose</td><td>notice</td></tr>
%% <tr><td>`brief'</td><td>brief, verbose</td><td>info</td></tr>
%% <tr><td>`verbose'</td><td>verbose</td><td>debug</td></tr>
%% </table>
%%
%% Task messages go to the console (down to brief), to the daily task log
%% `Logs/log YYYY-MM-DD.log', and to live subscribers (the web panel). Trace messages
%% and reports from OTP (crash reports) go to `Logs/trace YYYY-MM-DD.log'.
-module(cell_log).

-export([log/4, error/3, warning/3, notice/3, info/3, debug/3, trace/3]).
-export([set_level/2, level/1, reset_level/1, verbose_for/2, enabled/2,
         set_default_level/1, levels_version/0, levels_changed/0]).
-export([subscribe/0, unsubscribe/0, flush/0]).
-export([format_line/1, parse_line/1, file_name/2, query/1, default_level/0]).

-export_type([level/0, threshold/0, source/0, line/0, query/0]).

-type level() :: error | warning | silent | brief | verbose.
-type threshold() :: silent | brief | verbose.
-type source() :: atom() | binary().
-type line() :: #{time := integer(),       %% system time, milliseconds
                  level := level(),
                  source := binary(),
                  text := binary()}.
-type query() :: #{from => integer(),      %% ms, inclusive
                   to => integer(),        %% ms, exclusive
                   levels => [level()],
                   source => binary(),
                   offset => non_neg_integer(),
                   limit => pos_integer()}.

-define(LEVELS_TAB, cell_log_levels).
-define(SUBS_KEY, '$subscribers').
-define(DEFAULT_KEY, '$default').
%% An atom: every read of a persistent term hashes its key, and an atom keeps its hash.
-define(VERSION_KEY, cell_log_levels_version).

%% @doc Logs a message of the seed's levels for `Source', if its threshold allows.
-spec log(level(), source(), io:format(), [term()]) -> ok.
log(Level, Source, Format, Args) ->
    case loggable(Level, Source) of
        true -> emit(task, Level, Source, Format, Args);
        false -> ok
    end.

%% @doc An error, always logged.
-spec error(source(), io:format(), [term()]) -> ok.
error(Source, Format, Args) -> log(error, Source, Format, Args).

%% @doc A warning, always logged.
-spec warning(source(), io:format(), [term()]) -> ok.
warning(Source, Format, Args) -> log(warning, Source, Format, Args).

%% @doc A mandatory message (the seed's Silent level): logged at every threshold.
-spec notice(source(), io:format(), [term()]) -> ok.
notice(Source, Format, Args) -> log(silent, Source, Format, Args).

%% @doc Machine activity (the seed's Brief level).
-spec info(source(), io:format(), [term()]) -> ok.
info(Source, Format, Args) -> log(brief, Source, Format, Args).

%% @doc Detail (the seed's Verbose level).
-spec debug(source(), io:format(), [term()]) -> ok.
debug(Source, Format, Args) -> log(verbose, Source, Format, Args).

%% @doc A programmer-oriented message for the trace log only (seed 000 §5.2).
-spec trace(source(), io:format(), [term()]) -> ok.
trace(Source, Format, Args) ->
    emit(trace, verbose, Source, Format, Args).

%% @doc Whether a message of this level from this source would be logged: lets a
%% caller skip building an expensive message nobody reads.
-spec enabled(level(), source()) -> boolean().
enabled(Level, Source) ->
    loggable(Level, Source).

%% @doc A number that changes whenever a threshold may have changed. A caller asking
%% {@link enabled/2} on a hot path (a unit, once a cycle) keeps the answer with this
%% number and asks again only when it differs: reading it costs a persistent-term
%% read, where enabled/2 costs two table lookups. 0 until the log server first starts.
%%
%% The log server changes it after it has changed the table, so an answer kept with a
%% number is never older than that number. One case it does not see: between the
%% server's crash and its restart, when enabled/2 falls back to the application's
%% default, a kept answer stays as the table had it.
-spec levels_version() -> non_neg_integer().
levels_version() ->
    persistent_term:get(?VERSION_KEY, 0).

%% @private The log server has changed the thresholds (or made their table anew). The
%% number is a small integer: replacing it costs the node no scan of every process,
%% as replacing a compound term would (see persistent_term), and thresholds change
%% seldom (at a Start, an operator's choice).
-spec levels_changed() -> ok.
levels_changed() ->
    persistent_term:put(?VERSION_KEY, levels_version() + 1).

%% @doc Sets the threshold of every source without one of its own (the machine
%% settings' log level, applied at each Start).
-spec set_default_level(threshold()) -> ok.
set_default_level(Level) when Level =:= silent; Level =:= brief; Level =:= verbose ->
    cell_log_server:set_level(?DEFAULT_KEY, Level).

%% @doc Sets the threshold of one source.
-spec set_level(source(), threshold()) -> ok.
set_level(Source, Level) when Level =:= silent; Level =:= brief; Level =:= verbose ->
    cell_log_server:set_level(key(Source), Level).

%% @doc Drops a source's own threshold; it follows the default again.
-spec reset_level(source()) -> ok.
reset_level(Source) ->
    cell_log_server:reset_level(key(Source)).

%% @doc The threshold of one source (its own, or the default).
-spec level(source()) -> threshold().
level(Source) ->
    try ets:lookup(?LEVELS_TAB, key(Source)) of
        [{_, Level}] -> Level;
        [] ->
            %% The default, kept in the table by the log server so a check costs two
            %% lookups at most: it runs on every state change of every task.
            case ets:lookup(?LEVELS_TAB, ?DEFAULT_KEY) of
                [{_, Level}] -> Level;
                [] -> default_level()
            end
    catch
        error:badarg -> default_level()
    end.

%% @doc Switches one source to verbose for `Ms' milliseconds, then back.
-spec verbose_for(source(), pos_integer()) -> ok.
verbose_for(Source, Ms) ->
    cell_log_server:verbose_for(key(Source), Ms).

%% @doc The calling process receives `{cell_log, line()}' for every task log line
%% until it unsubscribes or exits.
-spec subscribe() -> ok.
subscribe() -> cell_log_server:subscribe(self()).

%% @doc Ends a {@link subscribe/0}.
-spec unsubscribe() -> ok.
unsubscribe() -> cell_log_server:unsubscribe(self()).

loggable(error, _) -> true;
loggable(warning, _) -> true;
loggable(Level, Source) -> rank(Level) =< rank(level(Source)).

rank(silent) -> 0;
rank(brief) -> 1;
rank(verbose) -> 2.

%% @private The default threshold from the application environment.
-spec default_level() -> threshold().
default_level() ->
    case application:get_env(cell_base, log_level, brief) of
        L when L =:= silent; L =:= brief; L =:= verbose -> L;
        _ -> brief
    end.

key(Source) when is_atom(Source) -> atom_to_binary(Source, utf8);
key(Source) when is_binary(Source) -> Source.

emit(Kind, Level, Source, Format, Args) ->
    Text = try unicode:characters_to_binary(io_lib:format(Format, Args)) of
               B when is_binary(B) -> B;
               _ -> iolist_to_binary(io_lib:format("~tp ~tp", [Format, Args]))
           catch
               error:_ -> iolist_to_binary(io_lib:format("bad log format ~tp ~tp",
                                                         [Format, Args]))
           end,
    Line = #{time => os:system_time(millisecond), level => Level, source => key(Source),
             text => Text},
    Kind =:= task andalso notify(Line),
    Metadata = [{cell_log, Kind}, {cell_line, Line}, {source, key(Source)}],
    _ = lager:log(lager_level(Level), Metadata, "~ts", [Text]),
    ok.

%% @doc Returns once every line logged before it has reached the log files: their
%% handlers write as the logger's event manager hands them each line, and this asks
%% that manager after them. A command that halts the VM right after logging calls it
%% first, or its last lines may never be written.
-spec flush() -> ok.
flush() ->
    _ = catch gen_event:which_handlers(lager_event),
    ok.

notify(Line) ->
    try ets:lookup(?LEVELS_TAB, ?SUBS_KEY) of
        [{_, Pids}] -> lists:foreach(fun(Pid) -> Pid ! {cell_log, Line} end, Pids);
        [] -> ok
    catch
        error:badarg -> ok
    end.

lager_level(error) -> error;
lager_level(warning) -> warning;
lager_level(silent) -> notice;
lager_level(brief) -> info;
lager_level(verbose) -> debug.

%% @doc One log file line: `YYYY-MM-DD HH:MM:SS.mmm LEVEL source: text', local time.
%% Line breaks inside the text continue on lines that start with two spaces.
-spec format_line(line()) -> iodata().
format_line(#{time := Ms, level := Level, source := Source, text := Text}) ->
    {{Y, Mo, D}, {H, Mi, S}} =
        calendar:system_time_to_local_time(Ms div 1000, second),
    Stamp = io_lib:format("~4..0w-~2..0w-~2..0w ~2..0w:~2..0w:~2..0w.~3..0w",
                          [Y, Mo, D, H, Mi, S, Ms rem 1000]),
    Body = binary:replace(Text, <<"\n">>, <<"\n  ">>, [global]),
    [Stamp, $\s, string:uppercase(atom_to_list(Level)), $\s, Source, ": ", Body, $\n].

%% @doc Parses a line written by {@link format_line/1} (continuation lines excluded).
-spec parse_line(binary()) -> {ok, line()} | error.
parse_line(<<Y:4/binary, $-, Mo:2/binary, $-, D:2/binary, $\s,
             H:2/binary, $:, Mi:2/binary, $:, S:2/binary, $., Ms:3/binary, $\s,
             Rest/binary>>) ->
    try
        Date = {binary_to_integer(Y), binary_to_integer(Mo), binary_to_integer(D)},
        Time = {binary_to_integer(H), binary_to_integer(Mi), binary_to_integer(S)},
        [LevelBin, Rest1] = binary:split(Rest, <<" ">>),
        [Source, Text] = binary:split(Rest1, <<": ">>),
        Level = level_of(LevelBin),
        [Utc | _] = calendar:local_time_to_universal_time_dst({Date, Time}),
        Secs = calendar:datetime_to_gregorian_seconds(Utc) - 62167219200,
        {ok, #{time => Secs * 1000 + binary_to_integer(Ms), level => Level,
               source => Source, text => Text}}
    catch
        error:_ -> error
    end;
parse_line(_) ->
    error.

level_of(<<"ERROR">>) -> error;
level_of(<<"WARNING">>) -> warning;
level_of(<<"SILENT">>) -> silent;
level_of(<<"BRIEF">>) -> brief;
level_of(<<"VERBOSE">>) -> verbose.

%% @doc The daily file of a kind for a local date: `log 2026-11-21.log'.
-spec file_name(task | trace, calendar:date()) -> string().
file_name(Kind, {Y, M, D}) ->
    Prefix = case Kind of task -> "log"; trace -> "trace" end,
    lists:flatten(io_lib:format("~s ~4..0w-~2..0w-~2..0w.log", [Prefix, Y, M, D])).

%% @doc Reads task log lines back from the daily files, oldest first: by time range,
%% levels and source, then `offset' and `limit' (default 200) for paging.
-spec query(query()) -> [line()].
query(Q) ->
    Now = os:system_time(millisecond),
    From = maps:get(from, Q, Now - 86400000),
    To = maps:get(to, Q, Now + 1),
    Dates = dates_between(From, To),
    Dir = cell_config:dir(logs),
    Lines = lists:append([read_file(filename:join(Dir, file_name(task, D))) || D <- Dates]),
    Keep = fun(#{time := T} = L) ->
                   T >= From andalso T < To andalso
                       level_ok(L, maps:get(levels, Q, all)) andalso
                       source_ok(L, maps:get(source, Q, all))
           end,
    Selected = [L || L <- Lines, Keep(L)],
    Offset = maps:get(offset, Q, 0),
    Limit = maps:get(limit, Q, 200),
    lists:sublist(safe_nthtail(Offset, Selected), Limit).

level_ok(_, all) -> true;
level_ok(#{level := L}, Levels) -> lists:member(L, Levels).

source_ok(_, all) -> true;
source_ok(#{source := S}, S) -> true;
source_ok(_, _) -> false.

safe_nthtail(N, L) when N >= length(L) -> [];
safe_nthtail(N, L) -> lists:nthtail(N, L).

dates_between(From, To) ->
    First = local_date(From),
    Last = local_date(max(From, To - 1)),
    dates_from(First, Last, []).

dates_from(Last, Last, Acc) -> lists:reverse([Last | Acc]);
dates_from(D, Last, Acc) ->
    Next = calendar:gregorian_days_to_date(calendar:date_to_gregorian_days(D) + 1),
    dates_from(Next, Last, [D | Acc]).

local_date(Ms) ->
    {Date, _} = calendar:system_time_to_local_time(Ms div 1000, second),
    Date.

read_file(Path) ->
    case file:read_file(Path) of
        {ok, Bin} -> parse_lines(binary:split(Bin, <<"\n">>, [global]), []);
        {error, _} -> []
    end.

parse_lines([], Acc) ->
    lists:reverse(Acc);
parse_lines([<<"  ", Cont/binary>> | Rest], [#{text := T} = Prev | Acc]) ->
    parse_lines(Rest, [Prev#{text := <<T/binary, $\n, Cont/binary>>} | Acc]);
parse_lines([Raw | Rest], Acc) ->
    case parse_line(Raw) of
        {ok, Line} -> parse_lines(Rest, [Line | Acc]);
        error -> parse_lines(Rest, Acc)
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

line_roundtrip_test_() ->
    Now = os:system_time(millisecond),
    Lines = [#{time => Now, level => brief, source => <<"loading_front">>,
               text => <<"Panel P1 arrived">>},
             #{time => 0, level => error, source => <<"hal/plc1">>,
               text => <<"connection lost: a: b">>},
             #{time => Now - 999, level => verbose, source => <<"x">>, text => <<>>}],
    [?_assertEqual({ok, L}, parse_line(iolist_to_binary(lists:droplast(
                                                              binary_to_list(iolist_to_binary(format_line(L)))))))
     || L <- Lines].

multiline_test() ->
    L = #{time => 1000, level => warning, source => <<"t">>, text => <<"a\nb">>},
    Bin = iolist_to_binary(format_line(L)),
    ?assertEqual([L], parse_lines(binary:split(Bin, <<"\n">>, [global]), [])).

garbage_lines_test() ->
    ?assertEqual(error, parse_line(<<"hello">>)),
    ?assertEqual(error, parse_line(<<"2026-13-45 99:99:99.999 BRIEF x: y">>)),
    ?assertEqual(error, parse_line(<<"2026-11-21 08:00:00.000 LOUD x: y">>)),
    ?assertEqual([], parse_lines([<<"  orphan continuation">>, <<>>], [])).

file_name_test() ->
    ?assertEqual("log 2026-11-21.log", file_name(task, {2026, 11, 21})),
    ?assertEqual("trace 2026-01-02.log", file_name(trace, {2026, 1, 2})).

threshold_test_() ->
    [?_assert(loggable(error, <<"nobody">>)),
     ?_assert(loggable(warning, <<"nobody">>)),
     ?_assert(loggable(silent, <<"nobody">>))].

dates_between_test() ->
    Day = 86400000,
    Noon = 1700000000000 - (1700000000000 rem Day) + Day div 2,
    ?assertEqual(1, length(dates_between(Noon, Noon + 1))),
    ?assertEqual(3, length(dates_between(Noon, Noon + 2 * Day))).
-endif.
