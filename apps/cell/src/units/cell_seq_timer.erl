%% @doc The timer of a step sequence (the seed's `ZAux.Timer'): `run_async(Seq, Name,
%% Ms)' starts it (`_timer.RunAsync(THIS^, DelayAufnehmen)'), and the sequence awaits
%% it by its name like any actuator. A timer belongs to the sequence that first ran it
%% and goes with it; a unit may also declare one among its actuators,
%% `#{delay => {cell_seq_timer, #{}}}', to share it between its sequences.
-module(cell_seq_timer).
-behaviour(cell_actuator).

-export([run_async/3]).
-export([new/3, command/3, event/2, status/1, interrupt/1, secure/1, describe/1,
         format_error/2]).

-record(timer, {status = idle :: idle | {running, non_neg_integer()}}).

%% @doc Starts (or restarts) the timer `Name': done `Ms' milliseconds from now.
-spec run_async(cell_sequence:seq(), atom(), non_neg_integer()) -> cell_sequence:seq().
run_async(Seq, Name, Ms) when is_integer(Ms), Ms >= 0 ->
    cell_sequence:command(cell_sequence:local_actuator(Seq, Name, ?MODULE, #{}), Name,
                          {run, Ms}).

%% cell_actuator

-spec new(atom(), map(), cell_actuator:resolve()) -> {ok, #timer{}} | {error, term()}.
new(_Name, Opts, _Resolve) when map_size(Opts) =:= 0 -> {ok, #timer{}};
new(_Name, Opts, _Resolve) -> {error, {bad_option, hd(maps:keys(Opts))}}.

-spec command(term(), #timer{}, cell_actuator:read()) ->
          {ok, #timer{}, [cell_actuator:effect()]} | {error, term()}.
command({run, 0}, T, _Read) ->
    {ok, T#timer{status = idle}, cancel(T)};
command({run, Ms}, T, _Read) when is_integer(Ms), Ms > 0 ->
    {ok, T#timer{status = {running, Ms}}, cancel(T) ++ [{timer, elapsed, Ms}]};
command(Other, _T, _Read) ->
    {error, {unknown_command, Other}}.

-spec event({watch, term(), term()} | {timer, term()}, #timer{}) -> {#timer{}, [cell_actuator:effect()]}.
event({timer, elapsed}, #timer{status = {running, _}} = T) -> {T#timer{status = idle}, []};
event(_Stale, T) -> {T, []}.

-spec status(#timer{}) -> idle | busy.
status(#timer{status = idle}) -> idle;
status(#timer{status = {running, _}}) -> busy.

-spec interrupt(#timer{}) -> {#timer{}, [cell_actuator:effect()]}.
interrupt(T) -> {T#timer{status = idle}, cancel(T)}.

cancel(#timer{status = {running, _}}) -> [{cancel_timer, elapsed}];
cancel(_) -> [].

-spec secure(#timer{}) -> [cell_actuator:effect()].
secure(_T) -> [].

-spec describe(#timer{}) -> map().
describe(#timer{status = idle}) -> #{type => timer, status => idle};
describe(#timer{status = {running, Ms}}) -> #{type => timer, status => running, ms => Ms}.

-spec format_error(atom(), term()) -> iodata().
format_error(Name, {unknown_command, C}) -> io_lib:format("timer ~ts cannot ~tp", [Name, C]);
format_error(Name, Why) -> io_lib:format("timer ~ts failed: ~tp", [Name, Why]).
