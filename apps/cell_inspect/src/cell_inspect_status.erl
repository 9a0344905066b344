%% @doc The status machine of one inspection block (seed 004): what the block does for
%% every command of the PLC and every answer of its cameras, as the seed's tables and
%% numbered steps say. Pure: {@link handle/2} takes an event and returns the new state
%% and the effects (writes to the PLC, requests to cameras, jobs) in the order the
%% block process ({@link cell_inspect_block}) carries them out.
%%
%% <b>InspectionStatus</b> (and when it changes):
%% <table>
%% <tr><th>code</th><th>status</th><th>entered</th><th>commands accepted</th></tr>
%% <tr><td>0</td><td>WaitingForIPM</td><td>at first start, until every workspace is
%%   loaded; ClearResults while one loads</td><td>TriggerInspection for a point without
%%   image processing; ClearResults; SendMessage</td></tr>
%% <tr><td>1</td><td>Ready</td><td>workspaces loaded; ClearResults</td>
%%   <td>all</td></tr>
%% <tr><td>2</td><td>Complete</td><td>results written (step 9); an override logged</td>
%%   <td>all</td></tr>
%% <tr><td>3</td><td>Requesting</td><td>a trigger accepted (step 6)</td>
%%   <td>CancelInspection (step 7); ClearResults; SendMessage</td></tr>
%% <tr><td>4</td><td>Processing</td><td>an image received (step 8); an override
%%   accepted</td><td>ClearResults; SendMessage</td></tr>
%% <tr><td>5</td><td>Error</td><td>with an ErrorCode: the point is unknown (2), no camera
%%   serves it (1), its processing failed (3), is misconfigured (5) or not loaded yet
%%   (6), the result could not be recorded (4), no result to override (2)</td>
%%   <td>ClearResults; SendMessage</td></tr>
%% <tr><td>6</td><td>Canceled</td><td>CancelInspection while Requesting</td>
%%   <td>all</td></tr>
%% </table>
%% A command that is not accepted is ignored (its echo is still written). ErrorCode is 0
%% except in Error.
%%
%% <b>MessageStatus</b>: Ready (0) until the first message; SendMessage withdraws a
%% message still waiting, then: no connected client NoAvailableClients (3), an unknown
%% MessageID MessageNotFound (2), else MessageResult is emptied and the status is
%% Waiting (1) until an answer: Yes AffirmativeResponse (5), No NegativeResponse (6), a
%% text AffirmativeResponse with the text in MessageResult; every client gone before an
%% answer NoAvailableClients (3).
%%
%% <b>Echoes and edges.</b> Every value the PLC writes is echoed at once. A command acts
%% when it reads 1 while its echo still says 0: the echo is the block's memory of the
%% edges it has taken, kept by the PLC, so a rising edge is taken once whatever the poll
%% period, and a command raised while the link was down or the block restarting is taken
%% when it is read. The command's writes come before its echo: once the PLC reads the
%% echo, InspectionStatus (and MessageStatus) already show the command's outcome.
%%
%% <b>Decisions where the seed is silent.</b> At a (re)start the block keeps the status
%% the PLC holds, except that an inspection under way (Requesting, Processing) becomes
%% Error with InternalError (4), and a message Waiting becomes ApplicationException (4):
%% the PLC learns its request was lost instead of waiting for ever. After a lost link
%% the block writes again every output the PLC holds differently. ClearResults during an
%% inspection clears the results but leaves the status (it is not a cancel). A camera
%% that connects while a request or a message waits receives it too; when every camera
%% asked for an image disconnects, the inspection ends in Error with DeviceNotFound (1).
-module(cell_inspect_status).

-export([new/2, handle/2, view/1, check_answer/4, status/1, outputs/1]).
-export([status_code/1, status_name/1, error_code/1, error_name/1, message_code/1,
         message_name/1]).

-export_type([state/0, event/0, effect/0, config/0, point_kind/0, message_def/0,
              message_kind/0, caps/0, ref/0, answer/0, status/0, error_name/0,
              message_status/0, client/0, job/0, result/0]).

