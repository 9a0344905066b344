%% @doc `/api/products' — the products in the cell: which task holds which serial,
%% with the product as the task keeps it; `/api/products/:serial' — one of them;
%% `/api/products/:serial/history' — where a product has been: its traceability
%% record from `cell_stats' (status, recipe, entry and exit, every event, change,
%% error and answer, oldest first), and where it is now if it is in the cell.
-module(cell_web_products_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(maps:get(what, Opts), R, C) end), Opts}.

handle(What, Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, view),
    case What of
        list ->
            {json, 200, in_cell()};
        one ->
            Serial = cell_web_req:binding(serial, Req),
            case [P || #{<<"serial">> := S} = P <- in_cell(), S =:= Serial] of
                [] -> cell_web_req:fail(404, not_found,
                                        [Serial, " is not in the cell (its history: ",
                                         "/api/products/", Serial, "/history)"]);
                Where -> {json, 200, #{<<"serial">> => Serial, <<"in_cell">> => Where}}
            end;
        history ->
            Serial = cell_web_req:binding(serial, Req),
            case cell_stats:product(Serial) of
                {ok, Record} ->
                    Where = [P || #{<<"serial">> := S} = P <- in_cell(), S =:= Serial],
                    {json, 200, (cell_web_json:term(Record))#{<<"in_cell">> => Where}};
                {error, not_found} ->
                    cell_web_req:fail(404, not_found, [Serial, " has never been recorded"])
            end
    end.

%% Every task holding a product, with the product as its task keeps it.
in_cell() ->
    [#{<<"serial">> => Serial, <<"task">> => atom_to_binary(Id, utf8), <<"zone">> => Zone,
       <<"lane">> => Lane, <<"state">> => cell_web_json:state(State),
       <<"product">> => product(Row)}
     || #{id := Id, serial := Serial, zone := Zone, lane := Lane, state := State} = Row
            <- cell_controller:tasks(), is_binary(Serial)].

product(#{pid := Pid}) when is_pid(Pid) ->
    try cell_task_proc:info(Pid) of
        #{product := P} -> cell_web_json:product(P)
    catch
        exit:_ -> null
    end;
product(_) ->
    null.
