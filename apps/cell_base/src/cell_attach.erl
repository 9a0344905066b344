%% @doc Staying attached to registered services that may restart: what a process does
%% that subscribes to a service it does not own (the cell's events, the log server).
%%
%% A subscription lives in the service's state and dies with it. Rather than stop with
%% the service (and make its own supervisor pay for a restart that was not its fault),
%% the subscriber monitors the service by name, and when the monitor fires it attaches
%% again: a timer with a backoff (10 ms doubling to 1 s) wakes it, it monitors and
%% subscribes anew, and resyncs whatever view it keeps. Nothing spins while the
%% service is away: one timer message per try.
%%
%% ```
%% attach(S) ->
%%     case cell_attach:watch([cell_events], fun() -> cell_events:subscribe() end) of
%%         {ok, Watch} -> resync(S#s{watch = Watch, backoff = cell_attach:first()});
%%         retry -> S#s{retry = cell_attach:retry_after(S#s.backoff)}
%%     end.
%% '''
%% The timer message is `{timeout, TRef, cell_attach}'.
-module(cell_attach).

-export([first/0, next/1, watch/2, unwatch/1, retry_after/1]).

-export_type([watch/0]).

-define(FIRST_MS, 10).
-define(MAX_MS, 1000).

%% Monitor references of the watched services, with their names.
-type watch() :: #{reference() => atom()}.

%% @doc The first delay after a service was lost, in milliseconds.
-spec first() -> pos_integer().
first() ->
    ?FIRST_MS.

%% @doc The delay after a try that failed: doubled, at most a second.
-spec next(pos_integer()) -> pos_integer().
next(Ms) when is_integer(Ms), Ms > 0 ->
    min(Ms * 2, ?MAX_MS).

%% @doc Monitors the services by name, then subscribes. `retry' when one of them is not
%% running (or stops during the subscription): nothing stays monitored then.
-spec watch([atom()], fun(() -> ok)) -> {ok, watch()} | retry.
watch(Names, Subscribe) ->
    Watch = maps:from_list([{monitor(process, N), N} || N <- Names]),
    try Subscribe() of
        ok -> {ok, Watch}
    catch
        %% The service was not there, or went while it was asked: try again later.
        exit:{Why, _} when Why =:= noproc; Why =:= normal; Why =:= shutdown;
                           Why =:= killed; element(1, Why) =:= shutdown ->
            ok = unwatch(Watch),
            retry
    end.

%% @doc Forgets the monitors (and any `DOWN' they already sent).
-spec unwatch(watch()) -> ok.
unwatch(Watch) ->
    _ = [demonitor(R, [flush]) || R <- maps:keys(Watch)],
    ok.

%% @doc Arms the timer for the next try, `{timeout, TRef, cell_attach}' to the caller.
-spec retry_after(pos_integer()) -> reference().
retry_after(Ms) ->
    erlang:start_timer(Ms, self(), cell_attach).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

backoff_test_() ->
    [?_assertEqual(10, first()),
     ?_assertEqual(20, next(10)),
     ?_assertEqual(1000, next(999)),
     ?_assertEqual(1000, next(500)),
     ?_assertEqual(1000, next(1000)),
     ?_assertError(function_clause, next(0))].

watch_test_() ->
    {setup,
     fun() ->
             Pid = spawn(fun() -> receive stop -> ok end end),
             true = register(cell_attach_test_service, Pid),
             Pid
     end,
     fun(Pid) -> Pid ! stop end,
     fun(_) ->
             [?_assertMatch({ok, #{}}, watch([cell_attach_test_service], fun() -> ok end)),
              %% A service not running: no monitor left behind, no DOWN in the mailbox.
              ?_test(begin
                         retry = watch([cell_attach_test_missing],
                                       fun() -> exit({noproc, {gen_server, call, []}}) end),
                         receive {'DOWN', _, _, _, _} = D -> error({left, D})
                         after 0 -> ok
                         end
                     end)]
     end}.
-endif.