-type status() :: waiting_for_ipm | ready | complete | requesting | processing | error
                | canceled.
-type error_name() :: no_error | device_not_found | inspection_not_found
                    | processing_error | internal_error | inspection_configuration_error
                    | processing_not_available.
-type message_status() :: ready | waiting | message_not_found | no_available_clients
                        | application_exception | affirmative_response
                        | negative_response.
-type point_kind() :: none | ipm | misconfigured.
-type message_kind() :: yes_no | ok | text | number | password.
-type message_def() :: #{text := binary(), kind := message_kind()}.
-type config() :: #{points := #{binary() => point_kind()},
                    messages := #{integer() => message_def()}}.
-type client() :: binary().
-type caps() :: #{points := all | [binary()], images := boolean(), messages := boolean()}.
-type ref() :: {term(), pos_integer()}.
-type answer() :: yes | no | {text, binary()}.
-type result() :: {pass | fail, binary()} | {error, error_name()}.
-type job() :: #{point := binary(), serial := binary(), client := client(),
                 image := term(), mode := none | ipm | {error, error_name()}}.
-type value() :: cell_inspect_tags:value().

-type event() :: {plc_up, #{inputs := #{cell_inspect_tags:in_tag() => value()},
                           outputs := #{cell_inspect_tags:out_tag() => value()}}}
               | plc_down
               | {input, cell_inspect_tags:in_tag(), value()}
               | heartbeat
               | {config, config()}
               | {workspace, binary(), loading | ready | failed}
               | {client_up, client(), caps()}
               | {client_down, client()}
               | {image, client(), ref(), term()}
               | {processed, ref(), result()}
               | {override_logged, ref(), logged | not_found | {error, term()}}
               | {answer, client(), ref(), answer()}.

-type effect() :: {write, cell_inspect_tags:out_tag(), value()}
                | {request_image, [client()], #{ref := ref(), point := binary(),
                                                serial := binary()}}
                | {cancel_image, [client()], ref()}
                | {process, ref(), job()}
                | {log_override, ref(), #{point := binary(), serial := binary(),
                                          employee := binary()}}
                | {show_message, [client()], #{ref := ref(), id := integer(),
                                                text := binary(), kind := message_kind()}}
                | {withdraw_message, [client()], ref()}
                | {log, cell_log:level(), io:format(), [term()]}.

-record(st, {inc :: term(),                              %% this incarnation, in every ref
             plc = unknown :: unknown | up | down,
             out = #{} :: #{cell_inspect_tags:out_tag() => value()},
             in = #{} :: #{cell_inspect_tags:in_tag() => value()},
             points = #{} :: #{binary() => point_kind()},
             workspaces = #{} :: #{binary() => loading | ready | failed},
             messages = #{} :: #{integer() => message_def()},
             clients = #{} :: #{client() => caps()},
             inspection :: undefined | #{ref := ref(), point := binary(), serial := binary(),
                                         stage := requesting | processing,
                                         clients := [client()]},
             message :: undefined | #{ref := ref(), id := integer(), def := message_def(),
                                      clients := [client()]},
             override :: undefined | ref(),
             seq = 0 :: non_neg_integer()}).

-opaque state() :: #st{}.

%% Ordered so that a reset comes before what follows it when several edges are read
%% in one poll.
-define(COMMAND_ORDER, [clear_results, cancel_inspection, trigger_inspection, log_override,
                        send_message]).

-define(REASSERT_ORDER,
        [heartbeat, inspection_pass, inspection_fail, inspection_string, message_result,
         inspection_point_id_echo, part_serial_echo, employee_override_echo, message_id_echo,
         error_code, inspection_status, message_status, trigger_inspection_echo,
         clear_results_echo, cancel_inspection_echo, log_override_echo, send_message_echo]).

%%====================================================================
%% API
%%====================================================================

