%% @doc IO groups (seed 000 §4.1): a module declares the named inputs and outputs of
%% one part of the machine (the general IO, a device task's IO, a teach pendant); a
%% group instance binds it to one PLC connection by configuration. One module serves
%% several instances through its options, as the seed's constructors take structure
%% names: a front and a rear lane, each at its own Modbus base address or ADS
%% structure.
%%
%% ```
%% -module(general_io).
%% -behaviour(cell_hal_group).
%% -export([points/1]).
%%
%% points(#{base := B}) ->
%%     [#{name => start_button, dir => in, type => bool, address => <<"A1.01.06">>,
%%        caption => <<"Start button">>, field => {discrete_input, B}},
%%      #{name => start_button_light, dir => out, type => bool,
%%        address => <<"A1.20.05">>, caption => <<"Start button light">>,
%%        field => {coil, B}}].
%% '''
%%
%% `address' is the wiring label of the point in the electrical drawings, `caption'
%% what the operator's IO page shows. `field' is where the driver finds the point:
%% <ul>
%% <li>Modbus: `{coil, A}', `{discrete_input, A}', `{holding_register, A}',
%%   `{input_register, A}', `{holding_register, A, Bit}', `{input_register, A, Bit}'
%%   (see {@link cell_hal_modbus_plan}); instance options `unit' and `word_order'.</li>
%% <li>ADS, structure based (seed §4.1.1): the member name with its leading dot,
%%   `<<".StartButton">>'; the instance options `input_struct' and `output_struct'
%%   name the PLC's structure instances, `<<".GeneralInputs">>' for a VAR_GLOBAL,
%%   `<<"MAIN.GeneralInputs">>' under a program. The symbol read is their
%%   concatenation, `.GeneralInputs.StartButton'.</li>
%% <li>ADS, image based (seed §4.1.2): the unique name of the hardware point,
%%   `<<"*ManipulatorInputs.FailPaletteIsIn">>', where `*' matches anything before
%%   the name in the image's symbol table.</li>
%% <li>Simulation ({@link cell_hal_sim}): any field; the simulated image keeps each
%%   point apart by its group and name, so a module written for a PLC runs unchanged
%%   against the simulation.</li>
%% </ul>
-module(cell_hal_group).

-export([check_points/1, ads_symbol/3]).

-export_type([point_def/0, ads_symbol/0]).

-type point_def() :: #{name := atom(),
                       dir := in | out,
                       type := cell_hal_type:type(),
                       address := binary(),
                       caption := binary(),
                       unit => binary(),
                       field := term()}.
-type ads_symbol() :: {symbol, binary()} | {image, binary()}.

%% The points of one instance of the group.
-callback points(Opts :: map()) -> [point_def()].

%% @doc Checks the point definitions a group module returned: each a map with the keys
%% above, names unique. The first fault is named: `{bad_point, Name, Key}'.
-spec check_points(term()) -> ok | {error, {bad_point, term(), atom()} | {bad_group, points}}.
check_points(Defs) when is_list(Defs) ->
    check_points(Defs, #{});
check_points(_) ->
    {error, {bad_group, points}}.

check_points([], _) ->
    ok;
check_points([#{name := Name} = Def | Rest], Seen) when is_atom(Name) ->
    case maps:is_key(Name, Seen) of
        true -> {error, {bad_point, Name, name}};
        false ->
            case check_def(Def) of
                ok -> check_points(Rest, Seen#{Name => true});
                {error, Key} -> {error, {bad_point, Name, Key}}
            end
    end;
check_points([#{name := Name} | _], _) ->
    {error, {bad_point, Name, name}};
check_points([Other | _], _) ->
    {error, {bad_point, Other, name}}.

check_def(Def) ->
    Checks = [{dir, fun(D) -> D =:= in orelse D =:= out end},
              {type, fun cell_hal_type:is_type/1},
              {address, fun is_binary/1},
              {caption, fun is_binary/1},
              {field, fun(_) -> true end}],
    case [K || {K, Ok} <- Checks, not (maps:is_key(K, Def) andalso Ok(maps:get(K, Def)))] of
        [] ->
            case maps:keys(maps:without([name, unit | [K || {K, _} <- Checks]], Def)) of
                [] when is_map_key(unit, Def), not is_binary(map_get(unit, Def)) -> {error, unit};
                [] -> ok;
                [Unknown | _] -> {error, Unknown}
            end;
        [Key | _] ->
            {error, Key}
    end.

%% @doc The ADS symbol of a point's field (for the ADS driver): a structure member
%% resolved against the instance's `input_struct' or `output_struct', or an image
%% name with its wildcard.
-spec ads_symbol(in | out, term(), map()) -> {ok, ads_symbol()} | {error, atom()}.
ads_symbol(_, <<"*", Name/binary>>, _) when byte_size(Name) > 0 ->
    {ok, {image, Name}};
