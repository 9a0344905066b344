%% @doc The brake on guessed passwords, as pure decisions on explicit times (the
%% sessions process holds the state and gives the clock).
%%
%% Failed logins are counted twice: for the pair of address and account, and for the
%% address as a whole. The tenth failure of a pair (the twentieth of an address)
%% opens a refusal window; every failure after it opens one twice as long as the one
%% before, up to a cap (an hour for a pair, a minute for an address). A login is
%% refused while a window of its pair, or of its address, is open, before the password
%% is checked (so a refusal tells nothing about the password).
%%
%% A success clears only its own pair: another user's login never helps a guesser. An
%% account that has logged in from an address is known there: the address's window
%% does not hold it back, so a guesser at a shared address never locks its known
%% users out; only the guessed account waits (its own pair). Counts are forgotten a
%% day after their last failure, known accounts after a week.
-module(cell_web_throttle).

-export([new/0, check/4, failed/4, succeeded/4, sweep/2, entries/1]).

-export_type([state/0]).

-type ms() :: integer().
-type count() :: #{failures := pos_integer(), last := ms(), until := ms()}.
-opaque state() :: #{{pair, binary(), binary()} | {address, binary()} => count(),
                     {known, binary(), binary()} => ms()}.

%% {the failure that opens the first window, first window, longest window}
-define(PAIR, {10, 60000, 3600000}).
-define(ADDRESS, {20, 1000, 60000}).
-define(FORGET_MS, 86400000).
-define(KNOWN_MS, 7 * 86400000).

-spec new() -> state().
new() -> #{}.

%% @doc Whether a login of `Name' from `Addr' may be tried at `Now', or how many
%% milliseconds it must wait.
-spec check(binary(), binary(), ms(), state()) -> ok | {wait, pos_integer()}.
check(Addr, Name, Now, S) ->
    Pair = wait({pair, Addr, Name}, Now, S),
    Address = case maps:is_key({known, Addr, Name}, S) of
                  true -> 0;
                  false -> wait({address, Addr}, Now, S)
              end,
    case max(Pair, Address) of
        0 -> ok;
        Ms -> {wait, Ms}
    end.

%% @doc A wrong name or password was given.
-spec failed(binary(), binary(), ms(), state()) -> state().
failed(Addr, Name, Now, S) ->
    count({address, Addr}, ?ADDRESS, Now, count({pair, Addr, Name}, ?PAIR, Now, S)).

%% @doc `Name' logged in from `Addr': its pair starts afresh and it is known there.
-spec succeeded(binary(), binary(), ms(), state()) -> state().
succeeded(Addr, Name, Now, S) ->
    (maps:remove({pair, Addr, Name}, S))#{{known, Addr, Name} => Now}.

