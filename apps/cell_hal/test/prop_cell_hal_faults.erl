%% A PropEr state-machine model of a HAL worker's single-point faults (the HAL's
%% contract in docs/architecture.md: "Single points a driver cannot serve", Waiting),
%% against a Modbus device of the project's codec (cell_hal_fake_modbus): the device
%% refuses the address of a point and answers it again, refuses every Nth request (as
%% in the suite's case where a worker once stopped polling), and its inputs change.
%%
%% The model: the device's inputs, which points it refuses, whether it refuses every
%% Nth request, the watches placed and how each may end. Checked: an input the device
%% changes is read by the HAL within a deadline while its address is answered (where
%% every Nth request is refused: read, or still asked, the polls never stopping); a
%% refused point reads
%% `{unavailable, Why}', its subscribers are told the fault and, once it is answered
%% again, that it is cleared and its value; the connection stays up throughout; each
%% watch ends exactly once, with its value once its condition held while the point was
%% usable, or with `{cell_hal_unavailable, Ref, Why}' once the point could not be read,
%% and never otherwise. Parallel runs race the device's side against the HAL's; at the
%% end the device answers everything again, every input reads its value, no watch ended
%% twice and the connection never went down.
-module(prop_cell_hal_faults).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([set_input/2, refuse/2, accept/1, fail_every/1, read/1, watch/2]).
-export([setup/0, cleanup/1, prop_sequential/0, prop_parallel/0]).

-define(WAIT, 5000).
-define(TAB, prop_cell_hal_faults).
-define(INPUTS, [int16_in, coil_in, discrete_in]).

-record(m, {values = #{int16_in => 0, coil_in => false, discrete_in => false} :: map(),
            refused = [] :: [atom()],
            every = 0 :: non_neg_integer(),
            watches = [] :: [{term(), atom(), term(), [none | fire | unavailable]}],
            mode = sequential :: sequential | parallel}).

faults_test_() ->
    {setup, fun setup/0, fun cleanup/1,
     fun(_) ->
             [{timeout, 600, ?_assert(proper:quickcheck(prop_sequential(),
                                                        [{to_file, user}, {numtests, 1000}]))},
              {timeout, 600, ?_assert(proper:quickcheck(prop_parallel(),
                                                        [{to_file, user}, {numtests, 1000}]))}]
     end}.

prop_sequential() ->
    ?FORALL(Cmds, commands(?MODULE),
            begin
                start_conn(),
                {History, State, Result} = run_commands(?MODULE, Cmds),
                Final = final_check(State),
                stop_conn(),
                ?WHENFAIL(io:format(user, "History: ~p~nState: ~p~nResult: ~p~nFinal: ~p~n",
                                    [History, State, Result, Final]),
                          aggregate(command_names(Cmds), Result =:= ok andalso Final =:= ok))
            end).

%% The device's side races the HAL's: each command acts; at the end the device answers
%% everything again, and every input reads the device's value, every watch ended at
%% most once and only with its own value.
prop_parallel() ->
    ?FORALL(Cmds, parallel_commands(?MODULE, #m{mode = parallel}),
            begin
                start_conn(parallel),
                {Seq, Par, Result} = run_parallel_commands(?MODULE, Cmds),
                Final = final_parallel(),
                stop_conn(),
                ?WHENFAIL(io:format(user, "Seq: ~p~nPar: ~p~nResult: ~p~nFinal: ~p~n",
                                    [Seq, Par, Result, Final]),
                          Result =:= ok andalso Final =:= ok)
            end).

%% -------------------------------------------------------------------------------------
%% The model
%% -------------------------------------------------------------------------------------

initial_state() -> #m{}.

value(int16_in) -> integer(0, 3);
value(_) -> boolean().

command(M) ->
    frequency([{6, ?LET(P, oneof(?INPUTS), {call, ?MODULE, set_input, [P, value(P)]})},
               {2, {call, ?MODULE, refuse, [oneof(?INPUTS), oneof([2, 4])]}},
               {3, {call, ?MODULE, accept, [oneof(?INPUTS)]}},
               {2, {call, ?MODULE, fail_every, [oneof([0, 0, 3, 5])]}},
               {3, {call, ?MODULE, read, [oneof(?INPUTS)]}},
               {3, ?LET(P, oneof(?INPUTS), {call, ?MODULE, watch, [P, value(P)]})}]
              ++ [{2, {call, ?MODULE, fail_every, [0]}} || M#m.every > 0]).

precondition(#m{mode = parallel}, _) -> true;
precondition(M, {call, _, refuse, [P, _]}) -> not lists:member(P, M#m.refused);
precondition(M, {call, _, accept, [P]}) -> lists:member(P, M#m.refused);
precondition(_, _) -> true.

%% Each watch carries the ways it may have ended so far: `none' (still open), `fire',
%% `unavailable'.
next_state(#m{mode = parallel} = M, _, _) -> M;
next_state(M, Res, Call) ->
    noise(next(M, Res, Call)).

next(M, _, {call, _, set_input, [P, V]}) ->
    holds(P, M#m{values = (M#m.values)#{P := V}});
next(M, _, {call, _, refuse, [P, _]}) ->
    %% A watch on a point that cannot be read ends with why.
    M#m{refused = [P | M#m.refused],
        watches = [case Q =:= P andalso lists:member(none, Ends) of
                       true -> {R, Q, V, [unavailable | Ends -- [none]]};
                       false -> W
                   end || {R, Q, V, Ends} = W <- M#m.watches]};
next(M, _, {call, _, accept, [P]}) ->
    holds(P, M#m{refused = M#m.refused -- [P]});
next(M, _, {call, _, fail_every, [N]}) ->
    M#m{every = N};
next(M, Ref, {call, _, watch, [P, V]}) ->
    Ends = case lists:member(P, M#m.refused) of
               true -> [unavailable];
               false -> [none]
           end,
    holds(P, M#m{watches = M#m.watches ++ [{Ref, P, V, Ends}]});
next(M, _, _) ->
    M.

%% Open watches whose condition holds on a point that is read fire.
holds(P, #m{values = Vs, refused = Refused, every = Every} = M) ->
    Fires = not lists:member(P, Refused),
    M#m{watches = [case Q =:= P andalso Fires andalso maps:get(P, Vs) =:= V
                            andalso lists:member(none, Ends) of
                       true when Every > 0 -> {R, Q, V, lists:usort([fire | Ends])};
                       true -> {R, Q, V, lists:usort([fire | Ends -- [none]])};
                       false -> W
                   end || {R, Q, V, Ends} = W <- M#m.watches]}.

%% Where every Nth request is refused, an open watch may meet its point unusable.
noise(#m{every = 0} = M) ->
    M;
noise(M) ->
    M#m{watches = [case lists:member(none, Ends) of
                       true -> {R, Q, V, lists:usort([unavailable | Ends])};
                       false -> W
                   end || {R, Q, V, Ends} = W <- M#m.watches]}.

postcondition(#m{mode = parallel}, _, Res) ->
    %% Nothing a command meets in a race is wrong by itself but a connection lost.
    Res =/= went_down;
postcondition(M, {call, _, set_input, [P, V]}, Res) ->
    case {lists:member(P, M#m.refused), M#m.every} of
        {true, _} -> match_unavailable(Res);
        {false, 0} -> Res =:= {ok, V};
        %% A device that refuses every Nth request may meet one request at the same
        %% place of the polls' cycle each time (the HAL rests a refused request, then
        %% asks it again): the HAL cannot promise that point's value, only that it goes
        %% on polling.
        {false, _} -> Res =:= {ok, V} orelse element(1, Res) =:= still_polling
    end andalso up();
postcondition(M, {call, _, refuse, _}, Res) ->
    %% Subscribers told, the point unreadable, the connection up. As for accept: where
    %% every Nth request is refused, the point's request may meet that refusal at each
    %% ask, so the subscribers are told the point's fault by that refusal (exception 6),
    %% now or already before this command, and never by its own (exception 2); the
    %% point is unreadable all the same.
    case Res of
        {told, Why, Read} ->
            is_binary(Why) andalso match_unavailable(Read) andalso up();
        {told_every_nth, Why, Read} when M#m.every > 0 ->
            every_nth(Why) andalso match_unavailable(Read) andalso up();
        {not_told, {error, {unavailable, Why}}} when M#m.every > 0 ->
            every_nth(Why) andalso up();
        _ ->
            false
    end;
postcondition(M, {call, _, accept, [P]}, Res) ->
    V = maps:get(P, M#m.values),
    case M#m.every of
        0 -> Res =:= {cleared, V};
        %% As for set_input: where every Nth request is refused, the point's request
        %% may meet that refusal at each ask, so its address answered again may still
        %% leave it unusable, by the every-Nth refusal now (exception 6) and not by its
        %% own (exception 2).
        _ -> Res =:= {cleared, V} orelse refused_every_nth(Res)
    end andalso up();
postcondition(M, {call, _, read, [P]}, Res) ->
    case {lists:member(P, M#m.refused), M#m.every} of
        {true, _} -> match_unavailable(Res);
        {false, 0} -> Res =:= {ok, maps:get(P, M#m.values)};
        {false, _} -> Res =:= {ok, maps:get(P, M#m.values)} orelse match_unavailable(Res)
    end;
postcondition(_, {call, _, watch, _}, Res) ->
    is_reference(Res);
postcondition(_, {call, _, fail_every, _}, Res) ->
    Res =:= ok.

refused_every_nth({not_cleared, {error, {unavailable, Why}}}) ->
    every_nth(Why);
refused_every_nth(_) ->
    false.

every_nth(Why) ->
    is_binary(Why) andalso binary:match(Why, <<"exception 6)">>) =/= nomatch.

match_unavailable({error, {unavailable, Why}}) -> is_binary(Why);
match_unavailable(_) -> false.

up() -> cell_hal:status(conn()) =:= up.

%% Each watch ended as its history allows, at most once; one still open is found so by
%% its cancel, unless the noise may have ended it.
final_check(#m{watches = Ws}) ->
    Msgs = drain(),
    Bad = lists:filtermap(
            fun({R, _P, V, Ends}) ->
                    Got = [case M of
                               {cell_hal_watch, R, V} -> fire;
                               {cell_hal_watch, R, Other} -> {wrong_value, Other};
                               {cell_hal_unavailable, R, _} -> unavailable
                           end || M <- Msgs, element(2, M) =:= R,
                                  element(1, M) =:= cell_hal_watch
                                      orelse element(1, M) =:= cell_hal_unavailable],
                    Open = cell_hal:cancel_watch(R),
                    Ok = case {Got, Open} of
                             {[], true} -> lists:member(none, Ends);
                             {[End], false} -> lists:member(End, Ends);
                             _ -> false
                         end,
                    case Ok of
                        true -> false;
                        %% With the messages themselves: an unavailable one says why.
                        false -> {true, {R, V, Ends, Got, Open,
                                         [M || M <- Msgs, is_tuple(M), tuple_size(M) > 1,
                                               element(2, M) =:= R]}}
                    end
            end, Ws),
    case Bad of
        [] -> ok;
        _ -> {watches, Bad}
    end.

%% -------------------------------------------------------------------------------------
%% Commands
%% -------------------------------------------------------------------------------------

%% The device changes an input; while its point is answered the HAL reads the new
%% value within the deadline, whatever else the device refuses.
set_input(P, V) ->
    ok = cell_hal_fake_modbus:set(dev(), address(P), word(V)),
    case mode() =:= parallel orelse lists:member(P, refused()) of
        true -> cell_hal:read(io, P);
        false -> await(P, V, erlang:monotonic_time(millisecond) + ?WAIT)
    end.

refuse(P, Code) ->
    {T, A} = address(P),
    case mode() of
        parallel -> refuse_now(T, A, Code);
        sequential -> refuse_and_wait(P, T, A, Code)
    end.

refuse_now(T, A, Code) ->
    cell_hal_fake_modbus:refuse(dev(), T, A, Code).

refuse_and_wait(P, T, A, Code) ->
    true = ets:insert(?TAB, {refused, [P | refused()]}),
    Key = {io, P},
    forget(Key),
    ok = cell_hal_fake_modbus:refuse(dev(), T, A, Code),
    await_fault(Key, <<"exception ", (integer_to_binary(Code))/binary, ")">>, none).

%% The fault of this refusal (where every Nth request is refused too, faults of those
%% may come first, and may be all there is: the last of them is then the answer).
await_fault(Key, Code, Other) ->
    receive
        {cell_hal_fault, Key, Why} when is_binary(Why) ->
            case binary:match(Why, Code) of
                nomatch -> await_fault(Key, Code, Why);
                _ -> {told, Why, await_unavailable(element(2, Key))}
            end
    after ?WAIT ->
            Read = cell_hal:read(element(1, Key), element(2, Key)),
            case Other of
                none -> {not_told, Read};
                _ -> {told_every_nth, Other, Read}
            end
    end.

%% What a subscriber was told of a point before now.
forget(Key) ->
    receive
        {cell_hal, Key, _} -> forget(Key);
        {cell_hal_fault, Key, _} -> forget(Key)
    after 0 -> ok
    end.

%% Answered again: told it is cleared, then its value.
accept(P) ->
    {T, A} = address(P),
    case mode() of
        parallel -> refuse_now(T, A, 0);
        sequential -> accept_and_wait(P, T, A)
    end.

accept_and_wait(P, T, A) ->
    true = ets:insert(?TAB, {refused, refused() -- [P]}),
    Key = {io, P},
    forget(Key),
    ok = cell_hal_fake_modbus:refuse(dev(), T, A, 0),
    receive
        {cell_hal_fault, Key, cleared} ->
            receive {cell_hal, Key, V} -> {cleared, V}
            after ?WAIT -> not_told_the_value
            end
    after ?WAIT -> {not_cleared, cell_hal:read(io, P)}
    end.

fail_every(N) ->
    ok = cell_hal_fake_modbus:fail_every(dev(), N, 6),
    case N =:= 0 andalso mode() =:= sequential of
        true -> usable_again([P || P <- ?INPUTS, not lists:member(P, refused())]);
        false -> ok
    end.

%% Once the device answers every request, each point it answers is read again (a point
%% a refused request left unusable waits for its next poll).
usable_again([]) ->
    ok;
usable_again([P | Ps] = All) ->
    Key = {io, P},
    case cell_hal:read(io, P) of
        {ok, _} ->
            usable_again(Ps);
        {error, {unavailable, _}} ->
            receive {cell_hal_fault, Key, cleared} -> usable_again(All)
            after ?WAIT -> {still_unavailable, P}
            end
    end.

read(P) ->
    cell_hal:read(io, P).

watch(P, V) ->
    {ok, Ref} = cell_hal:watch(io, P, {eq, V}),
    true = ets:insert(?TAB, {{watch, Ref}, true}),
    Ref.

%% The value read, or the point found unusable meanwhile (then its value when it is
%% told again): never a poll that stops.
await(P, V, Deadline) ->
    Key = {io, P},
    {ok, Ref} = cell_hal:watch(io, P, {eq, V}),
    Left = fun() -> max(0, Deadline - erlang:monotonic_time(millisecond)) end,
    receive
        {cell_hal_watch, Ref, V} -> {ok, V};
        {cell_hal_unavailable, Ref, _} ->
            Asked = cell_hal_fake_modbus:requests(dev()),
            receive {cell_hal, Key, _} -> await(P, V, Deadline)
            after Left() ->
                case cell_hal_fake_modbus:requests(dev()) - Asked of
                    0 -> {never_usable, cell_hal:read(io, P)};
                    N -> {still_polling, N, cell_hal:read(io, P)}
                end
            end
    after Left() ->
        _ = cell_hal:cancel_watch(Ref),
        {never_read, cell_hal:read(io, P), cell_hal:info(conn())}
    end.

%% A refused point's inputs read unavailable from the fault on (the fault is marked
%% before its subscribers are told).
await_unavailable(P) ->
    cell_hal:read(io, P).

%% After a parallel run: the device answers everything; each input is read with the
%% device's value; no watch ended twice or with a value not its own; the connection
%% never went down.
final_parallel() ->
    true = ets:insert(?TAB, {mode, sequential}),
    Dev = dev(),
    ok = cell_hal_fake_modbus:fail_every(Dev, 0, 0),
    _ = [cell_hal_fake_modbus:refuse(Dev, T, A, 0) || P <- ?INPUTS, {T, A} <- [address(P)]],
    Values = [{P, device_value(P)} || P <- ?INPUTS],
    Read = [{P, V, Got} || {P, V} <- Values,
                           Got <- [await(P, V, erlang:monotonic_time(millisecond) + ?WAIT)],
                           Got =/= {ok, V}],
    Msgs = drain(),
    Conn = conn(),
    Down = [M || {cell_hal_conn, C, down} = M <- Msgs, C =:= Conn],
    Watches = [R || {{watch, R}, _} <- ets:match_object(?TAB, {{watch, '_'}, '_'})],
    Twice = [R || R <- Watches,
                  length([M || M <- Msgs, element(1, M) =:= cell_hal_watch
                                   orelse element(1, M) =:= cell_hal_unavailable,
                               element(2, M) =:= R]) > 1],
    ets:match_delete(?TAB, {{watch, '_'}, '_'}),
    case {Read, Down, Twice} of
        {[], [], []} -> ok;
        _ -> {not_settled, Read, Down, Twice}
    end.

device_value(P) -> cell_hal_fake_modbus:get(dev(), address(P)).

%% -------------------------------------------------------------------------------------
%% A device and a connection for each run
%% -------------------------------------------------------------------------------------

setup() ->
    cell_hal_prop_env:start("prop_cell_hal_faults", ?TAB).

cleanup(Env) ->
    cell_hal_prop_env:stop(Env, ?TAB).

start_conn() ->
    start_conn(sequential).

start_conn(Mode) ->
    N = ets:update_counter(?TAB, run, 1),
    Conn = list_to_atom("hf_" ++ integer_to_list(N)),
    Dev = cell_hal_fake_modbus:start(),
    true = ets:insert(?TAB, [{conn, Conn}, {dev, Dev}, {refused, []}, {mode, Mode}]),
    true = ets:match_delete(?TAB, {{watch, '_'}, '_'}),
    ok = cell_hal:add_connection(#{id => Conn, driver => cell_hal_modbus,
                                   opts => #{host => "127.0.0.1",
                                             port => cell_hal_fake_modbus:port(Dev),
                                             poll_ms => 2, reconnect_ms => 5,
                                             max_reconnect_ms => 20, timeout_ms => 1000,
                                             refused_retry_ms => 2,
                                             max_refused_retry_ms => 8}}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => Conn,
                              opts => #{only => ?INPUTS}}),
    [ok = cell_hal:subscribe(io, P) || P <- ?INPUTS],
    {ok, _} = cell_hal:subscribe_connection(Conn),
    [{ok, _} = await(P, Zero, erlang:monotonic_time(millisecond) + ?WAIT)
     || {P, Zero} <- [{int16_in, 0}, {coil_in, false}, {discrete_in, false}]],
    _ = drain(),
    ok.

stop_conn() ->
    Conn = conn(),
    ok = cell_hal:unsubscribe_connection(Conn),
    [ok = cell_hal:unsubscribe(io, P) || P <- ?INPUTS],
    ok = cell_hal:remove_group(io),
    ok = cell_hal:remove_connection(Conn),
    ok = cell_hal_fake_modbus:stop(dev()),
    _ = drain(),
    ok.

%% Where cell_hal_test_io puts each input (base 0).
address(int16_in) -> {ir, 4};
address(coil_in) -> {co, 1};
address(discrete_in) -> {di, 0}.

word(V) when is_integer(V) -> V;
word(B) -> B.

conn() -> ets:lookup_element(?TAB, conn, 2).
mode() -> ets:lookup_element(?TAB, mode, 2).
dev() -> ets:lookup_element(?TAB, dev, 2).
refused() -> ets:lookup_element(?TAB, refused, 2).

drain() ->
    receive M -> [M | drain()] after 0 -> [] end.
