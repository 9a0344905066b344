%% @doc The subscriptions of an ADS connection ({@link cell_hal_ads_client}): who
%% subscribed to which variable, the PLC's notification handle that serves each one on
%% the present connection, and the notification on the PLC's symbol version. Pure: the
%% connection's process sends what this module decides.
%%
%% A subscription outlives the notification that serves it: when the PLC program
%% changes, its notification is forgotten ({@link refresh/1}) and the connection adds
%% a new one for it ({@link attach/3}). The subscriptions end with the connection (a
%% client is one connection).
%% Device notifications ({@link samples/2}) are decoded here into one message per
%% subscriber and frame, samples in the PLC's order.
-module(cell_hal_ads_subs).

-export([new/0, count/1, to_list/1, add/4, attach/3, take/2, owned/3, of_pid/2,
         watch_version/2, refresh/1, notes/1, note_request/2, samples/2]).

-export_type([subs/0, sub/0, note_opts/0, delivery/0]).

-type u32() :: 0..16#FFFFFFFF.

%% A notification's options in the PLC's units (100 ns).
-type note_opts() :: #{mode := on_change | cyclic, cycle := non_neg_integer(),
                       max_delay := non_neg_integer()}.

-type sub() :: #{pid := pid(), var := {binary(), cell_hal_ads_types:type()},
                 key := cell_hal_ads_vars:key(), opts := note_opts(), note => u32()}.

-record(subs, {subs = #{} :: #{reference() => sub()},
               notes = #{} :: #{u32() => reference() | symbol_version}}).

-opaque subs() :: #subs{}.

%% The samples of one notification frame for one subscription.
-type delivery() :: {pid(), reference(), [{integer(), cell_hal_ads_types:value()}]}.

%% @doc No subscriptions.
-spec new() -> subs().
new() ->
    #subs{}.

%% @doc How many subscriptions there are.
-spec count(subs()) -> non_neg_integer().
count(#subs{subs = S}) ->
    map_size(S).

%% @doc Every subscription.
-spec to_list(subs()) -> [{reference(), sub()}].
to_list(#subs{subs = S}) ->
    maps:to_list(S).

%% @doc A subscription the PLC serves with notification `Note'.
-spec add(reference(), sub(), u32(), subs()) -> subs().
add(Ref, Sub, Note, #subs{subs = S, notes = N} = T) ->
    T#subs{subs = S#{Ref => Sub#{note => Note}}, notes = N#{Note => Ref}}.

%% @doc A subscription served again, by a new notification; `gone' if it ended in the
%% meantime (the new notification is then the caller's to delete).
-spec attach(reference(), u32(), subs()) -> {ok, subs()} | gone.
attach(Ref, Note, #subs{subs = S} = T) ->
    case maps:find(Ref, S) of
        {ok, Sub} -> {ok, add(Ref, Sub, Note, T)};
        error -> gone
    end.

%% @doc Ends a subscription: it, and its notification to delete if it had one.
-spec take(reference(), subs()) -> {sub(), [u32()], subs()}.
take(Ref, #subs{subs = S, notes = N} = T) ->
    {Sub, S1} = maps:take(Ref, S),
    case Sub of
        #{note := Note} -> {Sub, [Note], T#subs{subs = S1, notes = maps:remove(Note, N)}};
        _ -> {Sub, [], T#subs{subs = S1}}
    end.

%% @doc The references of `Refs' that are subscriptions of `Pid'.
-spec owned([reference()], pid(), subs()) -> [reference()].
owned(Refs, Pid, #subs{subs = S}) ->
    [R || R <- Refs, case maps:find(R, S) of
                         {ok, #{pid := Pid}} -> true;
                         _ -> false
                     end].

%% @doc Every subscription of `Pid'.
-spec of_pid(pid(), subs()) -> [reference()].
of_pid(Pid, #subs{subs = S}) ->
    [R || {R, #{pid := P}} <- maps:to_list(S), P =:= Pid].

%% @doc The PLC tells of changes of its symbol version through `Note'.
-spec watch_version(u32(), subs()) -> subs().
watch_version(Note, #subs{notes = N} = T) ->
    T#subs{notes = N#{Note => symbol_version}}.

%% @doc The PLC program changed: the subscriptions' notifications (to delete) are
%% forgotten, the one on the symbol version stays.
-spec refresh(subs()) -> {[u32()], subs()}.
refresh(#subs{subs = S, notes = N}) ->
    {Gone, Kept} = lists:partition(fun({_, V}) -> is_reference(V) end, maps:to_list(N)),
    {[Note || {Note, _} <- Gone],
     #subs{subs = maps:map(fun(_, Sub) -> maps:remove(note, Sub) end, S),
           notes = maps:from_list(Kept)}}.

%% @doc Every notification of the present connection.
-spec notes(subs()) -> [u32()].
notes(#subs{notes = N}) ->
    maps:keys(N).

%% @doc The request that adds a notification for a subscription, its variable being
%% resolved in `Vars'.
-spec note_request(sub(), cell_hal_ads_vars:vars()) -> cell_hal_ads_codec:request().
note_request(#{key := K, opts := #{mode := Mode, cycle := Cycle, max_delay := Delay}}, Vars) ->
    {ok, Access, Size, _} = cell_hal_ads_vars:ready(K, Vars),
    {G, O, _} = cell_hal_ads_batch:item(Access, Size),
    {add_notification, G, O, Size, Mode, Delay, Cycle}.

%% @doc A device notification's payload: the samples for each subscription (times in
%% nanoseconds since the Unix epoch), the symbol versions it told of, and the samples
%% dropped because their value could not be read (`{Name, Reason}'). A notification
%% deleted a moment ago may still send once: its samples are ignored.
-spec samples(binary(), subs()) ->
          {ok, [delivery()], [byte()], [{binary(), term()}]} | {error, term()}.
samples(Payload, #subs{} = T) ->
    case cell_hal_ads_codec:decode_notification(Payload) of
        {ok, Stamps} ->
            {PerRef, Versions, Dropped} =
                lists:foldl(fun({Time, Samples}, Acc) ->
                                    Ns = cell_hal_ads_codec:filetime_to_ns(Time),
                                    lists:foldl(fun(S, Acc1) -> sample(Ns, S, Acc1, T) end,
                                                Acc, Samples)
                            end, {#{}, [], []}, Stamps),
            Deliveries = [{maps:get(pid, maps:get(Ref, T#subs.subs)), Ref, lists:reverse(Rev)}
                          || {Ref, Rev} <- maps:to_list(PerRef)],
            {ok, Deliveries, lists:reverse(Versions), lists:reverse(Dropped)};
        {error, _} = E ->
            E
    end.

sample(Ns, {Note, Bin}, {PerRef, Versions, Dropped} = Acc, #subs{subs = S, notes = N}) ->
    case maps:find(Note, N) of
        {ok, symbol_version} ->
            case Bin of
                <<V, _/binary>> -> {PerRef, [V | Versions], Dropped};
                _ -> Acc
            end;
        {ok, Ref} ->
            #{key := {_, Type}, var := {Name, _}} = maps:get(Ref, S),
            case cell_hal_ads_types:decode(Type, Bin) of
                {ok, Value} ->
                    {maps:update_with(Ref, fun(L) -> [{Ns, Value} | L] end, [{Ns, Value}],
                                      PerRef), Versions, Dropped};
                {error, Reason} ->
                    {PerRef, Versions, [{Name, Reason} | Dropped]}
            end;
        error ->
            Acc
    end.
