%% @doc A code reader wired through the PLC's IO, as industrial readers often are: the
%% PLC triggers it and maps its answer into the image. Built in as type `io' of the
%% kind `code_reader' ({@link cell_hal_code_reader}); any cell can wire one.
%%
%% The points, all in one IO group of the cell (options name the group and, when they
%% differ from these defaults, the points):
%% <ul>
%% <li>`trigger' (output, bool): on to read, off once the answer is taken;</li>
%% <li>`done' (input, bool): the reader answered the trigger; it falls when the
%%   trigger does;</li>
%% <li>`no_read' (input, bool; `none' if the reader has none): the answer is that no
%%   code was found (an empty result says the same);</li>
%% <li>`result' (input, string): the code read;</li>
%% <li>`count' (input, an integer type; `none' if the reader has none): the reader's
%%   read counter, one up with each answer. With it an answer is taken only once the
%%   counter moved past the value it had at the trigger, so a result read from the
%%   PLC a poll before its counter is never paired with the wrong trigger.</li>
%% </ul>
%%
%% A read: `done' is waited for to be off (the previous answer cleared), the trigger
%% set, `done' (and the counter moving) waited for, the result read, the trigger
%% cleared. Every wait is a HAL watch; nothing polls. A read not answered within
%% `deadline_ms' (default 2000) is `{error, timeout}', the trigger cleared; the late
%% answer is never taken for the next read, which waits for `done' to fall first.
%%
%% The object is up while its connection is up and down while it is down; a read in
%% progress when the connection goes is `{error, not_connected}'. Whenever the
%% connection comes (back), the trigger is written off first: a trigger a crashed
%% predecessor left on ends there, and its answer is never taken.
%%
%% ```
%% #{id => reader, kind => code_reader, type => io,
%%   opts => #{group => reader_io, count => read_count, deadline_ms => 1500}}
%% '''
-module(cell_hal_code_reader_io).
-behaviour(cell_hal_code_reader).

-export([check_opts/1, init/2, read/1, handle_call/2, handle_info/2]).
-export([answer/2, counted/2]).

-define(ROLES, [trigger, done, no_read, result, count]).
-define(INTEGERS, [byte, sbyte, int16, uint16, int32, uint32, int64, uint64]).

-record(s, {id :: atom(),
            group :: atom(),
            conn :: atom(),
            points :: #{atom() => atom() | none},
            deadline_ms :: pos_integer(),
            link = down :: up | down,
            back :: reference() | undefined,          %% waiting for the HAL's server
            %% idle | settling: done to fall before the trigger | reading: done to rise
            %% | counting: the counter to move
            phase = idle :: idle | settling | reading | counting,
            watch :: reference() | undefined,
            timer :: reference() | undefined,
            count0 :: integer() | undefined}).

%%====================================================================
%% Pure: what an answer means
%%====================================================================

%% @doc The read's outcome from the reader's no-read bit (`undefined' for a reader
%% without one) and result string.
-spec answer(boolean() | undefined, binary()) -> {ok, binary()} | {error, no_read}.
answer(true, _) -> {error, no_read};
answer(_, <<>>) -> {error, no_read};
answer(_, Code) when is_binary(Code) -> {ok, Code}.

