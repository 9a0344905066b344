%% @doc Path-following overhead of the interpolation channel, and the latch's position
%% error at a sensor edge (issue: axes and channels).
%%
%% Path following:
%% a channel of three simulated NC axes follows a path of 10,000 segments (lines and
%% arcs, as a routed panel's cuts give), and the runtime's cost per segment is set
%% beside the bare profile computation in the same run.
%%
%% Ours: the channel accepts the path (measured from where the axes stand, the range of
%% each axis checked against its limits, the profile planned, the three axes coupled)
%% and, while it runs, each axis is asked its position once per segment, as a task or
%% the SHDR adapter would read it: a call to each axis's process, which samples its
%% coupled motion for that moment. The peer: the same 10,000 × 3 positions computed
%% in one process straight from the profile and the path (`cell_hal_axis_profile:at/2'
%% and `cell_hal_path:at/2'), no planning, no processes: the floor of what following a
%% path costs. Both as microseconds per segment.
%%
%% The latch (seed 000 §2.3.7, the laser-beam measurement): an axis drives through a
%% sensor at 200 mm/s (a simulated NC profile), the sensor's edge at a random moment of
%% the cruise. The PLC stamps its position and sensor samples with its 1 ms cycle, and
%% `cell_hal_ads_latch:position_at_edge/3' takes the position at the first sensor
%% sample that shows the edge. The peer is a poll every 10 ms (a PC reading both over
%% the network): the position read at the first poll that sees the sensor changed. Both
%% as the median distance from the true position at the edge, over 1,000 edges.
-module(cell_hal_axis_bench).

-export([run/0]).

-define(SEGMENTS, 10000).
-define(AXES, [bx, by, bz]).
-define(RUNS, 5).
%% About a second along the path: longer than the reads of a run take, so they are
%% made while the axes move.
-define(PARAMS, #{velocity => 1.0e5, acceleration => 1.0e7, deceleration => 1.0e7}).

-spec run() -> [cell_bench:result()].
run() ->
    _ = application:load(lager),
    ok = application:set_env(lager, handlers, []),
    ok = application:set_env(lager, crash_log, false),
    {ok, _} = application:ensure_all_started(cell_hal),
    [ok = cell_hal_hw:add(#{id => A, kind => axis, type => sim,
                            opts => #{limits => {-1.0e6, 1.0e6}, home_ms => 1}})
     || A <- ?AXES],
    ok = cell_hal_hw:add(#{id => bxyz, kind => channel, type => sim, opts => #{axes => ?AXES}}),
    try
        [begin
             {ok, P} = cell_hal_axis:power(A, true),
             receive {P, done} -> ok end,
             {ok, H} = cell_hal_axis:home(A, 0.0),
             receive {H, done} -> ok end
         end || A <- ?AXES],
        {ok, Path} = cell_hal_path:new(segments(?SEGMENTS)),
        N = length(cell_hal_path:segments(Path)),
        Ours = cell_bench:stats([ours(Path, N) || _ <- lists:seq(1, ?RUNS)]),
        Bare = cell_bench:stats([bare(Path, N) || _ <- lists:seq(1, ?RUNS)]),
        Note = io_lib:format(
                 "~b segments (~b with the connecting lines), 3 axes; ~b runs each. Ours "
                 "includes accepting the path (its range per axis from ~b points, the "
                 "profile, the coupling) and a status call to each axis per segment; the "
                 "peer computes the same positions in one process. Nearly all of ours "
                 "is the three status calls a segment (the object's lookup, a call to "
                 "its process, its server's dispatch); the path's sampling itself is "
                 "the peer's figure. The axes never need the runtime per segment: each "
                 "samples the channel's profile on its own, so a path costs its "
                 "processes nothing until somebody reads a position.",
                 [?SEGMENTS, N, ?RUNS, 1000]),
        latch() ++
        [#{title => "following a path of 10,000 segments with 3 axes, per segment, median",
           unit => "µs", ours => maps:get(median, Ours), peer => maps:get(median, Bare),
           peer_name => "the bare profile and path computation (one process)",
           better => lower,
           goal => "the runtime's cost per segment beside the bare computation",
           note => Note}]
    after
        [cell_hal_hw:remove(Id) || {Id, _, _} <- cell_hal_hw:list()]
    end.

%% The channel follows the path; each axis read once per segment. Microseconds per
%% segment.
ours(Path, N) ->
    T0 = erlang:monotonic_time(microsecond),
    {ok, Ref} = cell_hal_channel:follow(bxyz, Path, ?PARAMS),
    _ = [[{ok, #{position := _}} = cell_hal_axis:status(A) || A <- ?AXES]
         || _ <- lists:seq(1, N)],
    T = erlang:monotonic_time(microsecond) - T0,
    receive {Ref, done} -> ok after 60000 -> error(path_not_done) end,
    %% Back to the start for the next run.
    {ok, Back} = cell_hal_channel:follow(bxyz, element(2, cell_hal_path:new(
                                                          [{line, position(), {0, 0, 0}}])),
                                         ?PARAMS),
    receive {Back, done} -> ok after 60000 -> error(not_back) end,
    T / N.

%% The same positions, one per segment and axis, computed directly.
bare(Path, N) ->
    T0 = erlang:monotonic_time(microsecond),
    Profile = cell_hal_axis_profile:move({0, 0}, cell_hal_path:length(Path), ?PARAMS),
    D = cell_hal_axis_profile:duration(Profile),
    _ = [[element(I, cell_hal_path:at(Path, element(1, cell_hal_axis_profile:at(Profile,
                                                                                D * K / N))))
          || I <- [1, 2, 3]]
         || K <- lists:seq(1, N)],
    (erlang:monotonic_time(microsecond) - T0) / N.

%% The latch's error and a poll's, in mm, at 1,000 random sensor edges.
latch() ->
    Profile = cell_hal_axis_profile:move({0, 0}, 600, #{velocity => 200, acceleration => 2000,
                                                        deceleration => 2000}),
    At = fun(Ms) -> element(1, cell_hal_axis_profile:at(Profile, Ms / 1000)) end,
    Cycle = 1.0,     %% ms
    Poll = 10.0,     %% ms
    rand:seed(exsss, {7, 11, 13}),
    Errors = [edge(At, 500.0 + rand:uniform() * 1900.0, Cycle, Poll)
              || _ <- lists:seq(1, 1000)],
    Latch = cell_bench:stats([abs(L) || {L, _} <- Errors]),
    Polled = cell_bench:stats([abs(P) || {_, P} <- Errors]),
    [#{title => "position at a sensor edge, 200 mm/s, error, median",
       unit => "mm", ours => maps:get(median, Latch), peer => maps:get(median, Polled),
       peer_name => "a poll every 10 ms (the position read when the sensor is seen)",
       better => lower,
       goal => "the latch's error against the one-sample error of a poll",
       note => io_lib:format("PLC cycle 1 ms (the samples' stamps), 1,000 edges at random "
                             "moments of the cruise; latch p99 ~.3f mm, poll p99 ~.3f mm. The "
                             "latch's error is at most the distance of one PLC cycle, a "
                             "poll's up to one poll period's.",
                             [maps:get(p99, Latch), maps:get(p99, Polled)])}].

%% One edge at time Te (ms): the latch's error and the poll's.
edge(At, Te, Cycle, Poll) ->
    True = At(Te),
    %% The PLC's samples: position and sensor each cycle, stamped in µs.
    Cycles = [C * Cycle || C <- lists:seq(0, 3000)],
    Positions = [{round(T * 1000), At(T)} || T <- Cycles],
    Sensor = [{round(T * 1000), T >= Te} || T <- Cycles],
    {ok, #{position := Latched}} =
        cell_hal_ads_latch:position_at_edge(Sensor, Positions, #{edge => rising}),
    %% The poll: the first poll at or after the edge, at a random phase.
    Phase = rand:uniform() * Poll,
    Seen = Phase + Poll * math:ceil((Te - Phase) / Poll),
    {Latched - True, At(Seen) - True}.

position() ->
    list_to_tuple([begin {ok, #{position := P}} = cell_hal_axis:status(A), P end
                   || A <- ?AXES]).

%% Rows of square modules, each cut as four lines with rounded corners (four arcs),
%% the next module's cut begun where the last ended.
segments(N) ->
    Modules = N div 8,
    lists:append([module(I) || I <- lists:seq(0, Modules - 1)]).

module(I) ->
    X = float(I rem 50) * 30.0,
    Y = float(I div 50) * 30.0,
    Z = -1.0,
    [{line, {X + 2, Y, Z}, {X + 18, Y, Z}}, {arc, {X + 18, Y + 2, Z}, 2, 270, 0},
     {line, {X + 20, Y + 2, Z}, {X + 20, Y + 18, Z}}, {arc, {X + 18, Y + 18, Z}, 2, 0, 90},
     {line, {X + 18, Y + 20, Z}, {X + 2, Y + 20, Z}}, {arc, {X + 2, Y + 18, Z}, 2, 90, 180},
     {line, {X, Y + 18, Z}, {X, Y + 2, Z}}, {arc, {X + 2, Y + 2, Z}, 2, 180, 270}].
