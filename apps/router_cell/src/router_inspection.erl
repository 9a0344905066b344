%% @doc What the router's PLC program does with an inspection block (seed 004), as pure
%% decisions: the unloading segment ({@link router_unloading_task}) reads the block's
%% tags through its group ({@link router_inspect_io}), asks {@link next/3} what to do,
%% and does it. The seed's handshake, never a pulse a poll could miss:
%%
%% <pre>
%%  phase      holds when                                      then
%%  prepare    TriggerInspection_ECHO and ClearResults_ECHO    write InspectionPointID and
%%             read 0 (the last commands seen dropped)         PartSerial, raise ClearResults
%%                                                             → cleared
%%  cleared    ClearResults_ECHO 1, InspectionStatus Ready,    drop ClearResults, raise
%%             the point's and the serial's echoes match       TriggerInspection → triggered
%%  triggered  TriggerInspection_ECHO 1 and InspectionStatus   drop TriggerInspection; the
%%             Complete, Error or Canceled                     verdict
%% </pre>
%%
%% Cleared first, the status reads Ready until the trigger's outcome: a Complete read
%% after the trigger's echo is this inspection's, never the last one's (over Modbus the
%% status and the echo are read by different requests of one poll).
%%
%% What the verdict does to the product ({@link product/2}): PASS keeps it good; FAIL
%% marks it failed (the next machine and the statistics see it); an Error of the block
%% (no camera, processing failed ...) or no answer at all (the block not running: the
%% step's watchdog) marks it failed as well, since it was not inspected, and says why in
%% a warning. The block records every inspection in the serial's history itself.
-module(router_inspection).

-export([next/3, expired/2, product/2, point/0]).

-export_type([phase/0, verdict/0]).

-type phase() :: prepare | cleared | triggered.
-type verdict() :: pass | fail | {error, integer()} | canceled | not_answered.
-type facts() :: #{atom() => cell_hal_type:value()}.

-define(READY, 1).
-define(COMPLETE, 2).
-define(ERROR, 5).
-define(CANCELED, 6).

%% @doc The InspectionPointID of the modules' inspection at the unloading exit.
-spec point() -> binary().
point() -> <<"MODULES">>.

%% @doc The next move in a phase, from the block's tags as read (`Facts', point =>
%% value) and the writes of the point and serial (`Ids', the PLC's STRING points =>
%% value, see {@link router_inspect_io:string/3}). A wait is for any of its conditions.
-spec next(phase(), facts(), [{atom(), cell_hal_type:value()}]) ->
          {wait, [{atom(), cell_hal_type:condition()}, ...]}
        | {write, [{atom(), cell_hal_type:value()}], phase()}
        | {done, verdict()}.
next(prepare, Facts, Ids) ->
    case unmet([{trigger_inspection_echo, false}, {clear_results_echo, false}], Facts) of
        {wait, _} = W -> W;
        met -> {write, Ids ++ [{trigger_inspection, false}, {clear_results, true}], cleared}
    end;
next(cleared, Facts, Ids) ->
    Echoes = [{echo(P), V} || {P, V} <- Ids],
    case unmet([{clear_results_echo, true}, {inspection_status, ?READY} | Echoes], Facts) of
        {wait, _} = W -> W;
        met -> {write, [{clear_results, false}, {trigger_inspection, true}], triggered}
    end;
next(triggered, Facts, _Ids) ->
    case unmet([{trigger_inspection_echo, true}], Facts) of
        {wait, _} = W -> W;
        met ->
            case maps:get(inspection_status, Facts, undefined) of
                ?COMPLETE ->
                    case {maps:get(inspection_pass, Facts, false),
                          maps:get(inspection_fail, Facts, false)} of
                        {true, false} -> {done, pass};
                        {false, true} -> {done, fail};
                        %% Complete is written last, PASS or FAIL before it; read as
                        %% neither, they were read before it by an earlier request of
                        %% the same poll (the clear dropped both): the next poll has
                        %% the verdict. Both at once the block never means.
                        {false, false} -> {wait, [{inspection_pass, {eq, true}},
                                                  {inspection_fail, {eq, true}}]};
                        _ -> {done, {error, 0}}
                    end;
                ?ERROR -> {done, {error, maps:get(error_code, Facts, 0)}};
                ?CANCELED -> {done, canceled};
                Other -> {wait, [{inspection_status, {ne, Other}}]}
            end
    end.

%% The first condition that does not hold, as a wait for it.
unmet([], _Facts) -> met;
unmet([{P, V} | Rest], Facts) ->
    case maps:get(P, Facts, undefined) of
        V -> unmet(Rest, Facts);
        _ -> {wait, [{P, {eq, V}}]}
    end.

%% @doc The verdict when the step's watchdog ends a phase: a Complete that never came
%% with PASS or FAIL is the block's Error 0; anything else is no answer.
-spec expired(phase(), facts()) -> verdict().
expired(triggered, #{trigger_inspection_echo := true, inspection_status := ?COMPLETE}) ->
    {error, 0};
expired(_Phase, _Facts) ->
    not_answered.

echo(inspection_point_id) -> inspection_point_id_echo;
echo(inspection_point_id_len) -> inspection_point_id_echo_len;
echo(part_serial) -> part_serial_echo;
echo(part_serial_len) -> part_serial_echo_len.

%% @doc The product after the verdict, and the warning to raise (`none' when it passed
%% or failed as inspected).
-spec product(verdict(), cell_product:product()) ->
          {cell_product:product(), none | {binary(), iodata()}}.
