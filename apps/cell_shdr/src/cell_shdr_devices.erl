%% @doc The MTConnect `Devices.xml' (schema 2.0) that declares exactly the data items
%% the adapter emits (pure): the same item list as the stream (see {@link
%% cell_shdr_items}), with ids, names, types, sub-types, categories, units and the
%% device uuid from the settings, so an agent can be pointed at the cell without
%% writing XML by hand.
%%
%% The cell is a Device; its Controller holds the cell-wide items and one Path per
%% device task; configured HAL points sit on the Device, or, configured on an axis, on
%% a Linear or Rotary component of the Device's Axes (`<name>.axes', `<name>.axis.<axis>').
%%
%% Ids are unique per cell, so several cells can feed one agent (which refuses a
%% device declaring an id another device has): each is derived from the device name,
%% itself unique in an agent and stable across restarts. The Device's id is the name,
%% a component's `<name>.controller' and `<name>.path.<task>', a data item's
%% `<name>_<key>'. A data item's name is its key, the same in every cell: it is what
%% the stream carries, and an agent finds an item of a device by its name.
-module(cell_shdr_devices).

-export([xml/3, version/0]).

%% @doc The MTConnect schema version of the document.
-spec version() -> binary().
version() -> <<"2.0">>.

%% @doc The document for these items and settings, created at `NowMs' (UTC ms).
-spec xml([cell_shdr_items:item()], map(), integer()) -> binary().
xml(Items, Settings, NowMs) ->
    Now = cell_shdr_codec:timestamp(NowMs),
    Esc = fun cell_shdr_assets:xml_escape/1,
    Name = maps:get(device_name, Settings),
    Paths = lists:usort([{Prefix, Task} || #{component := {path, Task, Prefix}} <- Items]),
    Axes = lists:usort([{Axis, Kind} || #{component := {axis, Kind, Axis}} <- Items]),
    iolist_to_binary(
      [<<"<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n">>,
       <<"<MTConnectDevices xmlns=\"urn:mtconnect.org:MTConnectDevices:">>, version(),
       <<"\" xmlns:xsi=\"http://www.w3.org/2001/XMLSchema-instance\" "
         "xsi:schemaLocation=\"urn:mtconnect.org:MTConnectDevices:">>, version(),
       <<" http://schemas.mtconnect.org/schemas/MTConnectDevices_">>, version(),
       <<".xsd\">\n">>,
       <<"  <Header creationTime=\"">>, Now, <<"\" sender=\"cellrt\" instanceId=\"1\" "
         "version=\"">>, version(), <<"\" deviceModelChangeTime=\"">>, Now,
       <<"\" bufferSize=\"131072\" assetBufferSize=\"1024\" assetCount=\"0\"/>\n">>,
       <<"  <Devices>\n">>,
       <<"    <Device id=\"">>, Esc(Name), <<"\" name=\"">>, Esc(Name), <<"\" uuid=\"">>,
       Esc(maps:get(uuid, Settings)), <<"\">\n">>,
       description(Settings, <<"      ">>),
       data_items(Name, [I || #{component := device} = I <- Items], <<"      ">>),
       <<"      <Components>\n">>,
       axes(Name, Axes, Items),
       <<"        <Controller id=\"">>, Esc(Name), <<".controller\" name=\"controller\">\n">>,
       data_items(Name, [I || #{component := controller} = I <- Items], <<"          ">>),
       case Paths of
           [] -> [];
           _ ->
               [<<"          <Components>\n">>,
                [path(Name, Prefix, Task, Items) || {Prefix, Task} <- Paths],
                <<"          </Components>\n">>]
       end,
       <<"        </Controller>\n">>,
       <<"      </Components>\n">>,
       <<"    </Device>\n">>,
       <<"  </Devices>\n">>,
       <<"</MTConnectDevices>\n">>]).

description(Settings, Indent) ->
    Esc = fun cell_shdr_assets:xml_escape/1,
    Attrs = [[$\s, A, <<"=\"">>, Esc(V), $"]
             || {F, A} <- [{manufacturer, <<"manufacturer">>},
                           {serial_number, <<"serialNumber">>}, {station, <<"station">>}],
                V <- [maps:get(F, Settings)], V =/= <<>>],
    [Indent, <<"<Description">>, Attrs, $>, Esc(maps:get(description, Settings)),
     <<"</Description>\n">>].

axes(_Device, [], _Items) ->
    [];
axes(Device, Axes, Items) ->
    Esc = fun cell_shdr_assets:xml_escape/1,
    [<<"        <Axes id=\"">>, Esc(Device), <<".axes\" name=\"axes\">\n">>,
     <<"          <Components>\n">>,
     [begin
          Tag = case Kind of linear -> <<"Linear">>; rotary -> <<"Rotary">> end,
          Mine = [I || #{component := {axis, K, A}} = I <- Items, K =:= Kind, A =:= Axis],
          [<<"            <">>, Tag, <<" id=\"">>, Esc(Device), <<".axis.">>, Esc(Axis),
           <<"\" name=\"">>, Esc(Axis), <<"\">\n">>,
           data_items(Device, Mine, <<"              ">>),
           <<"            </">>, Tag, <<">\n">>]
      end || {Axis, Kind} <- Axes],
     <<"          </Components>\n">>,
     <<"        </Axes>\n">>].

path(Device, Prefix, Task, Items) ->
    Esc = fun cell_shdr_assets:xml_escape/1,
    Mine = [I || #{component := {path, T, _}} = I <- Items, T =:= Task],
    [<<"            <Path id=\"">>, Esc(Device), <<".path.">>, Esc(Prefix), <<"\" name=\"">>,
     Esc(atom_to_binary(Task, utf8)), <<"\">\n">>,
     data_items(Device, Mine, <<"              ">>),
     <<"            </Path>\n">>].

data_items(_Device, [], _Indent) ->
    [];
data_items(Device, Items, Indent) ->
    [Indent, <<"<DataItems>\n">>,
     [[Indent, <<"  ">>, data_item(Device, I), $\n] || I <- Items],
     Indent, <<"</DataItems>\n">>].

data_item(Device, #{key := Key, type := Type, category := Cat} = I) ->
    Esc = fun cell_shdr_assets:xml_escape/1,
    Opt = fun(F, A) ->
                  case maps:find(F, I) of
                      {ok, V} -> [$\s, A, <<"=\"">>, Esc(V), $"];
                      error -> []
                  end
          end,
    Series = case I of
                 #{time_series := true, rate := Rate} ->
                     [<<" representation=\"TIME_SERIES\" sampleRate=\"">>,
                      cell_shdr_codec:format_rate(Rate), $"];
                 _ -> []
             end,
    [<<"<DataItem category=\"">>, category(Cat), <<"\" id=\"">>, Esc(Device), $_, Esc(Key),
     <<"\" name=\"">>, Esc(Key), <<"\" type=\"">>, Esc(Type), $",
     Opt(sub_type, <<"subType">>), Opt(units, <<"units">>), Series, <<"/>">>].

category(sample) -> <<"SAMPLE">>;
category(event) -> <<"EVENT">>;
category(condition) -> <<"CONDITION">>.
