%% @doc The operator's hand on a simulated machine: the actions a cell's simulation
%% offers (press the emergency stop, turn the service key, open a door, drop the air,
%% fault a drive ...), listed by the cell module's optional `machine_actions/1'
%% callback, and carried out where the simulation runs.
%%
%% A cell module that exports `machine_actions(Machine)' returns a list of actions,
%% each `#{id, caption, group, choices}': `id' an atom unique in the list, `caption'
%% and `group' the operator's words (the panel groups buttons by `group'), `choices'
%% the buttons of the action (at least one), each `#{id, caption, run}', `run' the
%% `{Module, Function, Args}' that carries it out, returning `ok' or `{error, Why}'.
%% An action with several choices is one thing on the machine in several positions
%% (the emergency stop pressed or released, a door open or closed).
%%
%% Where the simulation runs ({@link where/2}):
%% <ul>
%% <li>`local': the cell's HAL has a simulated PLC, so the physics runs in this VM;
%%   an action runs here.</li>
%% <li>`{vplc, Node, CookieFile}': the cell talks to a real PLC protocol and the
%%   environment names a virtual PLC's node (`CELLRT_VPLC_NODE', set by `make run',
%%   with its cookie in the file `CELLRT_VPLC_COOKIE'): an action runs on that node,
%%   which looks it up in its own cell module again ({@link cell_vplc:machine_action/3}).</li>
%% <li>`none': a real PLC, nothing simulated: there are no actions.</li>
%% </ul>
%% Either way the action runs in a process of its own ({@link erpc}) and the caller
%% waits at most its deadline: a simulation that hangs or a virtual PLC that is gone
%% costs the caller a clear error, never its own process.
-module(cell_machine_actions).

-export([list/0, run/3, carry_out/4, actions/2, check/1, find/3, json/1, where/2,
         vplc_env/0]).

-export_type([action/0, choice/0, where/0]).

-type choice() :: #{id := atom(), caption := binary(), run := {module(), atom(), [term()]}}.
-type action() :: #{id := atom(), caption := binary(), group := binary(),
                    choices := [choice(), ...]}.
-type where() :: local | {vplc, node(), file:filename()} | none.
-type failure() :: no_simulation | {unknown_action, binary()}
               | {unknown_choice, binary(), binary()} | {unreachable, node()} | not_distributed
               | {bad_cookie, file:filename()}
               | timeout | {refused, term()} | {failed, term()} | {bad_actions, term()}.
-export_type([failure/0]).

%% The longest a cookie file may be: a word of letters and digits.
-define(COOKIE_MAX, 255).

%%====================================================================
%% The cell's actions and where they run
%%====================================================================

%% @doc The actions of the running cell, and where they would run: none (`[]') for a
%% cell without a simulation to act on (`none'), or whose module lists none (a spec
%% given without a cell module has none either).
-spec list() -> {ok, where(), [action()]} | {error, {bad_actions, term()}}.
list() ->
    Where = where(cell_spec:running(), vplc_env()),
    case {Where, cell_module()} of
        {none, _} -> {ok, none, []};
        {_, undefined} -> {ok, Where, []};
        {_, Cell} ->
            case actions(Cell, cell_spec_helpers:machine_settings()) of
                {ok, Actions} -> {ok, Where, Actions};
                Error -> Error
            end
    end.

%% @doc Carries out the choice `Choice' of the action `Action' (their ids as text)
%% where the simulation runs, waiting at most `Timeout' ms: the action and choice
%% carried out, or why not.
-spec run(binary(), binary(), timeout()) ->
          {ok, action(), choice()} | {error, failure()}.
run(ActionId, ChoiceId, Timeout) when is_binary(ActionId), is_binary(ChoiceId) ->
    case list() of
        {ok, none, _} ->
            {error, no_simulation};
        {ok, Where, Actions} ->
            case find(Actions, ActionId, ChoiceId) of
                {ok, A, C} ->
                    case remote(Where, ActionId, ChoiceId, Timeout) of
                        ok -> {ok, A, C};
                        Error -> Error
                    end;
                Error ->
                    Error
            end;
        Error ->
            Error
    end.

remote(local, ActionId, ChoiceId, Timeout) ->
    call(node(), ?MODULE, carry_out,
         [cell_module(), cell_spec_helpers:machine_settings(), ActionId, ChoiceId], Timeout);
remote({vplc, Node, CookieFile}, ActionId, ChoiceId, Timeout) ->
    case {is_alive(), cookie(CookieFile)} of
        {false, _} ->
            {error, not_distributed};
        {true, {ok, Cookie}} ->
            true = erlang:set_cookie(Node, Cookie),
            call(Node, cell_vplc, machine_action, [cell_module(), ActionId, ChoiceId], Timeout);
        {true, error} ->
            {error, {bad_cookie, CookieFile}}
    end.

call(Node, M, F, A, Timeout) ->
    try erpc:call(Node, M, F, A, Timeout) of
        ok -> ok;
        {error, Why} -> {error, Why};
        Other -> {error, {failed, Other}}
    catch
        error:{erpc, timeout} -> {error, timeout};
        error:{erpc, noconnection} -> {error, {unreachable, Node}};
        error:{erpc, notsup} -> {error, {unreachable, Node}};
        error:{exception, Why, _Stack} -> {error, {failed, Why}};
        exit:{exception, Why} -> {error, {failed, Why}};
        exit:{signal, Why} -> {error, {failed, Why}};
        throw:Value -> {error, {failed, {thrown, Value}}}
    end.

%% @doc What runs where the simulation is: looks the action up in the cell module's
%% list for these machine settings and runs its choice. Returns what the choice's
%% function returns (`ok' or `{error, {refused, Why}}'), or why it was not run.
-spec carry_out(module(), map(), binary(), binary()) -> ok | {error, failure()}.
carry_out(Cell, Machine, ActionId, ChoiceId) ->
    case actions(Cell, Machine) of
        {ok, Actions} ->
            case find(Actions, ActionId, ChoiceId) of
                {ok, _, #{run := {M, F, A}}} ->
                    case apply(M, F, A) of
                        ok -> ok;
                        {error, Why} -> {error, {refused, Why}};
                        Other -> {error, {failed, {unexpected_answer, Other}}}
                    end;
                Error ->
                    Error
            end;
        Error ->
            Error
    end.

%% @doc The actions a cell module lists for these machine settings (none when it
%% exports no `machine_actions/1'), checked.
-spec actions(module(), map()) -> {ok, [action()]} | {error, {bad_actions, term()}}.
actions(Cell, Machine) ->
    _ = code:ensure_loaded(Cell),
    case erlang:function_exported(Cell, machine_actions, 1) of
        true -> check(Cell:machine_actions(Machine));
        false -> {ok, []}
    end.

%% @doc Whether a cell module's list of actions is well formed (see the module doc).
-spec check(term()) -> {ok, [action()]} | {error, {bad_actions, term()}}.
check(Actions) when is_list(Actions) ->
    case [A || A <- Actions, not is_action(A)] of
        [] ->
            Ids = [Id || #{id := Id} <- Actions],
            case Ids -- lists:usort(Ids) of
                [] -> {ok, Actions};
                Twice -> {error, {bad_actions, {ids_twice, lists:usort(Twice)}}}
            end;
        [Bad | _] ->
            {error, {bad_actions, Bad}}
    end;
check(Other) ->
    {error, {bad_actions, Other}}.

is_action(#{id := Id, caption := C, group := G, choices := [_ | _] = Choices} = A)
  when is_atom(Id), is_binary(C), is_binary(G), map_size(A) =:= 4 ->
    Ids = [I || #{id := I} <- Choices],
    lists:all(fun is_choice/1, Choices) andalso length(lists:usort(Ids)) =:= length(Choices);
is_action(_) ->
    false.

is_choice(#{id := Id, caption := C, run := {M, F, A}} = Ch)
  when is_atom(Id), is_binary(C), is_atom(M), is_atom(F), is_list(A), map_size(Ch) =:= 3 ->
    true;
is_choice(_) ->
    false.

%% @doc The action and choice of these ids (as text, never made atoms).
-spec find([action()], binary(), binary()) ->
          {ok, action(), choice()}
              | {error, {unknown_action, binary()} | {unknown_choice, binary(), binary()}}.
find(Actions, ActionId, ChoiceId) ->
    case [A || #{id := Id} = A <- Actions, atom_to_binary(Id, utf8) =:= ActionId] of
        [#{choices := Choices} = A] ->
            case [C || #{id := Id} = C <- Choices, atom_to_binary(Id, utf8) =:= ChoiceId] of
                [C] -> {ok, A, C};
                [] -> {error, {unknown_choice, ActionId, ChoiceId}}
            end;
        [] ->
            {error, {unknown_action, ActionId}}
    end.

%% @doc The actions as the panel shows them: everything but what runs them.
-spec json([action()]) -> [map()].
json(Actions) ->
    [#{id => Id, caption => C, group => G,
       choices => [#{id => I, caption => Cc} || #{id := I, caption := Cc} <- Choices]}
     || #{id := Id, caption := C, group := G, choices := Choices} <- Actions].

%% @doc Where the simulation of a cell with this running spec runs, given the
%% virtual PLC named by the environment (see {@link vplc_env/0}).
-spec where(map(), {ok, node(), file:filename()} | undefined) -> where().
where(Spec, Vplc) ->
    Conns = maps:get(connections, maps:get(hal, Spec, #{}), []),
    case [C || #{driver := cell_hal_sim} = C <- Conns] of
        [_ | _] ->
            local;
        [] ->
            case Vplc of
                {ok, Node, Cookie} -> {vplc, Node, Cookie};
                undefined -> none
            end
    end.

%% @doc The virtual PLC this cell's machine is served by, as `make run' names it:
%% `CELLRT_VPLC_NODE' (`name@host') and `CELLRT_VPLC_COOKIE' (the file holding its
%% cookie); `undefined' when either is unset or malformed.
-spec vplc_env() -> {ok, node(), file:filename()} | undefined.
vplc_env() ->
    case {os:getenv("CELLRT_VPLC_NODE"), os:getenv("CELLRT_VPLC_COOKIE")} of
        {Name, File} when is_list(Name), is_list(File), File =/= "" ->
            case node_name(Name) of
                {ok, Node} -> {ok, Node, File};
                error -> undefined
            end;
        _ ->
            undefined
    end.

%% One node name, from the environment the release was started with (not from a
%% request): checked to be a node's name before it is one atom.
node_name(Name) ->
    case re:run(Name, "^[A-Za-z0-9_-]{1,64}@[A-Za-z0-9_.-]{1,200}$", [{capture, none}]) of
        match -> {ok, list_to_atom(Name)};
        nomatch -> error
    end.

%% The virtual PLC's cookie, as scripts/vplc wrote it: one word of letters and
%% digits (the only atom made of the file, and the same one each time).
cookie(File) ->
    case file:read_file(File) of
        {ok, Bin} ->
            Word = string:trim(Bin),
            case re:run(Word, "^[A-Za-z0-9]{1," ++ integer_to_list(?COOKIE_MAX) ++ "}$",
                        [{capture, none}]) of
                match -> {ok, binary_to_atom(Word, latin1)};
                nomatch -> error
            end;
        {error, _} ->
            error
    end.

cell_module() ->
    case cell_config:get(cell, cell_module, undefined) of
        M when is_atom(M) -> M;
        Name when is_list(Name) -> loaded(Name);
        Name when is_binary(Name) -> loaded(binary_to_list(Name));
        _ -> undefined
    end.

%% The cell module is loaded (the cell runs from it): its atom exists.
loaded(Name) ->
    try list_to_existing_atom(Name)
    catch error:badarg -> undefined
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

sample() ->
    [#{id => estop, caption => <<"Emergency stop">>, group => <<"Safety">>,
       choices => [#{id => press, caption => <<"Press">>, run => {m, press, []}},
                   #{id => release, caption => <<"Release">>, run => {m, release, []}}]},
     #{id => air, caption => <<"Air">>, group => <<"Air">>,
       choices => [#{id => drop, caption => <<"Drop">>, run => {m, air, [false]}}]}].

check_test_() ->
    [A, B] = sample(),
    [?_assertEqual({ok, sample()}, check(sample())),
     ?_assertEqual({ok, []}, check([])),
     ?_assertMatch({error, {bad_actions, nope}}, check(nope)),
     ?_assertMatch({error, {bad_actions, {ids_twice, [estop]}}}, check([A, A])),
     ?_assertMatch({error, {bad_actions, _}}, check([B#{choices := []}])),
     ?_assertMatch({error, {bad_actions, _}}, check([B#{caption := "Air"}])),
     ?_assertMatch({error, {bad_actions, _}}, check([B#{extra => 1}])),
     ?_assertMatch({error, {bad_actions, _}},
                   check([B#{choices := [#{id => drop, caption => <<"D">>, run => {m, f}}]}])),
     ?_assertMatch({error, {bad_actions, _}},
                   check([A#{choices := [hd(maps:get(choices, A)), hd(maps:get(choices, A))]}]))].

find_test_() ->
    Actions = sample(),
    [?_assertMatch({ok, #{id := estop}, #{id := release}}, find(Actions, <<"estop">>, <<"release">>)),
     ?_assertEqual({error, {unknown_action, <<"nope">>}}, find(Actions, <<"nope">>, <<"press">>)),
     ?_assertEqual({error, {unknown_choice, <<"estop">>, <<"drop">>}},
                   find(Actions, <<"estop">>, <<"drop">>)),
     ?_assertEqual({error, {unknown_action, <<>>}}, find([], <<>>, <<>>))].

json_test() ->
    [#{id := estop, choices := [#{id := press, caption := <<"Press">>} = C | _]} = E, _] =
        json(sample()),
    ?assertNot(maps:is_key(run, C)),
    ?assertEqual(<<"Safety">>, maps:get(group, E)).

where_test_() ->
    Sim = #{hal => #{connections => [#{id => p, driver => cell_hal_sim}]}},
    Real = #{hal => #{connections => [#{id => p, driver => cell_hal_modbus}]}},
    Vplc = {ok, 'v@localhost', "/c"},
    [?_assertEqual(local, where(Sim, undefined)),
     ?_assertEqual(local, where(Sim, Vplc)),
     ?_assertEqual({vplc, 'v@localhost', "/c"}, where(Real, Vplc)),
     ?_assertEqual(none, where(Real, undefined)),
     ?_assertEqual(none, where(#{}, undefined))].

node_name_test_() ->
    [?_assertEqual({ok, 'cellrt_vplc@localhost'}, node_name("cellrt_vplc@localhost")),
     ?_assertEqual(error, node_name("no_host")),
     ?_assertEqual(error, node_name("a b@host")),
     ?_assertEqual(error, node_name(""))].

cookie_test() ->
    File = filename:join(os:getenv("TMPDIR", "/tmp"), "cellrt_eunit_cookie." ++ os:getpid()),
    ok = file:write_file(File, <<"ab12CD\n">>),
    ?assertEqual({ok, 'ab12CD'}, cookie(File)),
    ok = file:write_file(File, <<"two words">>),
    ?assertEqual(error, cookie(File)),
    ok = file:write_file(File, <<>>),
    ?assertEqual(error, cookie(File)),
    ok = file:delete(File),
    ?assertEqual(error, cookie(File)).

carry_out_test_() ->
    %% This module as a cell without actions: nothing to carry out.
    [?_assertEqual({error, {unknown_action, <<"estop">>}},
                   carry_out(?MODULE, #{}, <<"estop">>, <<"press">>)),
     ?_assertEqual({ok, []}, actions(?MODULE, #{}))].

-endif.
