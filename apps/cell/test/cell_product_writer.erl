%% A VM that writes product files for cell_product_SUITE, which kills it with
%% SIGKILL. Operation M (M = First, First + 1, ...) acts on file M rem Files: every seventh clears
%% it (the task holds no product), the others save a product carrying M. After each
%% operation it prints "ack M" and waits for "go" before the next, so when it is killed
%% at most one operation, the one after the last acknowledged, was under way.
-module(cell_product_writer).

-export([main/0, op/2]).

-spec main() -> no_return().
main() ->
    [Dir, Files, First] = init:get_plain_arguments(),
    io:format("pid ~s~n", [os:getpid()]),
    loop(Dir, list_to_integer(Files), list_to_integer(First)).

loop(Dir, Files, M) ->
    "go\n" = io:get_line(""),
    {File, Product} = op(M, Files),
    Stored = case Product of
                 undefined -> undefined;
                 _ -> cell_product:stored(Product, 1, undefined)
             end,
    ok = cell_product:save(filename:join(Dir, File), Stored),
    io:format("ack ~p~n", [M]),
    loop(Dir, Files, M + 1).

%% Mostly small products; every third one is megabytes, so that writing it takes
%% long enough for a kill to land in the middle of the write itself.
payload(M) when M rem 3 =:= 0 -> binary:copy(<<(M rem 251)>>, 2000000 + 1000 * (M rem 2000));
payload(M) -> binary:copy(<<(M rem 251)>>, 64 + M rem 3000).

%% The file operation M touches and the product it leaves there.
-spec op(pos_integer(), pos_integer()) -> {string(), cell_product:product() | undefined}.
op(M, Files) ->
    File = "task" ++ integer_to_list(M rem Files) ++ "@Lane.product",
    case M rem 7 of
        0 -> {File, undefined};
        _ -> {File, cell_product:new(<<"P-", (integer_to_binary(M))/binary>>, <<"recipe">>,
                                     #{op => M, payload => payload(M)})}
    end.
