%% The records behind a unit's step sequences: opaque to sequence modules, which use the
%% functions of cell_sequence on the seq() their steps are given.

%% One running sequence: the unit's state's own, or a sub-sequence it called. Only the
%% innermost sequence has a step under way: that step, when it was entered and whether
%% its body has run are the #seq's, so that a step costs one update of the #seq and
%% none of a #frame. A caller's frame keeps the step it called from.
-record(frame, {
    module :: module(),
    %% fun Module:step/2, made once: calling it skips the lookup of Module:step(...).
    %% What it returns is the sequence's word, checked by the runner: any term.
    body :: fun((term(), cell_sequence:seq()) -> term()),
    args = #{} :: map(),
    mode = several :: several | one,      %% several steps in one go, or one per cycle
    depth = 1 :: pos_integer(),           %% 1 for the state's sequence, 2 for one it called ...
    step :: term(),                       %% a caller's: the step it called from
    vars = #{} :: map(),                  %% the sequence's own variables
    return :: term(),                     %% the caller's next step once this one is done
    timers = [] :: [atom()]               %% the timers this sequence started
}).

%% The sequences of one unit and the actuators they drive.
-record(seq, {
    unit :: atom(),
    io = [] :: [atom()],                  %% IO group instances; the first is the default
    frames = [] :: [#frame{}],            %% the running sequence first, then its callers
    actuators = #{} :: #{atom() => {module(), term()}},
    haltable = true :: boolean(),         %% Halt applies to this state's sequence
    halt = false :: boolean(),
    held = false :: boolean(),            %% Halt has taken hold: the sequence waits
    service = false :: boolean(),
    settings = #{} :: map(),
    waiting :: undefined | {[term()], infinity | {integer(), non_neg_integer()}},
    armed = #{} :: #{term() => term()},   %% IO watches and the deadline of this step
    latched = #{} :: #{term() => term()}, %% IO conditions seen to hold in this step
    replies = #{} :: #{reference() => expected | {term()}},
    orders = #{} :: #{atom() => term()}, %% the standing orders given to the unit
    effects = [] :: [term()],             %% what the engine is to do, newest first
    read :: fun((atom(), atom()) -> {ok, term()} | {error, term()}),
    estop :: fun(() -> boolean()),
    now = 0 :: integer(),
    %% The innermost sequence's step (see #frame); its body has not yet returned since
    %% the step was entered (while the body runs, this is its first run: on_entry/1);
    %% when the step was entered (monotonic ms; await timeouts count from there).
    step :: term(),
    fresh = true :: boolean(),
    entered = 0 :: integer()
}).
