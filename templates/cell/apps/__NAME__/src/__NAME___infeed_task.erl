%% @doc The infeed conveyor: a part the previous machine put at its stopper gets the
%% next serial, then goes to the press over the handshake link `next'.
%%
%% <pre>
%%  phase     waits for                              then
%%  idle      a part at the stopper (STARVED)        a new serial, the product → full
%%  full      the press's NotBusy (offer, phase 1)   → offered
%%  offered   the press commits (phase 2)            belt on, release (phase 3) → released;
%%                                                   the offer gone (link restarted): → full
%%  released  the press's NotBusy off (phase 4)      belt off; completed → idle; given back
%%                                                   → full; interrupted: the operator
%%  in_transit  the operator's Ignore after          → full (Reset: forgotten at init)
%%              "Transfer interrupted"
%% </pre>
%%
%% The serial counter is retained data ({@link cell_task:retain_update/4}): on disk
%% before the serial is used, so no restart, crash or power cut makes one twice (one
%% taken just before a crash may be skipped, never repeated). The hand-over steps are
%% the framework's ({@link cell_handover}).
-module(__NAME___infeed_task).
-behaviour(cell_task).

-export([init/1, reconcile/2, step/1, uninit/1]).
-export([serial/2]).

-spec init(cell_task:task()) -> {ok, cell_task:task()}.
init(T) ->
    {ok, belt(cell_handover:after_reset(T), false)}.

%% After a restart: the part the record holds is at the stopper, or the operator says
%% where it is. A part the sensor sees and no record holds is simply the next one.
-spec reconcile(cell_task:held(), cell_task:task()) ->
          {ok, cell_task:task()} | {error, cell_alarms:spec(), cell_task:task()}.
reconcile(_Held, T0) ->
    case cell_handover:reconcile(T0, fun at_stopper/1, fun where/2) of
        {empty, T} -> {ok, phase(belt(T, false), idle)};
        {here, _By, T} -> {ok, phase(belt(T, false), full)};
        {gone, _Serial, T} -> {ok, phase(belt(T, false), idle)};
        {error, _, _} = Ask -> Ask
    end.

-spec uninit(cell_task:task()) -> cell_task:task().
uninit(T) ->
    belt(T, false).

-spec step(cell_task:task()) -> cell_task:step_result().
step(T) ->
    step(cell_handover:phase(T), cell_task:woken_by(T), T).

step(idle, _Woken, T) ->
    case at_stopper(T) of
        true -> {continue, phase(new_part(cell_task:unstarved(T)), full)};
        false -> {wait, {io, part_at_infeed, {eq, true}}, cell_task:starved(T)}
    end;
step(full, _Woken, T) ->
    Next = cell_task:arg(T, next, undefined),
    {wait, {handshake, Next, not_busy, true}, phase(cell_handshake:offer(T, Next), offered)};
step(offered, {handshake, Next, not_busy, true}, T) ->
    T1 = cell_handshake:release(belt(T, true), Next),
    {wait, {handshake, Next, not_busy, false}, phase(T1, released)};
step(offered, _Woken, T) ->
    cell_handover:offered(T, cell_task:arg(T, next, undefined), full);
step(released, _Woken, T) ->
    cell_handover:finish(T, cell_task:arg(T, next, undefined), idle, full,
                         fun(_Outcome, T1) -> belt(T1, false) end);
step(in_transit, _Woken, T) ->
    %% The operator's Ignore: the part of the interrupted transfer is here.
    case cell_task:product(T) of
        undefined -> {continue, phase(T, idle)};
        _ -> {continue, phase(cell_handshake:confirm_here(T), full)}
    end.

%% The next serial is durable before the product that carries it is made.
new_part(T0) ->
    {N, T1} = cell_task:retain_update(T0, serial, fun(S) -> S + 1 end, 0),
    Serial = serial(cell_task:setting(T1, serial_prefix, <<"P">>), N),
    Recipe = cell_task:setting(T1, recipe, <<"demo-part">>),
    T2 = cell_task:set_product(T1, cell_product:new(Serial, Recipe)),
    T3 = cell_task:transfer_in(cell_task:identifier_read(T2, Serial, <<"serial counter">>),
                               Serial),
    cell_task:log(T3, brief, "part ~ts (~ts) at the infeed", [Serial, Recipe]),
    T3.

%% @doc A serial: the prefix and the counter, six digits at least.
-spec serial(binary(), non_neg_integer()) -> binary().
serial(Prefix, N) ->
    Digits = integer_to_binary(N),
    Zeros = binary:copy(<<"0">>, max(0, 6 - byte_size(Digits))),
    <<Prefix/binary, Zeros/binary, Digits/binary>>.

where(T, Serial) ->
    {error, cell_task:error_spec(
              <<"where">>, "Part not at the infeed",
              io_lib:format("Records say part ~ts is at the infeed stopper; its sensor sees "
                            "none.~nRETRY: look again. IGNORE: it is there. RESET: it was "
                            "taken out of the machine.", [Serial]),
              [retry, ignore, reset]),
     T}.

at_stopper(T) ->
    cell_task:in(T, part_at_infeed).

belt(T, On) ->
    cell_task:out(T, infeed_belt, On).

phase(T, Phase) ->
    cell_handover:phase(T, Phase).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

serial_test() ->
    ?assertEqual(<<"P000042">>, serial(<<"P">>, 42)),
    ?assertEqual(<<"AB1234567">>, serial(<<"AB">>, 1234567)).
-endif.
