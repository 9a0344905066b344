%% @doc `/api/cell' — the cell and its flags; `/api/cell/start|pause|stop' — the
%% operator's commands (seed 000 §2.3.1).
-module(cell_web_cell_h).
-behaviour(cowboy_handler).

-export([init/2, cell/0]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:run(Req, fun handle/2), Opts}.

handle(Req, Caller) ->
    case {cowboy_req:method(Req), cowboy_req:binding(command, Req)} of
        {<<"GET">>, undefined} ->
            _ = cell_web_req:require(Caller, view),
            {json, 200, cell()};
        {<<"POST">>, Command} when Command =/= undefined ->
            command(Command, Req, Caller);
        {_, undefined} ->
            cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>});
        {_, _} ->
            cell_web_req:fail(405, method_not_allowed, "use POST", #{allow => <<"POST">>})
    end.

command(Command, Req, Caller0) ->
    Fun = case Command of
              <<"start">> -> fun cell_controller:start/1;
              <<"pause">> -> fun cell_controller:pause/1;
              <<"stop">> -> fun cell_controller:stop/1;
              _ -> cell_web_req:fail(404, not_found, "the commands are start, pause and stop")
          end,
    Caller = cell_web_req:require(Caller0, operator),
    %% A body is optional; when there is one, it must be well-formed.
    {_, _} = cell_web_req:read_json(Req),
    case Fun(cell_web_req:who_name(Caller)) of
        ok ->
            {json, 200, cell(), Command};
        {error, estop_active} ->
            cell_web_req:fail(409, estop_active,
                              "the emergency stop is active: release it, then press Start")
    end.

%% @doc The cell as `GET /api/cell' shows it.
-spec cell() -> map().
cell() ->
    Name = try cell_settings:get(machine, cell_name)
           catch error:_ -> <<"cell">>
           end,
    cell_web_json:cell(Name, cell_controller:flags()).
