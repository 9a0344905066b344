%% @doc The press: takes a part from the infeed over the handshake link `prev',
%% presses it as deep as its recipe says, and sends it out to the next machine.
%%
%% <pre>
%%  phase      waits for                                 then
%%  idle       the infeed's offer (STARVED)              commit (phase 2), belt on → moving_in
%%  moving_in  the infeed's Available off (phase 3)      → arriving; the transfer interrupted:
%%                                                       cell_handover:interrupted/3
%%  arriving   the part in the die, or the watchdog      belt off, complete (phase 4) → pressing;
%%                                                       late: "Part did not arrive" (RETRY:
%%                                                       → moving_in_again, the belt on again)
%%  pressing   -                                         depth from the recipe, ram down → stroke;
%%                                                       no depth: "Recipe not usable" (RETRY)
%%  stroke     the ram at the bottom, or the watchdog    ram up → pressed; late: ram up, "Press
%%                                                       stroke not completed" → stroke_answered
%%  stroke_answered  the ram at the top                  RETRY: → pressing; IGNORE: the part
%%                                                       marked failed → pressed
%%  pressed    the ram at the top                        belt on → ejecting
%%  ejecting   the part out of the die, or the watchdog  belt off, the product out → idle; still
%%                                                       there: "Part not out" (RETRY)
%%  in_transit the operator's Ignore after "Transfer     → pressing (Reset: forgotten at init)
%%             interrupted"
%% </pre>
%%
%% The product records how far it got (`pressed', `handing_out'), saved with it, so a
%% restart goes on where it was: {@link reconcile/2} holds that record against the die's
%% sensor and asks the operator where they disagree.
-module(__NAME___press_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, secure(cell_handover:after_reset(T))}.

-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(_Held, T0) ->
    case cell_task:product(T0) of
        #{handing_out := true, serial := S} ->
            case in_die(T0) of
                %% It had left when the task stopped: it is out.
                false -> {ok, phase(sent_out(T0, S), idle)};
                true -> {ok, phase(T0, pressed)}
            end;
        _ ->
            reconcile_record(T0)
    end.

reconcile_record(T0) ->
    case cell_handover:reconcile(T0, fun in_die/1, fun where/2) of
        {empty, T} ->
            case in_die(T) andalso
                cell_handover:unheld_anywhere([infeed], cell_task:others_products(T)) of
                true -> cell_handover:unheld_error(T, "Part in the press without a record",
                                                   "A part lies in the press", []);
                false -> {ok, phase(T, idle)}
            end;
        {here, _By, T} ->
            %% A stroke cut short is made again; a pressed part goes out.
            case cell_task:product(T) of
                #{pressed := true} -> {ok, phase(T, pressed)};
                _ -> {ok, phase(T, pressing)}
            end;
        {gone, _Serial, T} ->
            {ok, phase(T, idle)};
        {error, _, _} = Ask ->
            Ask
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    secure(T).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

%% -- take a part from the infeed --------------------------------------------------------
step(idle, _Woken, T) ->
    cell_handover:take(T, prev(T), moving_in, fun(T1) -> belt(T1, true) end);
step(moving_in, {handshake, _Prev, interrupted}, T) ->
    cell_handover:interrupted(belt(T, false), arriving, idle);
step(moving_in, {handshake, _Prev, available, false}, T) ->
    {wait, [{io, part_in_press, {eq, true}}, {timer, setting(T, transfer_timeout_ms)}],
     phase(T, arriving)};
step(moving_in, _Woken, T) ->
    {wait, {handshake, prev(T), available, false}, T};
step(arriving, _Woken, T) ->
    case in_die(T) of
        true ->
            T1 = cell_handshake:complete(belt(T, false), prev(T)),
            {continue, phase(T1, pressing)};
        false ->
            {error, cell_task:error_spec(
                      <<"not_arrived">>, "Part did not arrive in the press",
                      "The infeed let the part go, but it did not reach the press's die. "
                      "Check the belts for a jammed part, free it, then select RETRY.",
                      [retry]),
             phase(belt(T, false), moving_in_again)}
    end;
step(moving_in_again, _Woken, T) ->
    %% The operator's Retry: the belt runs again and the die's sensor is watched.
    {wait, [{io, part_in_press, {eq, true}}, {timer, setting(T, transfer_timeout_ms)}],
     phase(belt(T, true), arriving)};
