%% @doc Resolving variables against the PLC's symbols, in steps: what to ask the PLC
%% for, and what its answers mean. Pure: the connection ({@link cell_hal_ads_client})
%% sends the requests and hands the answers back; what was resolved is kept in its
%% handle cache ({@link cell_hal_ads_vars}).
%%
%% A variable `{Name, Type}' is resolved in three steps, each one round trip for all
%% the variables of a call:
%% <ol>
%% <li>its symbol: "*" names are looked up in the PLC's uploaded symbol table (one
%%     upload per symbol version), the others asked for by name (symbol info by name,
%%     0xF009, which also finds structure fields);</li>
%% <li>the symbol's type and size are checked against `Type';</li>
%% <li>a handle is taken (0xF003), or with `access => address' the symbol's own index
%%     group and offset are used.</li>
%% </ol>
-module(cell_hal_ads_resolve).

-include("cell_hal_ads.hrl").

-export([upload_info_request/0, upload_request/1, table/1, table_list/1, lookup_wild/2,
         info_requests/2, infos/2, check/2, by_address/1, handle_requests/2, handles/3,
         release_requests/2, registered/3, refreshed/2, info/1, find_error/3]).

-export_type([item/0, result/0]).

%% A variable to resolve, under its key in the cache.
-type item() :: {cell_hal_ads_vars:key(), binary(), cell_hal_ads_types:type()}.
-type symbol() :: cell_hal_ads_codec:symbol().
-type result() :: {ok, symbol(), cell_hal_ads_vars:access()} | {error, term()}.

%% Room for a symbol entry asked for by name: header, name, type, comment and the
%% extra information TwinCAT 3 appends.
-define(SYMBOL_INFO_LENGTH, 2048).

%%--------------------------------------------------------------------
%% The symbol table
%%--------------------------------------------------------------------

%% @doc The first request of an upload: the table's size.
-spec upload_info_request() -> cell_hal_ads_codec:request().
upload_info_request() ->
    {read, ?IG_SYM_UPLOADINFO, 0, 8}.

%% @doc The second: the table, of the size the first answer gave.
-spec upload_request(binary()) -> {ok, cell_hal_ads_codec:request()} | {error, term()}.
upload_request(InfoBin) ->
    case cell_hal_ads_codec:decode_upload_info(InfoBin) of
        {ok, #{size := Size}} -> {ok, {read, ?IG_SYM_UPLOAD, 0, Size}};
        {error, _} = E -> E
    end.

%% @doc The uploaded table.
-spec table(binary()) -> {ok, cell_hal_ads_symbols:table()} | {error, term()}.
table(TableBin) ->
    case cell_hal_ads_codec:decode_symbol_table(TableBin) of
        {ok, Symbols} -> {ok, cell_hal_ads_symbols:new(Symbols)};
        {error, _} = E -> E
    end.

%% @doc The table's symbols, sorted by name.
-spec table_list(cell_hal_ads_symbols:table()) -> [symbol()].
table_list(Table) ->
    lists:sort(fun(#{name := A}, #{name := B}) -> A =< B end,
               cell_hal_ads_symbols:to_list(Table)).

%% @doc A "*" name's symbol, from the table or the error that kept it from being read.
-spec lookup_wild(binary(), {ok, cell_hal_ads_symbols:table()} | {error, term()}) ->
          {ok, symbol()} | {error, term()}.
lookup_wild(Name, {ok, Table}) -> cell_hal_ads_symbols:lookup(Name, Table);
lookup_wild(_, {error, Reason}) -> {error, {symbol_table, Reason}}.

%%--------------------------------------------------------------------
%% Symbols by name
%%--------------------------------------------------------------------

%% @doc Symbol info by name for each item, as few requests as `Mode' allows.
-spec info_requests([item()], cell_hal_ads_batch:mode()) ->
          {[cell_hal_ads_codec:request()],
           cell_hal_ads_batch:assemble({ok, binary()} | {error, term()})}.
