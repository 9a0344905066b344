%% @doc The users of the operator panel: the settings object `web_users'
%% (`Settings/web_users.json'), so every change is a revision with who and when, like
%% any setting. Passwords are kept only as PBKDF2 hashes ({@link cell_web_password}).
%%
%% Roles rank operator &lt; service &lt; admin; each may do what the ones below it may.
%% A new cell has the demo accounts operator/operator, service/service and
%% admin/admin; {@link demo_accounts/0} names those that still have their demo
%% password, and a production build refuses to start while there are any.
%%
%% The object is edited through {@link put_user/3} and {@link delete_user/2} (for
%% admins, the panel's Users page over `/api/users'), never through the general
%% settings pages: the hashes are not shown there. Each user changes their own
%% password on the panel.
-module(cell_web_users).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).
-export([all/0, find/1, authenticate/2, put_user/3, set_password/3, delete_user/2,
         demo_accounts/0, check_name/1, role_of/1, rank/1, stamp/1, roles/0]).

-export_type([role/0, user/0]).

-type role() :: operator | service | admin.
-type user() :: #{name := binary(), role := role(), algorithm := pbkdf2_sha256,
                  iterations := pos_integer(), salt := binary(), hash := binary()}.

-define(MAX_USERS, 200).
-define(DEMO, [operator, service, admin]).

%%====================================================================
%% The settings object
%%====================================================================

-spec name() -> web_users.
name() -> web_users.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => users, type => {list, {object, cell_web_user}, ?MAX_USERS},
       default => [demo_user(R) || R <- ?DEMO],
       doc => <<"The panel's users.">>}].

