%% A cell of scripted tasks with the operator panel, for the browser tests: started
%% by test/browser/run.sh, driven through its standard input one command a line, each
%% answered `OK ...' (or `ERR ...') on standard output once the cell has taken it.
%%
%% Commands: `error TASK retry,reset' · `warning TASK ID CAPTION...' · `event TASK FUN'
%% · `product TASK SERIAL|none' · `log TASK TEXT...' · `recipe NAME' (a recipe whose
%% drawing has three cuts with their ExecOrder) · `offer TASK LINK' · `service on|off' ·
%% `estop on|off' · `sim GROUP POINT true|false|NUMBER' (a simulated input) · `flush'
%% (the statistics written) · `sync' · `quit'.
%%
%% Its IO is a simulated PLC (`demo_plc') with two groups of this module's points
%% (`general': the beacon the monitor drives, a service key, a pressure; `line': the
%% conveyor's motor, clamps and sensors) and a simulated camera; its tasks are linked
%% loader -> router -> unloader, so that only the unloader's products leave the cell.
%% `main(#{links => false})' starts it without the links: each task then takes its
%% products in from outside the cell and sends them out of it.
-module(cell_web_demo).
-behaviour(cell_hal_group).

-export([main/0, main/1, points/1]).

-define(TASKS, [{loader, <<"Loading">>, <<"Front">>}, {router, <<"Routing">>, <<"Front">>},
                {unloader, <<"Unloading">>, <<"Front">>}]).
-define(LINKS, [#{id => load_route, from => loader, to => router},
                #{id => route_unload, from => router, to => unloader}]).

-spec main() -> no_return().
main() ->
    main(#{}).

-spec main(#{links => boolean()}) -> no_return().
main(Opts) ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, [{lager_console_backend, [{level, critical}]}]),
    ok = application:set_env(lager, error_logger_redirect, false),
    Specs = [cell_web_demo_task:spec(Id, Z, L, self()) || {Id, Z, L} <- ?TASKS],
    _ = [application:load(A) || A <- [cell_base, cell, cell_web]],
    ok = application:set_env(cell, cell_spec, #{name => <<"demo">>, tasks => Specs,
                                                links => links(Opts), hal => hal(),
                                                monitor => monitor()}),
    ok = application:set_env(cell_web, port, 0),
    {ok, _} = application:ensure_all_started(cell_web),
    ok = cell_settings:put(machine, #{cell_name => <<"Demo router">>}, <<"demo">>),
    io:format("PORT ~p~n", [cell_web:port()]),
    loop(maps:from_list([{atom_to_binary(Id, utf8), {Id, S}} || #{id := Id} = S <- Specs])).

links(#{links := false}) -> [];
links(_) -> ?LINKS.

hal() ->
    #{connections => [#{id => demo_plc, driver => cell_hal_sim, opts => #{}}],
      groups => [#{id => general, module => ?MODULE, connection => demo_plc,
                   opts => #{kind => general}},
                 #{id => line, module => ?MODULE, connection => demo_plc,
                   opts => #{kind => line}}],
      hardware => [#{id => camera, kind => camera, type => sim,
                     opts => #{width => 64, height => 48}},
                   #{id => gantry_x, kind => axis, type => sim, opts => #{position => 25.0}}]}.

monitor() ->
    #{io => maps:from_list([{R, {general, R}} || R <- cell_monitor_spec:outputs()])}.

%% The points of the demo's IO groups (cell_hal_group).
-spec points(map()) -> [cell_hal_group:point_def()].
points(#{kind := general}) ->
    [#{name => R, dir => out, type => bool, address => <<"A1.20.0", (integer_to_binary(I))/binary>>,
       caption => <<"Beacon ", (lamp(R))/binary>>, field => R}
     || {I, R} <- lists:zip(lists:seq(1, 4), cell_monitor_spec:outputs())]
        ++ [#{name => service_key, dir => in, type => bool, address => <<"A1.01.04">>,
              caption => <<"Service key">>, field => service_key},
            #{name => air_pressure, dir => in, type => real, address => <<"A1.30.01">>,
              caption => <<"Air pressure">>, unit => <<"bar">>, field => air_pressure}];
points(#{kind := line}) ->
    [#{name => conveyor_motor, dir => out, type => bool, address => <<"A2.20.01">>,
       caption => <<"Conveyor motor">>, field => conveyor_motor},
     #{name => conveyor_speed, dir => out, type => int16, address => <<"A2.40.01">>,
       caption => <<"Conveyor speed">>, unit => <<"mm/s">>, field => conveyor_speed},
     #{name => clamp, dir => out, type => bool, address => <<"A2.20.02">>,
       caption => <<"Clamp">>, field => clamp},
     #{name => board_present, dir => in, type => bool, address => <<"A2.01.01">>,
       caption => <<"Board present">>, field => board_present},
     #{name => clamp_closed, dir => in, type => bool, address => <<"A2.01.02">>,
       caption => <<"Clamp closed">>, field => clamp_closed}].

lamp(beacon_red) -> <<"red">>;
lamp(beacon_yellow) -> <<"yellow">>;
lamp(beacon_green) -> <<"green">>;
lamp(beacon_blue) -> <<"blue">>.

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
run([<<"offer">>, Task, Link], Tasks) ->
    {ok, #{links := Links}} = application:get_env(cell, cell_spec),
    case [L || #{id := L} <- Links, atom_to_binary(L, utf8) =:= Link] of
        [L] -> send(Task, {offer, L}, Tasks);
        [] -> {error, {unknown_link, Link}}
    end;
run([<<"service">>, OnOff], _Tasks) ->
    cell_controller:service_mode(OnOff =:= <<"on">>, <<"key">>);
run([<<"estop">>, OnOff], _Tasks) ->
    cell_controller:estop(OnOff =:= <<"on">>, <<"button">>);
run([<<"sim">>, G, P, V], _Tasks) ->
    case [K || Gr <- cell_hal:groups(), atom_to_binary(Gr, utf8) =:= G,
               {ok, Ps} <- [cell_hal:points(Gr)], #{name := N} <- Ps,
               atom_to_binary(N, utf8) =:= P, K <- [{Gr, N}]] of
        [Key] -> cell_hal_sim:set(Key, sim_value(V));
        [] -> {error, {unknown_point, G, P}}
    end;
%% An axis of the demo: `power' and `home <at>' answer once the axis has done it;
%% `move <to> <velocity>' once it has begun.
run([<<"axis">>, Axis | Command], _Tasks) ->
    case [Id || {Id, axis, _} <- cell_hal_hw:list(), atom_to_binary(Id, utf8) =:= Axis] of
        [Id] -> axis(Id, Command);
        [] -> {error, {unknown_axis, Axis}}
    end;
run(Other, _Tasks) ->
    {error, {unknown_command, Other}}.

axis(Id, [<<"power">>]) ->
    job_end(cell_hal_axis:power(Id, true));
axis(Id, [<<"home">>, At]) ->
    job_end(cell_hal_axis:home(Id, sim_value(At)));
axis(Id, [<<"move">>, To, V]) ->
    case cell_hal_axis:move_absolute(Id, sim_value(To), #{velocity => sim_value(V),
                                                         acceleration => 1000,
                                                         deceleration => 1000}) of
        {ok, _} -> ok;
        {error, _} = Error -> Error
    end;
axis(_Id, Command) ->
    {error, {unknown_axis_command, Command}}.

job_end({ok, Ref}) ->
    receive {Ref, done} -> ok;
            {Ref, Other} -> {error, Other}
    after 10000 -> {error, no_end_of_job}
    end;
job_end({error, _} = Error) ->
    Error.

sim_value(<<"true">>) -> true;
sim_value(<<"false">>) -> false;
sim_value(V) -> try binary_to_integer(V) catch error:badarg -> binary_to_float(V) end.

send(Task, Command, Tasks) ->
    case maps:find(Task, Tasks) of
        {ok, {Id, Spec}} -> cell_web_demo_task:command(Spec, Id, Command);
        error -> {error, {unknown_task, Task}}
    end.
