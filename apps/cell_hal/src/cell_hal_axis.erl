%% @doc The axis, a hardware object (seed 000 §2.1 and §2.3.7: a task's `Axes', the
%% NcAxis of TwinCAT NC): power, home, moves, halt, stop, reset and the speed override,
%% with the state, position, velocity and error code read back. Its states and rules are
%% PLCopen motion control's ({@link cell_hal_axis_fsm}), so a PLC programmer recognises
%% them: MC_Power is {@link power/2}, MC_Home {@link home/2}, MC_MoveAbsolute {@link
%% move_absolute/3}, MC_MoveRelative {@link move_relative/3}, MC_Halt {@link halt/2},
%% MC_Stop {@link stop/3}, MC_Reset {@link reset/1}.
%%
%% Moves are asynchronous, as IO is to a task: a command is accepted or refused at once
%% (`{ok, Ref}' or `{error, Why}'), and the job's end comes later to the caller as the
%% message `{Ref, done | aborted | {error, Code}}' — `aborted' when a newer command
%% replaced it (PLCopen's CommandAborted), an error code when the axis faulted. A device
%% task starts a move in one step and waits for it with `{wait, [{reply, Ref}, {timer,
%% Ms}], T}' in the next; an error becomes its error with solutions.
%%
%% ```
%% {ok, _} = cell_hal_axis:power(x, true),
%% {ok, H} = cell_hal_axis:home(x, 0.0),          % then {H, done}
%% {ok, M} = cell_hal_axis:move_absolute(x, 250.0, #{velocity => 100,
%%                                                  acceleration => 1000,
%%                                                  deceleration => 1000})
%% '''
%%
%% Implementations: `sim' ({@link cell_hal_axis_sim}, a simulated NC axis) and `ads'
%% (cell_hal_ads_axis, an axis of TwinCAT NC over ADS).
-module(cell_hal_axis).

-export([power/2, home/2, move_absolute/3, move_relative/3, halt/2, stop/3, reset/1,
         set_override/2, status/1]).
-export([follow/2]).
-export([moving/1]).

-export_type([status/0]).

-type status() :: #{state := cell_hal_axis_fsm:state(),
                    position := float(),
                    velocity := float(),
                    error := non_neg_integer(),
                    homed := boolean(),
                    powered := boolean(),
                    override := number()}.

%% An implementation gets each command with the process to tell of its job's end.
-callback check_opts(map()) -> {ok, map()} | {error, term()}.
-callback init(atom(), map()) -> {ok, State :: term()} | {ok, State :: term(), up | down}
                                     | {error, term()}.
-callback command(pid(), cell_hal_axis_fsm:command(), State :: term()) ->
    {reply, {ok, reference()} | {error, term()}, State :: term()}.
-callback set_override(number(), State :: term()) -> {reply, ok | {error, term()}, State :: term()}.
-callback status(State :: term()) -> {reply, status(), State :: term()}.
-callback handle_call(term(), State :: term()) -> {reply, term(), State :: term()}.
%% `unchanged': nothing its status shows changed, so the object's watchers are not told
%% (see cell_hal_hw:watch/1).
-callback handle_info(term(), State :: term()) ->
    {noreply, State :: term()} | {noreply, State :: term(), unchanged}.

-define(TIMEOUT, 5000).

%% @doc MC_Power: switches the axis's drive on (Disabled to Standstill) or off (to
%% Disabled from any state but ErrorStop, aborting what runs).
-spec power(atom(), boolean()) -> {ok, reference()} | {error, term()}.
power(Id, On) when is_boolean(On) ->
    command(Id, {power, On}).

%% @doc MC_Home: from Standstill; the axis's position is `At' once done.
-spec home(atom(), number()) -> {ok, reference()} | {error, term()}.
home(Id, At) ->
    command(Id, {home, At}).

%% @doc MC_MoveAbsolute: to `Position' with the velocity, acceleration and
%% deceleration given (the axis homed, the target within its software limits).
-spec move_absolute(atom(), number(), cell_hal_axis_fsm:params()) ->
          {ok, reference()} | {error, term()}.
move_absolute(Id, Position, Params) ->
    command(Id, {move_absolute, Position, Params}).

%% @doc MC_MoveRelative: by `Distance' from where the axis is when it starts.
-spec move_relative(atom(), number(), cell_hal_axis_fsm:params()) ->
          {ok, reference()} | {error, term()}.
move_relative(Id, Distance, Params) ->
    command(Id, {move_relative, Distance, Params}).

%% @doc MC_Halt: decelerates to a stop with `Deceleration'; a newer move may follow.
-spec halt(atom(), number()) -> {ok, reference()} | {error, term()}.
halt(Id, Deceleration) ->
    command(Id, {halt, Deceleration}).

%% @doc MC_Stop: `Execute' true decelerates to a stop and holds the axis in Stopping,
%% refusing moves, until it is called with `Execute' false.
-spec stop(atom(), boolean(), number()) -> {ok, reference()} | {error, term()}.
stop(Id, Execute, Deceleration) when is_boolean(Execute) ->
    command(Id, {stop, Execute, Deceleration}).

%% @doc MC_Reset: leaves ErrorStop (for Standstill, or Disabled if power is off).
-spec reset(atom()) -> {ok, reference()} | {error, term()}.
reset(Id) ->
    command(Id, reset).

%% @private Couples the axis to a motion of several axes (an interpolation channel's
%% path): PLCopen's SynchronizedMotion until it is done.
-spec follow(atom(), cell_hal_axis_fsm:motion()) -> {ok, reference()} | {error, term()}.
follow(Id, Motion) ->
    command(Id, {follow, Motion}).

%% @doc The machine's speed override in percent (0–100), applied to what runs as it
%% changes (seed 000 §2.4: even while the machine runs).
-spec set_override(atom(), number()) -> ok | {error, term()}.
set_override(Id, Pct) ->
    cell_hal_hw:call(Id, {axis, {override, Pct}}, ?TIMEOUT).

%% @doc Whether an axis whose status reads so may be moving: homing, in a move, following
%% a path or stopping, or still at speed (an error stop coming to rest). A display or an
%% adapter reads a moving axis again at its own pace, and a resting one only when told.
-spec moving(status()) -> boolean().
moving(#{state := State, velocity := V}) ->
    lists:member(State, [homing, discrete_motion, synchronized_motion, stopping]) orelse V /= 0.

%% @doc The axis as its NC has it now.
-spec status(atom()) -> {ok, status()} | {error, term()}.
status(Id) ->
    case cell_hal_hw:call(Id, {axis, status}, ?TIMEOUT) of
        #{} = Status -> {ok, Status};
        {error, _} = Error -> Error
    end.

command(Id, Command) ->
    cell_hal_hw:call(Id, {axis, {command, self(), Command}}, ?TIMEOUT).
