%% @doc What the router's two robots share in moving their NC axes (seed 000 §2.1, a
%% task's `Axes', and §2.3.7, the interpolation channel over them): making the axes
%% ready one command at a time, where they stand, a line of the channel from there, and
%% an axis's refusal or fault in the operator's words, naming the axis.
%%
%% A robot's task starts one command in a step and waits for its end as a reply in the
%% next (`{wait, [{reply, Ref}, Watchdog], T}'); each of these returns what was started,
%% or the axis that refused it and why.
-module(router_axes).

-export([prepare/2, position/1, there/2, line/4, failed/3, words/1, halt/1]).

-export_type([started/0, failure/0]).

%% A command started on an axis or the channel, or refused: `{error, {Axis, Why}}'
%% names the axis that refused or failed.
-type started() :: {ok, reference()} | failure().
-type failure() :: {error, {atom(), term()}}.

%% How the channel stops its axes when a task is stopped or gives up on a move, mm/s².
-define(HALT_DEC, 5000.0).

%% @doc The next command the axes need before the robot moves, started: a path the
%% channel still follows (a predecessor's, or one cut short by a watchdog) halted, then
%% each axis out of error, powered, homed (at 0), halted if it moves on its own;
%% `ready' when none is needed.
-spec prepare(atom(), [atom()]) -> ready | started().
prepare(Channel, Axes) ->
    case cell_hal_channel:status(Channel) of
        {ok, #{state := idle}} -> next_axis(Axes);
        {ok, #{}} -> named(Channel, cell_hal_channel:halt(Channel, ?HALT_DEC));
        {error, Why} -> {error, {Channel, Why}}
    end.

next_axis([]) ->
    ready;
next_axis([A | Rest]) ->
    case cell_hal_axis:status(A) of
        {ok, #{state := error_stop}} -> named(A, cell_hal_axis:reset(A));
        {ok, #{powered := false}} -> named(A, cell_hal_axis:power(A, true));
        {ok, #{homed := false}} -> named(A, cell_hal_axis:home(A, 0.0));
        {ok, #{state := standstill}} -> next_axis(Rest);
        {ok, #{}} -> named(A, cell_hal_axis:halt(A, ?HALT_DEC));
        {error, Why} -> {error, {A, Why}}
    end.

named(_Who, {ok, Ref}) -> {ok, Ref};
named(Who, {error, Why}) -> {error, {Who, Why}}.

%% @doc Where the axes stand, X and Y; or the axis that cannot say.
-spec position([atom()]) -> {ok, {float(), float()}} | failure().
position([X, Y]) ->
    case {cell_hal_axis:status(X), cell_hal_axis:status(Y)} of
        {{ok, #{position := Px}}, {ok, #{position := Py}}} -> {ok, {Px, Py}};
        {{error, Why}, _} -> {error, {X, Why}};
        {_, {error, Why}} -> {error, {Y, Why}}
    end.

%% @doc Whether the axes standing at `Here' are at `To' (within a micrometre): a move
%% there is not made.
-spec there({float(), float()}, {float(), float()}) -> boolean().
there({X1, Y1}, {X2, Y2}) ->
    math:sqrt((X2 - X1) * (X2 - X1) + (Y2 - Y1) * (Y2 - Y1)) < 0.001.

%% @doc The channel follows a line from `From' to `To' (X, Y, on the tool's plane) with
%% these path parameters.
-spec line(atom(), {float(), float()}, {float(), float()}, cell_hal_axis_fsm:params()) ->
          {ok, reference()} | {error, term()}.
line(Channel, {X1, Y1}, {X2, Y2}, Params) ->
    {ok, Path} = cell_hal_path:new([{line, {X1, Y1, 0.0}, {X2, Y2, 0.0}}]),
    cell_hal_channel:follow(Channel, Path, Params).

%% @doc Which axis (or the channel) a move's failure names, and what happened to it in
%% the operator's words: a refusal or fault naming one of the `Axes' or `Who'
%% (`{error, {Axis, Why}}', as {@link prepare/2} gives it and the channel ends a path
%% an axis failed), or else `Who''s (the channel: a refusal of its path, an end
%% `{error, Code}'), or `aborted' (another command took the axes).
-spec failed({error, term()} | aborted, atom(), [atom()]) ->
          {atom(), iodata()}.
failed({error, {Axis, Why}}, Who, Axes) when is_atom(Axis) ->
    case Axis =:= Who orelse lists:member(Axis, Axes) of
        true -> {Axis, words(Why)};
        false -> {Who, words({Axis, Why})}
    end;
failed({error, Code}, Who, _Axes) ->
    {Who, words(Code)};
failed(aborted, Who, _Axes) ->
    {Who, "commanded elsewhere"}.

%% @doc An NC's answer in the operator's words.
-spec words(term()) -> iodata().
words(Code) when is_integer(Code) -> io_lib:format("NC error 16#~.16B", [Code]);
words({error_stop, Code}) -> io_lib:format("it is in error (NC error 16#~.16B)", [Code]);
words(not_present) -> "it is not available";
words(not_connected) -> "its NC is not connected";
words(Why) -> io_lib:format("~tp", [Why]).

%% @doc The channel halts its axes (a task stopped, or a move given up on); a halt it
%% cannot take (its axes gone) is left to the next preparation.
-spec halt(atom()) -> ok.
halt(Channel) ->
    _ = cell_hal_channel:halt(Channel, ?HALT_DEC),
    ok.
