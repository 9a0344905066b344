%% A PropEr state-machine property of the block's status machine (cell_inspect_status)
%% against a model written from seed 004: the Inspection Status, Error Code and
%% MessageStatus tables and the numbered steps of the Trigger, Override and Send
%% Message logic, plus the block's documented decisions where the seed is silent.
%%
%% The test plays the PLC (its writes to the input tags, with or without the echo
%% handshake), the cameras and the message clients (connecting, leaving, sending images,
%% answering), the image processing and the database (results, failures), the link
%% (down, up) and crashes (the block restarts from what the PLC holds). A harness
%% process runs the status machine and applies its writes to the PLC's copy of the
%% block while the link is up, as the block process does. Postconditions compare the
%% PLC's copy with the model after every command and check the order of the writes:
%% ErrorCode before Error, MessageResult emptied before Waiting, a command's echo last.
-module(prop_cell_inspect_status).
-include_lib("proper/include/proper.hrl").
-include_lib("eunit/include/eunit.hrl").

-behaviour(proper_statem).

-export([initial_state/0, command/1, precondition/2, postcondition/3, next_state/3]).
-export([plc_data/2, plc_bit/2, client_up/1, client_down/1, image/1, processed/1,
         override_done/0, answer/2, heartbeat/0, workspace/1, db/1, link/1, restart/0]).
-export([start_harness/0, stop_harness/0]).

-define(S, cell_inspect_status).
-define(HARNESS, prop_cell_inspect_status_harness).

%%====================================================================
%% EUnit
%%====================================================================

property_test_() ->
    {timeout, 300, ?_assert(proper:quickcheck(prop_status_machine(),
                                              [{to_file, user}, {numtests, 1000}]))}.

