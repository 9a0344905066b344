%% @doc Shifts, as pure functions: the statistics count time and items per shift and in
%% total. Shifts are given by their start times of day, local time ("06:00", "14:00",
%% "22:00"); a shift ends where the next begins, the last of the day at the first of the
%% next day. A shift is named by the date it starts on and its number that day, from 1:
%% the night shift that starts at 22:00 on 1 May and ends at 06:00 on 2 May is
%% `{{2024,5,1}, 3}'.
-module(cell_stats_shift).

-export([parse/1, parse_all/1, at/2, label/1, starts_text/1]).

-export_type([id/0, shift/0]).

-type id() :: {calendar:date(), pos_integer()}.
-type shift() :: #{id := id(), start := calendar:datetime(), 'end' := calendar:datetime()}.

-define(DAY, 86400).

%% @doc Minutes after midnight of an "HH:MM" start time.
-spec parse(binary()) -> {ok, 0..1439} | error.
parse(<<H1, H2, $:, M1, M2>>) when H1 >= $0, H1 =< $2, H2 >= $0, H2 =< $9,
                                   M1 >= $0, M1 =< $5, M2 >= $0, M2 =< $9 ->
    H = (H1 - $0) * 10 + H2 - $0,
    M = (M1 - $0) * 10 + M2 - $0,
    case H < 24 of
        true -> {ok, H * 60 + M};
        false -> error
    end;
parse(_) ->
    error.

%% @doc Every start time of a shift plan: at least one, each "HH:MM", in ascending
%% order without repeats. The error names the first bad entry (1-based).
-spec parse_all([binary()]) -> {ok, [0..1439, ...]} | {error, {pos_integer(), term()}}.
parse_all([]) ->
    {error, {1, no_shifts}};
parse_all(Texts) ->
    parse_all(Texts, 1, -1, []).

parse_all([], _I, _Last, Acc) ->
    {ok, lists:reverse(Acc)};
parse_all([T | Rest], I, Last, Acc) ->
    case parse(T) of
        {ok, M} when M > Last -> parse_all(Rest, I + 1, M, [M | Acc]);
        {ok, _} -> {error, {I, not_after_previous}};
        error -> {error, {I, not_hh_mm}}
    end.

%% @doc The shift a local date and time falls in, with its start and end (local).
-spec at(calendar:datetime(), [0..1439, ...]) -> shift().
at({Date, {H, Mi, S}} = Local, Starts) ->
    Seconds = H * 3600 + Mi * 60 + S,
    case [{N, M} || {N, M} <- lists:zip(lists:seq(1, length(Starts)), Starts),
                    M * 60 =< Seconds] of
        [] ->
            %% Before the first start of the day: the last shift of yesterday.
            Yesterday = add_days(Date, -1),
            N = length(Starts),
            shift(Yesterday, N, lists:nth(N, Starts), Date, hd(Starts), Local);
        Earlier ->
            {N, M} = lists:last(Earlier),
            case N =:= length(Starts) of
                true -> shift(Date, N, M, add_days(Date, 1), hd(Starts), Local);
                false -> shift(Date, N, M, Date, lists:nth(N + 1, Starts), Local)
            end
    end.

shift(Date, N, StartMin, EndDate, EndMin, _Local) ->
    #{id => {Date, N}, start => {Date, hm(StartMin)}, 'end' => {EndDate, hm(EndMin)}}.

hm(M) -> {M div 60, M rem 60, 0}.

add_days(Date, N) ->
    calendar:gregorian_days_to_date(calendar:date_to_gregorian_days(Date) + N).

%% @doc A shift's name for people and JSON: "2024-05-01/3".
-spec label(id()) -> binary().
label({{Y, M, D}, N}) ->
    iolist_to_binary(io_lib:format("~4..0b-~2..0b-~2..0b/~b", [Y, M, D, N])).

%% @doc Start times back to "HH:MM".
-spec starts_text([0..1439]) -> [binary()].
starts_text(Starts) ->
    [iolist_to_binary(io_lib:format("~2..0b:~2..0b", [M div 60, M rem 60])) || M <- Starts].

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

parse_test_() ->
    [?_assertEqual({ok, 0}, parse(<<"00:00">>)),
     ?_assertEqual({ok, 1439}, parse(<<"23:59">>)),
     ?_assertEqual({ok, 360}, parse(<<"06:00">>)),
     ?_assertEqual(error, parse(<<"24:00">>)),
     ?_assertEqual(error, parse(<<"06:60">>)),
     ?_assertEqual(error, parse(<<"6:00">>)),
     ?_assertEqual(error, parse(<<"06-00">>)),
     ?_assertEqual({ok, [360, 840, 1320]}, parse_all([<<"06:00">>, <<"14:00">>, <<"22:00">>])),
     ?_assertEqual({error, {2, not_after_previous}}, parse_all([<<"06:00">>, <<"06:00">>])),
     ?_assertEqual({error, {2, not_after_previous}}, parse_all([<<"14:00">>, <<"06:00">>])),
     ?_assertEqual({error, {1, not_hh_mm}}, parse_all([<<"x">>])),
     ?_assertEqual({error, {1, no_shifts}}, parse_all([]))].

at_test_() ->
    Three = [360, 840, 1320],
    D = {2024, 5, 1},
    [%% Both sides of every boundary.
     ?_assertMatch(#{id := {{2024, 4, 30}, 3}, start := {{2024, 4, 30}, {22, 0, 0}},
                     'end' := {D, {6, 0, 0}}}, at({D, {5, 59, 59}}, Three)),
     ?_assertMatch(#{id := {D, 1}, start := {D, {6, 0, 0}}, 'end' := {D, {14, 0, 0}}},
                   at({D, {6, 0, 0}}, Three)),
     ?_assertMatch(#{id := {D, 1}}, at({D, {13, 59, 59}}, Three)),
     ?_assertMatch(#{id := {D, 2}}, at({D, {14, 0, 0}}, Three)),
     ?_assertMatch(#{id := {D, 2}}, at({D, {21, 59, 59}}, Three)),
     ?_assertMatch(#{id := {D, 3}, 'end' := {{2024, 5, 2}, {6, 0, 0}}},
                   at({D, {22, 0, 0}}, Three)),
     ?_assertMatch(#{id := {D, 3}}, at({D, {23, 59, 59}}, Three)),
     ?_assertMatch(#{id := {{2024, 4, 30}, 3}}, at({D, {0, 0, 0}}, Three)),
     %% One shift a day, from midnight.
     ?_assertMatch(#{id := {D, 1}, start := {D, {0, 0, 0}}, 'end' := {{2024, 5, 2}, {0, 0, 0}}},
                   at({D, {12, 0, 0}}, [0])),
     %% Month and year ends.
     ?_assertMatch(#{id := {{2023, 12, 31}, 1}}, at({{2024, 1, 1}, {3, 0, 0}}, [360])),
     ?_assertEqual(<<"2024-05-01/3">>, label({D, 3})),
     ?_assertEqual([<<"06:00">>, <<"22:30">>], starts_text([360, 1350]))].
-endif.
