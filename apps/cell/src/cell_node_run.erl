%% @doc Whether the node's last run ended cleanly, and how many times the node started
%% again: after a clean stop, or after an unexpected one (killed, crashed, the power
%% cut, the node given up by its own supervisors).
%%
%% The record is `Data/cellrt.run', written durably ({@link cell_file:write_term/2}).
%% At every start the `cell' application reads it, decides ({@link decide/2}, pure),
%% logs an unexpected stop in words and writes `running' with the start time; an
%% orderly stop of the application writes `running => false'. So a record still saying
%% `running' at the next start is a run that never reached its orderly stop.
-module(cell_node_run).

-export([boot/0, stopped/0, counts/0]).
-export([decide/2, stop/1]).

-export_type([record/0, outcome/0]).

-define(RUN_FILE, "cellrt.run").

%% `running': the start time (UTC, ms) of the run in progress, or `false' after a clean
%% stop; the counts of starts after a clean and after an unexpected stop.
-type record() :: #{running := false | integer(), clean := non_neg_integer(),
                    unexpected := non_neg_integer()}.
-type outcome() :: first | clean | {unexpected, integer() | unknown}.

%% @doc What the previous run left (`none': no record, `damaged': one that cannot be
%% read) decides this start; the record to write for the run that begins at `Now'.
-spec decide(record() | none | damaged, integer()) -> {outcome(), record()}.
decide(none, Now) ->
    {first, #{running => Now, clean => 0, unexpected => 0}};
decide(damaged, Now) ->
    %% The counts are lost with it; the stop it tells of cannot have been clean, since
    %% a clean stop writes the record whole.
    {{unexpected, unknown}, #{running => Now, clean => 0, unexpected => 1}};
decide(#{running := false, clean := C} = R, Now) ->
    {clean, R#{running := Now, clean := C + 1}};
decide(#{running := Started, unexpected := U} = R, Now) when is_integer(Started) ->
    {{unexpected, Started}, R#{running := Now, unexpected := U + 1}}.

%% @doc The record after an orderly stop.
-spec stop(record()) -> record().
stop(R) ->
    R#{running := false}.

%% @doc At the application's start: reads the last run's record, logs how it ended when
%% it did not end cleanly, and records this run. Returns the outcome.
-spec boot() -> outcome().
boot() ->
    Now = os:system_time(millisecond),
    {Outcome, Record} = decide(read(), Now),
    case Outcome of
        {unexpected, Started} ->
            cell_log:warning(cell, "the cell restarted after an unexpected stop of the node "
                             "(killed, crashed or its power cut); the run that stopped had "
                             "started at ~ts. Restarts so far: ~b after an unexpected stop, "
                             "~b after a clean one",
                             [when_text(Started), maps:get(unexpected, Record),
                              maps:get(clean, Record)]);
        _ ->
            ok
    end,
    ok = write(Record),
    Outcome.

%% @doc At the application's orderly stop: the run ended cleanly.
-spec stopped() -> ok.
stopped() ->
    case read() of
        #{} = R -> write(stop(R));
        _ -> ok
    end.

%% @doc How many times the node started again after a clean stop and after an
%% unexpected one, since the record began.
-spec counts() -> #{clean := non_neg_integer(), unexpected := non_neg_integer()}.
counts() ->
    case read() of
        #{} = R -> maps:with([clean, unexpected], R);
        _ -> #{clean => 0, unexpected => 0}
    end.

read() ->
    case cell_file:read_term(path()) of
        {ok, #{running := Run, clean := C, unexpected := U} = R}
          when (Run =:= false orelse is_integer(Run)), is_integer(C), C >= 0,
               is_integer(U), U >= 0 ->
            maps:with([running, clean, unexpected], R);
        {error, enoent} ->
            none;
        _ ->
            damaged
    end.

write(Record) ->
    case cell_file:write_term(path(), Record) of
        ok ->
            ok;
        {error, Why} ->
            cell_log:error(cell, "could not record the node's run in ~ts: ~0tp",
                           [path(), Why])
    end.

path() ->
    filename:join(cell_config:dir(data), ?RUN_FILE).

when_text(unknown) ->
    "an unknown time (its record is damaged)";
when_text(Ms) ->
    calendar:system_time_to_rfc3339(Ms, [{unit, millisecond}, {time_designator, $\s}]).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

decide_test_() ->
    Clean = #{running => false, clean => 2, unexpected => 1},
    Running = #{running => 500, clean => 2, unexpected => 1},
    [?_assertEqual({first, #{running => 9, clean => 0, unexpected => 0}}, decide(none, 9)),
     ?_assertEqual({clean, #{running => 9, clean => 3, unexpected => 1}}, decide(Clean, 9)),
     ?_assertEqual({{unexpected, 500}, #{running => 9, clean => 2, unexpected => 2}},
                   decide(Running, 9)),
     ?_assertEqual({{unexpected, unknown}, #{running => 9, clean => 0, unexpected => 1}},
                   decide(damaged, 9)),
     %% A clean stop, then a start: clean; no stop, then a start: unexpected.
     ?_assertMatch({clean, _}, decide(stop(element(2, decide(Running, 9))), 10)),
     ?_assertMatch({{unexpected, 9}, _}, decide(element(2, decide(Clean, 9)), 10))].
-endif.
