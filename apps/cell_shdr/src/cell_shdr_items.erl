%% @doc The data items the adapter emits, in MTConnect vocabulary, and how each is
%% derived from the cell (pure functions). The same list feeds the stream and the
%% `Devices.xml' the adapter writes, so the two always declare the same items.
%%
%% The cell is one MTConnect Device with a Controller; each device task is a Path of
%% that Controller (an independent function with its own execution); configured HAL
%% points sit on the Device; each axis of the cell's spec (a hardware object of kind
%% `axis', seed 000's NcAxis) is a Linear component of the Device's Axes, or a Rotary
%% one for an axis that turns (its option `rotary').
%%
%% <table>
%% <tr><th>key</th><th>type (sub-type)</th><th>from</th></tr>
%% <tr><td>`avail'</td><td>AVAILABILITY</td><td>AVAILABLE while the adapter sees
%%   the cell's events</td></tr>
%% <tr><td>`estop'</td><td>EMERGENCY_STOP</td><td>TRIGGERED while the emergency stop
%%   is active, else ARMED</td></tr>
%% <tr><td>`mode'</td><td>CONTROLLER_MODE</td><td>MANUAL in service mode, else
%%   AUTOMATIC</td></tr>
%% <tr><td>`execution', `wait_state'</td><td>EXECUTION, WAIT_STATE</td><td>the
%%   cell's IPC-2541 state (table below)</td></tr>
%% <tr><td>`program'</td><td>PROGRAM</td><td>the recipe of the product whose work
%%   started last</td></tr>
%% <tr><td>`part_count', `part_count_good', `part_count_bad'</td><td>PART_COUNT (ALL,
%%   GOOD, BAD)</td><td>work completed or aborted, completed, aborted (seed 000
%%   §2.3.4 ItemWorkComplete / ItemWorkAbort), going on from the statistics' totals
%%   when the adapter starts</td></tr>
%% <tr><td>`cycle_time'</td><td>PROCESS_TIMER (PROCESS), seconds</td><td>work start
%%   to work complete of the last product completed</td></tr>
%% <tr><td>`system'</td><td>SYSTEM condition</td><td>the cell's own alarms (the
%%   emergency stop)</td></tr>
%% <tr><td>`T_execution', `T_wait_state'</td><td>EXECUTION, WAIT_STATE</td><td>task
%%   T's IPC-2541 state</td></tr>
%% <tr><td>`T_part_state'</td><td>PART_PROCESSING_STATE</td><td>task T's item
%%   events (table below)</td></tr>
%% <tr><td>`T_serial'</td><td>PART_UNIQUE_ID (SERIAL_NUMBER)</td><td>the serial of
%%   the product T holds</td></tr>
%% <tr><td>`T_program'</td><td>PROGRAM</td><td>the recipe of that product</td></tr>
%% <tr><td>`T_part_count'</td><td>PART_COUNT (ALL)</td><td>T's completed and aborted
%%   work, likewise (only for a task that does work: its spec's `work')</td></tr>
%% <tr><td>`T_cycle_time'</td><td>PROCESS_TIMER (PROCESS)</td><td>T's last work
%%   start to complete (likewise)</td></tr>
%% <tr><td>`T_system'</td><td>SYSTEM condition</td><td>T's errors, alarms,
%%   warnings</td></tr>
%% <tr><td>`A_position'</td><td>POSITION (ACTUAL), millimetres</td><td>axis A's actual
%%   position</td></tr>
%% <tr><td>`A_feedrate'</td><td>AXIS_FEEDRATE (ACTUAL), millimetres a second</td><td>the
%%   speed of axis A (its velocity's size)</td></tr>
%% <tr><td>`A_state'</td><td>AXIS_STATE</td><td>TRAVEL while axis A may be moving
%%   (cell_hal_axis:moving/1), STOPPED otherwise</td></tr>
%% </table>
%%
%% IPC-2541 state to EXECUTION and WAIT_STATE. The idle states say why the task
%% waits: STARVED waits for a part to come in, BLOCKED for its part to be taken.
%%
%% <table>
%% <tr><th>IPC-2541</th><th>EXECUTION</th><th>WAIT_STATE</th></tr>
%% <tr><td>OFF</td><td>STOPPED</td><td>UNAVAILABLE</td></tr>
%% <tr><td>DOWN (paused, or an error waits)</td><td>INTERRUPTED</td><td>UNAVAILABLE</td></tr>
%% <tr><td>SETUP (initialising)</td><td>WAIT</td><td>POWERING_UP</td></tr>
%% <tr><td>READY-IDLE-STARVED</td><td>READY</td><td>UNAVAILABLE</td></tr>
%% <tr><td>READY-IDLE-BLOCKED</td><td>WAIT</td><td>PART_UNLOAD</td></tr>
%% <tr><td>READY-PROCESSING-ACTIVE</td><td>ACTIVE</td><td>UNAVAILABLE</td></tr>
%% <tr><td>READY-PROCESSING-EXECUTING</td><td>ACTIVE</td><td>UNAVAILABLE</td></tr>
%% </table>
%%
%% Item events to PART_PROCESSING_STATE: TransferIn NEEDS_PROCESSING, WorkStart and
%% WorkResume IN_PROCESS, WorkComplete PROCESSING_ENDED_COMPLETE, WorkAbort
%% PROCESSING_ENDED_ABORTED, Blocked (the part waits for the next device)
%% WAITING_FOR_TRANSIT, Unblocked IN_TRANSIT, TransferOut TRANSIT_COMPLETE; the others
%% leave it.
%%
%% Conditions: an error or an alarm is a FAULT, a warning a WARNING; the native code
%% is the error id with `:' written as `.' (agents of MTConnect 2.3 and later read a
%% colon in a native code as the start of a condition id); the native severity is the
%% kind (`error', `alarm', `warning'); the text is the caption and the description.
-module(cell_shdr_items).

-export([items/2, items/3, items/4, prefixes/1, task_key/3, valid_name/1]).
-export([axis_items/1, axis_values/2]).
-export([execution/1, wait_state/1, part_state/1, controller_mode/1, estop/1,
         condition/1, native_code/1, condition_owner/2, is_message/1, point_value/2]).

-export_type([item/0, component/0, category/0]).

-type category() :: sample | event | condition.
-type component() :: device | controller | {path, atom(), binary()}
                   | {axis, linear | rotary, binary()}.
-type item() :: #{key := binary(), type := binary(), category := category(),
                  component := component(), sub_type => binary(), units => binary(),
                  time_series => true, rate => number()}.

%% @doc Every data item for these tasks (in order) and configured points, every task
%% doing work.
-spec items([atom()], [map()]) -> [item()].
items(Tasks, Points) ->
    items(Tasks, [], Points).

%% @doc Every data item for these tasks (in order) and configured points; the tasks in
%% `Idle' do no work (their spec's `work' is false): they have no part count and no
%% cycle time, which would never carry data.
-spec items([atom()], [atom()], [map()]) -> [item()].
items(Tasks, Idle, Points) ->
    items(Tasks, Idle, Points, #{}).

%% @doc Every data item for these tasks, configured points and axes (by id, the name
%% of each, from {@link prefixes/1}, and whether it moves along a line or turns).
-spec items([atom()], [atom()], [map()], #{atom() => {binary(), linear | rotary}}) ->
          [item()].
items(Tasks, Idle, Points, Axes) ->
    Prefixes = prefixes(Tasks),
    [ev(<<"avail">>, <<"AVAILABILITY">>, device),
     ev(<<"estop">>, <<"EMERGENCY_STOP">>, controller),
     ev(<<"mode">>, <<"CONTROLLER_MODE">>, controller),
     ev(<<"execution">>, <<"EXECUTION">>, controller),
     ev(<<"wait_state">>, <<"WAIT_STATE">>, controller),
     ev(<<"program">>, <<"PROGRAM">>, controller),
     (ev(<<"part_count">>, <<"PART_COUNT">>, controller))#{sub_type => <<"ALL">>},
     (ev(<<"part_count_good">>, <<"PART_COUNT">>, controller))#{sub_type => <<"GOOD">>},
     (ev(<<"part_count_bad">>, <<"PART_COUNT">>, controller))#{sub_type => <<"BAD">>},
     cycle_time(<<"cycle_time">>, controller),
     condition_item(<<"system">>, controller)]
        ++ lists:append([task_items(T, maps:get(T, Prefixes), not lists:member(T, Idle))
                         || T <- Tasks])
        ++ [point_item(P) || P <- Points]
        ++ axis_items(Axes).

%% @doc The items of the axes (by id, the name of each and whether it moves along a
%% line or turns): a Linear component each (position in millimetres, feedrate in
%% millimetres a second), or a Rotary one (angle in degrees, angular velocity in
%% degrees a second); each with its AXIS_STATE.
-spec axis_items(#{atom() => {binary(), linear | rotary}}) -> [item()].
axis_items(Axes) ->
    lists:append(
      [begin
           C = {axis, Kind, Name},
           Velocity = #{key => <<Name/binary, "_feedrate">>, category => sample,
                        component => C},
           {PosType, PosUnits, Vel} =
               case Kind of
                   linear -> {<<"POSITION">>, <<"MILLIMETER">>,
                              Velocity#{type => <<"AXIS_FEEDRATE">>, sub_type => <<"ACTUAL">>,
                                        units => <<"MILLIMETER/SECOND">>}};
                   %% ANGULAR_VELOCITY has no sub-types.
                   rotary -> {<<"ANGLE">>, <<"DEGREE">>,
                              Velocity#{type => <<"ANGULAR_VELOCITY">>,
                                        units => <<"DEGREE/SECOND">>}}
               end,
           [#{key => <<Name/binary, "_position">>, type => PosType,
              sub_type => <<"ACTUAL">>, category => sample, units => PosUnits,
              component => C},
            Vel,
            ev(<<Name/binary, "_state">>, <<"AXIS_STATE">>, C)]
       end || {_, {Name, Kind}} <- lists:sort(maps:to_list(Axes))]).

