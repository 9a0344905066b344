%% @doc Configuration read at the door: the cell root folder of seed 000 §3 and typed
%% values from the application environment or the OS environment, each checked, so a
%% malformed value is refused with an error that names it.
%%
%% The root folder holds `Settings/', `Products/', `Data/', `Logs/' and `Databases/'.
%% It is `$CELLRT_ROOT' when set, else the `root' key of `cell_base' (default `var',
%% relative to the working directory, which is the release folder in a release).
-module(cell_config).

-export([root/0, dir/1, ensure_root/0]).
-export([get/3, port/3, ip/3]).

-export_type([folder/0]).

-type folder() :: settings | products | data | logs | databases.

-define(FOLDERS, [{settings, "Settings"}, {products, "Products"}, {data, "Data"},
                  {logs, "Logs"}, {databases, "Databases"}]).

%% @doc The absolute path of the cell root folder.
-spec root() -> file:filename().
root() ->
    Root = case os:getenv("CELLRT_ROOT") of
               Env when is_list(Env), Env =/= "" -> Env;
               _ -> case application:get_env(cell_base, root, "var") of
                        "" -> "var";
                        R -> R
                    end
           end,
    filename:absname(Root).

%% @doc The absolute path of one folder of the root.
-spec dir(folder()) -> file:filename().
dir(Folder) ->
    {Folder, Name} = lists:keyfind(Folder, 1, ?FOLDERS),
    filename:join(root(), Name).

%% @doc Creates the root folder and its sub-folders where missing.
-spec ensure_root() -> ok | {error, {file:filename(), file:posix()}}.
ensure_root() ->
    ensure_dirs([dir(F) || {F, _} <- ?FOLDERS]).

ensure_dirs([]) ->
    ok;
ensure_dirs([Dir | Rest]) ->
    case filelib:ensure_dir(filename:join(Dir, ".")) of
        ok -> ensure_dirs(Rest);
        {error, Reason} -> {error, {Dir, Reason}}
    end.

%% @doc An application environment value, or `Default' when unset or empty.
-spec get(atom(), atom(), term()) -> term().
get(App, Key, Default) ->
    case application:get_env(App, Key) of
        {ok, ""} -> Default;
        {ok, <<>>} -> Default;
        {ok, Value} -> Value;
        undefined -> Default
    end.

%% @doc A TCP port from the application environment; strings (from the OS
%% environment through sys.config) are parsed. 0 means "any free port".
-spec port(atom(), atom(), inet:port_number()) ->
          {ok, inet:port_number()} | {error, {bad_config, atom(), atom(), term()}}.
port(App, Key, Default) ->
    case get(App, Key, Default) of
        P when is_integer(P), P >= 0, P =< 65535 ->
            {ok, P};
        S when is_list(S) ->
            try list_to_integer(string:trim(S)) of
                P when P >= 0, P =< 65535 -> {ok, P};
                _ -> {error, {bad_config, App, Key, S}}
            catch
                error:badarg -> {error, {bad_config, App, Key, S}}
            end;
        Other ->
            {error, {bad_config, App, Key, Other}}
    end.

%% @doc An IP address to bind to, from the application environment (a tuple or a
%% string such as "127.0.0.1" or "0.0.0.0").
-spec ip(atom(), atom(), inet:ip_address()) ->
          {ok, inet:ip_address()} | {error, {bad_config, atom(), atom(), term()}}.
ip(App, Key, Default) ->
    case get(App, Key, Default) of
        T when is_tuple(T) ->
            case inet:ntoa(T) of
                {error, einval} -> {error, {bad_config, App, Key, T}};
                _ -> {ok, T}
            end;
        S when is_list(S) ->
            case inet:parse_address(string:trim(S)) of
                {ok, Ip} -> {ok, Ip};
                {error, einval} -> {error, {bad_config, App, Key, S}}
            end;
        Other ->
            {error, {bad_config, App, Key, Other}}
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

port_test_() ->
    Set = fun(V) -> application:set_env(cell_base, test_port, V) end,
    [?_test(begin Set("8080"), ?assertEqual({ok, 8080}, port(cell_base, test_port, 1)) end),
     ?_test(begin Set(" 0 "), ?assertEqual({ok, 0}, port(cell_base, test_port, 1)) end),
     ?_test(begin Set("65535"), ?assertEqual({ok, 65535}, port(cell_base, test_port, 1)) end),
     ?_test(begin Set("65536"), ?assertMatch({error, {bad_config, _, _, _}},
                                              port(cell_base, test_port, 1)) end),
     ?_test(begin Set("-1"), ?assertMatch({error, _}, port(cell_base, test_port, 1)) end),
     ?_test(begin Set("http"), ?assertMatch({error, _}, port(cell_base, test_port, 1)) end),
     ?_test(begin Set(""), ?assertEqual({ok, 1}, port(cell_base, test_port, 1)) end),
     ?_test(begin Set(7878), ?assertEqual({ok, 7878}, port(cell_base, test_port, 1)) end)].

ip_test_() ->
    Set = fun(V) -> application:set_env(cell_base, test_ip, V) end,
    [?_test(begin Set("127.0.0.1"), ?assertEqual({ok, {127, 0, 0, 1}},
                                                  ip(cell_base, test_ip, {0, 0, 0, 0})) end),
     ?_test(begin Set("0.0.0.0"), ?assertEqual({ok, {0, 0, 0, 0}},
                                                ip(cell_base, test_ip, {1, 1, 1, 1})) end),
     ?_test(begin Set("300.1.1.1"), ?assertMatch({error, _},
                                                  ip(cell_base, test_ip, {0, 0, 0, 0})) end),
     ?_test(begin Set({1, 2, 3}), ?assertMatch({error, _},
                                               ip(cell_base, test_ip, {0, 0, 0, 0})) end)].
-endif.
