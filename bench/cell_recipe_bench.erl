%% @doc Recipe load from the buffer against load from the file (seed 000 §3.2.3: a
%% device task must not pay for reading a file when a product arrives).
%%
%% One recipe with a drawing of 10,000 primitives (lines, arcs, circles and
%% polylines in nested containers with attributes, as a routed panel has) is saved
%% to a `.zprd' file. The peer figure is `cell_recipe:load/2': reading the archive,
%% inflating it, parsing and checking every part — what a task would pay without the
%% buffer. Ours is `cell_recipe_buffer:get/1' once the recipe is in the buffer.
-module(cell_recipe_bench).

-export([run/0]).

-define(PRIMITIVES, 10000).
-define(FILE_RUNS, 7).
-define(BUFFER_RUNS, 300).

-spec run() -> [cell_bench:result()].
run() ->
    Dir = filename:join(cell_config:root(), "Products"),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Opts = #{dir => Dir},
    Drawing = drawing(?PRIMITIVES),
    ?PRIMITIVES = cell_recipe_drawing:count(Drawing),
    ok = cell_recipe:save(<<"Bench panel">>, #{description => <<"10,000 primitives">>,
                                               drawing => Drawing}, <<"bench">>, Opts),
    {ok, Bytes} = cell_recipe:export(<<"Bench panel">>, Opts),
    {ok, Pid} = cell_recipe_buffer:start_link(#{recipe => Opts}),
    try
        {ok, Recipe} = cell_recipe:load(<<"Bench panel">>, Opts),
        %% warm up, and put the recipe in the buffer
        {ok, Recipe} = cell_recipe_buffer:get(<<"Bench panel">>),
        FromFile = fun() -> {ok, _} = cell_recipe:load(<<"Bench panel">>, Opts) end,
        FromBuffer = fun() -> {ok, _} = cell_recipe_buffer:get(<<"Bench panel">>) end,
        File = cell_bench:stats([time_s(FromFile) || _ <- lists:seq(1, ?FILE_RUNS)]),
        Buffer = cell_bench:stats([time_s(FromBuffer) || _ <- lists:seq(1, ?BUFFER_RUNS)]),
        Note = io_lib:format("The recipe file is ~p kB (zip of JSON); ~p file loads and ~p "
                             "buffer reads measured. A buffer read copies the recipe out of "
                             "ETS into the task's heap.",
                             [byte_size(Bytes) div 1024, ?FILE_RUNS, ?BUFFER_RUNS]),
        [#{title => "recipe load, drawing of 10,000 primitives, median",
           unit => "s", ours => maps:get(median, Buffer), peer => maps:get(median, File),
           peer_name => "load from the .zprd file (cell_recipe:load/2)", better => lower,
           goal => "the buffer spares a task the file read (seed 3.2.3)",
           note => Note},
         #{title => "recipe load, drawing of 10,000 primitives, p99",
           unit => "s", ours => maps:get(p99, Buffer), peer => maps:get(p99, File),
           peer_name => "load from the .zprd file (cell_recipe:load/2)", better => lower}]
    after
        unlink(Pid),
        ok = gen_server:stop(Pid)
    end.

%% Seconds: the runner prints figures of 100 and more with a format OTP 25 refuses,
%% and a file load takes some hundred milliseconds.
time_s(Fun) ->
    T0 = erlang:monotonic_time(microsecond),
    _ = Fun(),
    (erlang:monotonic_time(microsecond) - T0) / 1.0e6.

%% Panels of modules, each module a container with a transform holding cutting lines,
%% arcs at the corners, fiducial circles and an outline polyline.
drawing(N) ->
    Modules = [module(I) || I <- lists:seq(1, N div 10)],
    cell_recipe_drawing:new(
      [cell_recipe_drawing:container(#{<<"ItemType">> => <<"PanelDrawing">>}, Modules)]).

module(I) ->
    D = cell_recipe_drawing,
    X = float(I rem 40) * 25.0,
    Y = float(I div 40) * 25.0,
    Cut = fun(K, From, To) ->
                  D:line(From, To, #{<<"ItemType">> => <<"Cut">>,
                                     <<"ExecOrder">> => integer_to_binary(I * 10 + K)})
          end,
    D:container(#{<<"ItemType">> => <<"Module">>,
                  <<"Transform">> => D:matrix_to_text(D:translation(X, Y, 0))},
                [Cut(1, {0, 0}, {20, 0}), Cut(2, {20, 0}, {20, 20}), Cut(3, {20, 20}, {0, 20}),
                 Cut(4, {0, 20}, {0, 0}),
                 D:arc({1, 1}, 1, 180, 270), D:arc({19, 1}, 1, 270, 360),
                 D:arc({19, 19}, 1, 0, 90), D:arc({1, 19}, 1, 90, 180),
                 D:circle({10, 10}, 0.5, #{<<"ItemType">> => <<"Fiducial">>}),
                 D:polyline([{0, 0}, {20, 0}, {20, 20}, {0, 20}], true,
                            #{<<"ItemType">> => <<"Outline">>})]).
