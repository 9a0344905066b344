%% @doc The panel's own settings object `web' (`Settings/web.json'), and how this app
%% reads its settings objects.
%%
%% The objects of this app (`web', `web_users', `oee') are registered with `cell_settings'
%% when the app starts. `cell_settings' runs inside the cell's supervisor and forgets
%% them if it restarts; {@link current/1} registers them again on the first read that
%% finds them gone, so a restarted cell never leaves the panel without its users.
-module(cell_web_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).
-export([register/0, current/1, get/1, schemas/0]).

-compile({no_auto_import, [get/1]}).

-spec name() -> web.
name() -> web.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => anonymous_view, type => boolean, default => true,
       doc => <<"Anyone who reaches the panel sees the line, the errors and the log "
                "without logging in. Commands always need a login.">>},
     #{name => idle_minutes, type => {integer, 1, 1440}, default => 30, unit => <<"min">>,
       doc => <<"A login ends after this long without a request.">>},
     #{name => session_hours, type => {integer, 1, 168}, default => 12, unit => <<"h">>,
       doc => <<"A login ends this long after it began, however busy.">>}].

%% @doc The schema modules of this app.
-spec schemas() -> [module()].
schemas() -> [?MODULE, cell_web_users, cell_web_oee_settings].

%% @doc Registers this app's settings objects.
-spec register() -> ok | {error, term()}.
register() ->
    lists:foldl(fun(Mod, ok) -> cell_settings:register(Mod);
                   (_, Error) -> Error
                end, ok, schemas()).

%% @doc The current object of one of this app's schema modules.
-spec current(module()) -> map().
current(Mod) ->
    Name = Mod:name(),
    try cell_settings:get(Name)
    catch
        error:{unknown_settings, Name} ->
            ok = register(),
            cell_settings:get(Name)
    end.

%% @doc One field of the `web' object.
-spec get(anonymous_view | idle_minutes | session_hours) -> term().
get(Field) ->
    maps:get(Field, current(?MODULE)).
