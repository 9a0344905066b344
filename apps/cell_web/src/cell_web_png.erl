%% @doc A camera image as PNG, so that the panel shows a grabbed image with an `<img>'
%% (no plug-in, nothing from outside the cell): 8-bit grey (`mono8') or RGB (`rgb8'),
%% no interlace, every row unfiltered, deflated by zlib. Pure.
-module(cell_web_png).

-export([encode/1]).

%% @doc The PNG file of an image as `cell_hal_camera:grab/2' returns it.
-spec encode(#{width := pos_integer(), height := pos_integer(), format := atom(),
               data := binary(), atom() => term()}) ->
          {ok, binary()} | {error, {unsupported_format, atom()} | bad_size}.
encode(#{width := W, height := H, format := Format, data := Data}) ->
    case Format of
        mono8 -> encode(W, H, 0, 1, Data);
        rgb8 -> encode(W, H, 2, 3, Data);
        Other -> {error, {unsupported_format, Other}}
    end.

encode(W, H, ColourType, Bytes, Data) when byte_size(Data) =:= W * H * Bytes ->
    Stride = W * Bytes,
    Raw = << <<0, Row:Stride/binary>> || <<Row:Stride/binary>> <= Data >>,
    {ok, <<137, "PNG", 13, 10, 26, 10,
           (chunk(<<"IHDR">>, <<W:32, H:32, 8, ColourType, 0, 0, 0>>))/binary,
           (chunk(<<"IDAT">>, zlib:compress(Raw)))/binary,
           (chunk(<<"IEND">>, <<>>))/binary>>};
encode(_, _, _, _, _) ->
    {error, bad_size}.

chunk(Type, Data) ->
    <<(byte_size(Data)):32, Type/binary, Data/binary, (erlang:crc32(<<Type/binary, Data/binary>>)):32>>.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

encode_test_() ->
    {ok, Png} = encode(#{width => 3, height => 2, format => mono8, data => <<1, 2, 3, 4, 5, 6>>}),
    <<137, "PNG", 13, 10, 26, 10, 13:32, "IHDR", 3:32, 2:32, 8, 0, 0, 0, 0, Crc:32, Rest/binary>> = Png,
    <<Len:32, "IDAT", Z:Len/binary, _:32, 0:32, "IEND", _:32>> = Rest,
    [?_assertEqual(erlang:crc32(<<"IHDR", 3:32, 2:32, 8, 0, 0, 0, 0>>), Crc),
     ?_assertEqual(<<0, 1, 2, 3, 0, 4, 5, 6>>, zlib:uncompress(Z)),
     ?_assertMatch({ok, <<137, "PNG", _/binary>>},
                   encode(#{width => 1, height => 1, format => rgb8, data => <<1, 2, 3>>})),
     ?_assertEqual({error, bad_size},
                   encode(#{width => 2, height => 2, format => mono8, data => <<1, 2, 3>>})),
     ?_assertEqual({error, {unsupported_format, bayer}},
                   encode(#{width => 1, height => 1, format => bayer, data => <<1>>}))].
-endif.