%% @doc Forgets what is old.
-spec sweep(ms(), state()) -> state().
sweep(Now, S) ->
    maps:filter(fun({known, _, _}, Since) -> Now - Since < ?KNOWN_MS;
                   (_, #{last := Last}) -> Now - Last < ?FORGET_MS
                end, S).

%% @doc How many entries are held.
-spec entries(state()) -> non_neg_integer().
entries(S) -> map_size(S).

wait(Key, Now, S) ->
    case S of
        #{Key := #{until := Until}} when Until > Now -> Until - Now;
        _ -> 0
    end.

count(Key, {Opens, First, Longest}, Now, S) ->
    N = case S of
            #{Key := #{failures := F, last := Last}} when Now - Last < ?FORGET_MS -> F + 1;
            _ -> 1
        end,
    Until = case N >= Opens of
                true -> Now + min(Longest, First bsl min(N - Opens, 32));
                false -> Now
            end,
    S#{Key => #{failures => N, last => Now, until => Until}}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

fail_n(Addr, Name, N, Now, S) ->
    lists:foldl(fun(_, Acc) -> failed(Addr, Name, Now, Acc) end, S, lists:seq(1, N)).

pair_windows_double_up_to_the_cap_test() ->
    S9 = fail_n(<<"a">>, <<"admin">>, 9, 0, new()),
    ?assertEqual(ok, check(<<"a">>, <<"admin">>, 0, S9)),
    S10 = failed(<<"a">>, <<"admin">>, 0, S9),
    ?assertEqual({wait, 60000}, check(<<"a">>, <<"admin">>, 0, S10)),
    ?assertEqual({wait, 1}, check(<<"a">>, <<"admin">>, 59999, S10)),
    ?assertEqual(ok, check(<<"a">>, <<"admin">>, 60000, S10)),
    S11 = failed(<<"a">>, <<"admin">>, 60000, S10),
    ?assertEqual({wait, 120000}, check(<<"a">>, <<"admin">>, 60000, S11)),
    S40 = fail_n(<<"a">>, <<"admin">>, 28, 60000, S11),
    ?assertEqual({wait, 3600000}, check(<<"a">>, <<"admin">>, 60000, S40)).

another_users_success_does_not_reset_test() ->
    S = fail_n(<<"a">>, <<"admin">>, 10, 0, new()),
    S1 = succeeded(<<"a">>, <<"operator">>, 0, S),
    ?assertMatch({wait, _}, check(<<"a">>, <<"admin">>, 0, S1)),
    ?assertEqual(ok, check(<<"a">>, <<"operator">>, 0, S1)),
    %% Its own success clears the pair.
    ?assertEqual(ok, check(<<"a">>, <<"admin">>, 0, succeeded(<<"a">>, <<"admin">>, 0, S1))).

address_brakes_unknown_accounts_only_test() ->
    Names = [integer_to_binary(I) || I <- lists:seq(1, 20)],
    S0 = succeeded(<<"a">>, <<"operator">>, 0, new()),
    S = lists:foldl(fun(N, Acc) -> failed(<<"a">>, N, 0, Acc) end, S0, Names),
    ?assertEqual({wait, 1000}, check(<<"a">>, <<"someone">>, 0, S)),
    ?assertEqual(ok, check(<<"a">>, <<"someone">>, 1000, S)),
    ?assertEqual(ok, check(<<"a">>, <<"operator">>, 0, S)),
    ?assertEqual(ok, check(<<"b">>, <<"someone">>, 0, S)),
    S21 = failed(<<"a">>, <<"x">>, 0, S),
    ?assertEqual({wait, 2000}, check(<<"a">>, <<"someone">>, 0, S21)),
    S40 = fail_n(<<"a">>, <<"y">>, 20, 0, S21),
    ?assertEqual({wait, 60000}, check(<<"a">>, <<"someone">>, 0, S40)).

free_failures_test() ->
    S9 = fail_n(<<"a">>, <<"admin">>, 9, 0, new()),
    ?assertEqual(ok, check(<<"a">>, <<"admin">>, 0, S9)),
    S19 = lists:foldl(fun(I, Acc) -> failed(<<"a">>, integer_to_binary(I), 0, Acc) end,
                      S9, lists:seq(1, 10)),
    ?assertMatch({wait, _}, check(<<"a">>, <<"other">>, 0, failed(<<"a">>, <<"z">>, 0, S19))),
    ?assertEqual(ok, check(<<"a">>, <<"other">>, 0, S19)).

forgotten_after_a_day_test() ->
    S = fail_n(<<"a">>, <<"admin">>, 12, 0, succeeded(<<"a">>, <<"op">>, 0, new())),
    Day = 86400000,
    ?assertEqual(3, entries(S)),
    ?assertEqual(1, entries(sweep(Day, S))),
    ?assertEqual(0, entries(sweep(7 * Day, S))),
    %% A failure after a quiet day counts as the first again.
    S1 = failed(<<"a">>, <<"admin">>, Day, S),
    ?assertEqual(ok, check(<<"a">>, <<"admin">>, Day, S1)).
-endif.