%% @doc The values of an axis's items (named `Name') for its status as it reads, or
%% UNAVAILABLE when it cannot be read (the object not there, its NC not connected).
-spec axis_values(binary(), {ok, map()} | {error, term()}) -> [{binary(), term()}].
axis_values(Name, {ok, #{position := X, velocity := V} = Status}) ->
    [{<<Name/binary, "_position">>, X}, {<<Name/binary, "_feedrate">>, abs(V)},
     {<<Name/binary, "_state">>, case cell_shdr_hal:axis_moving(Status) of
                                     true -> <<"TRAVEL">>;
                                     false -> <<"STOPPED">>
                                 end}];
axis_values(Name, _) ->
    [{<<Name/binary, Suffix/binary>>, unavailable}
     || Suffix <- [<<"_position">>, <<"_feedrate">>, <<"_state">>]].

task_items(Task, Prefix, Works) ->
    C = {path, Task, Prefix},
    K = fun(S) -> <<Prefix/binary, $_, S/binary>> end,
    [ev(K(<<"execution">>), <<"EXECUTION">>, C),
     ev(K(<<"wait_state">>), <<"WAIT_STATE">>, C),
     ev(K(<<"part_state">>), <<"PART_PROCESSING_STATE">>, C),
     (ev(K(<<"serial">>), <<"PART_UNIQUE_ID">>, C))#{sub_type => <<"SERIAL_NUMBER">>},
     ev(K(<<"program">>), <<"PROGRAM">>, C)]
        ++ case Works of
               true -> [(ev(K(<<"part_count">>), <<"PART_COUNT">>, C))#{sub_type => <<"ALL">>},
                        cycle_time(K(<<"cycle_time">>), C)];
               false -> []
           end
        ++ [condition_item(K(<<"system">>), C)].

point_item(#{name := Name, type := Type, category := Cat, sub_type := Sub,
             units := Units} = P) ->
    Component = case P of
                    #{component := Kind, axis := Axis} when Kind =:= linear;
                                                            Kind =:= rotary ->
                        {axis, Kind, Axis};
                    #{} ->
                        device
                end,
    Base = #{key => Name, type => Type, category => Cat, component => Component},
    B1 = case Sub of <<>> -> Base; _ -> Base#{sub_type => Sub} end,
    B2 = case Units of <<>> -> B1; _ -> B1#{units => Units} end,
    case P of
        #{time_series := true, rate := Rate} -> B2#{time_series => true, rate => Rate};
        _ -> B2
    end.

ev(Key, Type, Component) ->
    #{key => Key, type => Type, category => event, component => Component}.

cycle_time(Key, Component) ->
    #{key => Key, type => <<"PROCESS_TIMER">>, sub_type => <<"PROCESS">>,
      category => sample, units => <<"SECOND">>, component => Component}.

