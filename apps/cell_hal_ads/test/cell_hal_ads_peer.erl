%% Test peers written by others, run as OS processes: pyads' test server, Beckhoff's
%% AdsLib through pyads, and the suite's fake PLC (test/peers/*.py). A peer takes one
%% command a line and answers one Erlang term a line; `{notification, ...}' lines are
%% events and go to the process that called listen/1.
%%
%% The port is owned by this gen_server, started without a link, so a peer outlives
%% the common_test process that started it (init_per_suite, a test case) until stop/1.
-module(cell_hal_ads_peer).
-behaviour(gen_server).

-export([start/2, start/3, stop/1, cmd/2, cmd/3, ready/1, listen/1, os_pid/1]).
-export([top/0, python/0, script/1, await/2, await_event/2]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2, terminate/2]).

-define(START_TIMEOUT, 60000).
-define(CMD_TIMEOUT, 30000).

%% @doc Starts `test/peers/Script' with the project's Python; waits for its ready line.
start(Script, Args) ->
    start(Script, Args, ?START_TIMEOUT).

start(Script, Args, Timeout) ->
    Python = python(),
    case filelib:is_regular(Python) of
        false ->
            {error, {no_python, Python, "run `scripts/setup test` to create _pyenv/"}};
        true ->
            {ok, Pid} = gen_server:start(?MODULE, {Python, [script(Script) | Args]}, []),
            case catch gen_server:call(Pid, ready, Timeout) of
                {ok, Ready} ->
                    {ok, Pid, Ready};
                Other ->
                    stop(Pid),
                    {error, {peer_not_ready, Script, Other}}
            end
    end.

%% @doc Stops a peer: closes its stdin (it quits), then kills it by its OS pid if it
%% is still there.
stop(Pid) ->
    case is_process_alive(Pid) of
        true -> gen_server:call(Pid, stop, ?CMD_TIMEOUT);
        false -> ok
    end.

%% @doc One command, its answer.
cmd(Pid, Line) ->
    cmd(Pid, Line, ?CMD_TIMEOUT).

cmd(Pid, Line, Timeout) ->
    gen_server:call(Pid, {cmd, iolist_to_binary(Line)}, Timeout).

ready(Pid) ->
    gen_server:call(Pid, ready).

%% @doc The caller gets `{peer_event, Pid, Term}' for every event line from now on.
listen(Pid) ->
    gen_server:call(Pid, {listen, self()}).

os_pid(Pid) ->
    gen_server:call(Pid, os_pid).

%% @doc The project folder: $CELLRT_TOP (set by the Makefile and scripts/test), else
%% derived from this file's path, which rebar3 copies under _build/.
top() ->
    case os:getenv("CELLRT_TOP") of
        false ->
            case string:split(?FILE, "/_build/") of
                [Top, _] -> Top;
                [_] -> filename:dirname(filename:dirname(filename:dirname(
                                                           filename:dirname(?FILE))))
            end;
        Top ->
            Top
    end.

python() ->
    filename:join([top(), "_pyenv", "bin", "python"]).

script(Name) ->
    filename:join([top(), "apps", "cell_hal_ads", "test", "peers", Name]).

%% @doc Waits for a message matching `Fun' (returning `{true, Result}' or `false') until
%% `Timeout' ms; other messages stay in the mailbox.
await(Fun, Timeout) ->
    Deadline = erlang:monotonic_time(millisecond) + Timeout,
    await_loop(Fun, Deadline, []).

await_loop(Fun, Deadline, Skipped) ->
    Left = max(0, Deadline - erlang:monotonic_time(millisecond)),
    receive
        Msg ->
            case Fun(Msg) of
                {true, Result} ->
                    [self() ! M || M <- lists:reverse(Skipped)],
                    {ok, Result};
                false ->
                    await_loop(Fun, Deadline, [Msg | Skipped])
            end
    after Left ->
            [self() ! M || M <- lists:reverse(Skipped)],
            {error, timeout}
    end.

