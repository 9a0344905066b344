%% A PropEr state-machine property of the HAL against the simulated PLC: random
%% sequences of input changes, output writes, a cable pulled and plugged back, a
%% momentary loss, outputs changed on the PLC's side, and reads, each checked against
%% a model of what the HAL promises (written from the contract, not from the code):
%%
%% <ul>
%% <li>an input reads the PLC's value while the connection is up, `disconnected' while
%%   it is down;</li>
%% <li>an output reads its last commanded value; after a reconnect, what the PLC
%%   holds;</li>
%% <li>a write is confirmed while up and refused while down, and the PLC then holds
%%   it.</li>
%% </ul>
-module(cell_hal_statem_SUITE).
-include_lib("common_test/include/ct.hrl").
-include_lib("proper/include/proper.hrl").

-export([all/0, init_per_suite/1, end_per_suite/1]).
-export([hal_keeps_its_promises/1]).
-export([initial_state/0, command/1, precondition/2, next_state/3, postcondition/3]).
-export([set_input/2, write/2, read/1, link/1, drop/0, plc_sets_output/2]).

-define(CONN, statem_plc).
-define(WAIT, 5000).
-define(INPUTS, [int16_in, bool_in]).
-define(OUTPUTS, [int16_out, bool_out]).

all() -> [hal_keeps_its_promises].

