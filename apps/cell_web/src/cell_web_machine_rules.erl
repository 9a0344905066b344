%% @doc Who may act on the simulated machine from the panel, and how the panel answers
%% an action that was not carried out: the decisions of {@link cell_web_machine_h},
%% pure.
%%
%% The machine actions ({@link cell_machine_actions}) are the operator's hand on a
%% simulated machine (press the emergency stop, turn the service key, open a door ...):
%% they need a user of the role `service' or higher, whatever the cell is doing (an
%% emergency stop is pressed in any mode).
-module(cell_web_machine_rules).

-export([may_act/1, refusal/1, words/2]).

-define(ROLE, service).

%% @doc Whether a caller of this role may see and carry out machine actions: `ok', or
%% the HTTP status, code and words of the refusal.
-spec may_act(cell_web_users:role() | anonymous) ->
          ok | {error, cowboy:http_status(), atom(), binary()}.
may_act(anonymous) ->
    {error, 401, login_required, <<"log in as a service user to act on the machine">>};
may_act(Role) ->
    case cell_web_users:rank(Role) >= cell_web_users:rank(?ROLE) of
        true -> ok;
        false -> {error, 403, forbidden,
                  <<"acting on the machine needs the role service or higher; you are ",
                    (atom_to_binary(Role, utf8))/binary>>}
    end.

%% @doc The answer to an action not carried out: HTTP status, code and words.
-spec refusal(cell_machine_actions:failure()) -> {cowboy:http_status(), atom(), binary()}.
refusal(no_simulation) ->
    {409, no_simulation,
     <<"this machine has no simulation to act on: its PLC is a real one">>};
refusal({unknown_action, A}) ->
    {404, not_found, <<"the machine has no action '", (printable(A))/binary, "'">>};
refusal({unknown_choice, A, C}) ->
    {400, bad_request, <<"the action '", (printable(A))/binary, "' has no choice '",
                         (printable(C))/binary, "'">>};
refusal({unreachable, Node}) ->
    {503, unreachable,
     <<"the virtual PLC (", (atom_to_binary(Node, utf8))/binary, ") does not answer: "
       "is it running? Nothing was done">>};
refusal(not_distributed) ->
    {503, not_distributed,
     <<"this cell's node has no distribution name, so it cannot reach the virtual PLC: "
       "start it as the release does (bin/cellrt)">>};
refusal({bad_cookie, File}) ->
    {503, bad_cookie,
     iolist_to_binary(["the virtual PLC's cookie file ", File, " cannot be read or is not "
                       "one word of letters and digits; scripts/vplc --node makes it"])};
refusal(timeout) ->
    {504, timeout, <<"the machine did not answer in time; the action may still take place">>};
refusal({refused, not_running}) ->
    {409, not_running, <<"the machine's simulation is not running (it may be starting "
                         "again): try again in a moment">>};
refusal({refused, no_such_drive}) ->
    {409, no_such_drive, <<"this machine has no such drive">>};
refusal({refused, Why}) ->
    {409, refused, iolist_to_binary(["the machine refused: ", term(Why)])};
refusal({failed, Why}) ->
    {500, failed, iolist_to_binary(["the machine's simulation failed to act: ", term(Why)])};
refusal({bad_actions, Why}) ->
    {500, bad_actions, iolist_to_binary(["the cell's list of machine actions is not "
                                         "well formed: ", term(Why)])}.

%% @doc What was done, in the operator's words, for the log and the audit trail:
%% `Emergency stop: Press'.
-spec words(cell_machine_actions:action(), cell_machine_actions:choice()) -> binary().
words(#{caption := A}, #{caption := C}) ->
    <<A/binary, ": ", C/binary>>.

%% A request's text, shown back cut short and without control characters.
printable(Bin) ->
    Text = case unicode:characters_to_list(Bin) of
               L when is_list(L) -> L;
               _ -> "?"
           end,
    Clean = [case Ch < 32 of true -> $?; false -> Ch end || Ch <- lists:sublist(Text, 40)],
    unicode:characters_to_binary(Clean).

%% A reason in words when it is a plain name; the trace log holds the others.
term(Why) when is_atom(Why) ->
    string:replace(atom_to_list(Why), "_", " ", all);
term(_Why) ->
    "the trace log says why".

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

may_act_test_() ->
    [?_assertEqual(ok, may_act(service)),
     ?_assertEqual(ok, may_act(admin)),
     ?_assertMatch({error, 403, forbidden, _}, may_act(operator)),
     ?_assertMatch({error, 401, login_required, _}, may_act(anonymous))].

refusal_test_() ->
    [?_assertMatch({409, no_simulation, _}, refusal(no_simulation)),
     ?_assertMatch({404, not_found, <<"the machine has no action 'x?y'">>},
                   refusal({unknown_action, <<"x\ny">>})),
     ?_assertMatch({400, bad_request, _}, refusal({unknown_choice, <<"estop">>, <<"z">>})),
     ?_assertMatch({503, unreachable, _}, refusal({unreachable, 'v@localhost'})),
     ?_assertMatch({504, timeout, _}, refusal(timeout)),
     ?_assertMatch({503, not_distributed, _}, refusal(not_distributed)),
     ?_assertMatch({503, bad_cookie, _}, refusal({bad_cookie, "/r/Distribution/cookie"})),
     ?_assertMatch({409, not_running, _}, refusal({refused, not_running})),
     ?_assertMatch({409, no_such_drive, _}, refusal({refused, no_such_drive})),
     ?_assertEqual({409, refused, <<"the machine refused: door stuck">>},
                   refusal({refused, door_stuck})),
     ?_assertEqual({500, failed, <<"the machine's simulation failed to act: the trace log says why">>},
                   refusal({failed, {badarg, [1]}})),
     ?_assertMatch({500, failed, _}, refusal({failed, badarg})),
     ?_assertMatch({500, bad_actions, _}, refusal({bad_actions, x})),
     %% A long name is cut short.
     ?_assertEqual(byte_size(<<"the machine has no action ''">>) + 40,
                   byte_size(element(3, refusal({unknown_action, binary:copy(<<"a">>, 100)}))))].

words_test() ->
    ?assertEqual(<<"Emergency stop: Press">>,
                 words(#{caption => <<"Emergency stop">>}, #{caption => <<"Press">>})).
-endif.
