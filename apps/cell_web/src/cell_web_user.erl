%% @doc One user of the operator panel, as an entry of the `web_users' settings object
%% (see {@link cell_web_users}): a name, a role and the PBKDF2 hash of the password
%% (never the password).
-module(cell_web_user).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

%% Never a file of its own: the entries live in `web_users'.
-spec name() -> web_user.
name() -> web_user.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => name, type => {string, 64}, default => <<>>,
       doc => <<"The login name: letters, digits and . _ - @.">>},
     #{name => role, type => {enum, [operator, service, admin]}, default => operator,
       doc => <<"operator: Start, Pause, Stop, answering errors; service: also settings "
                "and recipes; admin: also users and the panel's own settings.">>},
     #{name => algorithm, type => {enum, [pbkdf2_sha256]}, default => pbkdf2_sha256,
       doc => <<"How the password is hashed.">>},
     #{name => iterations, type => {integer, 1000, 10000000},
       default => cell_web_password:default_iterations(),
       doc => <<"PBKDF2 iterations of this hash.">>},
     #{name => salt, type => {string, 64}, default => <<>>, secret => true,
       doc => <<"The salt, base64.">>},
     #{name => hash, type => {string, 64}, default => <<>>, secret => true,
       doc => <<"The derived key, base64; empty: the user cannot log in.">>}].

%% @doc A name is 1 to 64 letters, digits and `. _ - @'.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{name := Name}) ->
    case cell_web_users:check_name(Name) of
        ok -> ok;
        {error, Why} -> {error, [name], Why}
    end.
