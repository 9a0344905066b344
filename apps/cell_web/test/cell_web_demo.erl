%% A cell of scripted tasks with the operator panel, for the browser tests: started
%% by test/browser/run.sh, driven through its standard input one command a line, each
%% answered `OK ...' (or `ERR ...') on standard output once the cell has taken it.
%%
%% Commands: `error TASK retry,reset' · `warning TASK ID CAPTION...' · `event TASK FUN'
%% · `product TASK SERIAL|none' · `log TASK TEXT...' · `recipe NAME' (a recipe whose
%% drawing has three cuts with their ExecOrder) · `flush' (the statistics written) ·
%% `sync' · `quit'.
-module(cell_web_demo).

-export([main/0]).

-define(TASKS, [{loader, <<"Loading">>, <<"Front">>}, {router, <<"Routing">>, <<"Front">>},
                {unloader, <<"Unloading">>, <<"Front">>}]).

-spec main() -> no_return().
main() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false),
    Specs = [cell_web_demo_task:spec(Id, Z, L, self()) || {Id, Z, L} <- ?TASKS],
    _ = [application:load(A) || A <- [cell_base, cell, cell_web]],
    ok = application:set_env(cell, cell_spec, #{name => <<"demo">>, tasks => Specs}),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = cell_settings:put(machine, #{cell_name => <<"Demo router">>}, <<"demo">>),
    io:format("PORT ~p~n", [cell_web:port()]),
    loop(maps:from_list([{atom_to_binary(Id, utf8), {Id, S}} || #{id := Id} = S <- Specs])).

loop(Tasks) ->
    case io:get_line("") of
        eof ->
            erlang:halt(0);
        Line when is_list(Line) ->
            Words = string:lexemes(string:trim(unicode:characters_to_binary(Line)), " "),
            case Words of
                [<<"quit">>] ->
                    io:format("OK quit~n"),
                    erlang:halt(0);
                _ ->
                    Reply = try run(Words, Tasks) of
                                ok ->
                                    ok = cell_controller:sync(),
                                    ok = cell_alarms:sync(),
                                    ok = cell_controller:sync(),
                                    "OK";
                                {error, Why} ->
                                    io_lib:format("ERR ~0tp", [Why])
                            catch
                                C:R -> io_lib:format("ERR ~0tp:~0tp", [C, R])
                            end,
                    io:format("~s ~ts~n", [Reply, lists:join(" ", Words)]),
                    loop(Tasks)
            end
    end.

run([<<"sync">>], _Tasks) ->
    ok;
run([<<"flush">>], _Tasks) ->
    cell_stats:flush();
run([<<"error">>, Task, Sols], Tasks) ->
    Solutions = [S || B <- binary:split(Sols, <<",">>, [global]),
                      S <- cell_alarms:solutions(), atom_to_binary(S, utf8) =:= B],
    send(Task, {error, Solutions}, Tasks);
run([<<"warning">>, Task, Id | Caption], Tasks) ->
    send(Task, {warning, Id, lists:join(" ", Caption)}, Tasks);
run([<<"event">>, Task, Fun], Tasks) ->
    Funs = [starved, unstarved, blocked, unblocked, work_start, work_complete],
    case [F || F <- Funs, atom_to_binary(F, utf8) =:= Fun] of
        [F] -> send(Task, {event, F}, Tasks);
        [] -> {error, {unknown_event, Fun}}
    end;
run([<<"product">>, Task, <<"none">>], Tasks) ->
    send(Task, {product, undefined}, Tasks);
run([<<"product">>, Task, Serial], Tasks) ->
    send(Task, {product, Serial}, Tasks);
run([<<"recipe">>, Name], _Tasks) ->
    D = cell_recipe_drawing,
    Cut = fun(N, X) -> D:container(#{<<"ItemType">> => <<"Cut">>,
                                     <<"ExecOrder">> => integer_to_binary(N)},
                                   [D:line({X, 10}, {X, 90})])
          end,
    Panel = D:container(#{<<"ItemType">> => <<"PanelDrawing">>},
                        [D:polyline([{0, 0}, {200, 0}, {200, 100}, {0, 100}], true),
                         D:circle({15, 50}, 4, #{<<"ItemType">> => <<"Fiducial">>})]),
    Drawing = D:new([Panel, Cut(2, 120), Cut(1, 50), Cut(3, 180)]),
    cell_recipe:save(Name, #{description => <<"three cuts">>, drawing => Drawing}, <<"demo">>);
run([<<"log">>, Task | Text], Tasks) ->
    send(Task, {log, iolist_to_binary(lists:join(" ", Text))}, Tasks);
run(Other, _Tasks) ->
    {error, {unknown_command, Other}}.

send(Task, Command, Tasks) ->
    case maps:find(Task, Tasks) of
        {ok, {Id, Spec}} -> cell_web_demo_task:command(Spec, Id, Command);
        error -> {error, {unknown_task, Task}}
    end.
