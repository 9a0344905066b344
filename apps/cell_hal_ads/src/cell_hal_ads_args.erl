%% @doc The arguments of the ADS connection's calls ({@link cell_hal_ads_client}),
%% checked in the caller before anything is sent: a bad argument never reaches the
%% connection's process. Pure.
%%
%% Variables to resolve or subscribe to are checked in full (a valid symbol name, a
%% known type); variables to read, write or release only for their shape (what was not
%% resolved is answered `{not_resolved, Name}' by the connection), which keeps a group
%% read cheap.
-module(cell_hal_ads_args).

-export([request/1, vars/1, shapes/1, pairs/1, refs/1, subs/1, sub_opts/1, items/2]).

-type error() :: {error, {bad_variable | bad_argument | bad_sub_opts, term()}}.

%% The largest time the PLC takes, in microseconds (it counts in 100 ns, 32 bits).
-define(MAX_US, (16#FFFFFFFF div 10)).

%% @doc Whether a plain ADS command is well formed.
-spec request(term()) -> boolean().
request(read_device_info) -> true;
request(read_state) -> true;
request({read, G, O, L}) -> u32s([G, O, L]);
request({write, G, O, Data}) -> u32s([G, O]) andalso is_iodata(Data);
request({read_write, G, O, L, Data}) -> u32s([G, O, L]) andalso is_iodata(Data);
request({write_control, State, Dev, Data}) ->
    cell_hal_ads_codec:is_ads_state(State) andalso is_integer(Dev) andalso Dev >= 0
        andalso Dev =< 16#FFFF andalso is_iodata(Data);
request(_) -> false.

%% @doc Variables to resolve: `{Name, Type}' with a valid name and a known type.
-spec vars(term()) -> ok | error().
vars(Vars) ->
    check_list(Vars, fun is_var/1).

%% @doc Variables to read or release: `{Name, _}' with a binary name.
-spec shapes(term()) -> ok | error().
shapes(Vars) ->
    check_list(Vars, fun({Name, _}) -> is_binary(Name);
                        (_) -> false
                     end).

%% @doc Variables with values to write, each variable checked as by {@link shapes/1}.
-spec pairs(term()) -> ok | error().
pairs(Pairs) when is_list(Pairs) ->
    case lists:all(fun({_, _}) -> true; (_) -> false end, Pairs) of
        true -> shapes([V || {V, _} <- Pairs]);
        false -> {error, {bad_argument, Pairs}}
    end;
pairs(Pairs) ->
    {error, {bad_argument, Pairs}}.

%% @doc Subscription references to end.
-spec refs(term()) -> ok | error().
refs(Refs) when is_list(Refs) ->
    case lists:all(fun is_reference/1, Refs) of
        true -> ok;
        false -> {error, {bad_argument, Refs}}
    end;
refs(Refs) ->
    {error, {bad_argument, Refs}}.

%% @doc Subscriptions `{Var, Opts}': each variable as by {@link vars/1}, the options
%% turned into the PLC's units (100 ns).
-spec subs(term()) ->
          {ok, [{{binary(), cell_hal_ads_types:type()}, cell_hal_ads_subs:note_opts()}]}
        | error().
subs(Subs) when is_list(Subs) ->
    Checked = [{V, sub_opts(O)} || {V, O} <- Subs, is_var(V), is_map(O)],
    case length(Checked) =:= length(Subs) andalso [B || {_, {error, _} = B} <- Checked] of
        false -> {error, {bad_argument, Subs}};
        [] -> {ok, Checked};
        [{error, Bad} | _] -> {error, Bad}
    end;
subs(Subs) ->
    {error, {bad_argument, Subs}}.

%% @doc A subscription's options in microseconds, in the PLC's units.
-spec sub_opts(map()) -> cell_hal_ads_subs:note_opts() | {error, {bad_sub_opts, map()}}.
sub_opts(O) ->
    Mode = maps:get(mode, O, on_change),
    Cycle = maps:get(cycle_us, O, 10000),
    Delay = maps:get(max_delay_us, O, 0),
    Valid = (Mode =:= on_change orelse Mode =:= cyclic) andalso
        is_integer(Cycle) andalso Cycle >= 0 andalso Cycle =< ?MAX_US andalso
        is_integer(Delay) andalso Delay >= 0 andalso Delay =< ?MAX_US andalso
        maps:size(maps:without([mode, cycle_us, max_delay_us], O)) =:= 0,
    case Valid of
        true -> #{mode => Mode, cycle => Cycle * 10, max_delay => Delay * 10};
        false -> {error, {bad_sub_opts, O}}
    end.

%% @doc The items of a raw sum command: `{G, O, L}' reads, `{G, O, Data}' writes,
%% `{G, O, L, Data}' read-writes.
-spec items(reads | writes | read_writes, term()) -> boolean().
items(reads, Items) ->
    is_list(Items) andalso lists:all(fun({G, O, L}) -> u32s([G, O, L]); (_) -> false end, Items);
items(writes, Items) ->
    is_list(Items) andalso
        lists:all(fun({G, O, Data}) -> u32s([G, O]) andalso is_iodata(Data);
                     (_) -> false
                  end, Items);
items(read_writes, Items) ->
    is_list(Items) andalso
        lists:all(fun({G, O, L, Data}) -> u32s([G, O, L]) andalso is_iodata(Data);
                     (_) -> false
                  end, Items).

check_list(Vars, Valid) when is_list(Vars) ->
    case [V || V <- Vars, not Valid(V)] of
        [] -> ok;
        [Bad | _] -> {error, {bad_variable, Bad}}
    end;
check_list(Vars, _) ->
    {error, {bad_argument, Vars}}.

is_var({Name, Type}) ->
    cell_hal_ads_symbols:check_name(Name) =:= ok andalso cell_hal_ads_types:is_type(Type);
is_var(_) ->
    false.

u32s(Ns) -> lists:all(fun(N) -> is_integer(N) andalso N >= 0 andalso N =< 16#FFFFFFFF end, Ns).

is_iodata(Data) ->
    try iolist_size(Data) of
        _ -> true
    catch
        error:badarg -> false
    end.