product(pass, P) ->
    {P#{inspection => <<"pass">>}, none};
product(fail, P) ->
    {P#{inspection => <<"fail">>, failed => true}, none};
product(V, #{serial := S} = P) ->
    Why = case V of
              {error, Code} -> io_lib:format("the inspection block answered Error ~b", [Code]);
              canceled -> "the inspection was canceled";
              not_answered -> "the inspection block did not answer"
          end,
    {P#{inspection => <<"not_inspected">>, failed => true},
     {<<"not_inspected">>,
      io_lib:format("The modules of panel ~ts were not inspected (~ts): they leave marked "
                    "failed.", [S, Why])}}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

ids() ->
    [{inspection_point_id, <<"MODULES">>}, {inspection_point_id_len, 16#1007},
     {part_serial, <<"P1">>}, {part_serial_len, 16#3002}].

prepare_test_() ->
    [?_assertEqual({wait, [{trigger_inspection_echo, {eq, false}}]},
                   next(prepare, #{trigger_inspection_echo => true}, ids())),
     ?_assertEqual({wait, [{clear_results_echo, {eq, false}}]},
                   next(prepare, #{trigger_inspection_echo => false,
                                   clear_results_echo => true}, ids())),
     ?_assertMatch({write, [_, _, _, _, {trigger_inspection, false}, {clear_results, true}],
                    cleared},
                   next(prepare, #{trigger_inspection_echo => false,
                                   clear_results_echo => false}, ids()))].

cleared_test_() ->
    Echoed = #{clear_results_echo => true, inspection_status => 1,
               inspection_point_id_echo => <<"MODULES">>,
               inspection_point_id_echo_len => 16#1007, part_serial_echo => <<"P1">>,
               part_serial_echo_len => 16#3002},
    [?_assertEqual({write, [{clear_results, false}, {trigger_inspection, true}], triggered},
                   next(cleared, Echoed, ids())),
     ?_assertEqual({wait, [{clear_results_echo, {eq, true}}]},
                   next(cleared, Echoed#{clear_results_echo => false}, ids())),
     %% Still the last inspection's status: not ready for a trigger.
     ?_assertEqual({wait, [{inspection_status, {eq, 1}}]},
                   next(cleared, Echoed#{inspection_status => 2}, ids())),
     %% The serial's length not echoed yet (the characters come first).
     ?_assertEqual({wait, [{part_serial_echo_len, {eq, 16#3002}}]},
                   next(cleared, Echoed#{part_serial_echo_len => 16#3001}, ids()))].

triggered_test_() ->
    Done = #{trigger_inspection_echo => true, inspection_status => 2,
             inspection_pass => true, inspection_fail => false, error_code => 0},
    [?_assertEqual({done, pass}, next(triggered, Done, [])),
     ?_assertEqual({done, fail}, next(triggered, Done#{inspection_pass => false,
                                                       inspection_fail => true}, [])),
     ?_assertEqual({done, {error, 1}}, next(triggered, Done#{inspection_status => 5,
                                                             error_code => 1}, [])),
     ?_assertEqual({done, canceled}, next(triggered, Done#{inspection_status => 6}, [])),
     %% Complete read after PASS and FAIL were (two requests of one poll): the next
     %% poll's verdict, either way.
     ?_assertEqual({wait, [{inspection_pass, {eq, true}}, {inspection_fail, {eq, true}}]},
                   next(triggered, Done#{inspection_pass => false}, [])),
     ?_assertEqual({done, {error, 0}},
                   next(triggered, Done#{inspection_fail => true}, [])),
     ?_assertEqual({error, 0}, expired(triggered, Done#{inspection_pass => false})),
     ?_assertEqual(not_answered, expired(triggered, Done#{inspection_status => 4})),
     ?_assertEqual(not_answered, expired(cleared, Done)),
     ?_assertEqual({wait, [{trigger_inspection_echo, {eq, true}}]},
                   next(triggered, Done#{trigger_inspection_echo => false}, [])),
     %% Requesting, then Processing: each change looked at.
     ?_assertEqual({wait, [{inspection_status, {ne, 3}}]},
                   next(triggered, Done#{inspection_status => 3}, [])),
     ?_assertEqual({wait, [{inspection_status, {ne, 1}}]},
                   next(triggered, Done#{inspection_status => 1}, []))].

product_test_() ->
    P = #{serial => <<"P1">>, recipe => <<"r">>, failed => false},
    [?_assertMatch({#{inspection := <<"pass">>, failed := false}, none}, product(pass, P)),
     ?_assertMatch({#{inspection := <<"fail">>, failed := true}, none}, product(fail, P)),
     ?_assertMatch({#{inspection := <<"not_inspected">>, failed := true}, {<<"not_inspected">>, _}},
                   product(not_answered, P)),
     ?_assertMatch({#{failed := true}, {_, _}}, product({error, 1}, P))].
-endif.