ads_symbol(Dir, <<".", Member/binary>> = Field, GroupOpts) when byte_size(Member) > 0 ->
    Key = case Dir of in -> input_struct; out -> output_struct end,
    case maps:find(Key, GroupOpts) of
        {ok, Struct} when is_binary(Struct), byte_size(Struct) > 0 ->
            {ok, {symbol, <<Struct/binary, Field/binary>>}};
        {ok, _} ->
            {error, Key};
        error ->
            {error, Key}
    end;
ads_symbol(_, _, _) ->
    {error, bad_field}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

def(Name) ->
    #{name => Name, dir => in, type => bool, address => <<"A1.01.06">>,
      caption => <<"Start button">>, field => {coil, 1}}.

check_points_test_() ->
    [?_assertEqual(ok, check_points([def(a), def(b)])),
     ?_assertEqual(ok, check_points([])),
     ?_assertEqual({error, {bad_point, a, name}}, check_points([def(a), def(a)])),
     ?_assertEqual({error, {bad_point, a, dir}}, check_points([(def(a))#{dir := inout}])),
     ?_assertEqual({error, {bad_point, a, type}}, check_points([(def(a))#{type := float}])),
     ?_assertEqual({error, {bad_point, a, address}},
                   check_points([(def(a))#{address := "A1"}])),
     ?_assertEqual({error, {bad_point, a, caption}}, check_points([maps:remove(caption, def(a))])),
     ?_assertEqual({error, {bad_point, a, field}}, check_points([maps:remove(field, def(a))])),
     ?_assertEqual({error, {bad_point, a, colour}}, check_points([(def(a))#{colour => red}])),
     ?_assertEqual({error, {bad_point, "a", name}}, check_points([(def(a))#{name := "a"}])),
     ?_assertEqual({error, {bad_point, x, name}}, check_points([x])),
     ?_assertEqual({error, {bad_group, points}}, check_points(#{}))].

ads_symbol_test_() ->
    Opts = #{input_struct => <<".GeneralInputs">>, output_struct => <<"MAIN.GeneralOutputs">>},
    [?_assertEqual({ok, {symbol, <<".GeneralInputs.StartButton">>}},
                   ads_symbol(in, <<".StartButton">>, Opts)),
     ?_assertEqual({ok, {symbol, <<"MAIN.GeneralOutputs.StartButtonLight">>}},
                   ads_symbol(out, <<".StartButtonLight">>, Opts)),
     ?_assertEqual({ok, {image, <<"ManipulatorInputs.FailPaletteIsIn">>}},
                   ads_symbol(in, <<"*ManipulatorInputs.FailPaletteIsIn">>, #{})),
     ?_assertEqual({error, output_struct}, ads_symbol(out, <<".X">>, #{})),
     ?_assertEqual({error, input_struct}, ads_symbol(in, <<".X">>, #{input_struct => ""})),
     ?_assertEqual({error, bad_field}, ads_symbol(in, <<"StartButton">>, Opts)),
     ?_assertEqual({error, bad_field}, ads_symbol(in, <<"*">>, Opts)),
     ?_assertEqual({error, bad_field}, ads_symbol(in, {coil, 1}, Opts))].
-endif.
