%% @doc The router's cameras: at each lane's unloading exit a camera the lane's
%% inspection block (seed 004, {@link cell_inspect}) takes the modules' images with, and
%% a shell poke to make the next inspection fail.
%%
%% {@link configure/1} runs as the router cell starts, before the inspection
%% application (which starts after the cell in the release): it declares one block per
%% lane on the router's PLC ({@link router_cell:inspect_blocks/1}) in that
%% application's environment, unless the configuration declares blocks already, and
%% puts the demo's inspection settings in place for a block the `inspect' settings have
%% no entry for: the point `MODULES' with the simulated processing, and a simulated
%% camera (`camera_front', `camera_rear') whose images show a bad part now and then
%% (its `fail_rate', 0.05). What the operator changed there is kept.
-module(router_camera).

-export([configure/1, fail_next/1, camera/1]).

-define(FAIL_RATE, 0.05).

%% @doc Declares the inspection blocks and their demo settings for these lanes.
-spec configure([front | rear]) -> ok.
configure(Lanes) ->
    %% Loaded first: loading would put back the application file's empty list.
    _ = application:load(cell_inspect),
    case application:get_env(cell_inspect, blocks, []) of
        [] -> ok = application:set_env(cell_inspect, blocks, router_cell:inspect_blocks(Lanes));
        _ -> ok
    end,
    case cell_inspect_settings:register() of
        ok ->
            Have = [Id || #{id := Id} <- cell_settings:get(inspect, blocks)],
            New = [block(L) || L <- Lanes, not lists:member(block_id(L), Have)],
            put_blocks(New);
        {error, Why} ->
            cell_log:error(router, "the inspection settings cannot be registered: ~0tp", [Why])
    end.

put_blocks([]) ->
    ok;
put_blocks(New) ->
    case cell_settings:put(inspect, #{blocks => cell_settings:get(inspect, blocks) ++ New},
                           <<"router_cell">>) of
        ok -> ok;
        {error, Why} ->
            cell_log:error(router, "the demo's inspection settings are not saved: ~0tp", [Why])
    end.

%% @doc The next inspection of a lane's modules fails: its camera's next image shows a
%% bad part.
-spec fail_next(front | rear) -> ok | {error, term()}.
fail_next(Lane) ->
    cell_inspect_camera_sim:fail_next(camera(Lane)).

%% @doc The camera client of a lane's inspection block.
-spec camera(front | rear) -> binary().
camera(front) -> <<"camera_front">>;
camera(rear) -> <<"camera_rear">>.

block(L) ->
    #{id => block_id(L), heartbeat_ms => 5000, processing_timeout_ms => 30000,
      panel_messages => false,
      points => [#{id => router_inspection:point(),
                   caption => <<"The routed modules at the unloading exit">>,
                   processing => <<"sim">>, workspace => <<"router">>}],
      messages => [],
      clients => [#{id => camera(L), type => <<"sim">>, points => [], images => true,
                    messages => false, delay_ms => 300, manual => false, scene => <<"PASS">>,
                    fail_rate => ?FAIL_RATE}]}.

block_id(L) ->
    atom_to_binary(router_cell:group(inspection_block, L)).
