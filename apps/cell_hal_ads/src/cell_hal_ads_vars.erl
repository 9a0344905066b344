%% @doc The variables a connection has resolved, who uses them, and how they are
%% reached in the current connection. Pure: the client keeps this table and acts on
%% what its functions return.
%%
%% A variable is a PLC symbol name read as a point type (`{Name, Type}'). Processes
%% that resolved it are its users, counted per process; when the last one releases it
%% (or exits) the variable is unused and its handle can go back to the PLC. A handle
%% is valid for one connection and one symbol version only: after a program change
%% every variable in use is resolved again (a new connection is a new client, with a
%% table of its own).
%%
%% Names are looked up on every read of a group, so each spelling callers use is
%% remembered with its key (the case-folded key is not computed again).
%%
%% States of a variable: `pending' (declared, not resolved in this connection),
%% `ready' (symbol checked, handle or address known), `failed' (the PLC has no such
%% symbol, or not of that type; the reason says which).
-module(cell_hal_ads_vars).

-export([new/0, key/2, key_of/3, declare/3, find/2, use/3, unuse/3, drop_user/2, users/2,
         resolved/4, failed/3, reset/1, remove/2, keys/1, spellings/1, ready/2, state/2]).

-export_type([vars/0, key/0, access/0, var/0]).

-type key() :: {binary(), cell_hal_ads_types:type()}.

