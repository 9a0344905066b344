%% @doc The reasons an ADS connection ({@link cell_hal_ads_client}) gives, in words for
%% the people running the machine. Pure.
-module(cell_hal_ads_errors).

-export([format_error/1]).

%% @doc Any reason an ADS connection gives, in words for the people running the machine.
-spec format_error(term()) -> binary().
format_error(Reason) ->
    iolist_to_binary(text(Reason)).

text(timeout) -> "the PLC did not answer in time";
text(starting) -> "the connection is being set up";
text(disconnected) -> "not connected to the PLC";
text(no_answer) -> "the PLC stopped answering";
text(closed) -> "the PLC closed the connection";
text({connect, R}) -> ["cannot connect: ", inet_text(R)];
text({socket, timeout}) -> "the PLC stopped taking what is sent to it";
text({socket, R}) -> ["network error: ", inet_text(R)];
text({ads_error, Code, _}) ->
    io_lib:format("~ts (ADS error 0x~.16B)", [cell_hal_ads_codec:error_text(Code), Code]);
text({unknown_symbol, Name}) -> ["the PLC has no symbol ", Name];
text({ambiguous_symbol, Pattern, Names}) ->
    ["the name ", Pattern, " matches several symbols: ", lists:join(", ", Names)];
text({type_mismatch, Name, #{expected := E, plc_type := T, size := S}}) ->
    io_lib:format("symbol ~ts is ~ts (~b bytes) in the PLC, but the configuration "
                  "expects ~ts", [Name, T, S, E]);
text({bad_name, Name}) -> io_lib:format("~tp is not a valid symbol name", [Name]);
text({bad_variable, V}) -> io_lib:format("~tp is not a variable ({Name, Type})", [V]);
text({bad_value, Type, V}) -> io_lib:format("~tp is not a valid ~tp value", [V, Type]);
text({bad_size, Type, N}) -> io_lib:format("the PLC sent ~b bytes for a ~tp value", [N, Type]);
text({not_resolved, Name}) -> ["variable ", Name, " is not resolved on this connection"];
text({symbol_table, R}) -> ["the symbol table could not be read: ", text(R)];
text({symbol_error, Name, R}) -> ["symbol ", Name, ": ", text(R)];
text({bad_response, What}) -> ["the PLC sent a malformed answer (", words(What), ")"];
text({bad_frame, What}) -> ["the PLC sent a malformed frame (", words(What), ")"];
text({bad_notification, What}) -> ["the PLC sent a malformed notification (", words(What), ")"];
text({bad_symbol, What}) -> ["the PLC sent a malformed symbol entry (", words(What), ")"];
text({frame_too_long, N}) ->
    io_lib:format("the PLC announced a frame of ~b bytes, more than allowed", [N]);
text({unexpected_answer, Cmd, Expected}) ->
    io_lib:format("the PLC answered a ~p request with a ~p answer", [Expected, Cmd]);
text(symbols_changed) -> "the PLC program changed during the request; try again";
text({bad_sub_opts, O}) -> io_lib:format("~tp are not valid notification options", [O]);
text({bad_argument, A}) -> io_lib:format("bad argument ~tp", [A]);
text({restore, R}) -> ["the connection could not be set up: ", text(R)];
text(Other) -> io_lib:format("~tp", [Other]).

%% What the codec found wrong: `shorter_than_ams_header' reads "shorter than ams
%% header".
words(What) when is_atom(What) -> string:replace(atom_to_list(What), "_", " ", all);
words(What) -> io_lib:format("~tp", [What]).

inet_text(R) ->
    case inet:format_error(R) of
        "unknown POSIX error" ++ _ -> io_lib:format("~tp", [R]);
        Text -> Text
    end.

