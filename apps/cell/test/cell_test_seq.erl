%% A sequence its test drives: on entering its first step it notes `{{pending, Unit},
%% Key, Ref}' in the table `tab' and awaits `{reply, Ref}'; the test sends the unit
%% `{Ref, done}' (the sequence then runs three more steps and is done) or
%% `{Ref, {abort, Reason}}' (it is aborted at once).
-module(cell_test_seq).
-behaviour(cell_sequence).

-export([init/2, step/2]).
-export([complete/2, fail/3, pending/2]).

init(_Args, Seq) ->
    {ok, wait, Seq}.

step(wait, Seq0) ->
    Seq = case cell_sequence:on_entry(Seq0) of
              true ->
                  New = make_ref(),
                  true = ets:insert(cell_sequence:arg(Seq0, tab, undefined),
                                    {{pending, cell_sequence:unit(Seq0)},
                                     cell_sequence:arg(Seq0, key, undefined), New}),
                  cell_sequence:put(Seq0, ref, New);
              false ->
                  Seq0
          end,
    %% An operation that failed aborts the sequence at once, as an actuator would.
    Ref = cell_sequence:get(Seq, ref),
    case cell_sequence:await(Seq, {reply, Ref}, finish) of
        {next, finish, Seq1} ->
            case cell_sequence:reply(Seq1, Ref) of
                done -> cell_sequence:next(Seq1, finish);
                {abort, Why} -> cell_sequence:abort(Seq1, Why)
            end;
        Waiting ->
            Waiting
    end;
step(finish, Seq) ->
    cell_sequence:next(Seq, s1);
step(s1, Seq) ->
    cell_sequence:next(Seq, s2);
step(s2, Seq) ->
    cell_sequence:done(Seq).

%% The sequence a unit waits in: `{Key, Ref}', or none.
pending(Tab, Unit) ->
    case ets:lookup(Tab, {pending, Unit}) of
        [{_, Key, Ref}] -> {Key, Ref};
        [] -> none
    end.

%% Completes what the unit waits for; answers the sequence's key.
complete(Tab, Unit) ->
    send(Tab, Unit, done).

fail(Tab, Unit, Why) ->
    send(Tab, Unit, {abort, Why}).

send(Tab, Unit, Msg) ->
    case pending(Tab, Unit) of
        {Key, Ref} ->
            true = ets:delete(Tab, {pending, Unit}),
            cell_unit:whereis(Unit) ! {Ref, Msg},
            Key;
        none ->
            none
    end.