prop_status_machine() ->
    ?FORALL(Cmds, more_commands(10, proper_statem:commands(?MODULE)),
            begin
                ok = start_harness(),
                {History, Model, Result} = proper_statem:run_commands(?MODULE, Cmds),
                ok = stop_harness(),
                Reached = lists:usort(
                            [{status, ?S:status_name(maps:get(inspection_status, Img))}
                             || {_, #{image := Img}} <- History] ++
                            [{message, ?S:message_name(maps:get(message_status, Img))}
                             || {_, #{image := Img}} <- History]),
                ?WHENFAIL(io:format("history ~p~nmodel ~p~nresult ~p~n",
                                    [History, Model, Result]),
                          aggregate(proper_statem:command_names(Cmds),
                                    aggregate(Reached, Result =:= ok)))
            end).

%%====================================================================
%% The model, from the seed
%%====================================================================

-define(POINTS, [<<"P1">>, <<"P2">>, <<"P3">>, <<"NOPE">>]).
-define(CLIENTS, [<<"c1">>, <<"c2">>, <<"c3">>]).
%% Inspection points: P1 has no image processing (no IPM workspace), P2 has one, P3 is
%% misconfigured; NOPE is not configured.
kind(<<"P1">>) -> none;
kind(<<"P2">>) -> ipm;
kind(<<"P3">>) -> misconfigured;
kind(_) -> undefined.
%% c1 serves every point, c2 only P2, c3 takes messages only (as the panel does).
caps(<<"c1">>) -> #{points => all, images => true, messages => true};
caps(<<"c2">>) -> #{points => [<<"P2">>], images => true, messages => true};
caps(<<"c3">>) -> #{points => all, images => false, messages => true}.
%% Messages: 7 asks Yes / No, 8 asks for a text.
message_kind(7) -> yes_no;
message_kind(8) -> text;
message_kind(_) -> undefined.

-define(COMMANDS, [trigger_inspection, clear_results, cancel_inspection, log_override,
                   send_message]).

-record(m, {up = true :: boolean(),          %% the link to the PLC
            seen = true :: boolean(),        %% the block has read the PLC since it started
            in :: map(),                     %% what the PLC has written
            out :: map(),                    %% the block's outputs
            frozen :: map() | undefined,     %% the PLC's copy while the link is down
            clients = #{} :: map(),
            ws = loading :: loading | ready | failed,
            insp = none :: none | {requesting, binary(), binary(), [binary()]}
                         | {processing, binary(), binary(), term()},
            override = none :: none | {binary(), binary()},
            message = none :: none | {waiting, integer(), [binary()]},
            results = [] :: [{binary(), binary()}],
            db_ok = true :: boolean()}).

inputs0() ->
    #{trigger_inspection => false, clear_results => false, cancel_inspection => false,
      log_override => false, send_message => false, inspection_point_id => <<>>,
      part_serial => <<>>, override_employee_id => <<>>, message_id => 0}.

outputs0() ->
    maps:from_list([{T, case cell_inspect_tags:kind(T) of
                            bool -> false;
                            int -> 0;
                            _ -> <<>>
                        end} || T <- cell_inspect_tags:outputs()]).

%% The block has read a PLC holding point P1 and message 7, loaded its workspaces
%% (Ready), and camera c1 is connected.
initial_state() ->
    #m{in = start_inputs(), ws = ready, clients = #{<<"c1">> => caps(<<"c1">>)},
       out = (outputs0())#{inspection_status => 1, inspection_point_id_echo => <<"P1">>,
                           message_id_echo => 7}}.

start_inputs() ->
    (inputs0())#{inspection_point_id => <<"P1">>, message_id => 7}.

%% Weighted by state, so that whole sequences happen often: cameras connect, the PLC
%% raises a command when it would be accepted and drops it once echoed, the camera
%% asked sends its image, the client shown a message answers it. Everything else
%% (out-of-turn commands, links lost, crashes) keeps a small weight.
command(#m{in = In, clients = C, ws = Ws} = M) ->
    Connected = maps:keys(C),
    Absent = ?CLIENTS -- Connected,
    Asked = case M#m.insp of
                {requesting, _, _, Cs} -> Cs;
                _ -> []
            end,
    Shown = case M#m.message of
                {waiting, _, MCs} -> MCs;
                none -> []
            end,
    Status = status(M),
    Idle = lists:member(Status, [1, 2, 6]),
    Useful = fun(trigger_inspection) -> Idle;
                (clear_results) -> Status =:= 5 orelse Status =:= 2;
                (cancel_inspection) -> Status =:= 3;
                (log_override) -> Idle andalso M#m.results =/= [];
                (send_message) -> Connected =/= []
             end,
    Bits = [{case {maps:get(Cmd, In), Useful(Cmd)} of
                 {true, _} -> 4;              %% echoed: the PLC drops it
                 {false, true} when Cmd =:= cancel_inspection -> 3;
                 {false, true} -> 6;
                 {false, false} -> 1
             end, {call, ?MODULE, plc_bit, [Cmd, not maps:get(Cmd, In)]}}
            || Cmd <- ?COMMANDS],
    Cameras = [X || X <- Connected, maps:get(images, caps(X))],
    frequency(
      Bits ++
      [{case maps:get(inspection_point_id, In) of <<"P", _>> -> 1; _ -> 8 end,
        {call, ?MODULE, plc_data,
         [inspection_point_id, elements([<<"P1">>, <<"P1">>, <<"P2">> | ?POINTS])]}},
       {1, {call, ?MODULE, plc_data, [part_serial, elements([<<>>, <<"S1">>, <<"S2">>])]}},
       {1, {call, ?MODULE, plc_data, [override_employee_id, elements([<<"E1">>, <<"E2">>])]}},
       {1, {call, ?MODULE, plc_data, [message_id, elements([7, 8, 99])]}},
       {1, {call, ?MODULE, image, [elements(?CLIENTS)]}},
       {case M#m.insp of {processing, _, _, _} -> 8; _ -> 1 end,
        {call, ?MODULE, processed, [elements([pass, pass, fail, fail, processing_error])]}},
       {case M#m.override of none -> 1; _ -> 6 end, {call, ?MODULE, override_done, []}},
       {1, {call, ?MODULE, answer, [elements(?CLIENTS),
                                    elements([yes, no, {text, <<"T1">>}])]}},
       {1, {call, ?MODULE, heartbeat, []}},
       case Ws of
           loading -> {4, {call, ?MODULE, workspace, [elements([ready, ready, ready, failed])]}};
           _ -> {1, {call, ?MODULE, workspace, [elements([loading, ready, failed])]}}
       end,
       {1, {call, ?MODULE, db, [weighted_union([{3, true}, {1, false}])]}},
       {case M#m.up of true -> 1; false -> 5 end, {call, ?MODULE, link, [not M#m.up]}},
       {1, {call, ?MODULE, restart, []}}] ++
      [{12, {call, ?MODULE, image, [elements(Asked)]}} || Asked =/= []] ++
      [{8, {call, ?MODULE, answer, [elements(Shown), elements([yes, no, {text, <<"T1">>}])]}}
       || Shown =/= []] ++
      [{case Cameras of [] -> 8; _ -> 1 end, {call, ?MODULE, client_up, [elements(Absent)]}}
       || Absent =/= []] ++
      [{1, {call, ?MODULE, client_down, [elements(Connected)]}} || Connected =/= []]).

%% The PLC writes a value only when it changes it (the HAL reports changes).
precondition(#m{in = In}, {call, _, plc_data, [T, V]}) -> maps:get(T, In) =/= V;
precondition(#m{in = In}, {call, _, plc_bit, [T, V]}) -> maps:get(T, In) =/= V;
precondition(#m{clients = C}, {call, _, client_up, [Id]}) -> not maps:is_key(Id, C);
precondition(#m{clients = C}, {call, _, client_down, [Id]}) -> maps:is_key(Id, C);
precondition(#m{up = Up}, {call, _, link, [To]}) -> Up =/= To;
precondition(_, _) -> true.

%%--------------------------------------------------------------------
%% Transitions
%%--------------------------------------------------------------------

next_state(#m{in = In} = M, _, {call, _, plc_data, [T, V]}) ->
    M1 = M#m{in = In#{T => V}},
    case live(M) of
        true -> echo(T, V, M1);
        false -> M1
    end;
next_state(#m{in = In} = M, _, {call, _, plc_bit, [T, V]}) ->
    M1 = M#m{in = In#{T => V}},
    case live(M) of
        true -> bit(T, V, M1);
        false -> M1
    end;
next_state(M, _, {call, _, link, [false]}) ->
    M#m{up = false, frozen = M#m.out};
next_state(#m{seen = true} = M, _, {call, _, link, [true]}) ->
    settle(inputs(M#m{up = true, frozen = undefined}));
next_state(#m{seen = false, frozen = F} = M, _, {call, _, link, [true]}) ->
    settle(inputs(adopt(M#m{up = true, seen = true, frozen = undefined, out = F})));
next_state(#m{up = true} = M, _, {call, _, restart, []}) ->
    settle(inputs(adopt(forget(M))));
next_state(#m{up = false} = M, _, {call, _, restart, []}) ->
    (forget(M))#m{seen = false};
next_state(#m{clients = C} = M, _, {call, _, client_up, [Id]}) ->
    joined(Id, M#m{clients = C#{Id => caps(Id)}});
next_state(#m{clients = C} = M, _, {call, _, client_down, [Id]}) ->
    left(Id, M#m{clients = maps:remove(Id, C)});
next_state(#m{insp = {requesting, P, S, Cs}} = M, _, {call, _, image, [Id]}) ->
    case lists:member(Id, Cs) of
        true -> set(inspection_status, 4, M#m{insp = {processing, P, S, mode(P, M)}});
        false -> M
    end;
next_state(M, _, {call, _, image, [_]}) ->
    M;
next_state(#m{insp = {processing, P, S, Mode}} = M, _, {call, _, processed, [Choice]}) ->
    job_result(result(Mode, Choice, M), P, S, M#m{insp = none});
next_state(M, _, {call, _, processed, [_]}) ->
    M;
next_state(#m{override = {P, S}, db_ok = Ok, results = R} = M, _, {call, _, override_done, []}) ->
    M1 = M#m{override = none},
    case Ok andalso lists:member({P, S}, R) of
        true -> set(inspection_status, 2, M1);
        false when Ok -> error_status(2, M1);
        false -> error_status(4, M1)
    end;
next_state(M, _, {call, _, override_done, []}) ->
    M;
next_state(#m{message = {waiting, Id, Cs}} = M, _, {call, _, answer, [Client, A]}) ->
    case lists:member(Client, Cs) andalso fits(message_kind(Id), A) of
        true ->
            M1 = M#m{message = none},
            case A of
                yes -> set(message_status, 5, M1);
                no -> set(message_status, 6, M1);
                {text, T} -> set(message_status, 5, set(message_result, T, M1))
            end;
        false -> M
    end;
next_state(M, _, {call, _, answer, _}) ->
    M;
next_state(#m{seen = true, out = Out} = M, _, {call, _, heartbeat, []}) ->
    set(heartbeat, not maps:get(heartbeat, Out), M);
next_state(M, _, {call, _, heartbeat, []}) ->
    M;
next_state(M, _, {call, _, workspace, [W]}) ->
    case M#m.seen of
        true -> settle(M#m{ws = W});
        false -> M#m{ws = W}
    end;
next_state(M, _, {call, _, db, [Ok]}) ->
    M#m{db_ok = Ok}.

live(#m{up = Up, seen = Seen}) -> Up andalso Seen.

%% A restarted block loads its workspaces again.
forget(M) ->
    M#m{insp = none, override = none, message = none, ws = loading}.

%% InspectionStatus and MessageStatus the PLC holds after a restart.
adopt(#m{out = Out} = M) ->
    M1 = case maps:get(inspection_status, Out) of
             S when S =:= 3; S =:= 4 -> error_status(4, M);
             _ -> M
         end,
    case maps:get(message_status, M1#m.out) of
        1 -> set(message_status, 4, M1);
        _ -> M1
    end.

%% Everything the PLC holds, read at once: values first, then the commands, resets
%% before what follows them (the block's documented order).
inputs(#m{in = In} = M) ->
    M1 = lists:foldl(fun(T, Mx) -> echo(T, maps:get(T, In), Mx) end, M,
                     [inspection_point_id, part_serial, override_employee_id, message_id]),
    lists:foldl(fun(T, Mx) -> bit(T, maps:get(T, In), Mx) end, M1,
                [clear_results, cancel_inspection, trigger_inspection, log_override,
                 send_message]).

echo(T, V, M) -> set(cell_inspect_tags:echo(T), V, M).

%% A command acts when it reads 1 while its echo says 0.
bit(T, true, #m{out = Out} = M) ->
    Echo = cell_inspect_tags:echo(T),
    case maps:get(Echo, Out) of
        false -> set(Echo, true, command(T, M));
        true -> M
    end;
bit(T, false, M) ->
    set(cell_inspect_tags:echo(T), false, M).

status(#m{out = Out}) -> maps:get(inspection_status, Out).

%% Trigger step 1, Override step 1: accepted in Ready, Complete, Canceled; a trigger
%% also in WaitingForIPM for a point without a workspace.
command(trigger_inspection, #m{in = In} = M) ->
    P = maps:get(inspection_point_id, In),
    case lists:member(status(M), [1, 2, 6]) orelse (status(M) =:= 0 andalso kind(P) =:= none) of
        true -> trigger(P, maps:get(part_serial, In), set(inspection_status, 3, M));
        false -> M
    end;
command(clear_results, M) ->
    M1 = set(error_code, 0, set(inspection_fail, false, set(inspection_pass, false, M))),
    case status(M) of
        S when S =:= 3; S =:= 4 -> M1;
        _ when M#m.ws =:= loading -> set(inspection_status, 0, M1);
        _ -> set(inspection_status, 1, M1)
    end;
command(cancel_inspection, #m{insp = {requesting, _, _, _}} = M) ->
    set(inspection_status, 6, M#m{insp = none});
command(cancel_inspection, M) ->
    M;
command(log_override, #m{in = In} = M) ->
    case lists:member(status(M), [1, 2, 6]) of
        true -> set(inspection_status, 4,
                    M#m{override = {maps:get(inspection_point_id, In), maps:get(part_serial, In)}});
        false -> M
    end;
command(send_message, #m{in = In, clients = C} = M0) ->
    M = M0#m{message = none},
    Id = maps:get(message_id, In),
    case [X || X <- lists:sort(maps:keys(C)), maps:get(messages, caps(X))] of
        [] -> set(message_status, 3, M);
        Cs ->
            case message_kind(Id) of
                undefined -> set(message_status, 2, M);
                _ -> set(message_status, 1, set(message_result, <<>>,
                                                M#m{message = {waiting, Id, Cs}}))
            end
    end.

%% Trigger step 6.
trigger(P, S, #m{clients = C} = M) ->
    case kind(P) of
        undefined -> error_status(2, M);
        _ ->
            case [X || X <- lists:sort(maps:keys(C)), serves(X, P)] of
                [] -> error_status(1, M);
                Cs -> M#m{insp = {requesting, P, S, Cs}}
            end
    end.

serves(Client, P) ->
    case caps(Client) of
        #{images := true, points := all} -> true;
        #{images := true, points := Ps} -> lists:member(P, Ps);
        _ -> false
    end.

error_status(Code, M) ->
    set(inspection_status, 5, set(error_code, Code, M)).

%% ProcessingNotAvailable (6) while the workspace loads, InspectionConfigurationError
%% (5) when it failed to load or the point is misconfigured.
mode(P, #m{ws = Ws}) ->
    case {kind(P), Ws} of
        {none, _} -> none;
        {ipm, ready} -> ipm;
        {ipm, loading} -> {error, 6};
        {ipm, failed} -> {error, 5};
        {misconfigured, _} -> {error, 5}
    end.

%% What the processing job gives: a point without a workspace passes; a result that
%% cannot be recorded is InternalError (4).
result({error, C}, _, _) -> {error, C};
result(Mode, Choice, #m{db_ok = Ok}) ->
    R = case {Mode, Choice} of
            {none, _} -> pass;
            {ipm, processing_error} -> {error, 3};
            {ipm, V} -> V
        end,
    case R of
        {error, _} -> R;
        _ when Ok -> R;
        _ -> {error, 4}
    end.

%% Trigger step 9.
job_result({error, C}, _, _, M) ->
    error_status(C, M);
job_result(V, P, S, #m{results = R} = M) ->
    M1 = set(inspection_pass, V =:= pass, M#m{results = lists:usort([{P, S} | R])}),
    M2 = set(inspection_fail, V =:= fail, M1),
    set(inspection_status, 2, set(inspection_string, text(V), M2)).

text(pass) -> <<"T-PASS">>;
text(fail) -> <<>>.

fits(yes_no, A) -> A =:= yes orelse A =:= no;
fits(text, no) -> true;
fits(text, {text, _}) -> true;
fits(_, _) -> false.

%% A client that connects while a request or a message waits gets it.
joined(Id, #m{insp = {requesting, P, S, Cs}} = M) ->
    joined_msg(Id, case serves(Id, P) of
                       true -> M#m{insp = {requesting, P, S, Cs ++ [Id]}};
                       false -> M
                   end);
joined(Id, M) ->
    joined_msg(Id, M).

joined_msg(Id, #m{message = {waiting, MId, Cs}} = M) ->
    case maps:get(messages, caps(Id)) of
        true -> M#m{message = {waiting, MId, Cs ++ [Id]}};
        false -> M
    end;
joined_msg(_, M) ->
    M.

%% Every camera asked for an image gone: DeviceNotFound; every message client gone:
%% NoAvailableClients (Send Message step 6).
left(Id, M0) ->
    M = case M0#m.insp of
            {requesting, P, S, Cs} ->
                case {lists:member(Id, Cs), Cs -- [Id]} of
                    {true, []} -> error_status(1, M0#m{insp = none});
                    {true, Rest} -> M0#m{insp = {requesting, P, S, Rest}};
                    {false, _} -> M0
                end;
            _ -> M0
        end,
    case M#m.message of
        {waiting, MId, MCs} ->
            case {lists:member(Id, MCs), MCs -- [Id]} of
                {true, []} -> set(message_status, 3, M#m{message = none});
                {true, Rest2} -> M#m{message = {waiting, MId, Rest2}};
                {false, _} -> M
            end;
        none -> M
    end.

settle(#m{ws = Ws} = M) ->
    case status(M) =:= 0 andalso Ws =/= loading of
        true -> set(inspection_status, 1, M);
        false -> M
    end.

set(T, V, #m{out = Out} = M) -> M#m{out = Out#{T => V}}.

%%--------------------------------------------------------------------
%% Postconditions
%%--------------------------------------------------------------------

postcondition(M, Call, #{image := Img, pre := Pre, effects := Effects}) ->
    M1 = next_state(M, undefined, Call),
    Expected = case M1#m.up of
                   true -> M1#m.out;
                   false -> M1#m.frozen
               end,
    Writes = [{T, V} || {write, T, V} <- Effects],
    Img =:= Expected
        andalso consistent(Img)
        andalso ordered(Pre, Writes)
        andalso echo_last(M, Call, Writes);
postcondition(_, _, _) ->
    false.

%% At rest, ErrorCode is not 0 exactly in Error.
consistent(Img) ->
    (maps:get(error_code, Img) =/= 0) =:= (maps:get(inspection_status, Img) =:= 5).

%% Write by write: Error never shows without its code, Waiting never with an old result.
ordered(_, []) ->
    true;
ordered(Img, [{inspection_status, 5} | _]) when map_get(error_code, Img) =:= 0 ->
    false;
ordered(Img, [{message_status, 1} | _]) when map_get(message_result, Img) =/= <<>> ->
    false;
ordered(Img, [{T, V} | Rest]) ->
    ordered(Img#{T => V}, Rest).

%% A command taken at its edge: its echo is the last write, so a PLC that reads the
%% echo reads the command's outcome with it.
echo_last(#m{up = true, seen = true, out = Out}, {call, _, plc_bit, [T, true]}, Writes) ->
    Echo = cell_inspect_tags:echo(T),
    case maps:get(Echo, Out) of
        false -> lists:last(Writes) =:= {Echo, true};
        true -> true
    end;
echo_last(_, _, _) ->
    true.

%%====================================================================
%% The harness: the PLC, the cameras, the processing, the database
%%====================================================================

-record(h, {st :: term(),
            inc = 1 :: pos_integer(),
            up = true :: boolean(),
            img :: map(),                          %% the PLC's copy of the outputs
            in :: map(),
            clients = #{} :: map(),
            requests = #{} :: map(),               %% client -> ref of its request
            shown = #{} :: map(),                  %% client -> ref of its message
            job :: undefined | {term(), term(), binary(), binary()},
            override :: undefined | {term(), binary(), binary()},
            results = [] :: list(),
            db_ok = true :: boolean()}).

config() ->
    #{points => maps:from_list([{P, kind(P)} || P <- ?POINTS, kind(P) =/= undefined]),
      messages => #{7 => #{text => <<"OK?">>, kind => yes_no},
                    8 => #{text => <<"Lot">>, kind => text}}}.

start_harness() ->
    Pid = spawn(fun() ->
                        St0 = ?S:new(1, config()),
                        {St1, E1} = ?S:handle({plc_up, #{inputs => start_inputs(),
                                                         outputs => outputs0()}}, St0),
                        {St2, E2} = ?S:handle({workspace, <<"P2">>, ready}, St1),
                        {St, E3} = ?S:handle({client_up, <<"c1">>, caps(<<"c1">>)}, St2),
                        H = apply_effects(E1 ++ E2 ++ E3,
                                          #h{st = St, img = outputs0(), in = start_inputs(),
                                             clients = #{<<"c1">> => caps(<<"c1">>)}}),
                        loop(H)
                end),
    true = register(?HARNESS, Pid),
    ok.

stop_harness() ->
    Ref = monitor(process, ?HARNESS),
    ?HARNESS ! stop,
    receive {'DOWN', Ref, process, _, _} -> ok end.

loop(H) ->
    receive
        {step, From, Fun} ->
            Pre = H#h.img,
            {Effects, H1} = Fun(H),
            From ! {stepped, #{image => H1#h.img, pre => Pre, effects => Effects}},
            loop(H1);
        stop ->
            ok
    end.

step(Fun) ->
    ?HARNESS ! {step, self(), Fun},
    receive {stepped, R} -> R end.

%% Feeds events to the status machine and carries out its effects.
feed(Events, H) ->
    lists:foldl(fun(E, {Acc, Hx}) ->
                        {St, Effects} = ?S:handle(E, Hx#h.st),
                        {Acc ++ Effects, apply_effects(Effects, Hx#h{st = St})}
                end, {[], H}, Events).

apply_effects(Effects, H) ->
    lists:foldl(fun apply_effect/2, H, Effects).

apply_effect({write, T, V}, #h{up = true, img = Img} = H) -> H#h{img = Img#{T => V}};
apply_effect({write, _, _}, H) -> H;
apply_effect({request_image, Cs, #{ref := Ref}}, #h{requests = R} = H) ->
    H#h{requests = maps:merge(R, maps:from_list([{C, Ref} || C <- Cs]))};
apply_effect({cancel_image, Cs, _}, #h{requests = R} = H) -> H#h{requests = maps:without(Cs, R)};
apply_effect({process, Ref, #{mode := Mode, point := P, serial := S}}, H) ->
    H#h{job = {Ref, Mode, P, S}, requests = #{}};
apply_effect({log_override, Ref, #{point := P, serial := S}}, H) -> H#h{override = {Ref, P, S}};
apply_effect({show_message, Cs, #{ref := Ref}}, #h{shown = Sh} = H) ->
    H#h{shown = maps:merge(Sh, maps:from_list([{C, Ref} || C <- Cs]))};
apply_effect({withdraw_message, Cs, _}, #h{shown = Sh} = H) -> H#h{shown = maps:without(Cs, Sh)};
apply_effect({log, _, Fmt, Args}, H) -> _ = io_lib:format(Fmt, Args), H.

plc_data(T, V) ->
    step(fun(#h{in = In} = H) ->
                 H1 = H#h{in = In#{T => V}},
                 case H#h.up of
                     true -> feed([{input, T, V}], H1);
                     false -> {[], H1}
                 end
         end).

plc_bit(T, V) -> plc_data(T, V).

link(false) ->
    step(fun(H) -> feed([plc_down], H#h{up = false}) end);
link(true) ->
    step(fun(#h{in = In, img = Img} = H) ->
                 feed([{plc_up, #{inputs => In, outputs => Img}}], H#h{up = true})
         end).

%% The block crashes and starts again: its cameras attach first, then it reads the PLC.
restart() ->
    step(fun(#h{inc = N, clients = C, in = In, img = Img, up = Up} = H) ->
                 H0 = H#h{st = ?S:new(N + 1, config()), inc = N + 1, requests = #{},
                          shown = #{}, job = undefined, override = undefined},
                 Events = [{client_up, Id, Caps} || {Id, Caps} <- lists:sort(maps:to_list(C))]
                     ++ [{plc_up, #{inputs => In, outputs => Img}} || Up],
                 feed(Events, H0)
         end).

client_up(Id) ->
    step(fun(#h{clients = C} = H) ->
                 feed([{client_up, Id, caps(Id)}], H#h{clients = C#{Id => caps(Id)}})
         end).

client_down(Id) ->
    step(fun(#h{clients = C, requests = R, shown = Sh} = H) ->
                 feed([{client_down, Id}], H#h{clients = maps:remove(Id, C),
                                              requests = maps:remove(Id, R),
                                              shown = maps:remove(Id, Sh)})
         end).

image(Id) ->
    step(fun(#h{requests = R} = H) ->
                 feed([{image, Id, maps:get(Id, R, {stale, 0}), <<"image">>}], H)
         end).

%% The processing job: a point without a workspace passes; a result is recorded.
processed(Choice) ->
    step(fun(#h{job = undefined} = H) -> {[], H};
            (#h{job = {Ref, Mode, P, S}, db_ok = Ok, results = Rs} = H) ->
                 R = case {Mode, Choice} of
                         {{error, C}, _} -> {error, C};
                         {none, _} -> {pass, text(pass)};
                         {ipm, processing_error} -> {error, processing_error};
                         {ipm, V} -> {V, text(V)}
                     end,
                 {R1, Rs1} = case R of
                                 {error, _} -> {R, Rs};
                                 _ when Ok -> {R, [{P, S} | Rs]};
                                 _ -> {{error, internal_error}, Rs}
                             end,
                 feed([{processed, Ref, R1}], H#h{job = undefined, results = Rs1})
         end).

override_done() ->
    step(fun(#h{override = undefined} = H) -> {[], H};
            (#h{override = {Ref, P, S}, db_ok = Ok, results = Rs} = H) ->
                 R = case Ok of
                         false -> {error, aborted};
                         true ->
                             case lists:member({P, S}, Rs) of
                                 true -> logged;
                                 false -> not_found
                             end
                     end,
                 feed([{override_logged, Ref, R}], H#h{override = undefined})
         end).

answer(Id, A) ->
    step(fun(#h{shown = Sh} = H) ->
                 Ref = maps:get(Id, Sh, {stale, 0}),
                 case ?S:check_answer(H#h.st, Id, Ref, A) of
                     ok -> feed([{answer, Id, Ref, A}], H#h{shown = maps:remove(Id, Sh)});
                     {error, _} -> {[], H}
                 end
         end).

heartbeat() -> step(fun(H) -> feed([heartbeat], H) end).

workspace(W) -> step(fun(H) -> feed([{workspace, <<"P2">>, W}], H) end).

db(Ok) -> step(fun(H) -> {[], H#h{db_ok = Ok}} end).
