%% The status machine step by step, without processes: each numbered step of the
%% seed's Trigger, Override and Send Message logic, the writes in the order the PLC
%% sees them, and the decisions where the seed is silent.
-module(cell_inspect_status_tests).
-include_lib("eunit/include/eunit.hrl").

-define(S, cell_inspect_status).

config() ->
    #{points => #{<<"P1">> => none, <<"P2">> => ipm, <<"P3">> => misconfigured},
      messages => #{7 => #{text => <<"Part OK?">>, kind => yes_no},
                    8 => #{text => <<"Batch number">>, kind => text}}}.

inputs() ->
    #{trigger_inspection => false, clear_results => false, cancel_inspection => false,
      log_override => false, send_message => false, inspection_point_id => <<>>,
      part_serial => <<>>, override_employee_id => <<>>, message_id => 0}.

zeros() ->
    maps:from_list([{T, case cell_inspect_tags:kind(T) of
                            bool -> false;
                            int -> 0;
                            _ -> <<>>
                        end} || T <- cell_inspect_tags:outputs()]).

cam() -> #{points => all, images => true, messages => true}.

%% A block that has seen its PLC (all zeros), loaded P2's workspace, and has camera
%% `c1' connected.
ready() ->
    St0 = ?S:new(inc, config()),
    {St1, _} = ?S:handle({plc_up, #{inputs => inputs(), outputs => zeros()}}, St0),
    {St2, _} = ?S:handle({workspace, <<"P2">>, ready}, St1),
    {St3, []} = ?S:handle({client_up, <<"c1">>, cam()}, St2),
    St3.

run(Events, St) ->
    lists:foldl(fun(E, {S, Acc}) ->
                        {S1, Effects} = ?S:handle(E, S),
                        {S1, Acc ++ Effects}
                end, {St, []}, Events).

writes(Effects) -> [{T, V} || {write, T, V} <- Effects].

%% The PLC sets the point and serial, then raises TriggerInspection.
trigger(Point, Serial, St) ->
    run([{input, inspection_point_id, Point}, {input, part_serial, Serial},
         {input, trigger_inspection, true}], St).

start_test_() ->
    St0 = ?S:new(inc, config()),
    {St1, E1} = ?S:handle({plc_up, #{inputs => inputs(), outputs => zeros()}}, St0),
    {St2, E2} = ?S:handle({workspace, <<"P2">>, ready}, St1),
    [?_assertEqual(waiting_for_ipm, ?S:status(St1)),
     ?_assertEqual([], writes(E1)),
     ?_assertEqual([{inspection_status, 1}], writes(E2)),
     ?_assertEqual(ready, ?S:status(St2))].

%% Step 6: echoes first for the values, then Requesting, the checks, the trigger's echo.
unknown_point_test() ->
    {St, E} = trigger(<<"NOPE">>, <<"S1">>, ready()),
    ?assertEqual([{inspection_point_id_echo, <<"NOPE">>}, {part_serial_echo, <<"S1">>},
                  {inspection_status, 3}, {error_code, 2}, {inspection_status, 5},
                  {trigger_inspection_echo, true}], writes(E)),
    ?assertEqual(error, ?S:status(St)).

no_camera_test() ->
    {St1, _} = ?S:handle({client_down, <<"c1">>}, ready()),
    {_, E} = trigger(<<"P1">>, <<>>, St1),
    ?assertEqual([{inspection_point_id_echo, <<"P1">>}, {inspection_status, 3},
                  {error_code, 1}, {inspection_status, 5}, {trigger_inspection_echo, true}],
                 writes(E)).

%% A camera that serves other points only does not count.
camera_for_other_points_test() ->
    {St1, _} = ?S:handle({client_up, <<"c1">>, (cam())#{points => [<<"P2">>]}}, ready()),
    {_, E} = trigger(<<"P1">>, <<>>, St1),
    ?assertMatch([_, {inspection_status, 3}, {error_code, 1} | _], writes(E)).

%% Steps 6 to 9, PASS with a string.
pass_test() ->
    {St1, E1} = trigger(<<"P2">>, <<"SN-9">>, ready()),
    [{request_image, [<<"c1">>], #{ref := Ref, point := <<"P2">>, serial := <<"SN-9">>}}] =
        [X || {request_image, _, _} = X <- E1],
    ?assertEqual([{inspection_point_id_echo, <<"P2">>}, {part_serial_echo, <<"SN-9">>},
                  {inspection_status, 3}, {trigger_inspection_echo, true}], writes(E1)),
    {St2, E2} = run([{input, trigger_inspection, false}, {image, <<"c1">>, Ref, img}], St1),
    ?assertEqual([{trigger_inspection_echo, false}, {inspection_status, 4}], writes(E2)),
    ?assertMatch([{process, Ref, #{mode := ipm, client := <<"c1">>, image := img}}],
                 [X || {process, _, _} = X <- E2]),
    {St3, E3} = ?S:handle({processed, Ref, {pass, <<"OCR 12">>}}, St2),
    ?assertEqual([{inspection_pass, true}, {inspection_string, <<"OCR 12">>},
                  {inspection_status, 2}], writes(E3)),
    ?assertEqual(complete, ?S:status(St3)),
    %% The next trigger from Complete: FAIL this time; PASS goes back to 0.
    {St4, E4} = run([{input, trigger_inspection, true}], St3),
    [{request_image, _, #{ref := Ref2}}] = [X || {request_image, _, _} = X <- E4],
    {_, E5} = run([{image, <<"c1">>, Ref2, img}, {processed, Ref2, {fail, <<>>}}], St4),
    ?assertEqual([{inspection_status, 4}, {inspection_pass, false}, {inspection_fail, true},
                  {inspection_string, <<>>}, {inspection_status, 2}], writes(E5)).

%% Processing failures and their codes.
processing_codes_test_() ->
    Run = fun(Point, Events) ->
                  {St1, E1} = trigger(Point, <<>>, ready()),
                  [{request_image, _, #{ref := Ref}}] = [X || {request_image, _, _} = X <- E1],
                  {St2, E2} = ?S:handle({image, <<"c1">>, Ref, img}, St1),
                  [{process, Ref, #{mode := Mode}}] = [X || {process, _, _} = X <- E2],
                  {_, E3} = run([E(Ref) || E <- Events], St2),
                  {Mode, writes(E3)}
          end,
    [?_assertEqual({{error, inspection_configuration_error},
                    [{error_code, 5}, {inspection_status, 5}]},
                   Run(<<"P3">>, [fun(R) -> {processed, R, {error, inspection_configuration_error}} end])),
     ?_assertEqual({ipm, [{error_code, 3}, {inspection_status, 5}]},
                   Run(<<"P2">>, [fun(R) -> {processed, R, {error, processing_error}} end])),
     ?_assertEqual({none, [{inspection_pass, true}, {inspection_status, 2}]},
                   Run(<<"P1">>, [fun(R) -> {processed, R, {pass, <<>>}} end]))].

%% An image before the workspace is loaded: ProcessingNotAvailable.
workspace_loading_test() ->
    St0 = ready(),
    {St1, _} = ?S:handle({workspace, <<"P2">>, loading}, St0),
    {St2, E1} = trigger(<<"P2">>, <<>>, St1),
    [{request_image, _, #{ref := Ref}}] = [X || {request_image, _, _} = X <- E1],
    {_, E2} = ?S:handle({image, <<"c1">>, Ref, img}, St2),
    ?assertMatch([{process, Ref, #{mode := {error, processing_not_available}}}],
                 [X || {process, _, _} = X <- E2]).

%% Step 7: CancelInspection while Requesting.
cancel_test() ->
    {St1, E1} = trigger(<<"P1">>, <<>>, ready()),
    [{request_image, _, #{ref := Ref}}] = [X || {request_image, _, _} = X <- E1],
    {St2, E2} = run([{input, cancel_inspection, true}], St1),
    ?assertEqual([{cancel_image, [<<"c1">>], Ref}], [X || {cancel_image, _, _} = X <- E2]),
    ?assertEqual([{inspection_status, 6}, {cancel_inspection_echo, true}], writes(E2)),
    %% A late image is ignored.
    {St3, E3} = ?S:handle({image, <<"c1">>, Ref, img}, St2),
    ?assertEqual([], writes(E3)),
    ?assertEqual(canceled, ?S:status(St3)).

%% CancelInspection when nothing waits for an image: ignored, echoed.
cancel_ignored_test() ->
    {St, E} = run([{input, cancel_inspection, true}], ready()),
    ?assertEqual([{cancel_inspection_echo, true}], writes(E)),
    ?assertEqual(ready, ?S:status(St)).

%% Step 1: a trigger is ignored unless Ready, Complete or Canceled; ClearResults frees.
trigger_ignored_in_error_test() ->
    {St1, _} = trigger(<<"NOPE">>, <<>>, ready()),
    {St2, E2} = run([{input, trigger_inspection, false}, {input, inspection_point_id, <<"P1">>},
                     {input, trigger_inspection, true}], St1),
    ?assertEqual([{trigger_inspection_echo, false}, {inspection_point_id_echo, <<"P1">>},
                  {trigger_inspection_echo, true}], writes(E2)),
    {St3, E3} = run([{input, trigger_inspection, false}, {input, clear_results, true}], St2),
    ?assertEqual([{trigger_inspection_echo, false}, {error_code, 0}, {inspection_status, 1},
                  {clear_results_echo, true}], writes(E3)),
    ?assertEqual(ready, ?S:status(St3)).

%% In WaitingForIPM only a point without image processing may be triggered.
waiting_for_ipm_test() ->
    St0 = ?S:new(inc, config()),
    {St1, _} = ?S:handle({plc_up, #{inputs => inputs(), outputs => zeros()}}, St0),
    {St2, _} = ?S:handle({client_up, <<"c1">>, cam()}, St1),
    {_, E1} = trigger(<<"P2">>, <<>>, St2),
    ?assertEqual([], [X || {request_image, _, _} = X <- E1]),
    {_, E2} = trigger(<<"P1">>, <<>>, St2),
    ?assertMatch([{request_image, _, _}], [X || {request_image, _, _} = X <- E2]).

%% A pulse: the echo is the memory of the edge; 1 again while the echo says 1 is no edge.
edges_test() ->
    {St1, E1} = trigger(<<"P1">>, <<>>, ready()),
    ?assertEqual(1, length([X || {request_image, _, _} = X <- E1])),
    {_, E2} = run([{input, trigger_inspection, true}], St1),
    ?assertEqual([], E2).

%% Override, steps 1 to 4.
override_test() ->
    {St1, E1} = run([{input, override_employee_id, <<"E7">>}, {input, inspection_point_id, <<"P1">>},
                     {input, part_serial, <<"SN">>}, {input, log_override, true}], ready()),
    [{log_override, Ref, Ov}] = [X || {log_override, _, _} = X <- E1],
    ?assertEqual(#{point => <<"P1">>, serial => <<"SN">>, employee => <<"E7">>}, Ov),
    ?assertEqual([{employee_override_echo, <<"E7">>}, {inspection_point_id_echo, <<"P1">>},
                  {part_serial_echo, <<"SN">>}, {inspection_status, 4},
                  {log_override_echo, true}], writes(E1)),
    {St2, E2} = ?S:handle({override_logged, Ref, logged}, St1),
    ?assertEqual([{inspection_status, 2}], writes(E2)),
    {St3, E3} = run([{input, log_override, false}, {input, log_override, true}], St2),
    [{log_override, Ref3, _}] = [X || {log_override, _, _} = X <- E3],
    {_, E4} = ?S:handle({override_logged, Ref3, not_found}, St3),
    ?assertEqual([{error_code, 2}, {inspection_status, 5}], writes(E4)),
    %% Ignored while Processing (another override under way).
    {_, E5} = run([{input, log_override, false}, {input, trigger_inspection, true}], St3),
    ?assertEqual([{log_override_echo, false}, {trigger_inspection_echo, true}], writes(E5)).

override_db_failure_test() ->
    {St1, E1} = run([{input, log_override, true}], ready()),
    [{log_override, Ref, _}] = [X || {log_override, _, _} = X <- E1],
    {_, E2} = ?S:handle({override_logged, Ref, {error, aborted}}, St1),
    ?assertEqual([{error_code, 4}, {inspection_status, 5}], writes(E2)).

%% Send Message, steps 3 to 11.
message_test() ->
    St0 = ready(),
    {St1, E1} = run([{input, message_id, 7}, {input, send_message, true}], St0),
    [{show_message, [<<"c1">>], #{ref := Ref, id := 7, kind := yes_no}}] =
        [X || {show_message, _, _} = X <- E1],
    ?assertEqual([{message_id_echo, 7}, {message_status, 1}, {send_message_echo, true}],
                 writes(E1)),
    ?assertEqual({error, {bad_answer, yes_no}}, ?S:check_answer(St1, <<"c1">>, Ref, {text, <<"x">>})),
    ?assertEqual({error, not_shown_to_client}, ?S:check_answer(St1, <<"c9">>, Ref, yes)),
    ?assertEqual({error, no_such_message}, ?S:check_answer(St1, <<"c1">>, {inc, 99}, yes)),
    {St2, E2} = ?S:handle({answer, <<"c1">>, Ref, no}, St1),
    ?assertEqual([{message_status, 6}], writes(E2)),
    %% A text answer goes to MessageResult; the next message empties it first.
    {St3, E3} = run([{input, send_message, false}, {input, message_id, 8},
                     {input, send_message, true}], St2),
    [{show_message, _, #{ref := Ref3}}] = [X || {show_message, _, _} = X <- E3],
    {St4, E4} = ?S:handle({answer, <<"c1">>, Ref3, {text, <<"B-77">>}}, St3),
    ?assertEqual([{message_result, <<"B-77">>}, {message_status, 5}], writes(E4)),
    {_, E5} = run([{input, send_message, false}, {input, send_message, true}], St4),
    ?assertEqual([{send_message_echo, false}, {message_result, <<>>}, {message_status, 1},
                  {send_message_echo, true}], writes(E5)).

message_codes_test_() ->
    NoClients = element(1, ?S:handle({client_down, <<"c1">>}, ready())),
    Send = fun(Id, St) -> writes(element(2, run([{input, message_id, Id},
                                                 {input, send_message, true}], St))) end,
    [%% Step 4 before step 5: no client wins over an unknown message.
     ?_assertEqual([{message_id_echo, 99}, {message_status, 3}, {send_message_echo, true}],
                   Send(99, NoClients)),
     ?_assertEqual([{message_id_echo, 99}, {message_status, 2}, {send_message_echo, true}],
                   Send(99, ready()))].

%% Step 6: every client gone before an answer; a new message replaces one waiting.
message_clients_leave_test() ->
    {St0, _} = ?S:handle({client_up, <<"c2">>, cam()}, ready()),
    {St1, E1} = run([{input, message_id, 7}, {input, send_message, true}], St0),
    [{show_message, [<<"c1">>, <<"c2">>], #{ref := Ref}}] = [X || {show_message, _, _} = X <- E1],
    {St2, E2} = run([{input, send_message, false}, {input, send_message, true}], St1),
    ?assertMatch([{withdraw_message, [<<"c1">>, <<"c2">>], Ref}],
                 [X || {withdraw_message, _, _} = X <- E2]),
    {St3, E3} = ?S:handle({client_down, <<"c1">>}, St2),
    ?assertEqual([], writes(E3)),
    {_, E4} = ?S:handle({client_down, <<"c2">>}, St3),
    ?assertEqual([{message_status, 3}], writes(E4)).

%% A camera that connects while a request or a message waits gets them.
late_joiner_test() ->
    {St1, _} = trigger(<<"P1">>, <<>>, ready()),
    {St2, _} = run([{input, message_id, 7}, {input, send_message, true}], St1),
    {_, E} = ?S:handle({client_up, <<"c2">>, cam()}, St2),
    ?assertMatch([{request_image, [<<"c2">>], _}, {show_message, [<<"c2">>], _}], E).

%% Every camera asked for an image disconnects: DeviceNotFound.
cameras_leave_test() ->
    {St1, _} = trigger(<<"P1">>, <<>>, ready()),
    {_, E} = ?S:handle({client_down, <<"c1">>}, St1),
    ?assertEqual([{error_code, 1}, {inspection_status, 5}], writes(E)).

%% A restart in the middle: the PLC learns its request was lost.
restart_test_() ->
    Up = fun(Out) ->
                 {St, E} = ?S:handle({plc_up, #{inputs => inputs(), outputs => Out}},
                                     ?S:new(inc2, config())),
                 {?S:status(St), writes(E)}
         end,
    Z = zeros(),
    [?_assertEqual({error, [{error_code, 4}, {inspection_status, 5}]},
                   Up(Z#{inspection_status => 3})),
     ?_assertEqual({error, [{error_code, 4}, {inspection_status, 5}]},
                   Up(Z#{inspection_status => 4})),
     ?_assertEqual({complete, []}, Up(Z#{inspection_status => 2, inspection_pass => true})),
     ?_assertEqual({waiting_for_ipm, [{inspection_status, 0}]}, Up(Z#{inspection_status => 77})),
     ?_assertEqual({waiting_for_ipm, [{message_status, 4}]}, Up(Z#{message_status => 1}))].

%% A command raised while the block was away is taken when read; one already echoed is not.
restart_edges_test_() ->
    Up = fun(In, Out) ->
                 St0 = ?S:new(inc2, config()),
                 {St1, _} = ?S:handle({client_up, <<"c1">>, cam()}, St0),
                 {_, E} = ?S:handle({plc_up, #{inputs => maps:merge(inputs(), In),
                                               outputs => maps:merge(zeros(), Out)}}, St1),
                 E
         end,
    Ready = #{inspection_status => 1},
    [?_assertMatch([_ | _], [X || {request_image, _, _} = X
                                      <- Up(#{trigger_inspection => true,
                                              inspection_point_id => <<"P1">>}, Ready)]),
     ?_assertEqual([], [X || {request_image, _, _} = X
                                 <- Up(#{trigger_inspection => true,
                                         inspection_point_id => <<"P1">>},
                                       Ready#{trigger_inspection_echo => true,
                                              inspection_point_id_echo => <<"P1">>})]),
     ?_assertEqual([{trigger_inspection_echo, false}],
                   writes(Up(#{}, Ready#{trigger_inspection_echo => true})))].

%% After a lost link the block writes what the PLC holds differently.
reconnect_test() ->
    {St1, _} = trigger(<<"P1">>, <<>>, ready()),
    {St2, []} = ?S:handle(plc_down, St1),
    Out = (?S:outputs(St2))#{inspection_status => 0, heartbeat => true},
    {_, E} = ?S:handle({plc_up, #{inputs => (inputs())#{inspection_point_id => <<"P1">>,
                                                        trigger_inspection => true},
                                  outputs => Out}}, St2),
    ?assertEqual([{heartbeat, false}, {inspection_status, 3}], writes(E)).

heartbeat_test() ->
    {St1, E1} = ?S:handle(heartbeat, ready()),
    {_, E2} = ?S:handle(heartbeat, St1),
    ?assertEqual([{heartbeat, true}], writes(E1)),
    ?assertEqual([{heartbeat, false}], writes(E2)),
    ?assertEqual({?S:new(x, config()), []}, ?S:handle(heartbeat, ?S:new(x, config()))).

%% ClearResults during an inspection clears results but the inspection goes on.
clear_during_inspection_test() ->
    {St1, _} = trigger(<<"P1">>, <<>>, ready()),
    {St2, E} = run([{input, clear_results, true}], St1),
    ?assertEqual([{clear_results_echo, true}], writes(E)),
    ?assertEqual(requesting, ?S:status(St2)).

codes_test_() ->
    [?_assertEqual(6, ?S:status_code(canceled)), ?_assertEqual(waiting_for_ipm, ?S:status_name(0)),
     ?_assertEqual(6, ?S:error_code(processing_not_available)),
     ?_assertEqual(negative_response, ?S:message_name(6)),
     ?_assertEqual(3, ?S:message_code(no_available_clients))].

answers_test_() ->
    Msg = fun(Kind) ->
                  C = (config())#{messages => #{1 => #{text => <<"?">>, kind => Kind}}},
                  St0 = ?S:new(i, C),
                  {St1, _} = ?S:handle({plc_up, #{inputs => inputs(), outputs => zeros()}}, St0),
                  {St2, _} = ?S:handle({client_up, <<"c">>, cam()}, St1),
                  {St3, E} = run([{input, message_id, 1}, {input, send_message, true}], St2),
                  [{show_message, _, #{ref := R}}] = [X || {show_message, _, _} = X <- E],
                  fun(A) -> ?S:check_answer(St3, <<"c">>, R, A) end
          end,
    Ok = Msg(ok), Num = Msg(number), Pw = Msg(password),
    [?_assertEqual(ok, Ok(yes)), ?_assertEqual({error, {bad_answer, ok}}, Ok(no)),
     ?_assertEqual(ok, Num({text, <<"12">>})), ?_assertEqual(ok, Num({text, <<" -1.5 ">>})),
     ?_assertEqual({error, {bad_answer, number}}, Num({text, <<"12a">>})),
     ?_assertEqual({error, {bad_answer, number}}, Num({text, <<>>})),
     ?_assertEqual(ok, Num(no)), ?_assertEqual(ok, Pw({text, <<"1234">>})),
     ?_assertEqual({error, {bad_answer, password}}, Pw(yes))].
