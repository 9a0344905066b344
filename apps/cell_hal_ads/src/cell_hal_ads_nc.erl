%% @doc A TwinCAT NC axis as its ADS interface has it (the NC's AMS port 500): which
%% index group and offset each PLCopen command becomes, the axis's online state
%% decoded, and what a new online state means for the job that runs. Pure: the axis
%% process ({@link cell_hal_ads_axis}) sends the requests and polls the state.
%%
%% Index groups, for the NC axis with id `Axis' (1–255):
%% <ul>
%% <li>`16#4000 + Axis' parameters (not used);</li>
%% <li>`16#4100 + Axis' state: offset 0 the online structure (256 bytes from
%%   TwinCAT 3: error code, actual and set position, actual and set velocity,
%%   override, following error, the axis's status double word ...);</li>
%% <li>`16#4200 + Axis' functions: 1 reset, 2 stop (the NC's own deceleration),
%%   4 stop with a given deceleration and jerk, 16#10 reference (homing), 16#1A set
%%   the actual position `{type UINT32 (1 absolute), reserved UINT32, position
%%   LREAL}', 16#21 the extended start of a move `{type UINT32 (1 absolute),
%%   reserved UINT32, target LREAL, velocity LREAL}' followed by the acceleration,
%%   the deceleration and the jerk, each `{use the axis's own UINT32 (1 yes, 0 no),
%%   reserved UINT32, value LREAL}' (72 bytes);</li>
%% <li>`16#4300 + Axis' the cyclic axis interface PLC to NC: 2 controller enable,
%%   3 feed enable plus, 4 feed enable minus (UINT16 each), 16#21 velocity override
%%   (UINT32, 1000000 = 100 %).</li>
%% </ul>
%% The offsets and layouts follow Beckhoff's "ADS interface NC" tables (the
%% specification of the axis's state, functions and cyclic data). The layouts of the
%% set position and the extended start are as published ADS clients of the NC write
%% them, since the rows of the table that give them were not at hand: check a first
%% move on a new machine at a low velocity.
%%
%% Writes to the cyclic interface reach the NC only where the PLC program does not
%% write the same axis interface every cycle (an axis commanded over ADS is not also
%% the PLC's).
-module(cell_hal_ads_nc).

-export([groups/1, request/2, command_writes/3, effect_writes/3, decode_online/1,
         online_size/0, news/3, watch/1, resync/3]).

-export_type([request/0, online/0, watch/0, ctx/0]).

-define(IG_PARAMETERS, 16#4000).
-define(IG_STATE, 16#4100).
-define(IG_FUNCTIONS, 16#4200).
-define(IG_CYCLIC, 16#4300).

%% 0x4100 + Axis.
-define(ONLINE, 16#0).
-define(ONLINE_SIZE, 256).
%% 0x4200 + Axis.
-define(RESET, 16#1).
-define(STOP, 16#2).
-define(STOP_RAMP, 16#4).
-define(REFERENCE, 16#10).
-define(SET_POSITION, 16#1A).
-define(START, 16#21).
%% 0x4300 + Axis.
-define(CONTROLLER_ENABLE, 16#2).
-define(FEED_PLUS, 16#3).
-define(FEED_MINUS, 16#4).
-define(OVERRIDE, 16#21).

-define(START_ABSOLUTE, 1).
-define(SET_ABSOLUTE, 1).
%% The extended start's flag for a value given (0) or the axis's own (1).
-define(GIVEN, 0).
-define(OWN, 1).

%% Bits of the axis's status double word (as PLCopen's MC library decodes it).
-define(ST_READY, 0).
-define(ST_REFERENCED, 1).
-define(ST_NOT_MOVING, 2).
-define(ST_IN_TARGET, 4).
-define(ST_HAS_JOB, 8).
-define(ST_HOMING, 11).
-define(ST_CONTROL_LOOP_CLOSED, 20).
-define(ST_ERROR, 31).

-type u32() :: 0..16#FFFFFFFF.
-type request() :: {write, u32(), u32(), binary()}.

-type online() :: #{error := non_neg_integer(),
                    position := float(), set_position := float(),
                    velocity := float(), set_velocity := float(),
                    override := float(),      % percent
                    status := non_neg_integer(),
                    ready := boolean(), referenced := boolean(),
                    not_moving := boolean(), in_target := boolean(),
                    has_job := boolean(), homing := boolean(),
                    enabled := boolean(), in_error := boolean()}.

%% The job whose end the axis process waits for. Its end is judged only from online
%% states read after the job's writes were answered: the NC has then taken the job
%% (its "has job" bit is set once an ADS start is answered), so a state without it
%% means the job ended.
-type watch() :: #{job := cell_hal_axis_fsm:job() | undefined}.

%% The axis's NC id, the jerk of stops and the distance to the target within which a
%% move counts as arrived.
%% The axis's id; the jerk of its moves and the window of its in-position check where
%% a request or a state's news needs them.
-type ctx() :: #{axis := 1..255, jerk => number(), in_position => number()}.

%% @doc The index groups of an NC axis: parameters, state, functions, cyclic interface.
-spec groups(1..255) -> #{parameters | state | functions | cyclic => u32()}.
groups(Axis) ->
    #{parameters => ?IG_PARAMETERS + Axis, state => ?IG_STATE + Axis,
      functions => ?IG_FUNCTIONS + Axis, cyclic => ?IG_CYCLIC + Axis}.

%% @doc How many bytes of the online structure are read.
-spec online_size() -> pos_integer().
online_size() ->
    ?ONLINE_SIZE.

%% @doc One operation of the NC axis as ADS writes (a read of the online state is
%% `{read, Group, Offset, Size}').
-spec request(reset | stop | reference | {stop, number(), number()} | {enable, boolean()}
              | {override, number()} | {set_position, number()}
              | {start, number(), cell_hal_axis_fsm:params()} | online, ctx()) ->
          [request()] | {read, u32(), u32(), pos_integer()}.
request(online, #{axis := A}) ->
    {read, ?IG_STATE + A, ?ONLINE, ?ONLINE_SIZE};
request(reset, Ctx) ->
    [function(?RESET, <<>>, Ctx)];
request(stop, Ctx) ->
    [function(?STOP, <<>>, Ctx)];
request(reference, Ctx) ->
    [function(?REFERENCE, <<>>, Ctx)];
request({stop, Dec, Jerk}, Ctx) ->
    [function(?STOP_RAMP, <<(float(Dec)):64/float-little, (float(Jerk)):64/float-little>>,
              Ctx)];
request({enable, On}, #{axis := A}) ->
    V = case On of true -> 1; false -> 0 end,
    [{write, ?IG_CYCLIC + A, Off, <<V:16/little>>}
     || Off <- [?CONTROLLER_ENABLE, ?FEED_PLUS, ?FEED_MINUS]];
request({override, Pct}, #{axis := A}) ->
    [{write, ?IG_CYCLIC + A, ?OVERRIDE, <<(round(Pct * 10000)):32/little>>}];
request({set_position, X}, Ctx) ->
    [function(?SET_POSITION, <<?SET_ABSOLUTE:32/little, 0:32, (float(X)):64/float-little>>,
              Ctx)];
request({start, To, #{velocity := V, acceleration := Acc, deceleration := Dec}},
        #{jerk := J} = Ctx) ->
    [function(?START, <<?START_ABSOLUTE:32/little, 0:32,
                        (float(To)):64/float-little, (float(V)):64/float-little,
                        (given(Acc))/binary, (given(Dec))/binary, (given(J))/binary>>, Ctx)].

%% A value of the extended start: the one given, or the axis's own where none is (0).
given(X) when X > 0 ->
    <<?GIVEN:32/little, 0:32, (float(X)):64/float-little>>;
given(_) ->
    <<?OWN:32/little, 0:32, 0.0:64/float-little>>.

function(Offset, Data, #{axis := A}) ->
    {write, ?IG_FUNCTIONS + A, Offset, Data}.

%% @doc What a command needs of the NC beyond the effects the axis's state machine
%% gives: a reset is the NC's reset (its ErrorStop is the NC's error state), and power
%% off in ErrorStop still takes the drive's enables away.
-spec command_writes(cell_hal_axis_fsm:command(), cell_hal_axis_fsm:state(), ctx()) ->
          [request()].
command_writes(reset, error_stop, Ctx) ->
    request(reset, Ctx);
command_writes({power, false}, error_stop, Ctx) ->
    request({enable, false}, Ctx);
command_writes(_Command, _State, _Ctx) ->
    [].

%% @doc The NC's side of the state machine's effects, in order.
-spec effect_writes([cell_hal_axis_fsm:effect()], watch(), ctx()) -> {[request()], watch()}.
effect_writes(Effects, Watch, Ctx) ->
    lists:foldl(fun(E, {Acc, W}) ->
                        {Writes, W1} = effect(E, W, Ctx),
                        {Acc ++ Writes, W1}
                end, {[], Watch}, Effects).

effect(power_on, W, Ctx) ->
    {request({enable, true}, Ctx), W};
effect(power_off, W, Ctx) ->
    {request({enable, false}, Ctx), idle(W)};
effect({override, Pct}, W, Ctx) ->
    {request({override, Pct}, Ctx), W};
effect({run, #{kind := move, target := To, params := Params} = Job}, _W, Ctx) ->
    {request({start, To, Params}, Ctx), running(Job)};
effect({run, #{kind := home} = Job}, _W, Ctx) ->
    {request(reference, Ctx), running(Job)};
effect({run, #{kind := Kind, deceleration := Dec} = Job}, _W, #{jerk := J} = Ctx)
  when Kind =:= halt; Kind =:= stop ->
    {request({stop, Dec, J}, Ctx), running(Job)};
effect({done, #{kind := home, target := At}}, W, Ctx) ->
    %% Referenced: the position the caller named is the axis's position there.
    {request({set_position, At}, Ctx), idle(W)};
effect({done, _Job}, W, _Ctx) ->
    {[], idle(W)};
effect({failed, _Job, _Code}, W, _Ctx) ->
    {[], idle(W)};
effect({aborted, _Job}, W, _Ctx) ->
    %% The job that replaces it (if any) follows as its own {run, _}.
    {[], W};
effect(quick_stop, W, _Ctx) ->
    %% The NC stopped the axis itself when it faulted.
    {[], idle(W)}.

running(Job) -> #{job => Job}.
idle(W) -> W#{job := undefined}.

%% @doc No job watched.
-spec watch(cell_hal_axis_fsm:job() | undefined) -> watch().
watch(Job) ->
    #{job => Job}.

%% @doc The online structure read at 0x4100 + Axis, offset 0.
-spec decode_online(binary()) -> {ok, online()} | {error, {short_online_state, non_neg_integer()}}.
decode_online(<<Err:32/signed-little, _:32, Pos:64/float-little, _ModPos:64/float-little,
                SetPos:64/float-little, _ModSet:64/float-little, Vel:64/float-little,
                SetVel:64/float-little, Ovr:32/little, _:32, _Lag:64/float-little,
                _PeakNeg:64/float-little, _PeakPos:64/float-little, _CtrlOut:64/float-little,
                _TotalOut:64/float-little, Status:32/little, _/binary>>) ->
    Bit = fun(N) -> Status band (1 bsl N) =/= 0 end,
    {ok, #{error => abs(Err), position => Pos, set_position => SetPos, velocity => Vel,
           set_velocity => SetVel, override => Ovr / 10000, status => Status,
           ready => Bit(?ST_READY), referenced => Bit(?ST_REFERENCED),
           not_moving => Bit(?ST_NOT_MOVING), in_target => Bit(?ST_IN_TARGET),
           has_job => Bit(?ST_HAS_JOB), homing => Bit(?ST_HOMING),
           enabled => Bit(?ST_CONTROL_LOOP_CLOSED), in_error => Bit(?ST_ERROR)}};
decode_online(Bin) ->
    {error, {short_online_state, byte_size(Bin)}}.

%% @doc What a new online state means: the NC's news for the axis's state machine
%% (a fault, the job's end), and the watch carried to the next poll.
%%
%% The online state must have been read after the job's writes were answered (the
%% axis process drops a poll sent before them). A fault is the NC's error code, news
%% once (the state machine is in error_stop until reset). A move is done when the NC
%% has no job and the axis stands within `in_position' of its target; a halt or stop
%% when the NC has no job and the axis stands; homing when the NC has no job, is not
%% homing and the axis is referenced.
-spec news(online(), watch(), #{state := cell_hal_axis_fsm:state(), ctx := ctx()}) ->
          {[cell_hal_axis_fsm:event()], watch()}.
news(#{error := Code}, W, #{state := State}) when Code =/= 0, State =/= error_stop ->
    {[{fault, Code}], idle(W)};
news(#{error := Code}, W, _) when Code =/= 0 ->
    {[], W};
news(_Online, #{job := undefined} = W, _) ->
    {[], W};
news(Online, #{job := #{id := Id} = Job} = W, #{ctx := Ctx}) ->
    case ended(Job, Online, Ctx) of
        true -> {[{done, Id}], W};
        false -> {[], W}
    end.

ended(#{kind := move, target := To}, #{has_job := false, not_moving := true,
                                       position := X}, #{in_position := Tol}) ->
    abs(X - To) =< Tol;
ended(#{kind := home}, #{has_job := false, homing := false, referenced := true}, _) ->
    true;
ended(#{kind := Kind}, #{has_job := false, not_moving := true}, _)
  when Kind =:= halt; Kind =:= stop ->
    true;
ended(_Job, _Online, _Ctx) ->
    false.

%% @doc The axis's state machine rebuilt from what the NC says, after the connection
%% came (back): powered if its controller is enabled, homed if referenced, in
%% error_stop with the NC's error code. A job the NC may still run has no owner any
%% more and is not watched.
-spec resync(online(), cell_hal_axis_fsm:axis(), number()) -> cell_hal_axis_fsm:axis().
resync(#{enabled := Enabled, referenced := Referenced, error := Code, position := X}, New,
       Override) ->
    Steps = [{power, true} || Enabled] ++ [{home, X} || Enabled, Referenced],
    A1 = lists:foldl(fun(Command, A) -> replay(Command, X, A) end, New, Steps),
    A2 = case cell_hal_axis_fsm:set_override(Override, A1) of
             {ok, A, _} -> A;
             {error, _} -> A1
         end,
    case Code of
        0 -> A2;
        _ -> element(1, cell_hal_axis_fsm:event({fault, Code}, A2))
    end.

%% A command replayed as if the NC had done it: a home is at once done.
replay(Command, X, A) ->
    case cell_hal_axis_fsm:command(Command, X, A) of
        {ok, A1, Effects} ->
            case [Id || {run, #{id := Id}} <- Effects] of
                [Id] -> element(1, cell_hal_axis_fsm:event({done, Id}, A1));
                [] -> A1
            end;
        {error, _} ->
            A
    end.