%% @doc A block before it has seen its PLC. `Incarnation' makes its refs unique across
%% restarts.
-spec new(term(), config()) -> state().
new(Incarnation, #{points := Points, messages := Messages}) ->
    #st{inc = Incarnation, points = Points, messages = Messages}.

%% @doc One event: the new state and the effects, in order.
-spec handle(event(), state()) -> {state(), [effect()]}.
handle(Event, St) ->
    {St1, Acc} = event(Event, {St, []}),
    {St1, lists:reverse(Acc)}.

%% @doc The status now.
-spec status(state()) -> status().
status(#st{out = Out}) ->
    status_name(maps:get(inspection_status, Out, 0)).

%% @doc The outputs as the block holds them (what the PLC reads once written).
-spec outputs(state()) -> #{cell_inspect_tags:out_tag() => value()}.
outputs(#st{out = Out}) -> Out.

%% @doc What the panel and the API show of a block.
-spec view(state()) -> map().
view(#st{plc = Plc, out = Out, inspection = I, message = M, clients = C}) ->
    #{plc => Plc,
      status => status_name(maps:get(inspection_status, Out, 0)),
      error => error_name(maps:get(error_code, Out, 0)),
      message_status => message_name(maps:get(message_status, Out, 0)),
      message_result => maps:get(message_result, Out, <<>>),
      pass => maps:get(inspection_pass, Out, false),
      fail => maps:get(inspection_fail, Out, false),
      string => maps:get(inspection_string, Out, <<>>),
      inspection => case I of
                        undefined -> undefined;
                        #{point := P, serial := S, stage := Stage} ->
                            #{point => P, serial => S, stage => Stage}
                    end,
      message => case M of
                     undefined -> undefined;
                     #{ref := R, id := Id, def := #{text := T, kind := K}, clients := Cs} ->
                         #{ref => R, id => Id, text => T, kind => K, clients => Cs}
                 end,
      clients => lists:sort(maps:keys(C))}.

%% @doc Whether a client may give this answer to this message: it must be the message
%% waiting now, shown to that client, and an answer its kind offers (Yes / No; OK; a
%% text, a number or a password, or Cancel).
-spec check_answer(state(), client(), ref(), term()) ->
          ok | {error, no_such_message | not_shown_to_client | {bad_answer, message_kind()}}.
check_answer(#st{message = #{ref := Ref, clients := Cs, def := #{kind := Kind}}}, Client,
             Ref, Answer) ->
    case lists:member(Client, Cs) of
        false -> {error, not_shown_to_client};
        true ->
            case fits(Kind, Answer) of
                true -> ok;
                false -> {error, {bad_answer, Kind}}
            end
    end;
check_answer(#st{}, _, _, _) ->
    {error, no_such_message}.

fits(yes_no, A) -> A =:= yes orelse A =:= no;
fits(ok, A) -> A =:= yes;
fits(number, {text, T}) when is_binary(T) -> is_number_text(T);
fits(_, {text, T}) -> is_binary(T);
fits(_, no) -> true;
fits(_, _) -> false.

is_number_text(T) ->
    S = string:trim(binary_to_list(T)),
    parses(fun list_to_integer/1, S) orelse parses(fun list_to_float/1, S).

parses(Fun, S) ->
    try _ = Fun(S), true
    catch error:badarg -> false
    end.

%%====================================================================
%% Events
%%====================================================================

event({plc_up, #{inputs := In, outputs := Out}}, {#st{plc = unknown} = St, Acc}) ->
    S1 = adopt(Out, {St#st{plc = up}, Acc}),
    settle(inputs(In, S1));
event({plc_up, #{inputs := In, outputs := Out}}, {St, Acc}) ->
    S1 = reassert(Out, {St#st{plc = up}, Acc}),
    settle(inputs(In, S1));
event(plc_down, {#st{plc = unknown}, _} = S) ->
    S;
event(plc_down, {St, Acc}) ->
    {St#st{plc = down}, Acc};
event({input, Tag, V}, {#st{plc = up}, _} = S) ->
    input(Tag, V, S);
event({input, _, _}, S) ->
    S;                                      %% stale: read again when the PLC is up
event(heartbeat, {#st{plc = unknown}, _} = S) ->
    S;
event(heartbeat, {#st{out = Out}, _} = S) ->
    set(heartbeat, not maps:get(heartbeat, Out, false), S);
event({config, #{points := Points, messages := Messages}}, {St, Acc}) ->
    Ws = maps:with([P || {P, ipm} <- maps:to_list(Points)], St#st.workspaces),
    settle({St#st{points = Points, messages = Messages, workspaces = Ws}, Acc});
event({workspace, Point, State}, {#st{workspaces = Ws} = St, Acc}) ->
    settle({St#st{workspaces = Ws#{Point => State}}, Acc});
event({client_up, Id, Caps}, {#st{clients = C} = St, Acc}) ->
    late_joiner(Id, Caps, {St#st{clients = C#{Id => Caps}}, Acc});
event({client_down, Id}, {#st{clients = C} = St, Acc}) ->
    client_gone(Id, {St#st{clients = maps:remove(Id, C)}, Acc});
event({image, Client, Ref, Image},
      {#st{inspection = #{ref := Ref, stage := requesting, clients := Cs} = I}, _} = S) ->
    case lists:member(Client, Cs) of
        true -> image(Client, Image, I, S);
        false -> log(warning, "an image from ~ts, which was not asked for one, is ignored",
                     [Client], S)
    end;
event({image, Client, _Ref, _}, S) ->
    log(brief, "a late image from ~ts is ignored: no inspection is waiting for it",
        [Client], S);
event({processed, Ref, Result},
      {#st{inspection = #{ref := Ref, stage := processing} = I} = St, Acc}) ->
    processed(Result, I, {St#st{inspection = undefined}, Acc});
event({processed, _, _}, S) ->
    S;
event({override_logged, Ref, Result}, {#st{override = Ref} = St, Acc}) ->
    override_logged(Result, {St#st{override = undefined}, Acc});
event({override_logged, _, _}, S) ->
    S;
event({answer, Client, Ref, Answer}, {#st{message = #{ref := Ref} = M} = St, _} = S) ->
    case check_answer(St, Client, Ref, Answer) of
        ok -> answer(Client, Answer, M, S);
        {error, _} -> S
    end;
event({answer, _, _, _}, S) ->
    S.

%%--------------------------------------------------------------------
%% The PLC
%%--------------------------------------------------------------------

%% The first sight of the PLC since the block started: its copy of the outputs is the
%% truth, except for a request the block can no longer finish.
adopt(Out, {St, Acc}) ->
    S0 = {St#st{out = Out}, Acc},
    S1 = case status_code_of(Out) of
             C when C =:= 3; C =:= 4 ->
                 S = set(inspection_status, status_code(error),
                         set(error_code, error_code(internal_error), S0)),
                 log(warning, "an inspection was under way (InspectionStatus ~s) when the "
                     "block stopped: InspectionStatus Error, ErrorCode InternalError",
                     [label(status, status_name(C))], S);
             C when C >= 0, C =< 6 -> S0;
             _ -> set(inspection_status, status_code(waiting_for_ipm), S0)
         end,
    S2 = case maps:get(error_code, Out, 0) of
             E when is_integer(E), E >= 0, E =< 6 -> S1;
             _ -> set(error_code, error_code(no_error), S1)
         end,
    case maps:get(message_status, Out, 0) of
        1 ->
            log(warning, "a message was waiting for an answer when the block stopped: "
                "MessageStatus ApplicationException",
                [], set(message_status, message_code(application_exception), S2));
        M when is_integer(M), M >= 0, M =< 6 -> S2;
        _ -> set(message_status, message_code(ready), S2)
    end.

status_code_of(Out) ->
    case maps:get(inspection_status, Out, 0) of
        C when is_integer(C) -> C;
        _ -> -1
    end.

%% After a lost link: whatever the PLC holds differently is written again, in the
%% order a command writes: values and codes before the statuses that announce them,
%% the command echoes last.
reassert(Out, {#st{out = Mine} = St, Acc}) ->
    Differs = [{T, V} || T <- ?REASSERT_ORDER,
                         {ok, V} <- [maps:find(T, Mine)], maps:get(T, Out, V) =/= V],
    {St, lists:reverse([{write, T, V} || {T, V} <- Differs], Acc)}.

%% The whole input image: values first, then the commands, in a fixed order.
inputs(In, S) ->
    S1 = lists:foldl(fun(T, Sx) ->
                             case maps:find(T, In) of
                                 {ok, V} -> input(T, V, Sx);
                                 error -> Sx
                             end
                     end, S, cell_inspect_tags:data_inputs()),
    lists:foldl(fun(T, Sx) ->
                        case maps:find(T, In) of
                            {ok, V} -> input(T, V, Sx);
                            error -> Sx
                        end
                end, S1, ?COMMAND_ORDER).

input(Tag, V, {#st{in = In, out = Out} = St, Acc}) ->
    S = {St#st{in = In#{Tag => V}}, Acc},
    Echo = cell_inspect_tags:echo(Tag),
    case cell_inspect_tags:kind(Tag) of
        bool when V =:= true ->
            case maps:get(Echo, Out, false) of
                false -> set(Echo, true, command(Tag, S));
                true -> S
            end;
        _ ->
            set(Echo, V, S)
    end.

%%--------------------------------------------------------------------
%% Commands
%%--------------------------------------------------------------------

command(trigger_inspection, {St, _} = S) ->
    Point = in(inspection_point_id, St),
    Status = status(St),
    Kind = maps:get(Point, St#st.points, undefined),
    case lists:member(Status, [ready, complete, canceled])
         orelse (Status =:= waiting_for_ipm andalso Kind =:= none) of
        true -> trigger(Point, Kind, S);
        false -> ignored(trigger_inspection, S)
    end;
command(clear_results, {St, _} = S) ->
    S1 = set(error_code, error_code(no_error),
             set(inspection_fail, false, set(inspection_pass, false, S))),
    S2 = case status(St) of
             Busy when Busy =:= requesting; Busy =:= processing -> S1;
             _ ->
                 set(inspection_status, status_code(case loaded(St) of
                                                        true -> ready;
                                                        false -> waiting_for_ipm
                                                    end), S1)
         end,
    log(brief, "results cleared", [], S2);
command(cancel_inspection, {#st{inspection = #{stage := requesting, ref := Ref,
                                               point := P, clients := Cs}} = St, Acc}) ->
    S = {St#st{inspection = undefined}, [{cancel_image, Cs, Ref} | Acc]},
    log(brief, "inspection ~ts canceled by the PLC", [P],
        set(inspection_status, status_code(canceled), S));
command(cancel_inspection, S) ->
    ignored(cancel_inspection, S);
command(log_override, {St, _} = S) ->
    case lists:member(status(St), [ready, complete, canceled]) of
        true -> override(S);
        false -> ignored(log_override, S)
    end;
command(send_message, S) ->
    send_message(S).

ignored(Command, {St, _} = S) ->
    Status = status(St),
    log(brief, "~ts ignored: InspectionStatus is ~s",
        [cell_inspect_tags:seed_name(Command), label(status, Status)], S).

%% Step 6.
trigger(Point, Kind, S0) ->
    S = set(inspection_status, status_code(requesting), S0),
    {St, _} = S,
    Serial = in(part_serial, St),
    case Kind of
        undefined ->
            fail(inspection_not_found, "inspection point ~ts does not exist", [Point], S);
        _ ->
            case [C || {C, Caps} <- lists:sort(maps:to_list(St#st.clients)),
                       serves(Caps, Point)] of
                [] ->
                    fail(device_not_found, "no camera serving ~ts is connected", [Point], S);
                Clients ->
                    {St1, Acc1} = S,
                    {Ref, St2} = next_ref(St1),
                    I = #{ref => Ref, point => Point, serial => Serial, stage => requesting,
                          clients => Clients},
                    Req = #{ref => Ref, point => Point, serial => Serial},
                    log(brief, "inspection ~ts of part ~ts: image requested from ~ts",
                        [Point, serial_text(Serial), lists:join(", ", Clients)],
                        {St2#st{inspection = I}, [{request_image, Clients, Req} | Acc1]})
            end
    end.

serves(#{images := true, points := all}, _) -> true;
serves(#{images := true, points := Ps}, Point) -> lists:member(Point, Ps);
serves(_, _) -> false.

%% Error with its code: the code first, so the PLC never reads Error with the old one.
fail(Code, Fmt, Args, S) ->
    log(warning, Fmt ++ ": InspectionStatus Error, ErrorCode ~s",
        Args ++ [label(error, Code)],
        set(inspection_status, status_code(error), set(error_code, error_code(Code), S))).

%% Step 8: an image; the other cameras are told to stop.
image(Client, Image, #{ref := Ref, point := P, serial := Serial, clients := Cs} = I,
      {St, Acc}) ->
    Others = Cs -- [Client],
    Acc1 = case Others of
               [] -> Acc;
               _ -> [{cancel_image, Others, Ref} | Acc]
           end,
    S = set(inspection_status, status_code(processing),
            {St#st{inspection = I#{stage := processing}}, Acc1}),
    Job = #{point => P, serial => Serial, client => Client, image => Image,
            mode => mode(P, St)},
    {St2, Acc2} = log(brief, "inspection ~ts: image received from ~ts", [P, Client], S),
    {St2, [{process, Ref, Job} | Acc2]}.

mode(Point, #st{points = Points, workspaces = Ws}) ->
    case maps:get(Point, Points, undefined) of
        none -> none;
        ipm ->
            case maps:get(Point, Ws, loading) of
                ready -> ipm;
                loading -> {error, processing_not_available};
                failed -> {error, inspection_configuration_error}
            end;
        misconfigured -> {error, inspection_configuration_error};
        undefined -> {error, inspection_not_found}
    end.

%% Step 9.
processed({error, Code}, #{point := P}, S) ->
    fail(Code, "inspection ~ts could not be completed", [P], S);
processed({Verdict, Text}, #{point := P, serial := Serial}, S) ->
    S1 = set(inspection_string, Text,
             set(inspection_fail, Verdict =:= fail,
                 set(inspection_pass, Verdict =:= pass, S))),
    log(brief, "inspection ~ts of part ~ts: ~s~ts", [P, serial_text(Serial),
                                                    case Verdict of
                                                        pass -> "PASS";
                                                        fail -> "FAIL"
                                                    end, text_note(Text)],
        set(inspection_status, status_code(complete), S1)).

%% PLC Override Logic, step 4.
override({St, Acc}) ->
    {Ref, St1} = next_ref(St),
    Ov = #{point => in(inspection_point_id, St), serial => in(part_serial, St),
           employee => in(override_employee_id, St)},
    set(inspection_status, status_code(processing),
        {St1#st{override = Ref}, [{log_override, Ref, Ov} | Acc]}).

override_logged(logged, S) ->
    log(brief, "override logged", [], set(inspection_status, status_code(complete), S));
override_logged(not_found, S) ->
    fail(inspection_not_found, "no inspection result to override", [], S);
override_logged({error, _}, S) ->
    fail(internal_error, "the override could not be recorded", [], S).

%% Send Message Logic, steps 3 to 7.
send_message({St, Acc}) ->
    S = case St#st.message of
            #{ref := Old, clients := OldCs} ->
                {St#st{message = undefined}, [{withdraw_message, OldCs, Old} | Acc]};
            undefined ->
                {St, Acc}
        end,
    {St1, _} = S,
    Id = in(message_id, St1),
    case message_clients(St1) of
        [] ->
            log(warning, "message ~b not sent: no client is connected", [Id],
                set(message_status, message_code(no_available_clients), S));
        Clients ->
            case maps:find(Id, St1#st.messages) of
                error ->
                    log(warning, "message ~b is not configured", [Id],
                        set(message_status, message_code(message_not_found), S));
                {ok, #{text := Text, kind := Kind} = Def} ->
                    S1 = set(message_status, message_code(waiting),
                             set(message_result, <<>>, S)),
                    {St2, Acc2} = S1,
                    {Ref, St3} = next_ref(St2),
                    M = #{ref => Ref, id => Id, def => Def, clients => Clients},
                    Show = #{ref => Ref, id => Id, text => Text, kind => Kind},
                    log(brief, "message ~b sent to ~ts", [Id, lists:join(", ", Clients)],
                        {St3#st{message = M}, [{show_message, Clients, Show} | Acc2]})
            end
    end.

message_clients(#st{clients = C}) ->
    [Id || {Id, #{messages := true}} <- lists:sort(maps:to_list(C))].

%% Steps 8 to 11.
answer(Client, Answer, #{ref := Ref, id := Id, clients := Cs}, {St, Acc}) ->
    S0 = {St#st{message = undefined},
          case Cs -- [Client] of
              [] -> Acc;
              Others -> [{withdraw_message, Others, Ref} | Acc]
          end},
    S1 = case Answer of
             yes -> set(message_status, message_code(affirmative_response), S0);
             no -> set(message_status, message_code(negative_response), S0);
             {text, T} -> set(message_status, message_code(affirmative_response),
                              set(message_result, T, S0))
         end,
    log(brief, "message ~b answered by ~ts: ~ts", [Id, Client, answer_text(Answer)], S1).

answer_text(yes) -> "yes";
answer_text(no) -> "no";
answer_text({text, _}) -> "a text".

%%--------------------------------------------------------------------
%% Clients
%%--------------------------------------------------------------------

%% A camera that connects while a request or a message waits gets it too.
late_joiner(Id, Caps, {St, Acc}) ->
    S1 = case St#st.inspection of
             #{stage := requesting, point := P, serial := Serial, ref := Ref,
               clients := Cs} = I ->
                 case serves(Caps, P) andalso not lists:member(Id, Cs) of
                     true ->
                         {St#st{inspection = I#{clients := Cs ++ [Id]}},
                          [{request_image, [Id], #{ref => Ref, point => P, serial => Serial}}
                           | Acc]};
                     false -> {St, Acc}
                 end;
             _ -> {St, Acc}
         end,
    {St1, Acc1} = S1,
    case St1#st.message of
        #{ref := MRef, id := MId, def := #{text := T, kind := K}, clients := MCs} = M ->
            case maps:get(messages, Caps) andalso not lists:member(Id, MCs) of
                true ->
                    {St1#st{message = M#{clients := MCs ++ [Id]}},
                     [{show_message, [Id], #{ref => MRef, id => MId, text => T, kind => K}}
                      | Acc1]};
                false -> S1
            end;
        undefined -> S1
    end.

client_gone(Id, {St, _} = S) ->
    S1 = case St#st.inspection of
             #{stage := requesting, clients := Cs, point := P} = I ->
                 case lists:member(Id, Cs) of
                     true ->
                         case Cs -- [Id] of
                             [] ->
                                 {St1, Acc1} = S,
                                 fail(device_not_found,
                                      "inspection ~ts: every camera asked for an image "
                                      "disconnected", [P],
                                      {St1#st{inspection = undefined}, Acc1});
                             Left ->
                                 {St1, Acc1} = S,
                                 {St1#st{inspection = I#{clients := Left}}, Acc1}
                         end;
                     false -> S
                 end;
             _ -> S
         end,
    {St2, Acc2} = S1,
    case St2#st.message of
        #{clients := MCs, id := MId} = M ->
            case lists:member(Id, MCs) of
                true ->
                    case MCs -- [Id] of
                        [] ->
                            log(warning, "message ~b: every client disconnected before an "
                                "answer", [MId],
                                set(message_status, message_code(no_available_clients),
                                    {St2#st{message = undefined}, Acc2}));
                        Remaining ->
                            {St2#st{message = M#{clients := Remaining}}, Acc2}
                    end;
                false -> S1
            end;
        undefined -> S1
    end.

%%--------------------------------------------------------------------
%% Helpers
%%--------------------------------------------------------------------

%% WaitingForIPM ends once every workspace is loaded (or has failed to load).
settle({#st{plc = unknown}, _} = S) ->
    S;
settle({St, _} = S) ->
    case status(St) =:= waiting_for_ipm andalso loaded(St) of
        true -> log(brief, "image processing loaded: ready for a trigger", [],
                    set(inspection_status, status_code(ready), S));
        false -> S
    end.

loaded(#st{points = Points, workspaces = Ws}) ->
    lists:all(fun({P, ipm}) -> maps:get(P, Ws, loading) =/= loading;
                 (_) -> true
              end, maps:to_list(Points)).

in(Tag, #st{in = In}) ->
    maps:get(Tag, In, case cell_inspect_tags:kind(Tag) of
                          int -> 0;
                          _ -> <<>>
                      end).

next_ref(#st{inc = Inc, seq = N} = St) ->
    {{Inc, N + 1}, St#st{seq = N + 1}}.

%% An output changes: written only when it differs from what the PLC holds.
set(Tag, V, {#st{out = Out} = St, Acc} = S) ->
    case Out of
        #{Tag := V} -> S;
        _ -> {St#st{out = Out#{Tag => V}}, [{write, Tag, V} | Acc]}
    end.

log(Level, Fmt, Args, {St, Acc}) ->
    {St, [{log, Level, Fmt, Args} | Acc]}.

serial_text(<<>>) -> "(no serial)";
serial_text(S) -> S.

text_note(<<>>) -> "";
text_note(T) -> [" \"", T, "\""].

label(status, S) -> [seed_word(status, S), " (", integer_to_list(status_code(S)), ")"];
label(error, E) -> [seed_word(error, E), " (", integer_to_list(error_code(E)), ")"].

seed_word(status, waiting_for_ipm) -> "WaitingForIPM";
seed_word(status, ready) -> "Ready";
seed_word(status, complete) -> "Complete";
seed_word(status, requesting) -> "Requesting";
seed_word(status, processing) -> "Processing";
seed_word(status, error) -> "Error";
seed_word(status, canceled) -> "Canceled";
seed_word(error, no_error) -> "NoError";
seed_word(error, device_not_found) -> "DeviceNotFound";
seed_word(error, inspection_not_found) -> "InspectionNotFound";
seed_word(error, processing_error) -> "ProcessingError";
seed_word(error, internal_error) -> "InternalError";
seed_word(error, inspection_configuration_error) -> "InspectionConfigurationError";
seed_word(error, processing_not_available) -> "ProcessingNotAvailable".

%%====================================================================
%% The seed's tables
%%====================================================================

-define(STATUS, [{waiting_for_ipm, 0}, {ready, 1}, {complete, 2}, {requesting, 3},
                 {processing, 4}, {error, 5}, {canceled, 6}]).
-define(ERRORS, [{no_error, 0}, {device_not_found, 1}, {inspection_not_found, 2},
                 {processing_error, 3}, {internal_error, 4},
                 {inspection_configuration_error, 5}, {processing_not_available, 6}]).
-define(MESSAGE, [{ready, 0}, {waiting, 1}, {message_not_found, 2},
                  {no_available_clients, 3}, {application_exception, 4},
                  {affirmative_response, 5}, {negative_response, 6}]).

%% @doc InspectionStatus: the seed's code of a status.
-spec status_code(status()) -> 0..6.
status_code(S) -> code(S, ?STATUS).

%% @doc InspectionStatus: the status of a code (an unknown code reads WaitingForIPM).
-spec status_name(integer()) -> status().
status_name(C) -> name(C, ?STATUS, waiting_for_ipm).

%% @doc ErrorCode: the seed's code of an error.
-spec error_code(error_name()) -> 0..6.
error_code(E) -> code(E, ?ERRORS).

-spec error_name(integer()) -> error_name().
error_name(C) -> name(C, ?ERRORS, no_error).

%% @doc MessageStatus: the seed's code.
-spec message_code(message_status()) -> 0..6.
message_code(M) -> code(M, ?MESSAGE).

-spec message_name(integer()) -> message_status().
message_name(C) -> name(C, ?MESSAGE, ready).

code(Name, Table) ->
    {Name, C} = lists:keyfind(Name, 1, Table),
    C.

name(C, Table, Default) ->
    case lists:keyfind(C, 2, Table) of
        {Name, C} -> Name;
        false -> Default
    end.