%% @doc Names are unique, and there is an admin to manage the others.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{users := Users}) ->
    Names = [N || #{name := N} <- Users],
    case {Names -- lists:usort(Names), [U || #{role := admin} = U <- Users]} of
        {[Dup | _], _} -> {error, [users], {duplicate_user, Dup}};
        {[], []} -> {error, [users], no_admin};
        {[], _} -> ok
    end.

demo_user(Role) ->
    Name = atom_to_binary(Role, utf8),
    maps:merge(#{name => Name, role => Role}, cell_web_password:demo(Role)).

%%====================================================================
%% Users
%%====================================================================

%% @doc Every user, as saved.
-spec all() -> [user()].
all() ->
    maps:get(users, cell_web_settings:current(?MODULE)).

%% @doc A user by name.
-spec find(binary()) -> {ok, user()} | {error, not_found}.
find(Name) when is_binary(Name) ->
    case [U || #{name := N} = U <- all(), N =:= Name] of
        [U] -> {ok, U};
        [] -> {error, not_found}
    end.

%% @doc Checks a login. The hash is computed even for an unknown name, so the answer
%% takes as long either way and does not tell which names exist.
-spec authenticate(binary(), binary()) -> {ok, user()} | {error, bad_login}.
authenticate(Name, Password) when is_binary(Name), is_binary(Password) ->
    case find(Name) of
        {ok, User} ->
            case cell_web_hasher:verify(Password, hash_of(User)) of
                true -> {ok, User};
                false -> {error, bad_login}
            end;
        {error, not_found} ->
            false = cell_web_hasher:verify(Password, (cell_web_password:demo(admin))#{
                                                          hash := base64:encode(<<0:256>>)}),
            {error, bad_login}
    end.

%% @doc Creates a user or changes one: `#{role => Role, password => Bin}', both needed
%% for a new user. Saved as a new revision of the settings object by `Who'.
-spec put_user(binary(), #{role => role(), password => binary()}, binary()) ->
          {ok, created | updated} | {error, term()}.
put_user(Name, Changes, Who) ->
    case check_name(Name) of
        ok -> put_checked(Name, Changes, Who);
        {error, _} = E -> E
    end.

put_checked(Name, Changes, Who) ->
    Password = maps:get(password, Changes, undefined),
    case Password =:= undefined orelse cell_web_password:check_new(Password) of
        {error, Why} ->
            {error, {password, Why}};
        _ ->
            Users = all(),
            Hashed = case Password of
                         undefined -> #{};
                         _ -> cell_web_hasher:hash(Password)
                     end,
            Fields = maps:merge(maps:with([role], Changes), Hashed),
            case lists:partition(fun(#{name := N}) -> N =:= Name end, Users) of
                {[Old], _} ->
                    save(replace(Name, maps:merge(Old, Fields), Users), Who, updated);
                {[], _} when is_map_key(role, Changes), Password =/= undefined ->
                    save(Users ++ [Fields#{name => Name}], Who, created);
                {[], _} ->
                    {error, new_user_needs_role_and_password}
            end
    end.

%% @doc Sets a user's password (from the shell too: this is how the demo passwords
%% are changed before a production build is started on the same root folder).
-spec set_password(binary(), binary(), binary()) -> {ok, updated} | {error, term()}.
set_password(Name, Password, Who) ->
    case find(Name) of
        {ok, _} -> put_user(Name, #{password => Password}, Who);
        {error, _} = E -> E
    end.

%% @doc Removes a user; the last admin cannot be removed.
-spec delete_user(binary(), binary()) -> ok | {error, term()}.
delete_user(Name, Who) ->
    Users = all(),
    case [U || #{name := N} = U <- Users, N =/= Name] of
        Users -> {error, not_found};
        Rest -> case save(Rest, Who, deleted) of
                    {ok, deleted} -> ok;
                    {error, _} = E -> E
                end
    end.

replace(Name, New, Users) ->
    [case U of #{name := Name} -> New; _ -> U end || U <- Users].

save(Users, Who, What) ->
    case cell_settings:put(name(), #{users => Users}, Who) of
        ok -> {ok, What};
        {error, {invalid, [users], no_admin}} -> {error, last_admin};
        {error, _} = E -> E
    end.

%% @doc The demo accounts whose password is still their name. Checked once at start,
%% before the hashing process runs.
-spec demo_accounts() -> [binary()].
demo_accounts() ->
    [N || #{name := N} = U <- all(),
          lists:member(N, [atom_to_binary(D, utf8) || D <- ?DEMO]),
          cell_web_password:verify(N, hash_of(U))].

hash_of(User) ->
    maps:with([algorithm, iterations, salt, hash], User).

%% @doc A user's role.
-spec role_of(user()) -> role().
role_of(#{role := R}) -> R.

%% @doc The roles, lowest first.
-spec roles() -> [role()].
roles() -> ?DEMO.

%% @doc The rank of a role: a role may do what every role of a lower rank may.
-spec rank(role() | anonymous) -> 0..3.
rank(anonymous) -> 0;
rank(operator) -> 1;
rank(service) -> 2;
rank(admin) -> 3.

%% @doc What a session remembers of its user: a session ends when the user's role or
%% password changes or the user is removed.
-spec stamp(user()) -> binary().
stamp(#{role := Role, hash := Hash, salt := Salt}) ->
    crypto:hash(sha256, [atom_to_binary(Role, utf8), 0, Salt, 0, Hash]).

%% @doc A user name: 1 to 64 of letters, digits and `. _ - @'.
-spec check_name(term()) -> ok | {error, bad_user_name}.
check_name(Name) when is_binary(Name), byte_size(Name) >= 1, byte_size(Name) =< 64 ->
    case [C || <<C>> <= Name, not name_char(C)] of
        [] -> ok;
        _ -> {error, bad_user_name}
    end;
check_name(_) ->
    {error, bad_user_name}.

name_char(C) when C >= $a, C =< $z -> true;
name_char(C) when C >= $A, C =< $Z -> true;
name_char(C) when C >= $0, C =< $9 -> true;
name_char(C) -> lists:member(C, ".-_@").

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

schema_test() ->
    ?assertEqual(ok, cell_settings_schema:check_schema(?MODULE)),
    #{users := Demo} = cell_settings_schema:defaults(?MODULE),
    ?assertEqual([<<"operator">>, <<"service">>, <<"admin">>], [N || #{name := N} <- Demo]).

check_test_() ->
    #{users := Demo} = cell_settings_schema:defaults(?MODULE),
    [Op, Sv, Ad] = Demo,
    V = fun(Users) -> cell_settings_schema:validate(?MODULE, #{users => Users}) end,
    [?_assertMatch({ok, _}, V(Demo)),
     ?_assertMatch({error, {invalid, [users], no_admin}}, V([Op, Sv])),
     ?_assertMatch({error, {invalid, [users], {duplicate_user, <<"operator">>}}},
                   V([Op, Op, Ad])),
     ?_assertMatch({error, {invalid, [users, 1, name], bad_user_name}},
                   V([Op#{name => <<"a b">>}, Ad])),
     ?_assertMatch({error, {invalid, [users, 1, role], _}},
                   V([Op#{role => <<"root">>}, Ad]))].

names_test_() ->
    [?_assertEqual(ok, check_name(<<"a">>)),
     ?_assertEqual(ok, check_name(<<"j.doe-2_x@plant">>)),
     ?_assertEqual(ok, check_name(binary:copy(<<"a">>, 64))),
     ?_assertEqual({error, bad_user_name}, check_name(binary:copy(<<"a">>, 65))),
     ?_assertEqual({error, bad_user_name}, check_name(<<>>)),
     ?_assertEqual({error, bad_user_name}, check_name(<<"a/b">>)),
     ?_assertEqual({error, bad_user_name}, check_name(<<"Jürgen"/utf8>>)),
     ?_assertEqual({error, bad_user_name}, check_name(jdoe))].

rank_test() ->
    ?assertEqual([0, 1, 2, 3], [rank(R) || R <- [anonymous | roles()]]).
-endif.
