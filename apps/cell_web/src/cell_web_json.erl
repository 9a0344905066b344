%% @doc The cell as the panel's JSON shows it: the cell and its flags, tasks, errors,
%% log lines, events. Pure; every value passes through {@link term/1}, so anything a
%% task keeps in its product can be shown and nothing can crash the encoder.
%%
%% States are the IPC-2541 names (`READY-PROCESSING-EXECUTING'), times milliseconds
%% since the epoch (UTC).
-module(cell_web_json).

-export([encode/1, cell/2, task/1, unit/1, alarm/1, alarm_record/1, line/1, event/1, state/1,
         term/1, product/1]).

%% @doc JSON text of a value built by the functions here (or any term).
-spec encode(term()) -> binary().
encode(Value) ->
    jsx:encode(term(Value)).

%% @doc The cell: its name and the controller's flags.
-spec cell(binary(), map()) -> map().
cell(Name, Flags) ->
    maps:merge(term(maps:without([state], Flags)),
               #{<<"name">> => Name, <<"state">> => state(maps:get(state, Flags))}).

%% @doc A task's row of the registry.
-spec task(map()) -> map().
task(Row) ->
    #{<<"id">> => term(maps:get(id, Row)),
      <<"module">> => term(maps:get(module, Row, undefined)),
      <<"zone">> => term(maps:get(zone, Row, undefined)),
      <<"lane">> => term(maps:get(lane, Row, undefined)),
      <<"state">> => state(maps:get(state, Row, off)),
      <<"serial">> => term(maps:get(serial, Row, undefined)),
      <<"running">> => is_pid(maps:get(pid, Row, undefined))}.

%% @doc What a unit is doing, from its info: the unit's own state (`automatic',
%% `fault' ...), the step it runs (sequence module and step, nested sequences
%% innermost last), why it faulted and whether it is halted; `null' for a task.
-spec unit(map() | undefined) -> map() | null.
unit(#{kind := unit} = Info) ->
    #{sequences := Seqs} = Sequence = maps:get(sequence, Info, #{sequences => []}),
    #{<<"state">> => term(maps:get(unit_state, Info, undefined)),
      <<"step">> => case maps:get(step, Info, undefined) of
                        {_Depth, Mod, Step} -> #{<<"sequence">> => term(Mod),
                                                 <<"step">> => term(Step)};
                        undefined -> null
                    end,
      <<"sequences">> => [#{<<"sequence">> => term(M), <<"step">> => term(S)}
                          || #{module := M, step := S} <- Seqs],
      <<"waiting_for">> => [term(W) || W <- maps:get(waiting, Sequence, [])],
      <<"fault">> => term(maps:get(fault, Info, undefined)),
      <<"halt">> => maps:get(halt, Info, false) =:= true};
unit(_) ->
    null.

%% @doc An error, alarm or warning.
-spec alarm(map()) -> map().
alarm(A) ->
    term(maps:with([id, kind, task, caption, description, solutions, raised, cleared, who,
                    qualifier], A)).

%% @doc An entry of the history of answers.
-spec alarm_record(map()) -> map().
alarm_record(R) ->
    term(R).

%% @doc A task log line.
-spec line(cell_log:line()) -> map().
line(L) ->
    term(maps:with([time, level, source, text], L)).

%% @doc A product: its fields as the task keeps them.
-spec product(map() | undefined) -> map() | null.
product(undefined) -> null;
product(P) -> term(P).

%% @doc Any event of `cell_events'; states by their names, the monotonic stamp and the
%% trace journal's id and time left out (they mean nothing outside this node).
-spec event(map()) -> map().
event(E) ->
    maps:fold(fun(K, V, Acc) when K =:= state; K =:= from ->
                      Acc#{atom_to_binary(K, utf8) => state_or_term(V)};
                 (alarm, V, Acc) ->
                      Acc#{<<"alarm">> => alarm(V)};
                 (mono, _, Acc) ->
                      Acc;
                 %% The id and time of the event's record in the trace journal: the
                 %% runtime's own.
                 (K, _, Acc) when K =:= journal; K =:= at ->
                      Acc;
                 (K, V, Acc) ->
                      Acc#{key(K) => term(V)}
              end, #{}, E).

state_or_term(S) ->
    try state(S) catch error:_ -> term(S) end.

%% @doc An IPC-2541 state by its name.
-spec state(cell_ipc:state()) -> binary().
state(S) ->
    cell_ipc:name(S).

%% @doc Any term as a JSON value: atoms and text as strings, `undefined' as null,
%% maps as objects, lists as arrays (text as a string), anything else printed.
-spec term(term()) -> term().
term(undefined) -> null;
term(null) -> null;
term(B) when is_boolean(B) -> B;
term(A) when is_atom(A) -> atom_to_binary(A, utf8);
term(N) when is_integer(N) -> N;
term(F) when is_float(F) -> F;
term(B) when is_binary(B) ->
    case unicode:characters_to_binary(B) of
        B -> B;
        _ -> printed(B)
    end;
term(M) when is_map(M) ->
    maps:fold(fun(K, V, Acc) -> Acc#{key(K) => term(V)} end, #{}, M);
term([]) -> [];
term(L) when is_list(L) ->
    case io_lib:printable_unicode_list(L) of
        true -> unicode:characters_to_binary(L);
        false ->
            try [term(E) || E <- L]
            catch error:_ -> printed(L)          %% an improper list
            end
    end;
term(T) ->
    printed(T).

key(K) when is_atom(K) -> atom_to_binary(K, utf8);
key(K) when is_binary(K) -> term(K);
key(K) when is_integer(K) -> integer_to_binary(K);
key(K) -> printed(K).

printed(T) ->
    unicode:characters_to_binary(io_lib:format("~0tp", [T])).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

term_test_() ->
    [?_assertEqual(null, term(undefined)),
     ?_assertEqual(true, term(true)),
     ?_assertEqual(<<"retry">>, term(retry)),
     ?_assertEqual(<<"Sägen"/utf8>>, term(<<"Sägen"/utf8>>)),
     ?_assertEqual(<<"<<255,0>>">>, term(<<255, 0>>)),
     ?_assertEqual(<<"abc">>, term("abc")),
     ?_assertEqual([1, 2, <<"x">>], term([1, 2, x])),
     ?_assertEqual(<<"[1|2]">>, term([1 | 2])),
     ?_assertEqual(#{<<"a">> => 1, <<"7">> => <<"{1,2}">>, <<"{k}">> => null},
                   term(#{a => 1, 7 => {1, 2}, {k} => undefined})),
     ?_assert(is_binary(term(self()))),
     ?_assert(is_binary(term(make_ref())))].

encode_anything_test_() ->
    %% Whatever a task keeps in its product, the encoder gives valid JSON.
    Terms = [#{serial => <<"P1">>, tool => {drill, 3}, pid => self(), f => fun() -> ok end},
             [<<255>>, "ü", {}, #{}], 1.5e300, -0.0],
    [?_assert(jsx:is_json(encode(T))) || T <- Terms].

event_test() ->
    E = #{type => task_state, task => robot, zone => <<"Z">>, lane => <<"L">>, time => 5,
          mono => 99, state => {ready, processing, executing}, from => down},
    ?assertEqual(#{<<"type">> => <<"task_state">>, <<"task">> => <<"robot">>,
                   <<"zone">> => <<"Z">>, <<"lane">> => <<"L">>, <<"time">> => 5,
                   <<"state">> => <<"READY-PROCESSING-EXECUTING">>, <<"from">> => <<"DOWN">>},
                 event(E)).

task_test() ->
    Row = #{id => robot, module => m, zone => <<"Z">>, lane => <<"L">>, state => down,
            serial => undefined, pid => self(), settings_key => undefined},
    ?assertEqual(#{<<"id">> => <<"robot">>, <<"module">> => <<"m">>, <<"zone">> => <<"Z">>,
                   <<"lane">> => <<"L">>, <<"state">> => <<"DOWN">>, <<"serial">> => null,
                   <<"running">> => true}, task(Row)).

cell_test() ->
    Flags = #{state => off, request => stop, estop => false, service_mode => false,
              has_alarm => false, has_error => true, has_warning => false},
    ?assertMatch(#{<<"name">> := <<"c">>, <<"state">> := <<"OFF">>, <<"request">> := <<"stop">>,
                   <<"has_error">> := true}, cell(<<"c">>, Flags)).
-endif.