init_per_suite(Config) ->
    _ = application:load(cell_base),
    ok = application:set_env(cell_base, root, filename:join(?config(priv_dir, Config), "root")),
    {ok, Apps} = application:ensure_all_started(cell_hal),
    ok = cell_hal:add_connection(#{id => ?CONN, driver => cell_hal_sim,
                                   opts => #{poll_ms => 5, reconnect_ms => 10,
                                             max_reconnect_ms => 40, timeout_ms => 500}}),
    ok = cell_hal:add_group(#{id => io, module => cell_hal_test_io, connection => ?CONN,
                              opts => #{only => ?INPUTS ++ ?OUTPUTS}}),
    [{apps, Apps} | Config].

end_per_suite(Config) ->
    ok = cell_hal:remove_group(io),
    ok = cell_hal:remove_connection(?CONN),
    [application:stop(A) || A <- lists:reverse(?config(apps, Config))],
    ok.

hal_keeps_its_promises(_Config) ->
    true = proper:quickcheck(
             ?FORALL(Cmds, proper_statem:commands(?MODULE),
                     begin
                         ok = reset(),
                         {History, State, Result} = proper_statem:run_commands(?MODULE, Cmds),
                         ?WHENFAIL(ct:pal("commands ~p~nhistory ~p~nmodel ~p~nresult ~p",
                                          [Cmds, History, State, Result]),
                                   aggregate(proper_statem:command_names(Cmds), Result =:= ok))
                     end),
             [{to_file, user}, {numtests, 40}, {max_size, 30}]).

%% Every run starts from the same place: link up, the PLC's image all zero, the HAL up.
reset() ->
    flush(),
    ok = cell_hal_sim:link(?CONN, up),
    ok = cell_hal_sim:preset(?CONN, maps:from_list([{{io, P}, zero(P)} || P <- ?INPUTS ++ ?OUTPUTS])),
    case cell_hal:subscribe_connection(?CONN) of
        {ok, up} -> ok;
        {ok, down} -> ok = await_status(up)
    end,
    %% A reconnect reads the zeroed outputs back.
    ok = drop(),
    [{ok, _} = await(P, zero(P)) || P <- ?INPUTS],
    ok.

%%--------------------------------------------------------------------
%% The model
%%--------------------------------------------------------------------

-record(model, {up = true :: boolean(),
                plc = #{} :: #{atom() => term()},       %% the PLC's image
                hal_out = #{} :: #{atom() => term()}}).  %% what the HAL's outputs read

initial_state() ->
    Zero = maps:from_list([{P, zero(P)} || P <- ?INPUTS ++ ?OUTPUTS]),
    #model{plc = Zero, hal_out = maps:with(?OUTPUTS, Zero)}.

zero(P) when P =:= bool_in; P =:= bool_out -> false;
zero(_) -> 0.

value(P) when P =:= bool_in; P =:= bool_out -> boolean();
value(_) -> integer(-32768, 32767).

command(#model{up = Up}) ->
    frequency([{4, ?LET(P, oneof(?INPUTS), {call, ?MODULE, set_input, [P, value(P)]})},
               {4, ?LET(P, oneof(?OUTPUTS), {call, ?MODULE, write, [P, value(P)]})},
               {4, {call, ?MODULE, read, [oneof(?INPUTS ++ ?OUTPUTS)]}},
               {2, ?LET(P, oneof(?OUTPUTS), {call, ?MODULE, plc_sets_output, [P, value(P)]})},
               {case Up of true -> 2; false -> 3 end, {call, ?MODULE, link, [oneof([up, down])]}},
               {1, {call, ?MODULE, drop, []}}]).

precondition(#model{up = false}, {call, _, drop, []}) -> false;
precondition(_, _) -> true.

next_state(M, _, {call, _, set_input, [P, V]}) ->
    M#model{plc = (M#model.plc)#{P := V}};
next_state(#model{up = true} = M, _, {call, _, write, [P, V]}) ->
    M#model{plc = (M#model.plc)#{P := V}, hal_out = (M#model.hal_out)#{P := V}};
next_state(M, _, {call, _, write, _}) ->
    M;
next_state(M, _, {call, _, plc_sets_output, [P, V]}) ->
    M#model{plc = (M#model.plc)#{P := V}};
next_state(#model{up = false} = M, _, {call, _, link, [up]}) ->
    reconnected(M);
next_state(M, _, {call, _, link, [up]}) ->
    M;
next_state(M, _, {call, _, link, [down]}) ->
    M#model{up = false};
next_state(M, _, {call, _, drop, []}) ->
    reconnected(M);
next_state(M, _, {call, _, read, _}) ->
    M.

%% After a reconnect the outputs read what the PLC holds.
reconnected(M) ->
    M#model{up = true, hal_out = maps:with(?OUTPUTS, M#model.plc)}.

postcondition(#model{up = Up, plc = Plc}, {call, _, set_input, [P, V]}, Result) ->
    %% While up the HAL sees the new value; while down it must not.
    case Up of
        true -> Result =:= {ok, V};
        false -> Result =:= {error, disconnected} andalso maps:is_key(P, Plc)
    end;
postcondition(#model{up = true}, {call, _, write, [_, V]}, Result) ->
    Result =:= {ok, ok, {ok, V}, {ok, V}};
postcondition(#model{up = false, hal_out = Out}, {call, _, write, [P, _]}, Result) ->
    Result =:= {{error, disconnected}, maps:get(P, Out)};
postcondition(#model{up = Up, plc = Plc, hal_out = Out}, {call, _, read, [P]}, Result) ->
    case lists:member(P, ?INPUTS) of
        true when Up -> Result =:= {ok, maps:get(P, Plc)};
        true -> Result =:= {error, disconnected};
        false -> Result =:= {ok, maps:get(P, Out)}
    end;
postcondition(#model{hal_out = Out}, {call, _, plc_sets_output, [P, _]}, Result) ->
    %% The HAL does not poll outputs: it keeps reading the commanded value.
    Result =:= {ok, maps:get(P, Out)};
postcondition(M, {call, _, link, [Link]}, Result) ->
    Result =:= ok andalso outputs_as_modelled(next_state(M, x, {call, ?MODULE, link, [Link]}));
postcondition(M, {call, _, drop, []}, Result) ->
    Result =:= ok andalso outputs_as_modelled(next_state(M, x, {call, ?MODULE, drop, []})).

outputs_as_modelled(#model{hal_out = Out}) ->
    lists:all(fun(P) -> cell_hal:read(io, P) =:= {ok, maps:get(P, Out)} end, ?OUTPUTS).

%%--------------------------------------------------------------------
%% The commands, each waiting until the HAL has settled (never a fixed sleep)
%%--------------------------------------------------------------------

%% Sets an input on the PLC; while up, waits for the HAL to read it.
set_input(P, V) ->
    ok = cell_hal_sim:set({io, P}, V),
    case cell_hal:status(?CONN) of
        up -> await(P, V);
        down -> cell_hal:read(io, P)
    end.

%% Writes an output; while up, also what the HAL and the PLC read back.
write(P, V) ->
    case cell_hal:write_sync(io, P, V, ?WAIT) of
        ok -> {ok, ok, cell_hal:read(io, P), cell_hal_sim:get({io, P})};
        Error -> {Error, element(2, cell_hal:read(io, P))}
    end.

read(P) ->
    cell_hal:read(io, P).

plc_sets_output(P, V) ->
    ok = cell_hal_sim:set({io, P}, V),
    cell_hal:read(io, P).

link(Link) ->
    Was = cell_hal:status(?CONN),
    ok = cell_hal_sim:link(?CONN, Link),
    case {Was, Link} of
        {up, down} -> await_status(down);
        {down, up} -> await_status(up);
        _ -> ok
    end.

drop() ->
    ok = cell_hal_sim:drop(?CONN),
    ok = await_status(down),
    await_status(up).

await(P, V) ->
    {ok, Ref} = cell_hal:watch(io, P, {eq, V}),
    receive {cell_hal_watch, Ref, V} -> {ok, V}
    after ?WAIT -> {timeout, cell_hal:read(io, P)}
    end.

await_status(Status) ->
    receive {cell_hal_conn, ?CONN, Status} -> ok
    after ?WAIT -> {timeout, Status, cell_hal:status(?CONN)}
    end.

flush() ->
    receive {cell_hal_conn, ?CONN, _} -> flush() after 0 -> ok end.
