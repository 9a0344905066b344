%% @doc Many reads, writes or read-writes as few ADS requests as the PLC allows. Pure.
%%
%% With sum commands, a batch of N items goes out as ceil(N / MaxSum) sum requests
%% (TwinCAT takes at most 500 sub-commands in one; the limit is an option); a batch of
%% one item is a plain request. Without them (PLCs that lack sum commands), every item
%% is its own request; the client still keeps them in flight together.
%%
%% Each builder returns the requests and a function that turns their answers (in the
%% same order) into one result per item.
%%
%% Reads and writes of resolved variables are planned here too ({@link plan_read/2},
%% {@link plan_write/3}): what can be asked for becomes an item of the batch, what
%% cannot (a variable not resolved, a value that does not fit) is its answer at once,
%% and {@link merge/3} puts the batch's results back in the caller's order.
-module(cell_hal_ads_batch).

-include("cell_hal_ads.hrl").

-export([reads/2, writes/2, read_writes/2, chunks/2]).
-export([item/2, plan_read/2, plan_write/3, merge/3, decode_value/2]).

-export_type([mode/0, answer/0, assemble/1, plan/1]).

-type mode() :: #{sum := boolean(), max_sum := pos_integer()}.

%% The answer to one request, as the client hands it over.
-type answer() :: {ok, cell_hal_ads_codec:response()} | {error, term()}.

-type assemble(Result) :: fun(([answer()]) -> [Result]).

-type u32() :: 0..16#FFFFFFFF.

%% One variable of a read or write: an item to send, or its answer given at once.
-type plan(Item) :: {read | write, Item, cell_hal_ads_types:type()} | {error, term()}.

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

%%--------------------------------------------------------------------
%% Variables
%%--------------------------------------------------------------------

%% @doc Where a resolved variable is read or written: through its handle, or at its
%% index group and offset; `X' is the length to read or the data to write.
-spec item(cell_hal_ads_vars:access(), X) -> {u32(), u32(), X}.
item({handle, H}, X) -> {?IG_SYM_VALBYHND, H, X};
item({address, G, O}, X) -> {G, O, X}.

%% @doc What a read of one variable needs: a read item, or an error without asking.
-spec plan_read({binary(), cell_hal_ads_types:type()}, cell_hal_ads_vars:vars()) ->
          plan({u32(), u32(), non_neg_integer()}).
plan_read({Name, Type}, Vars) ->
    case cell_hal_ads_vars:ready(cell_hal_ads_vars:key_of(Name, Type, Vars), Vars) of
        {ok, Access, Size, _} -> {read, item(Access, Size), Type};
        {error, not_resolved} -> {error, {not_resolved, Name}};
        {error, _} = E -> E
    end.

%% @doc What a write of one variable needs: a write item with the value encoded, or an
%% error without asking (a value that does not fit its type is never sent).
-spec plan_write({binary(), cell_hal_ads_types:type()}, cell_hal_ads_types:value(),
                 cell_hal_ads_vars:vars()) -> plan({u32(), u32(), binary()}).
plan_write({Name, Type}, Value, Vars) ->
    case cell_hal_ads_vars:ready(cell_hal_ads_vars:key_of(Name, Type, Vars), Vars) of
        {ok, Access, Size, _} ->
            case cell_hal_ads_types:encode(Type, Value, Size) of
                {ok, Bin} -> {write, item(Access, Bin), Type};
                {error, _} = E -> E
            end;
        {error, not_resolved} -> {error, {not_resolved, Name}};
        {error, _} = E -> E
    end.

%% @doc The planned items' results back in the caller's order, each through `F' with
%% its type; the errors planned at once kept in their places.
-spec merge([plan(term())], [R], fun((cell_hal_ads_types:type(), R) -> T)) ->
          [T | {error, term()}].
merge([], [], _) ->
    [];
merge([{error, _} = E | Plan], Results, F) ->
    [E | merge(Plan, Results, F)];
merge([{_, _, Type} | Plan], [R | Results], F) ->
    [F(Type, R) | merge(Plan, Results, F)].

%% @doc A read's answer as a value of its type.
-spec decode_value(cell_hal_ads_types:type(), {ok, binary()} | {error, term()}) ->
          {ok, cell_hal_ads_types:value()} | {error, term()}.
decode_value(Type, {ok, Bin}) -> cell_hal_ads_types:decode(Type, Bin);
decode_value(_, {error, _} = E) -> E.
