%% @doc `GET /api/layout' — the picture of the machine as {@link cell_web_layout}
%% derives it from the running cell spec, with what is live now: each link's phase
%% and the product it carries, the beacon's lamps, this shift's counters. The page
%% reads it once and then follows the websocket (`task', `link', `counters', `io').
-module(cell_web_layout_h).
-behaviour(cowboy_handler).

-export([init/2, links/1, counters/0]).

-define(LINK_TIMEOUT, 1000).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, view),
    Layout = cell_web_layout:layout(cell_spec:running()),
    Beacon = [L#{value => value(G, P), forced => cell_hal_force:forced(G, P)}
              || #{group := G, point := P} = L <- maps:get(beacon, Layout)],
    {json, 200, cell_web_json:term(Layout#{links := links(maps:get(links, Layout)),
                                           beacon := Beacon,
                                           counters => counters()})}.

%% @doc The links with their phase now (`unknown' for one not running on this node).
-spec links([map()]) -> [map()].
links(Links) ->
    [L#{phase => Phase, serial => Serial} || #{id := Id} = L <- Links,
                                             {Phase, Serial} <- [phase(Id)]].

phase(Id) ->
    case cell_handshake_link:whereis(Id) of
        undefined ->
            {unknown, undefined};
        Pid ->
            try gen_server:call(Pid, status, ?LINK_TIMEOUT) of
                #{phase := P, product := #{serial := S}} -> {P, S};
                #{phase := P} -> {P, undefined}
            catch
                exit:_ -> {unknown, undefined}
            end
    end.

value(G, P) ->
    case cell_hal:read(G, P) of
        {ok, V} -> V;
        {error, _} -> undefined
    end.

%% @doc This shift's counters of the cell: items in and out, good, scrapped, the
%% mean cycle time (ms); zeros while the statistics cannot be read.
-spec counters() -> map().
counters() ->
    Cell = try cell_stats:summary(cell_stats:shift_now()) of
               #{cell := C, period := Label} -> C#{period => Label}
           catch
               exit:_ -> #{};
               error:badarg -> #{}
           end,
    #{period => maps:get(period, Cell, undefined),
      in => maps:get(in, Cell, 0), out => maps:get(out, Cell, 0),
      good => maps:get(good, Cell, 0), scrapped => maps:get(scrapped, Cell, 0),
      cycle_ms => maps:get(mean, maps:get(cycle_ms, Cell, #{}), undefined)}.
