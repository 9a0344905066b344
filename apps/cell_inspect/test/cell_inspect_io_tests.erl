%% The block's HAL points in both forms, as data: the S7 UDT over Modbus registers
%% (fields checked by the HAL's own Modbus planner) and the Allen-Bradley names as ADS
%% symbols (resolved by the HAL's own rule for structure members).
-module(cell_inspect_io_tests).
-include_lib("eunit/include/eunit.hrl").

-define(IO, cell_inspect_io).

s7() -> {ok, O} = ?IO:check_opts(#{layout => s7}), O.
ads() -> {ok, O} = ?IO:check_opts(#{layout => ads}), O.

field(O, Name) ->
    [F] = [F || #{name := N, field := F} <- ?IO:points(O), N =:= Name],
    F.

point(O, Name) ->
    [P] = [P || #{name := N} = P <- ?IO:points(O), N =:= Name],
    P.

%% The seed's byte offsets as holding registers from base 0.
s7_registers_test_() ->
    O = s7(),
    F = fun(N) -> field(O, N) end,
    [?_assertEqual({holding_register, 0, 8}, F(heartbeat)),
     ?_assertEqual({holding_register, 0, 9}, F(trigger_inspection_echo)),
     ?_assertEqual({holding_register, 0, 15}, F(send_message_echo)),
     ?_assertEqual({holding_register, 1}, F(inspection_status)),
     ?_assertEqual({holding_register, 2}, F(error_code)),
     ?_assertEqual({holding_register, 3}, F(inspection_point_id_echo_len)),
     ?_assertEqual({holding_register, 4}, F(inspection_point_id_echo)),
     ?_assertEqual({holding_register, 12}, F(part_serial_echo_len)),
     ?_assertEqual({holding_register, 37}, F(employee_override_echo_len)),
     ?_assertEqual({holding_register, 62}, F(inspection_string_len)),
     ?_assertEqual({holding_register, 87, 8}, F(trigger_inspection)),
     ?_assertEqual({holding_register, 87, 12}, F(send_message)),
     ?_assertEqual({holding_register, 88}, F(inspection_point_id_len)),
     ?_assertEqual({holding_register, 97}, F(part_serial_len)),
     ?_assertEqual({holding_register, 122}, F(override_employee_id_len)),
     ?_assertEqual({holding_register, 147}, F(message_id)),
     ?_assertEqual({holding_register, 148}, F(message_id_echo)),
     ?_assertEqual({holding_register, 149}, F(message_status)),
     ?_assertEqual({holding_register, 150}, F(message_result_len)),
     ?_assertEqual({holding_register, 151}, F(message_result)),
     ?_assertMatch(#{type := {string, 48}, dir := out}, point(O, message_result)),
     ?_assertMatch(#{type := int16, dir := in, address := <<"DBW294">>,
                     caption := <<"MessageId">>}, point(O, message_id))].

%% Every point is a field the HAL's Modbus driver accepts, and the whole block is
%% registers base .. base + 174, read by the planner in two requests (125 at most each).
s7_fields_are_valid_test_() ->
    {ok, O} = ?IO:check_opts(#{layout => s7, base => 1000, unit => 3}),
    Points = ?IO:points(O),
    Resolved = [begin
                    {ok, F} = cell_hal_modbus:check_point(#{unit => 1, word_order => big},
                                                          blk, O, P),
                    {N, T, F}
                end || #{name := N, type := T} = P <- Points],
    Plan = cell_hal_modbus_plan:plan(Resolved, 0),
    Regs = lists:usort(lists:append(
                         [lists:seq(S, S + C - 1)
                          || {_, {read_holding_registers, S, C}} <-
                                 cell_hal_modbus_plan:requests(Plan)])),
    [?_assertEqual(ok, cell_hal_group:check_points(Points)),
     ?_assertEqual(lists:seq(1000, 1174), Regs),
     ?_assertEqual([3], lists:usort([U || {_, _, #{unit := U}} <- Resolved]))].

%% The ADS form: the seed's Allen-Bradley names as members of MVSCAMERA.
ads_symbols_test_() ->
    O = ads(),
    Sym = fun(N) ->
                  #{dir := Dir, field := F} = point(O, N),
                  cell_hal_group:ads_symbol(Dir, F, O)
          end,
    [?_assertEqual({ok, {symbol, <<"MVSCAMERA.TRIGGERINSPECTION">>}}, Sym(trigger_inspection)),
     ?_assertEqual({ok, {symbol, <<"MVSCAMERA.EMPLOYEEOVERRIDE_ECHO">>}},
                   Sym(employee_override_echo)),
     ?_assertEqual({ok, {symbol, <<"MVSCAMERA.MESSAGESTATUS">>}}, Sym(message_status)),
     ?_assertMatch(#{type := {string, 16}}, point(O, inspection_point_id)),
     ?_assertMatch(#{type := {string, 32}}, point(O, part_serial)),
     ?_assertMatch(#{type := int16}, point(O, error_code)),
     ?_assertEqual(26, length(?IO:points(O))),
     ?_assertEqual(ok, cell_hal_group:check_points(?IO:points(O))),
     ?_assertEqual(lists:sort([<<"MVSCAMERA.", (cell_inspect_tags:ab_name(T))/binary>>
                               || T <- cell_inspect_tags:all()]),
                   lists:sort([S || #{dir := D, field := F} <- ?IO:points(O),
                                    {ok, {symbol, S}} <- [cell_hal_group:ads_symbol(D, F, O)]]))].

ads_struct_under_a_program_test() ->
    {ok, O} = ?IO:check_opts(#{layout => ads, struct => <<"MAIN.MVSCAMERA">>,
                               lengths => #{serial => 40}}),
    #{dir := D, field := F, type := T} = point(O, part_serial_echo),
    ?assertEqual({ok, {symbol, <<"MAIN.MVSCAMERA.PARTSERIAL_ECHO">>}},
                 cell_hal_group:ads_symbol(D, F, O)),
    ?assertEqual({string, 40}, T).

options_test_() ->
    [?_assertEqual({error, {bad_option, base}}, ?IO:check_opts(#{layout => s7, base => -1})),
     ?_assertEqual({error, {bad_option, base}}, ?IO:check_opts(#{layout => s7, base => 65400})),
     ?_assertEqual({error, {bad_option, unit}}, ?IO:check_opts(#{layout => s7, unit => 256})),
     ?_assertEqual({error, {bad_option, struct}}, ?IO:check_opts(#{layout => ads, struct => <<>>})),
     ?_assertEqual({error, {bad_option, layout}}, ?IO:check_opts(#{layout => s5})),
     ?_assertEqual({error, {bad_option, colour}}, ?IO:check_opts(#{layout => s7, colour => red})),
     ?_assertEqual({error, {bad_option, base}}, ?IO:check_opts(#{layout => ads, base => 1})),
     ?_assertEqual({error, {bad_option, result}},
                   ?IO:check_opts(#{layout => s7, lengths => #{result => 300}})),
     ?_assertMatch({ok, #{layout := s7, base := 0}}, ?IO:check_opts(#{})),
     ?_assertEqual({error, {bad_option, io}}, ?IO:check_opts(s7))].

%% Strings go out as one byte a character, characters first, then the length word.
writes_test_() ->
    O = s7(),
    A = ads(),
    [?_assertEqual([{part_serial_echo, <<"SN-1">>}, {part_serial_echo_len, 48 * 256 + 4}],
                   ?IO:writes(O, part_serial_echo, <<"SN-1">>)),
     ?_assertEqual([{inspection_string, <<"Gr", 252, "n">>},
                    {inspection_string_len, 48 * 256 + 4}],
                   ?IO:writes(O, inspection_string, <<"Grün"/utf8>>)),
     ?_assertEqual([{inspection_point_id_echo, <<"0123456789ABCDEF">>},
                    {inspection_point_id_echo_len, 16 * 256 + 16}],
                   ?IO:writes(O, inspection_point_id_echo, <<"0123456789ABCDEFGH">>)),
     ?_assertEqual([{message_result, <<"?">>}], ?IO:writes(A, message_result, <<"€"/utf8>>)),
     ?_assertEqual([{inspection_status, 2}], ?IO:writes(O, inspection_status, 2)),
     ?_assertEqual(<<"Gr", 252, "n">>, ?IO:to_plc(<<"Grün"/utf8>>, 10)),
     ?_assertEqual(<<"a?b">>, ?IO:to_plc(<<"a", 0, "b">>, 10)),
     ?_assertEqual(<<"Grün"/utf8>>, ?IO:from_plc(<<"Gr", 252, "n">>)),
     ?_assertEqual(<<"Gr?">>, ?IO:normalize(O, message_result, <<"Gr€"/utf8>>))].

tag_of_test_() ->
    O = s7(),
    [?_assertEqual({ok, part_serial}, ?IO:tag_of(O, part_serial_len)),
     ?_assertEqual({ok, part_serial}, ?IO:tag_of(O, part_serial)),
     ?_assertEqual({ok, trigger_inspection}, ?IO:tag_of(O, trigger_inspection)),
     ?_assertEqual(error, ?IO:tag_of(O, nope)),
     ?_assertEqual(error, ?IO:tag_of(ads(), part_serial_len)),
     ?_assertEqual(lists:sort([trigger_inspection, clear_results, cancel_inspection,
                               log_override, send_message, inspection_point_id,
                               inspection_point_id_len, part_serial, part_serial_len,
                               override_employee_id, override_employee_id_len, message_id]),
                   lists:sort(?IO:input_points(O)))].
