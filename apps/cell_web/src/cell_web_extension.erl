%% @doc The panel's extension point: an application that serves pages or live messages
%% on the panel declares a module of this behaviour in its own environment,
%%
%% ```
%% {env, [{cell_web_extension, my_app_web}, ...]}
%% '''
%%
%% and the panel takes its routes (before its own catch-all) and, on every websocket,
%% its feed. The panel never names an extension's modules. Its routes are those of
%% every application on the code path, loaded or not (the `.app' files are read when
%% the listener starts), so an extension's application may start after the panel,
%% stop, or not run at all: its handlers say what they answer then. A page joins the
%% feeds of the applications loaded when it connects (a release loads all of its
%% applications at boot).
%%
%% The feed callbacks are optional. `feed_join/1' is called in each page's websocket
%% process as it connects: `{ok, Watch, Messages}' sends the messages with the first
%% frame and monitors `Watch' (the page reconnects when it goes down: close 1012);
%% `not_running' leaves the page without this feed. Any message the websocket process
%% then receives that the panel does not know itself is offered to `feed_info/1' of
%% the joined extensions (`{ok, Messages}' to send, `ignore' when it is not theirs); a
%% message nobody takes crashes the page's process, as any unexpected message.
%% `feed_resync/0' gives the messages of a fresh snapshot when the page asks for one.
%% Messages are JSON maps, each with a `<<"type">>'.
-module(cell_web_extension).

-export([modules/0, declared/0, routes/0]).

-export_type([route/0]).

-type route() :: {string() | binary(), module(), term()}.

-callback routes() -> [route()].
-callback feed_join(Page :: pid()) -> {ok, Watch :: pid() | atom(), [map()]} | not_running.
-callback feed_resync() -> [map()].
-callback feed_info(Message :: term()) -> {ok, [map()]} | ignore.
-optional_callbacks([feed_join/1, feed_resync/0, feed_info/1]).

%% @doc The extension modules the loaded applications declare.
-spec modules() -> [module()].
modules() ->
    lists:usort([Mod || {App, _, _} <- application:loaded_applications(),
                        {ok, Mod} <- [application:get_env(App, cell_web_extension)],
                        is_atom(Mod)]).

%% @doc The extension modules every application on the code path declares, loaded or
%% not: the loaded ones' environment, the others' `.app' files.
-spec declared() -> [module()].
declared() ->
    Loaded = [atom_to_list(App) || {App, _, _} <- application:loaded_applications()],
    %% Erlang/OTP's own applications declare none; an application loaded declared its
    %% own above. Reading every other `.app' file on the path took seconds on a busy
    %% machine, with the listener waiting.
    Otp = filename:join(code:root_dir(), "lib"),
    lists:usort(modules() ++ [Mod || Dir <- code:get_path(), not lists:prefix(Otp, Dir),
                                      File <- filelib:wildcard("*.app", Dir),
                                      not lists:member(filename:basename(File, ".app"), Loaded),
                                      {ok, Mod} <- [app_file(filename:join(Dir, File))]]).

%% @doc The routes of every extension declared.
-spec routes() -> [route()].
routes() ->
    lists:append([Mod:routes() || Mod <- declared()]).

app_file(File) ->
    case file:consult(File) of
        {ok, [{application, _App, Keys}]} when is_list(Keys) ->
            env_extension(proplists:get_value(env, Keys, []));
        _ ->
            none
    end.

env_extension(Env) when is_list(Env) ->
    case lists:keyfind(cell_web_extension, 1, Env) of
        {_, Mod} when is_atom(Mod) -> {ok, Mod};
        _ -> none
    end;
env_extension(_) ->
    none.
