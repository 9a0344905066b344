%% @doc Many reads, writes or read-writes as few ADS requests as the PLC allows. Pure.
%%
%% With sum commands, a batch of N items goes out as ceil(N / MaxSum) sum requests
%% (TwinCAT takes at most 500 sub-commands in one; the limit is an option); a batch of
%% one item is a plain request. Without them (PLCs that lack sum commands), every item
%% is its own request; the client still keeps them in flight together.
%%
%% Each builder returns the requests and a function that turns their answers (in the
%% same order) into one result per item.
-module(cell_hal_ads_batch).

-export([reads/2, writes/2, read_writes/2, chunks/2]).

-export_type([mode/0, answer/0, assemble/1]).

-type mode() :: #{sum := boolean(), max_sum := pos_integer()}.

%% The answer to one request, as the client hands it over.
-type answer() :: {ok, cell_hal_ads_codec:response()} | {error, term()}.

-type assemble(Result) :: fun(([answer()]) -> [Result]).

-type u32() :: 0..16#FFFFFFFF.

%% @doc Reads of `{Group, Offset, Length}'.
-spec reads([{u32(), u32(), u32()}], mode()) ->
          {[cell_hal_ads_codec:request()], assemble({ok, binary()} | {error, term()})}.
reads(Items, Mode) ->
    batch(Items, Mode,
          fun({G, O, L}) -> {read, G, O, L} end,
          fun(A) -> A end,
          fun cell_hal_ads_codec:sum_read/1,
          fun(Chunk, Bin) ->
                  cell_hal_ads_codec:decode_sum_read([L || {_, _, L} <- Chunk], Bin)
          end).

%% @doc Writes of `{Group, Offset, Data}'.
-spec writes([{u32(), u32(), iodata()}], mode()) ->
          {[cell_hal_ads_codec:request()], assemble(ok | {error, term()})}.
writes(Items, Mode) ->
    batch(Items, Mode,
          fun({G, O, D}) -> {write, G, O, D} end,
          fun({ok, ok}) -> ok;
             ({error, _} = E) -> E
          end,
          fun cell_hal_ads_codec:sum_write/1,
          fun(Chunk, Bin) -> cell_hal_ads_codec:decode_sum_write(length(Chunk), Bin) end).

%% @doc ReadWrites of `{Group, Offset, ReadLength, Data}'.
-spec read_writes([{u32(), u32(), u32(), iodata()}], mode()) ->
          {[cell_hal_ads_codec:request()], assemble({ok, binary()} | {error, term()})}.
read_writes(Items, Mode) ->
    batch(Items, Mode,
          fun({G, O, L, D}) -> {read_write, G, O, L, D} end,
          fun(A) -> A end,
          fun cell_hal_ads_codec:sum_read_write/1,
          fun(Chunk, Bin) -> cell_hal_ads_codec:decode_sum_read_write(length(Chunk), Bin) end).

batch([], _, _, _, _, _) ->
    {[], fun([]) -> [] end};
batch(Items, #{sum := Sum, max_sum := Max}, Single, Unwrap, _, _)
  when not Sum; length(Items) =:= 1; Max =:= 1 ->
    {[Single(I) || I <- Items], fun(Answers) -> [Unwrap(A) || A <- Answers] end};
batch(Items, #{max_sum := Max}, Single, Unwrap, SumRequest, SumDecode) ->
    Chunks = chunks(Items, Max),
    Requests = [case Chunk of
                    [One] -> Single(One);
                    _ -> SumRequest(Chunk)
                end || Chunk <- Chunks],
    Assemble = fun(Answers) ->
                       lists:append(lists:zipwith(fun(Chunk, Answer) ->
                                                          chunk_results(Chunk, Answer, Unwrap,
                                                                        SumDecode)
                                                  end, Chunks, Answers))
               end,
    {Requests, Assemble}.

chunk_results([_], Answer, Unwrap, _) ->
    [Unwrap(Answer)];
chunk_results(Chunk, {ok, Bin}, _, SumDecode) when is_binary(Bin) ->
    case SumDecode(Chunk, Bin) of
        {ok, Results} -> Results;
        {error, _} = E -> [E || _ <- Chunk]
    end;
chunk_results(Chunk, {error, _} = E, _, _) ->
    [E || _ <- Chunk].

%% @doc A list cut into pieces of at most `Max' elements, in order.
-spec chunks([T], pos_integer()) -> [[T]].
chunks([], _) ->
    [];
chunks(List, Max) when length(List) =< Max ->
    [List];
chunks(List, Max) ->
    {Chunk, Rest} = lists:split(Max, List),
    [Chunk | chunks(Rest, Max)].
