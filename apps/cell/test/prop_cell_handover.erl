%% A PropEr state-machine property of the framework's hand-over patterns
%% (cell_handover): a line of 3 or 4 segments written with them only
%% (cell_handover_task) is driven by prop_cell_line's commands — products fed in,
%% Start, Pause, Stop, the emergency stop, segments killed, links restarted, the line
%% drained — and by an operator who answers the open errors with any solution they
%% offer (Reset included: the product is then forgotten by the operator's word) and
%% a sensor that goes blind and sees again (the restart reconciliation's question).
%%
%% Checked, with prop_cell_line's harness: every pause and stop settles within a bound
%% (no deadlock); whenever the line is still, every product fed in is out, waiting in
%% the feed, owned by exactly one segment (on disk and in memory), or forgotten at
%% the operator's Reset (none lost, none duplicated, none sent out twice); a drain
%% gets every product out.
-module(prop_cell_handover).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([answer/1, blind/1, cut/1]).

handover_test_() ->
    {timeout, 300, ?_assert(proper:quickcheck(prop_handover(),
                                              [{to_file, user}, {numtests, 80}, {max_shrinks, 20}]))}.

prop_handover() ->
    ?FORALL(Size, range(3, 4),
            ?FORALL(Cmds, commands(?MODULE, prop_cell_line:model(Size)),
                    begin
                        prop_cell_line:setup(Size, cell_handover_task, 10),
                        {History, State, Result} = run_commands(?MODULE, Cmds),
                        Final = prop_cell_line:final_check(),
                        prop_cell_line:teardown(),
                        ?WHENFAIL(io:format(user, "Size ~p~nHistory: ~p~nState: ~p~n"
                                            "Result: ~p~nFinal: ~p~n",
                                            [Size, History, State, Result, Final]),
                                  aggregate(command_names(Cmds),
                                            Result =:= ok andalso Final =:= ok))
                    end)).

%% -------------------------------------------------------------------------------------
%% Model: prop_cell_line's, with the operator's answers and the sensor beside it.
%% -------------------------------------------------------------------------------------

initial_state() -> prop_cell_line:model(3).

command(M) ->
    frequency([{12, prop_cell_line:command(M)},
               {3, {call, ?MODULE, answer, [range(1, 3)]}},
               {1, {call, ?MODULE, blind, [range(1, 4)]}},
               {2, {call, ?MODULE, cut, [elements([link, upstream])]}}]).

precondition(_M, {call, ?MODULE, _, _}) -> true;
precondition(M, Call) -> prop_cell_line:precondition(M, Call).

next_state(M, _Res, {call, ?MODULE, _, _}) -> M;
next_state(M, Res, Call) -> prop_cell_line:next_state(M, Res, Call).

postcondition(_M, {call, ?MODULE, _, _}, Res) -> Res =:= ok;
postcondition(M, Call, Res) -> prop_cell_line:postcondition(M, Call, Res).

%% -------------------------------------------------------------------------------------
%% Commands
%% -------------------------------------------------------------------------------------

%% The operator answers the oldest open error with its `I'th solution (counted round).
%% A Reset makes the segment forget its product: noted first, as the operator's word.
answer(I) ->
    case lists:keysort(2, [{A, R} || #{kind := error, raised := R} = A <- cell_alarms:list()]) of
        [] ->
            ok;
        [{#{id := Id, task := Task, solutions := Sols}, _} | _] ->
            Choice = lists:nth((I - 1) rem length(Sols) + 1, Sols),
            _ = Choice =:= reset andalso forgotten(Task),
            _ = cell_alarms:answer(Id, Choice, <<"property">>),
            ok
    end.

forgotten(Task) ->
    case prop_cell_line:info(Task) of
        #{product := #{serial := S}} -> ets:insert(prop_cell_line:tab(), {{forgotten, S}, Task});
        _ -> true
    end.

%% The product sensor of segment `I' (counted round) goes blind, or sees again.
blind(I) ->
    Task = prop_cell_line:task((I - 1) rem prop_cell_line:size() + 1),
    Tab = prop_cell_line:tab(),
    _ = case ets:member(Tab, {blind, Task}) of
            true -> ets:delete(Tab, {blind, Task});
            false -> ets:insert(Tab, {{blind, Task}, true})
        end,
    ok.

%% As soon as a product starts to move into a segment (within a bound: the line may
%% stand still), its link is restarted or the segment it leaves is killed: the
%% transfer is cut off while the product moves.
cut(What) ->
    flush_arriving(),
    receive
        {line_arriving, Seg} ->
            "seg" ++ N = atom_to_list(Seg),
            Prev = list_to_integer(N) - 1,
            case What of
                link -> prop_cell_line:kill_link(list_to_atom("hs" ++ integer_to_list(Prev)));
                upstream -> prop_cell_line:kill_task(prop_cell_line:task(Prev))
            end
    after 300 ->
        ok
    end.

flush_arriving() ->
    receive {line_arriving, _} -> flush_arriving() after 0 -> ok end.
