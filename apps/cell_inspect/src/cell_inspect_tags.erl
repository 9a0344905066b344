%% @doc The tags of seed 004's PLC I/O block, by name, with the direction each is
%% written in, its kind, the seed's name and the Allen-Bradley tag name.
%%
%% `out' tags are written by this application and read only by the PLC (the seed's
%% "Outputs"; the S7 UDT lists them under INPUTS, from the PLC's side); `in' tags are
%% written by the PLC. Every `in' tag has an echo among the `out' tags, written with
%% the value read as soon as it is read.
%%
%% Strings come in length classes, so that a tag and its echo always have the same
%% length: `point_id' (InspectionPointID and its echo, 16 characters), `serial'
%% (PartSerial and its echo), `employee' (OverrideEmployeeID and EmployeeOverride_ECHO),
%% `string' (Inspection_STRING) and `result' (MessageResult). The lengths themselves
%% belong to the PLC's declaration (see {@link cell_inspect_udt} and
%% {@link cell_inspect_io}).
-module(cell_inspect_tags).

-export([all/0, inputs/0, outputs/0, commands/0, data_inputs/0, echo/1, kind/1, dir/1,
         seed_name/1, ab_name/1]).

-export_type([tag/0, in_tag/0, out_tag/0, command/0, kind/0, length_class/0, value/0]).

-type command() :: trigger_inspection | clear_results | cancel_inspection | log_override
                 | send_message.
-type in_tag() :: command() | inspection_point_id | part_serial | override_employee_id
                | message_id.
-type out_tag() :: heartbeat | trigger_inspection_echo | clear_results_echo
                 | cancel_inspection_echo | log_override_echo | inspection_pass
                 | inspection_fail | send_message_echo | inspection_status | error_code
                 | inspection_point_id_echo | part_serial_echo | employee_override_echo
                 | inspection_string | message_id_echo | message_status | message_result.
-type tag() :: in_tag() | out_tag().
-type length_class() :: point_id | serial | employee | string | result.
-type kind() :: bool | int | {string, length_class()}.
%% Strings are UTF-8 binaries here; the PLC holds them in single bytes (Latin-1).
-type value() :: boolean() | integer() | binary().

%% {Tag, Dir, Kind, Seed name, Allen-Bradley name}, in the order of the S7 UDT.
-define(TAGS,
        [{heartbeat, out, bool, "Heartbeat", "HEARTBEAT"},
         {trigger_inspection_echo, out, bool, "TriggerInspection_ECHO", "TRIGGERINSPECTION_ECHO"},
         {clear_results_echo, out, bool, "ClearResults_ECHO", "CLEARRESULTS_ECHO"},
         {cancel_inspection_echo, out, bool, "CancelInspection_ECHO", "CANCELINSPECTION_ECHO"},
         {log_override_echo, out, bool, "LogOverride_ECHO", "LOGOVERRIDE_ECHO"},
         {inspection_pass, out, bool, "Inspection_PASS", "INSPECTION_PASS"},
         {inspection_fail, out, bool, "Inspection_FAIL", "INSPECTION_FAIL"},
         {send_message_echo, out, bool, "SendMessage_ECHO", "SENDMESSAGE_ECHO"},
         {inspection_status, out, int, "InspectionStatus", "INSPECTIONSTATUS"},
         {error_code, out, int, "ErrorCode", "ERRORCODE"},
         {inspection_point_id_echo, out, {string, point_id}, "InspectionPointID_ECHO",
          "INSPECTIONPOINTID_ECHO"},
         {part_serial_echo, out, {string, serial}, "PartSerial_ECHO", "PARTSERIAL_ECHO"},
         {employee_override_echo, out, {string, employee}, "EmployeeOverride_ECHO",
          "EMPLOYEEOVERRIDE_ECHO"},
         {inspection_string, out, {string, string}, "Inspection_STRING", "INSPECTION_STRING"},
         {trigger_inspection, in, bool, "TriggerInspection", "TRIGGERINSPECTION"},
         {clear_results, in, bool, "ClearResults", "CLEARRESULTS"},
         {cancel_inspection, in, bool, "CancelInspection", "CANCELINSPECTION"},
         {log_override, in, bool, "LogOverride", "LOGOVERRIDE"},
         {send_message, in, bool, "SendMessage", "SENDMESSAGE"},
         {inspection_point_id, in, {string, point_id}, "InspectionPointID", "INSPECTIONPOINTID"},
         {part_serial, in, {string, serial}, "PartSerial", "PARTSERIAL"},
         {override_employee_id, in, {string, employee}, "OverrideEmployeeID",
          "OVERRIDEEMPLOYEEID"},
         {message_id, in, int, "MessageId", "MESSAGEID"},
         {message_id_echo, out, int, "MessageId_ECHO", "MESSAGEID_ECHO"},
         {message_status, out, int, "MessageStatus", "MESSAGESTATUS"},
         {message_result, out, {string, result}, "MessageResult", "MESSAGERESULT"}]).

