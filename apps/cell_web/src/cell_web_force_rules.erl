%% @doc When an IO point may be forced from the panel, and when forces end: the
%% decisions of {@link cell_web_forces}, pure.
%%
%% A force needs the cell in service mode, a user of the role `service' or higher,
%% and no emergency stop (which ends every force). Every force ends when service mode
%% ends and on an emergency stop; a user's forces end when that user logs out; the HAL
%% ends every force when its server restarts (`io_restarted').
-module(cell_web_force_rules).

-export([may_force/2, ending/2]).

-export_type([cause/0]).


-type cause() :: {service_mode, boolean()} | {estop, boolean()} | {logout, binary()}
               | restarted | io_restarted.

%% @doc Whether a caller of this role may force now, given the cell's flags
%% (`service_mode', `estop'): `ok', or the HTTP status, code and words of the refusal.
-spec may_force(cell_web_users:role() | anonymous, map()) ->
          ok | {error, cowboy:http_status(), atom(), binary()}.
may_force(anonymous, _Flags) ->
    {error, 401, login_required, <<"log in as a service user to force IO">>};
may_force(Role, Flags) ->
    case cell_web_users:rank(Role) >= cell_web_users:rank(service) of
        false ->
            {error, 403, forbidden,
             <<"forcing IO needs the role service or higher; you are ",
               (atom_to_binary(Role, utf8))/binary>>};
        true ->
            case Flags of
                #{estop := true} ->
                    {error, 409, estop_active,
                     <<"the emergency stop is active: no IO is forced while it is">>};
                #{service_mode := true} ->
                    ok;
                _ ->
                    {error, 409, not_service_mode,
                     <<"IO is forced only in service mode: turn the service key first">>}
            end
    end.

%% @doc Which of the forces (each with its `who') end on this cause, and why, in
%% words for the audit trail; `[]' when none does.
-spec ending(cause(), [#{who := binary(), atom() => term()}]) -> {[map()], binary()}.
ending({service_mode, false}, Forces) -> {Forces, <<"service mode ended">>};
ending({estop, true}, Forces) -> {Forces, <<"emergency stop">>};
ending({logout, User}, Forces) ->
    {[F || #{who := W} = F <- Forces, W =:= User], <<User/binary, " logged out">>};
ending(restarted, Forces) -> {Forces, <<"the panel's force keeper started again">>};
ending(io_restarted, Forces) -> {Forces, <<"forces ended: the IO service restarted">>};
ending(_, _Forces) -> {[], <<>>}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

may_force_test_() ->
    Service = #{service_mode => true, estop => false},
    [?_assertEqual(ok, may_force(service, Service)),
     ?_assertEqual(ok, may_force(admin, Service)),
     ?_assertMatch({error, 403, forbidden, _}, may_force(operator, Service)),
     ?_assertMatch({error, 401, login_required, _}, may_force(anonymous, Service)),
     ?_assertMatch({error, 409, not_service_mode, _},
                   may_force(service, Service#{service_mode := false})),
     ?_assertMatch({error, 409, not_service_mode, _}, may_force(service, #{})),
     ?_assertMatch({error, 409, estop_active, _}, may_force(service, Service#{estop := true})),
     %% The role is checked before the cell's flags: an operator learns only that.
     ?_assertMatch({error, 403, forbidden, _}, may_force(operator, #{estop => true}))].

ending_test_() ->
    Fs = [#{who => <<"anna">>, point => a}, #{who => <<"ben">>, point => b}],
    [?_assertEqual({Fs, <<"service mode ended">>}, ending({service_mode, false}, Fs)),
     ?_assertEqual({[], <<>>}, ending({service_mode, true}, Fs)),
     ?_assertEqual({Fs, <<"emergency stop">>}, ending({estop, true}, Fs)),
     ?_assertEqual({[], <<>>}, ending({estop, false}, Fs)),
     ?_assertEqual({[hd(Fs)], <<"anna logged out">>}, ending({logout, <<"anna">>}, Fs)),
     ?_assertEqual({[], <<"carl logged out">>}, ending({logout, <<"carl">>}, Fs)),
     ?_assertMatch({Fs, _}, ending(restarted, Fs)),
     ?_assertEqual({Fs, <<"forces ended: the IO service restarted">>}, ending(io_restarted, Fs))].
-endif.
