%% @doc Commands of the release's start script that work on the panel's users while the
%% cell is stopped: `bin/cellrt set_password USER'. A production build refuses to start
%% while a demo account keeps its demo password; this is how they are changed on a
%% machine that has only the release.
%%
%% Only the settings owner runs, on the cell root folder the release's configuration
%% names, for as long as the change takes: the change is a revision of the `web_users'
%% settings object with who and when, like a change made on the panel.
-module(cell_web_cli).

-export([set_password/1, set_password/3]).

%% @doc `-run cell_web_cli set_password USER WHO': the new password is one line on
%% standard input. Prints what happened and halts: 0 when the password was set.
-spec set_password([string()]) -> no_return().
set_password([User, Who]) ->
    ok = io:setopts(standard_io, [binary, {encoding, unicode}]),
    Password = case io:get_line("") of
                   Line when is_binary(Line) -> string:trim(Line, trailing, "\r\n");
                   _ -> <<>>
               end,
    Name = unicode:characters_to_binary(User),
    case set_password(Name, Password, unicode:characters_to_binary(Who)) of
        {ok, updated} ->
            io:format("The password of ~ts is set.~n", [Name]),
            %% The change's revision line is in the log before the VM goes.
            ok = cell_log:flush(),
            erlang:halt(0);
        {error, Why} ->
            io:format("The password of ~ts is not set: ~ts.~n", [Name, describe(Why)]),
            ok = cell_log:flush(),
            erlang:halt(1)
    end.

%% @doc Sets a user's password with the cell stopped.
-spec set_password(binary(), binary(), binary()) -> {ok, updated} | {error, term()}.
set_password(Name, Password, Who) ->
    %% The root folder and the logs as the cell has them; nothing on the console.
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, []),
    ok = application:set_env(lager, error_logger_redirect, false),
    case application:ensure_all_started(cell_base) of
        {ok, _} ->
            case cell_settings:start_link(#{schemas => [cell_web_users]}) of
                {ok, Pid} ->
                    unlink(Pid),
                    try
                        cell_web_users:set_password(Name, Password, Who)
                    after
                        gen_server:stop(Pid)
                    end;
                {error, Why} ->
                    {error, {settings, Why}}
            end;
        {error, Why} ->
            {error, {root_folder, Why}}
    end.

describe(not_found) ->
    "there is no such user";
describe({password, too_short}) ->
    "a password needs at least 8 characters";
describe({password, too_long}) ->
    "a password may be at most 1024 bytes long";
describe({password, not_text}) ->
    "a password must be text (UTF-8)";
describe({root_folder, Why}) ->
    io_lib:format("the cell root folder cannot be used (~tp)", [Why]);
describe(Other) ->
    io_lib:format("~tp", [Other]).