%% -- press it -----------------------------------------------------------------------------
step(pressing, _Woken, T) ->
    #{recipe := Recipe, serial := S} = cell_task:product(T),
    case __NAME___recipes:stroke_depth(Recipe) of
        {ok, Depth} ->
            T1 = cell_task:work_start(cell_task:out(T, stroke_depth, Depth)),
            cell_task:log(T1, verbose, "pressing part ~ts ~.1f mm deep", [S, Depth / 10]),
            {wait, [{io, ram_down, {eq, true}}, {timer, setting(T, stroke_timeout_ms)}],
             phase(ram(T1, true), stroke)};
        {error, Why} ->
            {error, cell_task:error_spec(
                      <<"recipe">>, "Recipe not usable",
                      io_lib:format("Part ~ts is of recipe ~ts, which gives no stroke depth "
                                    "(~p). Correct the recipe, then select RETRY.",
                                    [S, Recipe, Why]),
                      [retry]),
             T}
    end;
step(stroke, _Woken, T) ->
    case cell_task:in(T, ram_down) of
        true ->
            P = cell_task:product(T),
            Force = cell_task:in(T, force_kn),
            T1 = cell_task:set_product(T, P#{pressed => true, force_kn => Force}),
            {wait, {io, ram_up, {eq, true}}, phase(ram(cell_task:work_complete(T1), false), pressed)};
        false ->
            {error, cell_task:error_spec(
                      <<"stroke">>, "Press stroke not completed",
                      io_lib:format("The ram did not reach the bottom within ~b ms; it is "
                                    "raised.~nRETRY: press again. IGNORE: the part goes on "
                                    "unpressed, marked failed.",
                                    [setting(T, stroke_timeout_ms)]),
                      [retry, ignore]),
             phase(ram(T, false), stroke_answered)}
    end;
step(stroke_answered, _Woken, T) ->
    case cell_task:answer(T) of
        ignore ->
            P = cell_task:product(T),
            T1 = cell_task:set_product(T, P#{pressed => true, failed => true}),
            {wait, {io, ram_up, {eq, true}}, phase(T1, pressed)};
        _Retry ->
            {wait, {io, ram_up, {eq, true}}, phase(T, pressing)}
    end;
%% -- send it out --------------------------------------------------------------------------
step(pressed, _Woken, T) ->
    case cell_task:in(T, ram_up) of
        true ->
            %% Saved as begun before it goes: a restart in between does not send it twice.
            P = cell_task:product(T),
            T1 = cell_task:set_product(T, P#{handing_out => true}),
            {wait, [{io, part_in_press, {eq, false}}, {timer, setting(T, transfer_timeout_ms)}],
             phase(belt(T1, true), ejecting)};
        false ->
            {wait, {io, ram_up, {eq, true}}, T}
    end;
step(ejecting, _Woken, T) ->
    #{serial := S} = cell_task:product(T),
    case in_die(T) of
        false ->
            cell_task:log(T, brief, "part ~ts out", [S]),
            {continue, phase(sent_out(belt(T, false), S), idle)};
        true ->
            {error, cell_task:error_spec(
                      <<"not_out">>, "Part not out of the press",
                      io_lib:format("Part ~ts is still in the die. Free the outfeed, then "
                                    "select RETRY.", [S]),
                      [retry]),
             phase(belt(T, false), pressed)}
    end;
step(in_transit, _Woken, T) ->
    %% The operator's Ignore after "Transfer interrupted": the part is in the press.
    case cell_task:product(T) of
        undefined -> {continue, phase(T, idle)};
        _ -> {continue, phase(cell_handshake:confirm_here(T), pressing)}
    end.

sent_out(T, Serial) ->
    cell_task:clear_product(cell_task:transfer_out(T, Serial)).

where(T, Serial) ->
    {error, cell_task:error_spec(
              <<"where">>, "Part not in the press",
              io_lib:format("Records say part ~ts is in the press; the die's sensor sees "
                            "none.~nRETRY: look again. IGNORE: it is there. RESET: it was "
                            "taken out of the machine.", [Serial]),
              [retry, ignore, reset]),
     T}.

%% Belt stopped, ram up.
secure(T) ->
    ram(belt(T, false), false).

in_die(T) ->
    cell_task:in(T, part_in_press).

belt(T, On) ->
    cell_task:out(T, press_belt, On).

ram(T, Down) ->
    cell_task:out(T, ram_lower, Down).

prev(T) ->
    cell_task:arg(T, prev, undefined).

setting(T, Key) ->
    cell_task:setting(T, Key, 5000).

phase(T, Phase) ->
    cell_handover:phase(T, Phase).
