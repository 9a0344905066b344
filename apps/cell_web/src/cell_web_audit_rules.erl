%% @doc The audit trail's pure decisions: which refused anonymous requests are written
%% and which are only counted, how long a field may be, how the files of a day are
%% named, and which files are old enough to go.
%%
%% Refused requests of callers who are not logged in cost an attacker nothing, so they
%% must not cost the trail a synced line each: the first one of an address is written
%% as it comes; the ones after it, until the interval ends (the audit process keeps
%% the clock), are counted, and the count is written as one line when it ends. Beyond
%% `max_addresses' addresses in one interval, the others are counted together under
%% the address `others'.
-module(cell_web_audit_rules).

-export([new/1, refused/2, flush/2, clip/2, file_name/2, parse_name/1, expired/3]).

-export_type([refusals/0]).

-opaque refusals() :: #{max := pos_integer(),
                        counts := #{binary() => {non_neg_integer(), map()}}}.

-define(OTHERS, <<"others">>).

%% @doc No refusal counted yet; at most `Max' addresses followed one by one.
-spec new(pos_integer()) -> refusals().
new(Max) -> #{max => Max, counts => #{}}.

%% @doc A refused anonymous request: `write' it now, or it is only `counted'.
-spec refused(#{address := binary(), atom() => term()}, refusals()) ->
          {write | counted, refusals()}.
refused(#{address := Addr} = Entry, #{max := Max, counts := Counts} = R) ->
    case Counts of
        #{Addr := {N, First}} ->
            {counted, R#{counts := Counts#{Addr := {N + 1, First}}}};
        #{} when map_size(Counts) < Max ->
            {write, R#{counts := Counts#{Addr => {0, Entry}}}};
        #{?OTHERS := {N, First}} ->
            {counted, R#{counts := Counts#{?OTHERS := {N + 1, First}}}};
        #{} ->
            {counted, R#{counts := Counts#{?OTHERS => {1, Entry#{address := ?OTHERS}}}}}
    end.

%% @doc The interval of `Seconds' is over: the lines for what was only counted (each
%% the first request of its address, with the count in `detail'), and a fresh count.
-spec flush(pos_integer(), refusals()) -> {[map()], refusals()}.
flush(Seconds, #{counts := Counts} = R) ->
    Lines = [First#{detail => iolist_to_binary(
                                [integer_to_binary(N), " more refused requests from ",
                                 address_words(A), " in ", integer_to_binary(Seconds),
                                 " s, counted, not written one by one; the first: ",
                                 maps:get(detail, First, <<>>)])}
             || {A, {N, First}} <- lists:sort(maps:to_list(Counts)), N > 0],
    {Lines, R#{counts := #{}}}.

address_words(?OTHERS) -> "further addresses";
address_words(_) -> "this address".

%% @doc A field cut to at most `Max' bytes, marked `...' when cut, never splitting a
%% UTF-8 character.
-spec clip(binary(), pos_integer()) -> binary().
clip(Bin, Max) when byte_size(Bin) =< Max -> Bin;
clip(Bin, Max) ->
    Head = binary:part(Bin, 0, Max - 3),
    Whole = case unicode:characters_to_binary(Head) of
                B when is_binary(B) -> B;
                {incomplete, Good, _} -> Good;
                {error, _, _} -> Head         %% not UTF-8 anyway: the bytes as they are
            end,
    <<Whole/binary, "...">>.

%% @doc The file of a day's part: part 1 is `audit 2026-11-21.jsonl', the parts after
%% it (when a day's file reaches its size limit) `audit 2026-11-21 (2).jsonl'.
-spec file_name(calendar:date(), pos_integer()) -> string().
file_name({Y, M, D}, 1) ->
    lists:flatten(io_lib:format("audit ~4..0w-~2..0w-~2..0w.jsonl", [Y, M, D]));
file_name({Y, M, D}, Part) ->
    lists:flatten(io_lib:format("audit ~4..0w-~2..0w-~2..0w (~w).jsonl", [Y, M, D, Part])).

%% @doc The day and part of an audit file's name, or `error' for any other file.
-spec parse_name(string()) -> {ok, calendar:date(), pos_integer()} | error.
parse_name(Name) ->
    case io_lib:fread("audit ~4d-~2d-~2d", Name) of
        {ok, [Y, M, D], Rest} ->
            Part = case Rest of
                       ".jsonl" -> 1;
                       " (" ++ More ->
                           case string:to_integer(More) of
                               {P, ").jsonl"} when is_integer(P), P > 1 -> P;
                               _ -> error
                           end;
                       _ -> error
                   end,
            case Part =/= error andalso calendar:valid_date(Y, M, D) of
                true -> {ok, {Y, M, D}, Part};
                false -> error
            end;
        _ ->
            error
    end.

%% @doc The audit files among `Names' older than `KeepDays' days before `Today'.
-spec expired([string()], calendar:date(), pos_integer()) -> [string()].
expired(Names, Today, KeepDays) ->
    Oldest = calendar:date_to_gregorian_days(Today) - KeepDays,
    [N || N <- Names, {ok, Date, _} <- [parse_name(N)],
          calendar:date_to_gregorian_days(Date) < Oldest].

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

e(Addr, Target) ->
    #{address => Addr, target => Target, detail => <<"log in first">>}.

refused_test() ->
    R0 = new(2),
    {write, R1} = refused(e(<<"a">>, <<"/x">>), R0),
    {counted, R2} = refused(e(<<"a">>, <<"/y">>), R1),
    {counted, R3} = refused(e(<<"a">>, <<"/z">>), R2),
    {write, R4} = refused(e(<<"b">>, <<"/x">>), R3),
    %% Beyond two addresses, the others are counted together.
    {counted, R5} = refused(e(<<"c">>, <<"/c">>), R4),
    {counted, R6} = refused(e(<<"d">>, <<"/d">>), R5),
    {Lines, R7} = flush(60, R6),
    ?assertMatch([#{address := <<"a">>, target := <<"/x">>},
                  #{address := <<"others">>, target := <<"/c">>}], Lines),
    [#{detail := D1}, #{detail := D2}] = Lines,
    ?assertMatch(<<"2 more refused requests from this address in 60 s", _/binary>>, D1),
    ?assertMatch(<<"2 more refused requests from further addresses", _/binary>>, D2),
    %% A new interval writes the first again.
    ?assertEqual({[], R7}, flush(60, R7)),
    ?assertMatch({write, _}, refused(e(<<"a">>, <<"/x">>), R7)).

clip_test() ->
    ?assertEqual(<<"abc">>, clip(<<"abc">>, 3)),
    ?assertEqual(<<"ab...">>, clip(<<"abcdef">>, 5)),
    %% "é" is two bytes: never cut in half.
    ?assertEqual(<<"a...">>, clip(<<"aébcdef"/utf8>>, 5)),
    ?assertEqual(200, byte_size(clip(binary:copy(<<"x">>, 2048), 200))).

file_names_test() ->
    ?assertEqual("audit 2026-01-02.jsonl", file_name({2026, 1, 2}, 1)),
    ?assertEqual("audit 2026-01-02 (3).jsonl", file_name({2026, 1, 2}, 3)),
    ?assertEqual({ok, {2026, 1, 2}, 1}, parse_name("audit 2026-01-02.jsonl")),
    ?assertEqual({ok, {2026, 1, 2}, 3}, parse_name("audit 2026-01-02 (3).jsonl")),
    [?assertEqual(error, parse_name(N))
     || N <- ["audit 2026-13-02.jsonl", "audit 2026-01-02 (1).jsonl", "audit 2026-01-02.txt",
              "audit 2026-01-02 (x).jsonl", "task 2026-01-02.log", "audit"]].

expired_test() ->
    Names = ["audit 2026-01-01.jsonl", "audit 2026-01-01 (2).jsonl", "audit 2026-01-02.jsonl",
             "audit 2026-01-31.jsonl", "tasks 2025-01-01.log"],
    ?assertEqual(["audit 2026-01-01.jsonl", "audit 2026-01-01 (2).jsonl"],
                 expired(Names, {2026, 1, 31}, 29)),
    ?assertEqual([], expired(Names, {2026, 1, 31}, 30)).
-endif.
