%% The NC I channel's ADS mapping (cell_hal_ads_nci) without a process: the part
%% program a path becomes, the requests, the interpreter's state decoded and what a
%% state read means for the job that runs.
-module(cell_hal_ads_nci_tests).
-include_lib("eunit/include/eunit.hrl").

-define(CTX, #{channel => 2}).

program_test() ->
    {ok, Path} = cell_hal_path:new([{line, {10, 0}, {60, 0}},
                                    {arc, {60, 20}, 20, -90, 90},
                                    {arc, {60, 60}, 20, 270, 90, cw},
                                    {line, {0, 0, 5}, {0, 0, -2}}]),
    ?assertEqual(<<"N10 G17 G71 G90\n"
                   "N20 G01 X10.0000 Y0.0000 F600.0000\n"
                   "N30 G01 X60.0000 Y0.0000 F600.0000\n"
                   %% Counter-clockwise round (60, 20): the centre 20 above the start.
                   "N40 G03 X60.0000 Y40.0000 I0.0000 J20.0000 F600.0000\n"
                   %% Clockwise round (60, 60) from (60, 40) to (60, 80).
                   "N50 G02 X60.0000 Y80.0000 I0.0000 J20.0000 F600.0000\n"
                   %% A connecting line to the next segment's start, then the segment.
                   "N60 G01 X0.0000 Y0.0000 F600.0000\n"
                   "N70 G01 X0.0000 Y0.0000 F600.0000\n"
                   "N80 M30\n">>,
                 cell_hal_ads_nci:program(Path, 10, 2)),
    %% Three axes: Z written too.
    {ok, Line} = cell_hal_path:new([{line, {0, 0, 5}, {0, 0, -2}}]),
    ?assertEqual(<<"N10 G17 G71 G90\n"
                   "N20 G01 X0.0000 Y0.0000 Z5.0000 F60.0000\n"
                   "N30 G01 X0.0000 Y0.0000 Z-2.0000 F60.0000\n"
                   "N40 M30\n">>,
                 cell_hal_ads_nci:program(Line, 1, 3)).

requests_test_() ->
    R = fun(Op) -> cell_hal_ads_nci:request(Op, ?CTX) end,
    [?_assertEqual({write, 16#2202, 16#10, <<>>}, R(reset)),
     ?_assertEqual({write, 16#2202, 16#11, <<>>}, R(stop)),
     ?_assertEqual({write, 16#2202, 2, <<>>}, R(start)),
     ?_assertEqual({write, 16#2202, 4, <<"C:\\p.nc", 0>>}, R({load, <<"C:\\p.nc">>})),
     ?_assertEqual({read, 16#2102, 3, 4}, R(state)),
     ?_assertEqual({read, 16#2102, 1, 4}, R(error_code)),
     %% The path override in the cyclic interface, 1000000 = 100 %.
     ?_assertEqual({write, 16#2302, 2, <<500000:32/little>>}, R({override, 50})),
     ?_assertEqual({write, 16#2302, 2, <<1000000:32/little>>}, R({override, 100})),
     ?_assertEqual({write, 16#2302, 2, <<125000:32/little>>}, R({override, 12.5})),
     %% The system service: FOPEN for writing, binary, by a generic path.
     ?_assertEqual({read_write, 120, 16#10012, 4, <<"C:\\p.nc", 0>>},
                   cell_hal_ads_nci:file_writes(open, <<"C:\\p.nc">>, ?CTX)),
     ?_assertEqual({read_write, 123, 7, 0, <<"N10 M30\n">>},
                   cell_hal_ads_nci:file_writes({write, 7, <<"N10 M30\n">>}, <<"x">>, ?CTX)),
     ?_assertEqual({read_write, 121, 7, 0, <<>>},
                   cell_hal_ads_nci:file_writes({close, 7}, <<"x">>, ?CTX))].

decode_test_() ->
    D = fun(N) -> {ok, S} = cell_hal_ads_nci:decode_state(<<N:32/little>>), S end,
    [?_assertEqual(idle, D(1)), ?_assertEqual(ready, D(2)),
     ?_assertEqual([running], lists:usort([D(N) || N <- [3, 4, 5, 6, 7, 8, 9, 10, 16, 17]])),
     ?_assertEqual([aborted], lists:usort([D(N) || N <- [11, 12, 13]])),
     ?_assertEqual([idle], lists:usort([D(N) || N <- [14, 15]])),
     ?_assertEqual({other, 0}, D(0)),
     ?_assertEqual({other, 99}, D(99)),
     ?_assertMatch({error, {bad_state, _}}, cell_hal_ads_nci:decode_state(<<1, 2>>)),
     ?_assertEqual({ok, -5}, cell_hal_ads_nci:decode_error(<<-5:32/little-signed>>)),
     ?_assertMatch({error, {bad_error_code, _}}, cell_hal_ads_nci:decode_error(<<>>))].

news_test_() ->
    N = fun cell_hal_ads_nci:news/3,
    [?_assertEqual(running, N(follow, running, 0)),
     ?_assertEqual(done, N(follow, ready, 0)),
     ?_assertEqual(aborted, N(follow, idle, 0)),
     ?_assertEqual(aborted, N(follow, aborted, 0)),
     %% An error code fails the path whatever the interpreter shows.
     ?_assertEqual({error, 16#4650}, N(follow, aborted, 16#4650)),
     ?_assertEqual({error, 16#4650}, N(follow, running, 16#4650)),
     ?_assertEqual(running, N(halt, running, 0)),
     ?_assertEqual(done, N(halt, idle, 0)),
     ?_assertEqual(done, N(halt, ready, 0))].
