%% @doc A virtual PLC: a cell's simulated machine served over Modbus TCP, on the
%% addresses the cell's real-mode spec gives its IO, so that the cell with
%% `simulation_mode' off (or an HMI, a SCADA) talks to it as it would to the machine's
%% PLC. It runs on a node of its own (`scripts/vplc'), never beside the cell it serves.
%%
%% At its start it
%% <ol>
%% <li>builds the cell's spec as the cell does at boot, from the settings in its own
%%   cell root, with `simulation_mode' off (written so in its `Settings/machine.json');</li>
%% <li>takes the spec's Modbus TCP connection (the `connection' key when it has more
%%   than one) and every IO group bound to it, and resolves each point's unit, table,
%%   address and word order as the Modbus driver does ({@link cell_vplc_image});</li>
%% <li>puts the same connection and groups in its own HAL on a simulated PLC
%%   ({@link cell_hal_sim}), so that the cell's simulation finds the points it knows;</li>
%% <li>starts the cell's simulation: the children its cell module returns from an
%%   optional `simulation(Machine)' (the router's physics, {@link router_sim}); a cell
%%   without one is served as a plain image that only its clients change;</li>
%% <li>listens for Modbus TCP clients ({@link cell_vplc_protocol}).</li>
%% </ol>
%% A client's writes to coils and holding registers set the simulated PLC's outputs,
%% which move the physics through the rules it put on them; its reads of discrete
%% inputs and input registers return what the physics set. The machine's state lives
%% in the simulation (the router's world file in the root's `Data/'), so a virtual PLC
%% killed and started again finds its panels where they were.
-module(cell_vplc).
-behaviour(gen_server).

-export([start_link/0, port/0, setup/2, main/0, merge_settings/2, machine_action/3]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, terminate/2]).

-define(LISTENER, cell_vplc_listener).

-type served() :: #{conn := atom(), points := [cell_vplc_image:point()],
                    hal := #{connections := [map()], groups := [map()]}}.

%% @doc Starts the virtual PLC of the `cell_vplc' application's `cell'.
-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The TCP port the virtual PLC listens on.
-spec port() -> inet:port_number().
port() ->
    ranch:get_port(?LISTENER).

%% @doc Carries out one of the cell's machine actions on the machine served here (see
%% {@link cell_machine_actions}): what the cell calls on this node, when `scripts/vplc'
%% started it with a node name, for the operator's hand on the panel. `Cell' must be
%% the cell served; the action and choice are looked up in its list again here.
-spec machine_action(module(), binary(), binary()) -> ok | {error, term()}.
machine_action(Cell, ActionId, ChoiceId) when is_binary(ActionId), is_binary(ChoiceId) ->
    case {application:get_env(cell_vplc, cell), whereis(?MODULE)} of
        {{ok, Cell}, Pid} when is_pid(Pid) ->
            cell_machine_actions:carry_out(Cell, cell_spec_helpers:machine_settings(),
                                           ActionId, ChoiceId);
        {{ok, Cell}, undefined} ->
            {error, {refused, not_running}};
        {{ok, Other}, _} ->
            {error, {refused, {serves_another_cell, Other}}};
        {undefined, _} ->
            {error, {refused, not_running}}
    end.