%% @doc The next event of a peer matching `Fun'.
await_event(Fun, Timeout) ->
    await(fun({peer_event, _, Term}) -> Fun(Term);
             (_) -> false
          end, Timeout).

%% gen_server

init({Python, Args}) ->
    Port = open_port({spawn_executable, Python},
                     [{args, Args}, {line, 1 bsl 20}, binary, exit_status, use_stdio]),
    {ok, #{port => Port, partial => <<>>, ready => undefined, waiting_ready => [],
           pending => queue:new(), listener => undefined, exited => false}}.

handle_call(ready, From, #{ready := undefined, waiting_ready := W} = S) ->
    {noreply, S#{waiting_ready := [From | W]}};
handle_call(ready, _From, #{ready := Ready} = S) ->
    {reply, {ok, Ready}, S};
handle_call({cmd, _}, _From, #{exited := true} = S) ->
    {reply, {error, peer_exited}, S};
handle_call({cmd, Line}, From, #{port := Port, pending := P} = S) ->
    true = port_command(Port, [Line, $\n]),
    {noreply, S#{pending := queue:in(From, P)}};
handle_call({listen, Pid}, _From, S) ->
    {reply, ok, S#{listener := Pid}};
handle_call(os_pid, _From, #{port := Port} = S) ->
    {reply, proplists:get_value(os_pid, erlang:port_info(Port)), S};
handle_call(stop, _From, S) ->
    {stop, normal, ok, S}.

handle_cast(_, S) ->
    {noreply, S}.

handle_info({Port, {data, {noeol, Part}}}, #{port := Port, partial := Acc} = S) ->
    {noreply, S#{partial := <<Acc/binary, Part/binary>>}};
handle_info({Port, {data, {eol, Part}}}, #{port := Port, partial := Acc} = S) ->
    {noreply, line(<<Acc/binary, Part/binary>>, S#{partial := <<>>})};
handle_info({Port, {exit_status, Status}}, #{port := Port, pending := P} = S) ->
    [gen_server:reply(From, {error, {peer_exited, Status}}) || From <- queue:to_list(P)],
    [gen_server:reply(From, {error, {peer_exited, Status}}) || From <- maps:get(waiting_ready, S)],
    {noreply, S#{exited := true, pending := queue:new(), waiting_ready := []}};
handle_info(_, S) ->
    {noreply, S}.

terminate(_, #{exited := true}) ->
    ok;
terminate(_, #{port := Port}) ->
    %% A peer quits on `quit'; one stuck in a call is killed by its OS pid.
    OsPid = proplists:get_value(os_pid, erlang:port_info(Port)),
    catch port_command(Port, <<"quit\n">>),
    receive
        {Port, {exit_status, _}} -> ok
    after 5000 ->
            _ = os:cmd("kill -9 " ++ integer_to_list(OsPid)),
            catch port_close(Port),
            ok
    end.

line(Bin, S) ->
    case parse(Bin) of
        {ok, Term} when element(1, Term) =:= notification, tuple_size(Term) > 1 ->
            case S of
                #{listener := Pid} when is_pid(Pid) -> Pid ! {peer_event, self(), Term};
                _ -> ok
            end,
            S;
        {ok, Term} when element(1, Term) =:= ready, tuple_size(Term) > 1,
                        map_get(ready, S) =:= undefined ->
            [gen_server:reply(From, {ok, Term}) || From <- maps:get(waiting_ready, S)],
            S#{ready := Term, waiting_ready := []};
        {ok, Term} ->
            reply(Term, S);
        {error, _} ->
            %% A line that is not a term (a library's own print): not an answer.
            ct:log("peer said: ~ts", [Bin]),
            S
    end.

reply(Term, #{pending := P} = S) ->
    case queue:out(P) of
        {{value, From}, P1} ->
            gen_server:reply(From, Term),
            S#{pending := P1};
        {empty, _} ->
            ct:log("unexpected answer from a peer: ~tp", [Term]),
            S
    end.

parse(Bin) ->
    case erl_scan:string(binary_to_list(Bin) ++ ".") of
        {ok, Tokens, _} -> erl_parse:parse_term(Tokens);
        {error, E, _} -> {error, E}
    end.
