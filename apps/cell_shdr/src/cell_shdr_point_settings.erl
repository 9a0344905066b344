%% @doc One HAL point the adapter publishes (an element of the `points' list of
%% {@link cell_shdr_settings}): which IO point, under which data item name, as which
%% MTConnect type, and how: every change as a sample or event, or sampled at a fixed
%% rate and sent as a time series of `count' samples a line.
-module(cell_shdr_point_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

%% @doc Its name (it is only ever nested in the `shdr' object, never a file of its own).
-spec name() -> shdr_point.
name() -> shdr_point.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => name, type => {string, 64}, default => <<"point">>,
       doc => <<"The data item's id and name (letters, digits, _ . -).">>},
     #{name => group, type => {string, 64}, default => <<>>,
       doc => <<"The HAL IO group instance.">>},
     #{name => point, type => {string, 64}, default => <<>>,
       doc => <<"The point of that group.">>},
     #{name => category, type => {enum, [sample, event]}, default => sample,
       doc => <<"MTConnect category: a sample (a number) or an event.">>},
     #{name => type, type => {string, 64}, default => <<"TEMPERATURE">>,
       doc => <<"MTConnect data item type, as TEMPERATURE, PRESSURE, DOOR_STATE.">>},
     #{name => sub_type, type => {string, 64}, default => <<>>,
       doc => <<"MTConnect sub-type, or empty.">>},
     #{name => units, type => {string, 32}, default => <<>>,
       doc => <<"MTConnect units of a sample, as CELSIUS, PASCAL, MILLIMETER.">>},
     #{name => time_series, type => boolean, default => false,
       doc => <<"Sample at a fixed rate and send time series instead of changes.">>},
     #{name => rate, type => {float, 0.1, 1000.0}, default => 10.0, unit => <<"Hz">>,
       doc => <<"Sampling rate of a time series.">>},
     #{name => count, type => {integer, 1, 1000}, default => 10,
       doc => <<"Samples per time series line.">>},
     #{name => component, type => {enum, [device, linear, rotary]}, default => device,
       doc => <<"Where the item sits: on the device, or on an axis (a Linear or Rotary "
                "component of the device's Axes), as an axis's position and velocity.">>},
     #{name => axis, type => {string, 32}, default => <<>>,
       doc => <<"The axis's name (X, Y, C ...) for a Linear or Rotary component.">>}].

%% @doc Types and sub-types are MTConnect words; a time series is a sample; an item on
%% an axis names the axis.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{type := Type, sub_type := Sub, units := Units} = P) ->
    case {word(Type), Sub =:= <<>> orelse word(Sub), Units =:= <<>> orelse unit(Units)} of
        {false, _, _} -> {error, [type], {not_an_mtconnect_word, Type}};
        {_, false, _} -> {error, [sub_type], {not_an_mtconnect_word, Sub}};
        {_, _, false} -> {error, [units], {not_an_mtconnect_word, Units}};
        _ ->
            case P of
                #{time_series := true, category := event} ->
                    {error, [category], time_series_is_a_sample};
                #{component := C, axis := Axis} when C =/= device ->
                    case Axis =/= <<>> andalso cell_shdr_items:valid_name(Axis) of
                        true -> ok;
                        false -> {error, [axis], {an_axis_needs_a_name, Axis}}
                    end;
                _ ->
                    ok
            end
    end.

%% Units also divide and raise to powers: MILLIMETER/SECOND, MILLIMETER^3.
unit(B) -> word(binary:replace(B, [<<"/">>, <<"^">>], <<"_">>, [global])).

word(<<>>) -> false;
word(B) -> lists:all(fun(C) -> (C >= $A andalso C =< $Z) orelse (C >= $0 andalso C =< $9)
                                   orelse C =:= $_ end, binary_to_list(B)).