%% @doc What `scripts/vplc' runs: starts the application, or stops the node saying why.
%% A virtual PLC that cannot go on (its port taken, its cell's spec refused: its
%% supervisor gives up) ends its node too, so whoever started it sees the process end.
-spec main() -> ok.
main() ->
    case application:ensure_all_started(cell_vplc) of
        {ok, _} ->
            Sup = whereis(cell_vplc_sup),
            _ = spawn(fun() ->
                              Ref = monitor(process, Sup),
                              receive
                                  {'DOWN', Ref, process, _, Why} ->
                                      stopped(init:get_status(), Why)
                              end
                      end),
            ok;
        {error, Why} ->
            io:format(standard_error, "the virtual PLC could not start: ~tp~n", [Why]),
            erlang:halt(1)
    end.

%% The node stopping (SIGTERM) stops the application too: that is no failure.
stopped({stopping, _}, _Why) ->
    ok;
stopped(_, Why) ->
    io:format(standard_error, "the virtual PLC stopped: ~tp~n", [Why]),
    erlang:halt(1).

%% @doc Sets fields of settings objects saved in the cell root `Root' (`Settings/<name>.json'
%% for each `Name => Fields'), keeping the fields already there: how `make run' points
%% the default cell at its virtual PLC (`simulation_mode' off, the PLC's host and port)
%% or back at the in-VM simulated PLC, before the cell starts there. A file that is
%% not a JSON object is an error and is left as it is.
-spec merge_settings(file:filename(), #{atom() => map()}) -> ok | {error, term()}.
merge_settings(Root, Objects) ->
    Dir = filename:join(Root, "Settings"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    maps:fold(fun(Name, Fields, ok) ->
                      merge_file(filename:join(Dir, atom_to_list(Name) ++ ".json"), Fields);
                 (_, _, Error) ->
                      Error
              end, ok, Objects).

merge_file(Path, Fields) ->
    case saved_object(Path) of
        {ok, Saved} ->
            New = maps:fold(fun(K, V, Acc) -> Acc#{atom_to_binary(K) => V} end, Saved, Fields),
            case cell_file:write(Path, jsx:encode(New)) of
                ok -> ok;
                {error, Why} -> {error, {cannot_write, Path, Why}}
            end;
        Error ->
            Error
    end.

saved_object(Path) ->
    case file:read_file(Path) of
        {ok, Bin} ->
            try jsx:decode(Bin, [return_maps]) of
                Saved when is_map(Saved) -> {ok, Saved};
                _ -> {error, {not_a_json_object, Path}}
            catch
                error:_ -> {error, {not_a_json_object, Path}}
            end;
        {error, enoent} ->
            {ok, #{}};
        {error, Why} ->
            {error, {cannot_read, Path, Why}}
    end.

%% @doc What a cell spec's HAL serves over Modbus: the connection (`Conn', or the
%% only Modbus TCP one when `undefined'), its groups and their points resolved to
%% Modbus fields, and the same connection and groups on a simulated PLC.
-spec setup(map(), atom()) -> {ok, served()} | {error, term()}.
setup(#{hal := #{connections := Conns} = Hal}, Conn) ->
    Modbus = [C || #{driver := cell_hal_modbus} = C <- Conns,
                   Conn =:= undefined orelse maps:get(id, C) =:= Conn],
    case Modbus of
        [#{id := Id} = C] ->
            Opts = maps:get(opts, C, #{}),
            Field = #{unit => maps:get(unit, Opts, 1),
                      word_order => maps:get(word_order, Opts, big)},
            Groups = [G || #{connection := Id1} = G <- maps:get(groups, Hal, []), Id1 =:= Id],
            case points(Groups, Field) of
                {ok, Points} ->
                    {ok, #{conn => Id, points => Points,
                           hal => #{connections => [#{id => Id, driver => cell_hal_sim,
                                                      opts => maps:with([poll_ms], Opts)}],
                                    groups => Groups}}};
                Error ->
                    Error
            end;
        [] when Conn =:= undefined -> {error, no_modbus_connection};
        [] -> {error, {no_modbus_connection, Conn}};
        Several -> {error, {several_modbus_connections, [I || #{id := I} <- Several]}}
    end;
setup(_, _) ->
    {error, no_hal}.

points(Groups, Field) ->
    try
        {ok, [point(G, Field, Def) || #{module := Mod} = G <- Groups,
                                      Def <- Mod:points(maps:get(opts, G, #{}))]}
    catch
        throw:Why -> {error, Why}
    end.

point(#{id := G} = Group, Field, #{name := Name, type := Type} = Def) ->
    case cell_hal_modbus:check_point(Field, G, maps:get(opts, Group, #{}), Def) of
        {ok, #{bit := none} = F} -> {{G, Name}, Type, F};
        {ok, #{table := holding_register} = F} when Type =:= bool -> {{G, Name}, Type, F};
        {ok, _} -> throw({bit_of_register_not_served, {G, Name}});
        {error, Why} -> throw({bad_point, {G, Name}, Why})
    end.

%%====================================================================
%% gen_server
%%====================================================================

-spec init([]) -> {ok, map(), {continue, setup}}.
init([]) ->
    process_flag(trap_exit, true),
    {ok, #{}, {continue, setup}}.

-spec handle_continue(setup, map()) -> {noreply, map()} | {stop, term(), map()}.
handle_continue(setup, S) ->
    Cell = env(cell),
    case start(Cell) of
        {ok, Port, Served} ->
            #{conn := Conn, points := Points} = Served,
            Ip = inet:ntoa(env(ip)),
            cell_log:notice(vplc, "virtual PLC of the cell ~s serves its connection ~s "
                            "over Modbus TCP at ~s port ~b (~b points)",
                            [Cell, Conn, Ip, Port, length(Points)]),
            %% The line scripts and tests wait for, on the node's standard output.
            io:format("virtual PLC of ~s listening on ~s port ~b~n", [Cell, Ip, Port]),
            {noreply, S#{cell => Cell, listening => true}};
        {error, Why} ->
            cell_log:error(vplc, "the virtual PLC of the cell ~s cannot start: ~tp",
                           [Cell, Why]),
            {stop, {shutdown, Why}, S}
    end.

start(Cell) ->
    maybe_ok([fun() -> real_mode() end,
              fun(_) -> spec(Cell) end,
              fun(Spec) -> setup(Spec, env(connection)) end,
              fun(Served) -> hal(Served) end,
              fun(Served) -> simulation(Cell, Served) end,
              fun(Served) -> listen(Served) end]).

maybe_ok([First | Rest]) ->
    lists:foldl(fun(F, {ok, V}) -> F(V);
                   (_, Error) -> Error
                end, First(), Rest).

%% The cell's spec in real mode, from the settings of this root.
real_mode() ->
    Machine = cell_spec_helpers:machine_settings(),
    Path = filename:join(cell_config:dir(settings), "machine.json"),
    Json = cell_settings_schema:to_json(cell_machine_settings,
                                        Machine#{simulation_mode => false}),
    case cell_file:write(Path, Json) of
        ok -> {ok, Machine};
        {error, Why} -> {error, {cannot_write, Path, Why}}
    end.

spec(Cell) ->
    case code:ensure_loaded(Cell) of
        {module, Cell} ->
            try Cell:cell_spec() of
                Spec when is_map(Spec) -> {ok, Spec};
                Other -> {error, {not_a_cell_spec, Other}}
            catch
                Class:Why -> {error, {cell_spec_failed, Class, Why}}
            end;
        {error, _} ->
            {error, {unknown_cell_module, Cell}}
    end.

hal(#{hal := #{connections := Conns, groups := Groups}} = Served) ->
    %% The connections before the groups bound to them.
    AddedConns = [cell_hal:add_connection(C) || C <- Conns],
    Added = AddedConns ++ [cell_hal:add_group(G) || G <- Groups],
    %% Set up again after a restart of this process: the HAL kept them.
    case [E || {error, E} <- Added, element(1, E) =/= already_exists] of
        [] -> {ok, Served};
        [Why | _] -> {error, {hal, Why}}
    end.

simulation(Cell, Served) ->
    Machine = cell_spec_helpers:machine_settings(),
    case erlang:function_exported(Cell, simulation, 1) of
        true ->
            Started = [cell_vplc_sup:start_simulation(C) || C <- Cell:simulation(Machine)],
            case [E || {error, _} = E <- Started] of
                [] -> {ok, Served};
                [{error, Why} | _] -> {error, {simulation, Why}}
            end;
        false ->
            cell_log:warning(vplc, "the cell ~s has no simulation (simulation/1): the "
                             "virtual PLC serves its IO image, which only its clients "
                             "change", [Cell]),
            {ok, Served}
    end.

listen(#{points := Points} = Served) ->
    case cell_vplc_image:new(Points) of
        {ok, Image} ->
            Transport = #{socket_opts => [{ip, env(ip)}, {port, env(port)}],
                          max_connections => 32},
            case ranch:start_listener(?LISTENER, ranch_tcp, Transport, cell_vplc_protocol,
                                      #{image => Image}) of
                {ok, _} -> {ok, ranch:get_port(?LISTENER), Served};
                {error, {already_started, _}} -> {ok, ranch:get_port(?LISTENER), Served};
                {error, Why} -> {error, {cannot_listen, env(port), Why}}
            end;
        Error ->
            Error
    end.

env(Key) ->
    {ok, V} = application:get_env(cell_vplc, Key),
    V.

-spec handle_call(term(), gen_server:from(), map()) -> no_return().
handle_call(Request, _From, _S) ->
    erlang:error({unexpected_call, Request}).

-spec handle_cast(term(), map()) -> no_return().
handle_cast(Msg, _S) ->
    erlang:error({unexpected_cast, Msg}).

-spec terminate(term(), map()) -> ok.
terminate(_Why, S) ->
    case S of
        #{cell := Cell, listening := true} ->
            _ = ranch:stop_listener(?LISTENER),
            cell_log:notice(vplc, "virtual PLC of the cell ~s stopped: its clients are "
                            "disconnected", [Cell]);
        _ ->
            ok
    end.
