%% @doc `/api/tasks' — every device task: state, product serial, zone and lane;
%% `/api/tasks/:id' — one task in full: why it is DOWN, its pending request, its
%% product, the settings it runs on (the snapshot taken at the last Start) and, for a
%% unit, its own state and the step its sequence is at; `/api/tasks/:id/retained' —
%% the task's retained data (its counters, the last serial made: see
%% `cell_task:retain/3'), as its file holds them, or why the file cannot be read.
-module(cell_web_tasks_h).
-behaviour(cowboy_handler).

-export([init/2, task_id/1]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    What = maps:get(what, Opts, task),
    {ok, cell_web_req:run(Req, fun(R, C) -> handle(What, R, C) end), Opts}.

handle(What, Req, Caller) ->
    cowboy_req:method(Req) =:= <<"GET">>
        orelse cell_web_req:fail(405, method_not_allowed, "use GET", #{allow => <<"GET">>}),
    _ = cell_web_req:require(Caller, view),
    case cowboy_req:binding(id, Req) of
        undefined ->
            {json, 200, [cell_web_json:task(Row) || Row <- cell_controller:tasks()]};
        Bin when What =:= retained ->
            {json, 200, retained(task_id(Bin))};
        Bin ->
            {json, 200, detail(task_id(Bin))}
    end.

%% What the task retained, as its registry row has it from the task's file.
retained(Id) ->
    {ok, Row} = cell_registry:task(Id),
    {Data, Error} = case Row of
                        #{retained_error := Why} when Why =/= undefined ->
                            {null, unicode:characters_to_binary(cell_retain:text(Why))};
                        #{retained := R} when is_map(R) ->
                            {cell_web_json:term(R), null};
                        _ ->
                            {null, null}
                    end,
    #{<<"task">> => atom_to_binary(Id, utf8), <<"zone">> => maps:get(zone, Row),
      <<"lane">> => maps:get(lane, Row), <<"retained">> => Data, <<"error">> => Error}.

%% @doc The task a URL names, matched against the running cell's ids (an atom is never
%% made from the request).
-spec task_id(binary()) -> atom().
task_id(Bin) ->
    case [Id || Id <- cell_registry:task_ids(), atom_to_binary(Id, utf8) =:= Bin] of
        [Id] -> Id;
        [] -> cell_web_req:fail(404, not_found, ["there is no task ", Bin])
    end.

detail(Id) ->
    {ok, Row} = cell_registry:task(Id),
    Base = cell_web_json:task(Row#{id => Id}),
    Info = case maps:get(pid, Row, undefined) of
               Pid when is_pid(Pid) ->
                   try cell_task_proc:info(Pid)
                   catch exit:_ -> undefined    %% it has just exited or is busy: say so
                   end;
               undefined ->
                   undefined
           end,
    Base#{<<"request">> => info(request, Info),
          <<"service_mode">> => info(service_mode, Info),
          <<"down">> => case Info of
                            undefined -> null;
                            _ -> down(maps:get(down, Info, undefined))
                        end,
          <<"product">> => case Info of
                               undefined -> null;
                               _ -> cell_web_json:product(maps:get(product, Info, undefined))
                           end,
          <<"alarms">> => [cell_web_json:alarm(A) || A <- cell_alarms:list(Id)],
          <<"settings">> => settings(maps:get(settings_key, Row, undefined)),
          <<"unit">> => cell_web_json:unit(Info)}.

info(_Key, undefined) -> null;
info(Key, Info) -> cell_web_json:term(maps:get(Key, Info, undefined)).

%% Why a task is DOWN, as the engine says it.
down(undefined) -> null;
down({paused, pause}) -> #{<<"why">> => <<"paused">>};
down({paused, service}) -> #{<<"why">> => <<"service_mode">>};
down({error, AlarmId, Origin}) ->
    #{<<"why">> => <<"error">>, <<"alarm">> => AlarmId, <<"origin">> => cell_web_json:term(Origin)};
down(Other) ->
    #{<<"why">> => cell_web_json:term(Other)}.

%% The settings object the task runs on, as it was at the last Start, and whether
%% the saved object differs (its changes apply at the next Start).
settings(undefined) ->
    null;
settings(Name) ->
    case cell_settings:schema(Name) of
        {ok, Mod} ->
            InForce = case cell_settings:last_snapshot() of
                          #{Name := Obj} -> Obj;
                          _ -> undefined
                      end,
            Saved = cell_settings:get(Name),
            #{<<"name">> => atom_to_binary(Name, utf8),
              <<"in_force">> => case InForce of
                                    undefined -> null;
                                    _ -> cell_web_settings_h:encode(Mod, InForce)
                                end,
              <<"pending">> => InForce =/= undefined andalso InForce =/= Saved};
        {error, _} ->
            null
    end.