-type access() :: {handle, 0..16#FFFFFFFF} | {address, 0..16#FFFFFFFF, 0..16#FFFFFFFF}.

-type var() :: #{name := binary(),
                 type := cell_hal_ads_types:type(),
                 state := pending | ready | failed,
                 symbol => cell_hal_ads_codec:symbol(),
                 access => access(),
                 size => non_neg_integer(),
                 error => term(),
                 users := #{pid() => pos_integer()}}.

-opaque vars() :: #{vars := #{key() => var()},
                    spellings := #{{binary(), cell_hal_ads_types:type()} => key()}}.

%% @doc An empty table.
-spec new() -> vars().
new() ->
    #{vars => #{}, spellings => #{}}.

%% @doc The key of a variable: names are case-insensitive.
-spec key(binary(), cell_hal_ads_types:type()) -> key().
key(Name, Type) ->
    {cell_hal_ads_symbols:key(Name), Type}.

%% @doc The key of a variable as a caller spells it, remembered for a known
%% variable.
-spec key_of(binary(), cell_hal_ads_types:type(), vars()) -> key().
key_of(Name, Type, #{spellings := Spellings}) ->
    case maps:find({Name, Type}, Spellings) of
        {ok, K} -> K;
        error -> key(Name, Type)
    end.

%% @doc Declares a variable (pending) unless it is known; remembers the spelling.
-spec declare(binary(), cell_hal_ads_types:type(), vars()) -> vars().
declare(Name, Type, #{vars := Vs, spellings := Sp} = Vars) ->
    K = key(Name, Type),
    Vs1 = case maps:is_key(K, Vs) of
              true -> Vs;
              false -> Vs#{K => #{name => Name, type => Type, state => pending, users => #{}}}
          end,
    Vars#{vars := Vs1, spellings := Sp#{{Name, Type} => K}}.

%% @doc A variable.
-spec find(key(), vars()) -> {ok, var()} | error.
find(K, #{vars := Vs}) ->
    maps:find(K, Vs).

%% @doc One more use of a declared variable by `Pid'.
-spec use(key(), pid(), vars()) -> vars().
use(K, Pid, #{vars := Vs} = Vars) ->
    #{users := Users} = V = maps:get(K, Vs),
    Vars#{vars := Vs#{K := V#{users := maps:update_with(Pid, fun(N) -> N + 1 end, 1, Users)}}}.

%% @doc One use less by `Pid'; `unused' when nobody uses the variable any more.
-spec unuse(key(), pid(), vars()) -> {vars(), used | unused | unknown}.
unuse(K, Pid, #{vars := Vs} = Vars) ->
    case maps:find(K, Vs) of
        {ok, #{users := Users} = V} ->
            Users1 = case maps:find(Pid, Users) of
                         {ok, 1} -> maps:remove(Pid, Users);
                         {ok, N} -> Users#{Pid := N - 1};
                         error -> Users
                     end,
            {Vars#{vars := Vs#{K := V#{users := Users1}}}, used_or_not(Users1)};
        error ->
            {Vars, unknown}
    end.

%% @doc Forgets every use by a process (it exited); the keys now unused.
-spec drop_user(pid(), vars()) -> {vars(), [key()]}.
drop_user(Pid, #{vars := Vs} = Vars) ->
    {Vs1, Unused} =
        maps:fold(fun(K, #{users := Users} = V, {Acc, Unused}) ->
                          case maps:is_key(Pid, Users) of
                              true ->
                                  Users1 = maps:remove(Pid, Users),
                                  Unused1 = case used_or_not(Users1) of
                                                unused -> [K | Unused];
                                                used -> Unused
                                            end,
                                  {Acc#{K := V#{users := Users1}}, Unused1};
                              false ->
                                  {Acc, Unused}
                          end
                  end, {Vs, []}, Vs),
    {Vars#{vars := Vs1}, Unused}.

used_or_not(Users) when map_size(Users) =:= 0 -> unused;
used_or_not(_) -> used.

%% @doc How many uses a variable has.
-spec users(key(), vars()) -> non_neg_integer().
users(K, #{vars := Vs}) ->
    case maps:find(K, Vs) of
        {ok, #{users := Users}} -> lists:sum(maps:values(Users));
        error -> 0
    end.

%% @doc The variable was resolved in this connection.
-spec resolved(key(), cell_hal_ads_codec:symbol(), access(), vars()) -> vars().
resolved(K, Symbol, Access, #{vars := Vs} = Vars) ->
    V = maps:get(K, Vs),
    Vars#{vars := Vs#{K := maps:remove(error, V#{state => ready, symbol => Symbol,
                                                 access => Access,
                                                 size => cell_hal_ads_symbols:read_size(Symbol)})}}.

%% @doc The variable could not be resolved, for `Reason'.
-spec failed(key(), term(), vars()) -> vars().
failed(K, Reason, #{vars := Vs} = Vars) ->
    V = maps:get(K, Vs),
    Vars#{vars := Vs#{K := maps:without([access, size], V#{state => failed, error => Reason})}}.

%% @doc A new connection or program: every variable is pending again (handles of the
%% old one mean nothing now).
-spec reset(vars()) -> vars().
reset(#{vars := Vs} = Vars) ->
    Vars#{vars := maps:map(fun(_, V) -> maps:without([access, size, error], V#{state => pending})
                           end, Vs)}.

%% @doc Forgets a variable.
-spec remove(key(), vars()) -> vars().
remove(K, #{vars := Vs, spellings := Sp}) ->
    #{vars => maps:remove(K, Vs), spellings => maps:filter(fun(_, K1) -> K1 =/= K end, Sp)}.

%% @doc Every key.
-spec keys(vars()) -> [key()].
keys(#{vars := Vs}) ->
    maps:keys(Vs).

%% @doc Every spelling callers declared, with its variable's key.
-spec spellings(vars()) -> [{binary(), cell_hal_ads_types:type(), key()}].
spellings(#{spellings := Sp}) ->
    [{Name, Type, K} || {{Name, Type}, K} <- maps:to_list(Sp)].

%% @doc How to reach a variable now: its access, read size and type, or why not.
-spec ready(key(), vars()) ->
          {ok, access(), non_neg_integer(), cell_hal_ads_types:type()}
        | {error, term()}.
ready(K, #{vars := Vs}) ->
    case maps:find(K, Vs) of
        {ok, #{state := ready, access := A, size := S, type := T}} -> {ok, A, S, T};
        {ok, #{state := failed, error := Reason}} -> {error, Reason};
        {ok, #{state := pending, name := Name}} -> {error, {not_resolved, Name}};
        error -> {error, not_resolved}
    end.

%% @doc The state of a variable.
-spec state(key(), vars()) -> pending | ready | failed | unknown.
state(K, #{vars := Vs}) ->
    case maps:find(K, Vs) of
        {ok, #{state := S}} -> S;
        error -> unknown
    end.
