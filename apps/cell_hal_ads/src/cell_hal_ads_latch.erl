%% @doc Latching a value at a sensor edge from time-stamped samples (seed 000 §2.3.7).
%%
%% The laser-beam example: to measure a tool's diameter, an axis drives the tool
%% through a laser beam. ADS lag is 3-20 ms, too slow to read the axis position when
%% the beam breaks. Instead the PLC sends both the sensor and the axis position as
%% device notifications; TwinCAT stamps each sample with the time of the real-time
%% cycle that took it, and samples of one cycle carry the same stamp. Afterwards the
%% first sensor edge is found, and the axis position at that stamp is the answer.
%%
%% Samples are `{Time, Value}' with any integer time (the client delivers nanoseconds
%% since the Unix epoch). Notifications on change send a value when it changes, so
%% between two samples the value held: the position at time T is that of the last
%% sample at or before T (`hold', the default). `interpolate' draws a straight line
%% between the samples around T instead, for a position sampled cyclically while the
%% axis moves steadily. A sample stamped exactly T is always taken as it is.
-module(cell_hal_ads_latch).

-export([position_at_edge/3, first_edge/2]).

-export_type([sample/0, opts/0]).

-type sample() :: {Time :: integer(), term()}.

-type opts() :: #{edge => rising | falling,
                  %% only edges at or after this time count
                  from => integer(),
                  %% the sensor level before its first sample; without it the first
                  %% sample only sets the level and is never an edge
                  initial => boolean(),
                  method => hold | interpolate}.

%% @doc The position at the first sensor edge: `{ok, #{time, position, exact}}' where
%% `exact' says a position sample carries the edge's very stamp. `no_edge' when the
%% sensor never changed that way, `{no_position, Time}' when no position sample lies
%% at or before the edge (or, to interpolate, none after it).
-spec position_at_edge([sample()], [sample()], opts()) ->
          {ok, #{time := integer(), position := number(), exact := boolean()}}
        | {error, no_edge | {no_position, integer()}}.
position_at_edge(Sensor, Positions, Opts) ->
    case first_edge(Sensor, Opts) of
        {ok, T} -> position_at(T, lists:keysort(1, Positions), maps:get(method, Opts, hold));
        none -> {error, no_edge}
    end.

%% @doc The stamp of the first edge of a boolean sensor signal (samples in any order;
%% samples with equal stamps keep their order).
-spec first_edge([sample()], opts()) -> {ok, integer()} | none.
first_edge(Sensor, Opts) ->
    Initial = maps:get(initial, Opts, undefined),
    To = case maps:get(edge, Opts, rising) of
             rising -> true;
             falling -> false
         end,
    From = maps:get(from, Opts, undefined),
    edge(lists:keysort(1, Sensor), Initial, To, From).

edge([], _, _, _) ->
    none;
edge([{T, Level} | Rest], Prev, To, From) when is_boolean(Level) ->
    case Level =:= To andalso Prev =:= (not To) andalso (From =:= undefined orelse T >= From) of
        true -> {ok, T};
        false -> edge(Rest, Level, To, From)
    end.

position_at(T, Positions, Method) ->
    {Before, After} = lists:splitwith(fun({Ts, _}) -> Ts =< T end, Positions),
    case {lists:reverse(Before), After} of
        {[{T, P} | _], _} ->
            {ok, #{time => T, position => P, exact => true}};
        {[{_, P} | _], _} when Method =:= hold ->
            {ok, #{time => T, position => P, exact => false}};
        {[{T0, P0} | _], [{T1, P1} | _]} when Method =:= interpolate ->
            {ok, #{time => T, position => P0 + (P1 - P0) * (T - T0) / (T1 - T0),
                   exact => false}};
        _ ->
            {error, {no_position, T}}
    end.