info_requests(Items, Mode) ->
    cell_hal_ads_batch:read_writes([{?IG_SYM_INFOBYNAMEEX, 0, ?SYMBOL_INFO_LENGTH,
                                     <<Name/binary, 0>>} || {_, Name, _} <- Items], Mode).

%% @doc The items with their symbols, from the assembled answers.
-spec infos([item()], [{ok, binary()} | {error, term()}]) ->
          [{item(), {ok, symbol()} | {error, term()}}].
infos(Items, Results) ->
    lists:zipwith(fun({_, Name, _} = I, R) -> {I, symbol_info(Name, R)} end, Items, Results).

symbol_info(Name, {ok, Bin}) ->
    case cell_hal_ads_codec:decode_symbol(Bin) of
        {ok, Symbol} -> {ok, Symbol};
        {error, Reason} -> {error, {symbol_error, Name, Reason}}
    end;
symbol_info(Name, {error, Reason}) ->
    {error, symbol_error(Name, Reason)}.

symbol_error(Name, {ads_error, 16#710, _}) -> {unknown_symbol, Name};
symbol_error(_, timeout) -> timeout;
symbol_error(_, disconnected) -> disconnected;
symbol_error(Name, Reason) -> {symbol_error, Name, Reason}.

%% @doc A found symbol checked against the type the variable expects.
-spec check(item(), {ok, symbol()} | {error, term()}) -> {ok, symbol()} | {error, term()}.
check({_, Name, Type}, {ok, Symbol}) ->
    case cell_hal_ads_symbols:check_type(Name, Type, Symbol) of
        ok -> {ok, Symbol};
        Error -> Error
    end;
check(_, {error, _} = E) ->
    E.

%%--------------------------------------------------------------------
%% Handles
%%--------------------------------------------------------------------

%% @doc With `access => address': each checked symbol at its own group and offset.
-spec by_address([{item(), {ok, symbol()} | {error, term()}}]) ->
          [{cell_hal_ads_vars:key(), result()}].
by_address(Checked) ->
    [{K, case R of
             {ok, #{group := G, offset := O} = S} -> {ok, S, {address, G, O}};
             {error, _} = E -> E
         end} || {{K, _, _}, R} <- Checked].

%% @doc A handle for each symbol checked good (a "*" name asked for by the full name it
%% matched).
-spec handle_requests([{item(), symbol()}], cell_hal_ads_batch:mode()) ->
          {[cell_hal_ads_codec:request()],
           cell_hal_ads_batch:assemble({ok, binary()} | {error, term()})}.
handle_requests(Ok, Mode) ->
    cell_hal_ads_batch:read_writes([{?IG_SYM_HNDBYNAME, 0, 4, <<(handle_name(N, S))/binary, 0>>}
                                    || {{_, N, _}, S} <- Ok], Mode).

%% @doc Every item's result: the handles taken for the good ones, the errors of the
%% others.
-spec handles([{item(), symbol()}], [{ok, binary()} | {error, term()}],
              [{item(), {ok, symbol()} | {error, term()}}]) ->
          [{cell_hal_ads_vars:key(), result()}].
handles(Ok, Results, Checked) ->
    lists:zipwith(fun({{K, N, _}, S}, R) -> {K, handle(N, S, R)} end, Ok, Results)
        ++ [{K, E} || {{K, _, _}, {error, _} = E} <- Checked].

handle_name(Name, #{name := Full}) ->
    case cell_hal_ads_symbols:is_wildcard(Name) of
        true -> Full;
        false -> Name
    end.

handle(_, S, {ok, <<H:32/little>>}) -> {ok, S, {handle, H}};
handle(N, _, {ok, _}) -> {error, {symbol_error, N, {bad_response, handle_size}}};
handle(N, _, {error, Reason}) -> {error, symbol_error(N, Reason)}.

%% @doc Handles given back to the PLC.
-spec release_requests([cell_hal_ads_vars:access()], cell_hal_ads_batch:mode()) ->
          [cell_hal_ads_codec:request()].
release_requests(Accesses, Mode) ->
    {Requests, _} = cell_hal_ads_batch:writes([{?IG_SYM_RELEASEHND, 0, <<H:32/little>>}
                                               || {handle, H} <- Accesses], Mode),
    Requests.

%%--------------------------------------------------------------------
%% Into the cache
%%--------------------------------------------------------------------

%% @doc Variables resolved for a caller, into the cache: a variable another caller
%% registered meanwhile keeps its handle (the second one, in `Extra', goes back). The
%% errors come back as `{Name, Type, Reason}' for the log.
-spec registered([{cell_hal_ads_vars:key(), result()}],
                 #{cell_hal_ads_vars:key() => {binary(), cell_hal_ads_types:type()}},
                 cell_hal_ads_vars:vars()) ->
          {cell_hal_ads_vars:vars(), [cell_hal_ads_vars:access()],
           [{binary(), cell_hal_ads_types:type(), term()}]}.
registered(Found, Names, Vars0) ->
    lists:foldl(
      fun({K, {ok, Symbol, Access}}, {Vars, Extra, Failed}) ->
              case cell_hal_ads_vars:state(K, Vars) of
                  ready ->
                      {Vars, [Access | Extra], Failed};
                  _ ->
                      {Name, Type} = maps:get(K, Names),
                      Vars1 = cell_hal_ads_vars:declare(Name, Type, Vars),
                      {cell_hal_ads_vars:resolved(K, Symbol, Access, Vars1), Extra, Failed}
              end;
         ({K, {error, Reason}}, {Vars, Extra, Failed}) ->
              {Name, Type} = maps:get(K, Names),
              {Vars, Extra, Failed ++ [{Name, Type, Reason}]}
      end, {Vars0, [], []}, Found).

%% @doc Variables in use resolved again (after a connect or a program change), into the
%% cache: those released meanwhile are left out (their new handles, in `Gone', go
%% back); the errors come back for the log.
-spec refreshed([{cell_hal_ads_vars:key(), result()}], cell_hal_ads_vars:vars()) ->
          {cell_hal_ads_vars:vars(), [cell_hal_ads_vars:access()],
           [{binary(), cell_hal_ads_types:type(), term()}]}.
refreshed(Results, Vars0) ->
    lists:foldl(
      fun({K, Result}, {Vars, Gone, Failed}) ->
              case {cell_hal_ads_vars:find(K, Vars), Result} of
                  {error, {ok, _, Access}} ->
                      {Vars, [Access | Gone], Failed};
                  {error, {error, _}} ->
                      {Vars, Gone, Failed};
                  {{ok, _}, {ok, Symbol, Access}} ->
                      {cell_hal_ads_vars:resolved(K, Symbol, Access, Vars), Gone, Failed};
                  {{ok, #{name := Name, type := Type}}, {error, Reason}} ->
                      {cell_hal_ads_vars:failed(K, Reason, Vars), Gone,
                       Failed ++ [{Name, Type, Reason}]}
              end
      end, {Vars0, [], []}, Results).

%% @doc What a caller is told of a resolved symbol.
-spec info(symbol()) -> cell_hal_ads_client:var_info().
info(#{name := Name, type := Type, size := Size, group := G, offset := O}) ->
    #{symbol => Name, plc_type => Type, size => Size, group => G, offset => O}.

%% @doc Why a variable of a call was not resolved.
-spec find_error(cell_hal_ads_vars:key(), [{cell_hal_ads_vars:key(), result()}],
                 #{cell_hal_ads_vars:key() => {binary(), cell_hal_ads_types:type()}}) -> term().
find_error(K, Found, Names) ->
    case lists:keyfind(K, 1, Found) of
        {_, {error, Reason}} ->
            Reason;
        _ ->
            {Name, _} = maps:get(K, Names),
            {not_resolved, Name}
    end.
