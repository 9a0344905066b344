%% @doc The clamps of a lane's routing fixture as a unit (seed 001): two pneumatic
%% clamps ({@link router_clamps_io}) that hold the panel while the lower robot routes
%% it and until the upper robot has lifted the modules out, driven as `cell_cylinder'
%% actuators by step sequences.
%%
%% The clamps, not the gripper: the clamps' lifecycle is the fixture's own (closed
%% for a panel's whole stay, opened for the frame to leave), commanded by one task,
%% the lane's work segment ({@link router_work_task}), and their state must survive
%% every restart on the sensors alone; the gripper is part of the upper robot's moves,
%% which its task sequences with the robot's position and product records.
%%
%% <pre>
%%  state           sequence                     what the clamps do
%%  go_home         router_clamps_sequences home  recover from the sensors: a panel in
%%                                               the fixture with a clamp closed on it →
%%                                               both closed (never opened under a panel
%%                                               being routed); otherwise both open
%%  automatic       router_clamps_automatic      follow the work segment's standing
%%                                               order `clamp' (cell_unit:order/3):
%%                                               true → both closed, false → both open
%%  stop            router_clamps_sequences stop  nothing moves: the valves hold
%%  fault_reaction  router_clamps_sequences       both coils of each valve off: the
%%                  fault_reaction               bistable valves hold where they are,
%%                                               a clamped panel stays clamped
%% </pre>
%%
%% A clamp that does not reach its end within `timeout_ms' aborts the sequence: the
%% unit's fault (an error the operator answers with RESET, once the clamp is free),
%% then GoHome and, the cell running, Automatic again, following the order it kept.
%% The emergency stop and a crash leave the valves as they are (`safe => keep'): air on
%% a closed clamp keeps the panel held.
%%
%% Args: `lane' (whose fixture: its work segment's IO is read too), `timeout_ms' (the
%% clamps' travel limit, default 3000).
-module(router_clamps_unit).
-behaviour(cell_unit).

-export([unit/1]).

-spec unit(map()) -> map().
unit(Args) ->
    Timeout = maps:get(timeout_ms, Args, 3000),
    WorkIo = router_cell:group(work, maps:get(lane, Args, front)),
    #{sequences => #{go_home => {router_clamps_sequences, #{sequence => home,
                                                            work_io => WorkIo}},
                     automatic => router_clamps_automatic,
                     stop => {router_clamps_sequences, #{sequence => stop}},
                     fault_reaction => {router_clamps_sequences, #{sequence => fault_reaction}}},
      actuators =>
          maps:from_list(
            [{actuator(Name),
              {cell_cylinder, #{closed => #{out => Close, sensor => IsClosed},
                                open => #{out => Open, sensor => IsOpen},
                                timeout_ms => Timeout, safe => keep}}}
             || #{name := Name, close := Close, open := Open, is_closed := IsClosed,
                  is_open := IsOpen} <- router_clamps_io:clamps()]),
      idle => starved}.

actuator(a) -> clamp_a;
actuator(b) -> clamp_b.