condition_item(Key, Component) ->
    #{key => Key, type => <<"SYSTEM">>, category => condition, component => Component}.

%% @doc The key prefix of each task: its id where that is a valid data item name,
%% else the id with other characters written as `_' (and a number added where two
%% tasks would meet).
-spec prefixes([atom()]) -> #{atom() => binary()}.
prefixes(Tasks) ->
    {Map, _} = lists:foldl(
                 fun(T, {Acc, Taken}) ->
                         P = unique(sanitize(atom_to_binary(T, utf8)), Taken, 1),
                         {Acc#{T => P}, Taken#{P => true}}
                 end, {#{}, reserved()}, lists:usort(Tasks)),
    Map.

%% Cell-level keys a task prefix must not shadow.
reserved() ->
    maps:from_list([{K, true} || K <- [<<"avail">>, <<"estop">>, <<"mode">>,
                                       <<"execution">>, <<"wait_state">>, <<"program">>,
                                       <<"part_count">>, <<"cycle_time">>, <<"system">>]]).

unique(P, Taken, 1) when not is_map_key(P, Taken) -> P;
unique(P, Taken, N) ->
    Q = <<P/binary, $_, (integer_to_binary(N + 1))/binary>>,
    case Taken of
        #{Q := _} -> unique(P, Taken, N + 1);
        _ -> Q
    end.

sanitize(B) ->
    S0 = << <<(case name_char(C) of true -> C; false -> $_ end)>> || <<C>> <= B >>,
    S = binary:replace(S0, <<"--multiline--">>, <<"_multiline_">>, [global]),
    case S of
        <<C, _/binary>> when (C >= $a andalso C =< $z); (C >= $A andalso C =< $Z); C =:= $_ -> S;
        _ -> <<"t_", S/binary>>
    end.

name_char(C) ->
    (C >= $a andalso C =< $z) orelse (C >= $A andalso C =< $Z) orelse
        (C >= $0 andalso C =< $9) orelse C =:= $_ orelse C =:= $- orelse C =:= $..

%% @doc The key of one of a task's items: `task_key(Prefixes, robot, <<"serial">>)'.
-spec task_key(#{atom() => binary()}, atom(), binary()) -> binary().
task_key(Prefixes, Task, Suffix) ->
    <<(maps:get(Task, Prefixes))/binary, $_, Suffix/binary>>.

%% @doc A valid data item id and name: an XML name without colons, of at most 64
%% characters, that a line cannot misread (no `|', no blanks, no `@' first, no
%% `--multiline--', which an agent takes for the start of an asset anywhere in a line).
-spec valid_name(binary()) -> boolean().
valid_name(<<C, _/binary>> = B) when byte_size(B) =< 64,
                                     ((C >= $a andalso C =< $z) orelse
                                      (C >= $A andalso C =< $Z) orelse C =:= $_) ->
    lists:all(fun name_char/1, binary_to_list(B)) andalso
        binary:match(B, <<"--multiline--">>) =:= nomatch;
valid_name(_) ->
    false.

%%====================================================================
%% Derivations
%%====================================================================

%% @doc EXECUTION of an IPC-2541 state (see the module doc).
-spec execution(cell_ipc:state()) -> binary().
execution(off) -> <<"STOPPED">>;
execution(down) -> <<"INTERRUPTED">>;
execution(setup) -> <<"WAIT">>;
execution({ready, idle, starved}) -> <<"READY">>;
execution({ready, idle, blocked}) -> <<"WAIT">>;
execution({ready, processing, _}) -> <<"ACTIVE">>.

%% @doc WAIT_STATE: why EXECUTION says WAIT.
-spec wait_state(cell_ipc:state()) -> binary() | unavailable.
wait_state(setup) -> <<"POWERING_UP">>;
wait_state({ready, idle, blocked}) -> <<"PART_UNLOAD">>;
wait_state(_) -> unavailable.

%% @doc PART_PROCESSING_STATE after an event of seed 000 §2.3.4, or `keep'.
-spec part_state(cell_events:type()) -> binary() | keep.
part_state(item_transfer_in) -> <<"NEEDS_PROCESSING">>;
part_state(item_work_start) -> <<"IN_PROCESS">>;
part_state(item_work_resume) -> <<"IN_PROCESS">>;
part_state(item_work_complete) -> <<"PROCESSING_ENDED_COMPLETE">>;
part_state(item_work_abort) -> <<"PROCESSING_ENDED_ABORTED">>;
part_state(equipment_blocked) -> <<"WAITING_FOR_TRANSIT">>;
part_state(equipment_unblocked) -> <<"IN_TRANSIT">>;
part_state(item_transfer_out) -> <<"TRANSIT_COMPLETE">>;
part_state(_) -> keep.

-spec controller_mode(boolean()) -> binary().
controller_mode(true) -> <<"MANUAL">>;
controller_mode(false) -> <<"AUTOMATIC">>.

-spec estop(boolean()) -> binary().
estop(true) -> <<"TRIGGERED">>;
estop(false) -> <<"ARMED">>.

%% @doc A condition for an active error, alarm or warning.
-spec condition(cell_alarms:alarm()) -> cell_shdr_codec:condition().
condition(#{id := Id, kind := Kind, caption := Caption, description := Desc} = Alarm) ->
    Level = case Kind of warning -> warning; _ -> fault end,
    Text = case Desc of
               <<>> -> Caption;
               _ -> <<Caption/binary, ": ", Desc/binary>>
           end,
    C = #{level => Level, code => native_code(Id), severity => atom_to_binary(Kind, utf8),
          text => Text},
    case Alarm of
        #{qualifier := high} -> C#{qualifier => <<"HIGH">>};
        #{qualifier := low} -> C#{qualifier => <<"LOW">>};
        _ -> C
    end.

%% @doc The native code of an error id: `robot:lost' is `robot.lost'.
-spec native_code(binary()) -> binary().
native_code(Id) ->
    binary:replace(Id, <<":">>, <<".">>, [global]).

%% @doc Whether a configured point is a MESSAGE, whose lines carry a native code and
%% a text (`key|code|text') instead of one value.
-spec is_message(#{type := binary(), atom() => term()}) -> boolean().
is_message(#{type := Type}) ->
    Type =:= <<"MESSAGE">>.

%% @doc The value a HAL point's reading is published as. An agent reads a sample as a
%% number and drops anything else, so a sample is a number: a boolean is 1 or 0, text
%% that reads as a number stays, and any other reading is UNAVAILABLE. An event
%% carries its reading as text.
-spec point_value(#{category := sample | event, atom() => term()}, term()) ->
          cell_shdr_codec:value().
point_value(#{category := sample}, V) when is_number(V) -> V;
point_value(#{category := sample}, true) -> 1;
point_value(#{category := sample}, false) -> 0;
point_value(#{category := sample}, V) when is_binary(V) ->
    Text = string:trim(V),
    case number(Text) of
        {ok, _} -> Text;
        error -> unavailable
    end;
point_value(#{category := sample}, _) -> unavailable;
point_value(#{category := event}, true) -> <<"true">>;
point_value(#{category := event}, false) -> <<"false">>;
point_value(#{category := event}, V) when is_number(V); is_binary(V) -> V;
point_value(#{category := event}, {Y, M, D}) when is_integer(Y), is_integer(M),
                                                  is_integer(D) ->
    iolist_to_binary(io_lib:format("~4..0w-~2..0w-~2..0w", [Y, M, D]));
point_value(#{category := event}, V) ->
    iolist_to_binary(io_lib:format("~0tp", [V])).

number(B) ->
    try {ok, binary_to_integer(B)}
    catch error:badarg ->
            try {ok, binary_to_float(B)}
            catch error:badarg -> error
            end
    end.

%% @doc The condition item an alarm of `Task' shows on: the task's own, or the
%% cell's `system' for the cell's alarms and tasks the adapter does not know.
-spec condition_owner(#{atom() => binary()}, atom()) -> binary().
condition_owner(Prefixes, Task) ->
    case Prefixes of
        #{Task := P} -> <<P/binary, "_system">>;
        _ -> <<"system">>
    end.