-define(ECHOES, [{trigger_inspection, trigger_inspection_echo},
                 {clear_results, clear_results_echo},
                 {cancel_inspection, cancel_inspection_echo},
                 {log_override, log_override_echo},
                 {send_message, send_message_echo},
                 {inspection_point_id, inspection_point_id_echo},
                 {part_serial, part_serial_echo},
                 {override_employee_id, employee_override_echo},
                 {message_id, message_id_echo}]).

%% @doc Every tag, in the order of the S7 UDT's byte offsets.
-spec all() -> [tag()].
all() -> [T || {T, _, _, _, _} <- ?TAGS].

%% @doc The tags the PLC writes.
-spec inputs() -> [in_tag()].
inputs() -> [T || {T, in, _, _, _} <- ?TAGS].

%% @doc The tags this application writes.
-spec outputs() -> [out_tag()].
outputs() -> [T || {T, out, _, _, _} <- ?TAGS].

%% @doc The PLC's command bits, each acted on at its rising edge.
-spec commands() -> [command()].
commands() -> [T || {T, in, bool, _, _} <- ?TAGS].

%% @doc The values the PLC writes for its commands to use.
-spec data_inputs() -> [in_tag()].
data_inputs() -> [T || {T, in, K, _, _} <- ?TAGS, K =/= bool].

%% @doc The echo of a tag the PLC writes.
-spec echo(in_tag()) -> out_tag().
echo(Tag) ->
    {Tag, Echo} = lists:keyfind(Tag, 1, ?ECHOES),
    Echo.

-spec kind(tag()) -> kind().
kind(Tag) -> element(3, row(Tag)).

-spec dir(tag()) -> in | out.
dir(Tag) -> element(2, row(Tag)).

%% @doc The name the seed gives the tag (the S7 UDT's member name).
-spec seed_name(tag()) -> binary().
seed_name(Tag) -> list_to_binary(element(4, row(Tag))).

%% @doc The member name of the Allen-Bradley tag structure (`MVSCAMERA.<name>').
-spec ab_name(tag()) -> binary().
ab_name(Tag) -> list_to_binary(element(5, row(Tag))).

row(Tag) ->
    case lists:keyfind(Tag, 1, ?TAGS) of
        false -> erlang:error({unknown_tag, Tag});
        Row -> Row
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% The seed lists 26 tags: 17 written by the application, 9 by the PLC.
counts_test_() ->
    [?_assertEqual(26, length(all())),
     ?_assertEqual(17, length(outputs())),
     ?_assertEqual(9, length(inputs())),
     ?_assertEqual([trigger_inspection, clear_results, cancel_inspection, log_override,
                    send_message], commands())].

%% Every PLC-written tag has an echo of the same kind.
echoes_test_() ->
    [?_assertEqual({T, kind(T)}, {T, kind(echo(T))}) || T <- inputs()] ++
    [?_assertEqual(out, dir(echo(T))) || T <- inputs()].

%% The Allen-Bradley names of the seed, all 26 of them.
ab_names_test() ->
    Seed = ["CANCELINSPECTION", "CANCELINSPECTION_ECHO", "CLEARRESULTS", "CLEARRESULTS_ECHO",
            "EMPLOYEEOVERRIDE_ECHO", "ERRORCODE", "HEARTBEAT", "INSPECTION_FAIL",
            "INSPECTION_PASS", "INSPECTION_STRING", "INSPECTIONPOINTID",
            "INSPECTIONPOINTID_ECHO", "INSPECTIONSTATUS", "LOGOVERRIDE", "LOGOVERRIDE_ECHO",
            "OVERRIDEEMPLOYEEID", "PARTSERIAL", "PARTSERIAL_ECHO", "TRIGGERINSPECTION",
            "TRIGGERINSPECTION_ECHO", "MESSAGEID", "MESSAGEID_ECHO", "SENDMESSAGE",
            "SENDMESSAGE_ECHO", "MESSAGERESULT", "MESSAGESTATUS"],
    ?assertEqual(lists:sort([list_to_binary(N) || N <- Seed]),
                 lists:sort([ab_name(T) || T <- all()])).

unknown_tag_test() ->
    ?assertError({unknown_tag, nope}, kind(nope)).
-endif.
