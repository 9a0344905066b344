%% @doc The __NAME__ cell: the cell spec the controller builds the cell from (the
%% `cell' application's `cell_module', set in `config/sys.config.src').
%%
%% ```
%%   previous   ┌────────┐ infeed_press ┌───────┐   next
%%   machine ──▶│ infeed │─────────────▶│ press │──▶ machine
%%              └────────┘              └───────┘
%% '''
%%
%% Two device tasks: the infeed conveyor ({@link __NAME___infeed_task}) gives each part
%% that arrives a serial and hands it to the press ({@link __NAME___press_task}), which
%% presses it and sends it out. The arrow is a handshake link. Their IO is one group,
%% `line_io' ({@link __NAME___io}), on one PLC connection: simulated when the machine
%% setting `simulation_mode' is on (the physics of {@link __NAME___sim} moves it),
%% otherwise the PLC over Modbus TCP at the `plc_*' fields of the cell's settings
%% ({@link __NAME___settings}). The settings are read, and the PLC chosen, with {@link
%% cell_spec_helpers}; a change applies at the next boot of the cell.
-module(__NAME__).

-export([cell_spec/0, cell_spec/2]).

-define(CONN, __NAME___plc).

%% @doc The cell spec, from the settings files as they are at boot.
-spec cell_spec() -> map().
cell_spec() ->
    cell_spec(cell_spec_helpers:machine_settings(),
              cell_spec_helpers:saved_settings(__NAME___settings)).

%% @doc The cell spec for given machine settings and cell settings.
-spec cell_spec(cell_spec_helpers:machine(), map()) -> map().
cell_spec(Machine, Own) ->
    Plc = cell_spec_helpers:connection(
            ?CONN, Machine,
            #{real => {cell_hal_modbus, #{host => binary_to_list(maps:get(plc_host, Own)),
                                          port => maps:get(plc_port, Own),
                                          unit => maps:get(plc_unit, Own)}},
              opts => #{poll_ms => maps:get(hal_poll_ms, Own)}}),
    Common = #{lane => <<"Main">>, io => [line_io], settings => __NAME__},
    #{name => maps:get(cell_name, Machine),
      tasks => [cell_spec_helpers:task(infeed, __NAME___infeed_task,
                                       Common#{zone => <<"Infeed">>,
                                               args => #{next => infeed_press}}),
                cell_spec_helpers:task(press, __NAME___press_task,
                                       Common#{zone => <<"Press">>,
                                               args => #{prev => infeed_press}})],
      links => [#{id => infeed_press, from => infeed, to => press}],
      settings => [__NAME___settings],
      hal => #{connections => [Plc],
               groups => [#{id => line_io, module => __NAME___io, connection => ?CONN,
                            opts => #{base => 0}}]}}.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

spec_test_() ->
    Own = cell_settings_schema:defaults(__NAME___settings),
    Sim = cell_spec(#{simulation_mode => true, cell_name => <<"test">>}, Own),
    Real = cell_spec(#{simulation_mode => false, cell_name => <<"test">>}, Own),
    [?_assertMatch({ok, _}, cell_spec:validate(Sim)),
     ?_assertMatch({ok, _}, cell_spec:validate(Real)),
     ?_assertMatch(#{hal := #{connections := [#{driver := cell_hal_sim}]}}, Sim),
     ?_assertMatch(#{hal := #{connections := [#{driver := cell_hal_modbus,
                                                opts := #{port := 502}}]}}, Real)].
-endif.
