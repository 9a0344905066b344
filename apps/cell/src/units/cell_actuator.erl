%% @doc The behaviour of an actuator a unit's sequences drive: a cylinder, an axis, a
%% timer. An actuator is pure: its commands and the events it is sent return the
%% effects the unit's engine carries out (outputs to write, IO conditions to watch,
%% timers), so one process, the unit's, owns every output of the unit and nothing
%% blocks.
%%
%% A sequence starts a command (`cell_sequence:command/3', or the actuator's own
%% functions such as `cell_cylinder:move_up/2') and awaits the actuator by name: it is
%% done when {@link status/1} says `idle' again, and an actuator whose status becomes
%% `{error, Why}' aborts the running sequence, naming itself (`format_error/2').
%%
%% Callbacks:
%% <ul>
%% <li>`new(Name, Opts, Resolve)' — checks the options; `Resolve' turns a point name
%%     into `{Group, Point}' (a bare name is in the unit's first IO group).</li>
%% <li>`command(Command, State, Read)' — starts a command (a new command replaces one
%%     under way); `Read(Group, Point)' reads an input now, so a command whose goal
%%     already holds is done at once.</li>
%% <li>`event({watch, Tag, Value} | {timer, Tag}, State)' — a watch or timer it asked
%%     for.</li>
%% <li>`status(State)' — `idle', `busy' or `{error, Why}'.</li>
%% <li>`interrupt(State)' — Stop or a fault: forget the command under way, cancel its
%%     watches and timers (the unit does not wait for it).</li>
%% <li>`secure(State)' — the outputs that leave it safe (emergency stop, crash).</li>
%% <li>`describe(State)' — for the panel and `cell_unit:info/1'.</li>
%% <li>`format_error(Name, Why)' — an error in words for the operator.</li>
%% </ul>
-module(cell_actuator).

-export([check_point/2]).

-export_type([effect/0, point/0, resolve/0, read/0]).

-type point() :: {atom(), atom()}.
-type resolve() :: fun((atom() | point()) -> {ok, point()} | {error, term()}).
-type read() :: fun((atom(), atom()) -> {ok, cell_hal_type:value()} | {error, term()}).
-type effect() :: {write, point(), cell_hal_type:value()}
                | {watch, term(), point(), cell_hal_type:condition()}
                | {cancel_watch, term()}
                | {timer, term(), non_neg_integer()}
                | {cancel_timer, term()}.

-callback new(Name :: atom(), Opts :: map(), resolve()) -> {ok, term()} | {error, term()}.
-callback command(Command :: term(), State :: term(), read()) ->
    {ok, term(), [effect()]} | {error, term()}.
-callback event({watch, term(), cell_hal_type:value()} | {timer, term()}, State :: term()) ->
    {term(), [effect()]}.
-callback status(State :: term()) -> idle | busy | {error, term()}.
-callback interrupt(State :: term()) -> {term(), [effect()]}.
-callback secure(State :: term()) -> [effect()].
-callback describe(State :: term()) -> map().
-callback format_error(Name :: atom(), Why :: term()) -> iodata().

%% @doc Resolves an optional point option (what `maps:find/2' gave): `{ok, Point}',
%% `none' when absent, `error' when it names no point.
-spec check_point(resolve(), {ok, term()} | error) -> {ok, point()} | none | error.
check_point(_Resolve, error) ->
    none;
check_point(Resolve, {ok, P}) when is_atom(P); is_tuple(P) ->
    case Resolve(P) of
        {ok, {G, N}} when is_atom(G), is_atom(N) -> {ok, {G, N}};
        _ -> error
    end;
check_point(_Resolve, {ok, _}) ->
    error.