%% @doc Whether the counter moved past its value at the trigger (`undefined': the
%% reader has no counter, the done bit alone pairs the answer).
-spec counted(integer() | undefined, integer() | undefined) -> boolean().
counted(undefined, _) -> true;
counted(Count0, Count) -> Count =/= Count0.

%%====================================================================
%% cell_hal_code_reader
%%====================================================================

%% @private
-spec check_opts(map()) -> {ok, map()} | {error, {bad_option, atom()}}.
check_opts(Opts) ->
    Name = fun(V) -> is_atom(V) andalso V =/= undefined end,
    Optional = fun(V) -> is_atom(V) andalso V =/= undefined end,
    case cell_hal_hw:check_opts(Opts, #{group => {undefined, Name},
                                        trigger => {trigger, Name}, done => {done, Name},
                                        no_read => {no_read, Optional},
                                        result => {result, Name}, count => {none, Optional},
                                        deadline_ms => {2000, fun(V) -> is_integer(V) andalso
                                                                            V > 0 end}}) of
        {ok, #{group := undefined}} -> {error, {bad_option, group}};
        {ok, #{trigger := none}} -> {error, {bad_option, trigger}};
        {ok, #{done := none}} -> {error, {bad_option, done}};
        {ok, #{result := none}} -> {error, {bad_option, result}};
        Checked -> Checked
    end.

%% The group and its points are checked here, against the HAL's configuration (the
%% monitor adds the groups before the hardware objects); the connection is attached
%% from the object's first message.
%% @private
-spec init(atom(), map()) -> {ok, #s{}, down} | {error, term()}.
init(Id, #{group := Group, deadline_ms := Deadline} = Opts) ->
    Points = maps:with(?ROLES, Opts),
    case cell_hal:connection_of(Group) of
        {ok, Conn} ->
            case check_points(Group, Points) of
                ok ->
                    self() ! {?MODULE, attach},
                    {ok, #s{id = Id, group = Group, conn = Conn, points = Points,
                            deadline_ms = Deadline}, down};
                {error, _} = Error ->
                    Error
            end;
        {error, unknown_group} ->
            {error, {unknown_group, Group}}
    end.

check_points(Group, Points) ->
    Bad = [{Role, P} || {Role, P} <- lists:sort(maps:to_list(Points)), P =/= none,
                        not fits(Role, cell_hal:describe(Group, P))],
    case Bad of
        [] -> ok;
        [{Role, P} | _] -> {error, {bad_point, Role, P}}
    end.

fits(trigger, {ok, #{dir := out, type := bool}}) -> true;
fits(done, {ok, #{dir := in, type := bool}}) -> true;
fits(no_read, {ok, #{dir := in, type := bool}}) -> true;
fits(result, {ok, #{dir := in, type := {string, _}}}) -> true;
fits(count, {ok, #{dir := in, type := T}}) -> lists:member(T, ?INTEGERS);
fits(_, _) -> false.

%% @private
-spec read(#s{}) -> {reply, {error, term()}, #s{}} | {noreply, #s{}}.
read(#s{link = down} = S) ->
    {reply, {error, not_connected}, S};
read(#s{deadline_ms = Ms} = S) ->
    Timer = erlang:start_timer(Ms, self(), {?MODULE, deadline}),
    case point(done, S) of
        {ok, false} -> trigger(S#s{timer = Timer});
        %% The last answer not yet cleared, or the inputs not yet read since the
        %% connection came back: done watched until it is off.
        _ -> wait(done, {eq, false}, settling, S#s{timer = Timer})
    end.

%% @private
-spec handle_call(term(), #s{}) -> no_return().
handle_call(Request, _S) ->
    erlang:error({unexpected_call, Request}).

%% @private
-spec handle_info(term(), #s{}) -> {noreply, #s{}} | {reply, term(), #s{}}.
handle_info({?MODULE, attach}, S) ->
    attach(S);
handle_info({cell_hal_back, Ref}, #s{back = Ref} = S) ->
    attach(S#s{back = undefined});
handle_info({cell_hal_conn, Conn, Link}, #s{conn = Conn} = S) ->
    connection(Link, S);
handle_info({cell_hal_watch, Ref, _}, #s{watch = Ref, phase = settling} = S) ->
    trigger(S#s{watch = undefined});
handle_info({cell_hal_watch, Ref, _}, #s{watch = Ref, phase = reading} = S) ->
    case counted(S#s.count0, count(S)) of
        true -> finish(S#s{watch = undefined});
        false -> wait(count, {ne, S#s.count0}, counting, S#s{watch = undefined})
    end;
handle_info({cell_hal_watch, Ref, _}, #s{watch = Ref, phase = counting} = S) ->
    finish(S#s{watch = undefined});
handle_info({cell_hal_unavailable, Ref, Why}, #s{watch = Ref} = S) ->
    fail({unavailable, Why}, S#s{watch = undefined});
handle_info({timeout, Ref, {?MODULE, deadline}}, #s{timer = Ref, id = Id} = S) ->
    cell_log:warning(Id, "the code reader ~s did not answer within ~b ms", [Id, S#s.deadline_ms]),
    fail(timeout, S#s{timer = undefined});
handle_info(_Stale, S) ->
    %% A watch cancelled after it fired, a deadline that lost the race to an answer,
    %% a message the HAL's server repeats: over.
    {noreply, S}.

%%====================================================================
%% The connection
%%====================================================================

attach(#s{conn = Conn, id = Id} = S) ->
    case cell_hal:subscribe_connection(Conn) of
        {ok, Link} ->
            connection(Link, S);
        {error, disconnected} ->
            %% The HAL's server restarts: asked again once it is back.
            {noreply, S#s{back = cell_hal:notify_back()}};
        {error, unknown_connection} ->
            cell_log:error(Id, "the code reader ~s: its connection ~s is not configured",
                           [Id, Conn]),
            {noreply, S}
    end.

connection(up, #s{link = up} = S) ->
    {noreply, S};
connection(up, S) ->
    %% A trigger left on (by a predecessor that crashed mid-read) ends here.
    _ = write(false, S),
    ok = cell_hal_hw:set_status(up),
    {noreply, S#s{link = up}};
connection(down, #s{link = down} = S) ->
    {noreply, S};
connection(down, #s{phase = idle} = S) ->
    ok = cell_hal_hw:set_status(down),
    {noreply, S#s{link = down}};
connection(down, S) ->
    ok = cell_hal_hw:set_status(down),
    {reply, {error, not_connected}, idle(S#s{link = down})}.

%%====================================================================
%% A read
%%====================================================================

trigger(S) ->
    Count0 = case S#s.points of
                 #{count := none} -> undefined;
                 #{} -> count(S)
             end,
    case write(true, S) of
        ok -> wait(done, {eq, true}, reading, S#s{count0 = Count0});
        {error, Why} -> fail(Why, S)
    end.

finish(S) ->
    NoRead = case point(no_read, S) of
                 {ok, B} -> B;
                 {error, _} -> undefined
             end,
    case point(result, S) of
        {ok, Code} -> {reply, answer(NoRead, Code), idle(S)};
        {error, Why} -> fail(Why, S)
    end.

%% The HAL's `disconnected' (the connection went, or its server restarts) can come
%% before the connection's own news does: to the asker it is the same lost read.
fail(disconnected, S) ->
    {reply, {error, not_connected}, idle(S)};
fail(Why, S) ->
    {reply, {error, Why}, idle(S)}.

%% The read is over: its watch and deadline dropped, the trigger cleared.
idle(#s{watch = W, timer = T} = S) ->
    _ = [cell_hal:cancel_watch(W) || W =/= undefined],
    _ = [erlang:cancel_timer(T) || T =/= undefined],
    _ = S#s.link =:= up andalso write(false, S),
    S#s{phase = idle, watch = undefined, timer = undefined, count0 = undefined}.

wait(Role, Cond, Phase, #s{group = G, points = Points} = S) ->
    case cell_hal:watch(G, maps:get(Role, Points), Cond) of
        {ok, Ref} -> {noreply, S#s{watch = Ref, phase = Phase}};
        {error, Why} -> fail(Why, S)
    end.

write(V, #s{group = G, points = #{trigger := P}}) ->
    cell_hal:write(G, P, V).

point(Role, #s{group = G, points = Points}) ->
    case maps:get(Role, Points) of
        none -> {error, none};
        P -> cell_hal:read(G, P)
    end.

count(S) ->
    case point(count, S) of
        {ok, N} -> N;
        {error, _} -> undefined
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

answer_test() ->
    ?assertEqual({ok, <<"P1">>}, answer(false, <<"P1">>)),
    ?assertEqual({ok, <<"P1">>}, answer(undefined, <<"P1">>)),
    ?assertEqual({error, no_read}, answer(true, <<"P1">>)),
    ?assertEqual({error, no_read}, answer(false, <<>>)),
    ?assertEqual({error, no_read}, answer(undefined, <<>>)).

counted_test() ->
    ?assert(counted(undefined, 7)),
    ?assert(counted(undefined, undefined)),
    ?assertNot(counted(7, 7)),
    ?assert(counted(7, 8)),
    %% A counter that wrapped round moved too.
    ?assert(counted(65535, 0)).

check_opts_test() ->
    ?assertEqual({error, {bad_option, group}}, check_opts(#{})),
    ?assertMatch({ok, #{group := g, trigger := trigger, done := done, no_read := no_read,
                        result := result, count := none, deadline_ms := 2000}},
                 check_opts(#{group => g})),
    ?assertEqual({error, {bad_option, deadline_ms}}, check_opts(#{group => g, deadline_ms => 0})),
    ?assertEqual({error, {bad_option, trigger}}, check_opts(#{group => g, trigger => none})),
    ?assertEqual({error, {bad_option, result}}, check_opts(#{group => g, result => "r"})),
    ?assertEqual({error, {bad_option, colour}}, check_opts(#{group => g, colour => red})),
    ?assertMatch({ok, #{no_read := none, count := n}},
                 check_opts(#{group => g, no_read => none, count => n})).
-endif.
