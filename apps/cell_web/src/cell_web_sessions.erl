%% @doc Logins of the operator panel: sessions, their CSRF tokens, the websockets
%% that belong to them, and the brake on guessed passwords.
%%
%% A session is known by a random 32-byte id, which only the browser holds (in an
%% HttpOnly, SameSite=Strict cookie); the table keys sessions by the SHA-256 of the
%% id, so the table never holds a usable id. Each session has its own CSRF token,
%% which the page sends in the `x-csrf-token' header of every state-changing request.
%% A session ends at logout, after `idle_minutes' without a request, `session_hours'
%% after login (the `web' settings), or when its user's role or password changes or
%% the user is removed; its websockets are told and close.
%%
%% Failed logins are braked per account and address, and per address, with windows
%% that grow with every failure; the decisions are {@link cell_web_throttle}'s, the
%% state is held here.
%%
%% Requests read the table directly; this process alone writes it.
-module(cell_web_sessions).
-behaviour(gen_server).

-export([start_link/0, create/2, lookup/1, delete/1, attach/1, revalidate/0,
         login_allowed/2, login_failed/2, login_succeeded/2, count/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([session/0]).

-type session() :: #{user := binary(), role := cell_web_users:role(), csrf := binary(),
                     created := integer(), last_seen := integer(), addr := binary(),
                     stamp := binary(), demo_password := boolean()}.

-define(TAB, cell_web_session_table).
-define(SWEEP_MS, 60000).
-define(TOUCH_MS, 10000).

-record(state, {sockets = #{} :: #{pid() => {reference(), binary() | anonymous}},
                logins = cell_web_throttle:new() :: cell_web_throttle:state()}).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc A new session for a user who has just logged in (with a demo password, or
%% not): its id (for the cookie) and the session.
-spec create(cell_web_users:user(), #{addr := binary(), demo_password := boolean()}) ->
          {binary(), session()}.
create(User, Opts) ->
    gen_server:call(?MODULE, {create, User, Opts}).

%% @doc The session of an id, if it is still valid.
-spec lookup(binary()) -> {ok, session()} | {error, no_session}.
lookup(Id) when is_binary(Id), byte_size(Id) =:= 64 ->
    Key = key(Id),
    case ets:lookup(?TAB, Key) of
        [{Key, S}] ->
            Now = now_ms(),
            case valid(S, Now) of
                true ->
                    _ = Now - maps:get(last_seen, S) > ?TOUCH_MS
                        andalso gen_server:cast(?MODULE, {touch, Key, Now}),
                    {ok, S};
                false ->
                    gen_server:cast(?MODULE, {expire, Key}),
                    {error, no_session}
            end;
        [] ->
            {error, no_session}
    end;
lookup(_) ->
    {error, no_session}.

%% @doc Ends a session (logout).
-spec delete(binary()) -> ok.
delete(Id) when is_binary(Id) ->
    gen_server:call(?MODULE, {delete, key(Id)}).

%% @doc The calling websocket belongs to a session (by id) or to nobody
%% (`anonymous'); it receives `{cell_web_session, ended}' when that session ends, or
%% when anonymous viewing is switched off.
-spec attach(binary() | anonymous) -> ok.
attach(anonymous) ->
    gen_server:call(?MODULE, {attach, self(), anonymous});
attach(Id) when is_binary(Id) ->
    gen_server:call(?MODULE, {attach, self(), key(Id)}).

%% @doc Checks every session again (after a change to the users or the `web'
%% settings): those no longer valid end at once.
-spec revalidate() -> ok.
revalidate() ->
    gen_server:call(?MODULE, revalidate).

%% @doc Whether `Name' may try to log in from `Addr' now, or how many milliseconds
%% it must wait (see {@link cell_web_throttle}).
-spec login_allowed(binary(), binary()) -> ok | {wait, pos_integer()}.
login_allowed(Addr, Name) ->
    gen_server:call(?MODULE, {login_allowed, Addr, Name}).

%% @doc A login of `Name' from `Addr' was refused (wrong name or password).
-spec login_failed(binary(), binary()) -> ok.
login_failed(Addr, Name) ->
    gen_server:call(?MODULE, {login_failed, Addr, Name}).

%% @doc `Name' logged in from `Addr'.
-spec login_succeeded(binary(), binary()) -> ok.
login_succeeded(Addr, Name) ->
    gen_server:call(?MODULE, {login_succeeded, Addr, Name}).

%% @doc How many sessions there are.
-spec count() -> non_neg_integer().
count() ->
    ets:info(?TAB, size).

key(Id) -> crypto:hash(sha256, Id).

now_ms() -> erlang:monotonic_time(millisecond).

valid(#{created := C, last_seen := L, user := Name, stamp := Stamp}, Now) ->
    #{idle_minutes := Idle, session_hours := Hours} =
        cell_web_settings:current(cell_web_settings),
    Now - L =< Idle * 60000 andalso Now - C =< Hours * 3600000
        andalso case cell_web_users:find(Name) of
                    {ok, U} -> cell_web_users:stamp(U) =:= Stamp;
                    {error, not_found} -> false
                end.

-spec init([]) -> {ok, #state{}}.
init([]) ->
    ?TAB = ets:new(?TAB, [named_table, protected, {read_concurrency, true}]),
    _ = erlang:send_after(?SWEEP_MS, self(), sweep),
    {ok, #state{}}.

-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({create, #{name := Name, role := Role} = User,
             #{addr := Addr, demo_password := Demo}}, _From, State) ->
    Id = token(),
    Now = now_ms(),
    S = #{user => Name, role => Role, csrf => token(), created => Now, last_seen => Now,
          addr => Addr, stamp => cell_web_users:stamp(User), demo_password => Demo},
    true = ets:insert(?TAB, {key(Id), S}),
    {reply, {Id, S}, State};
handle_call({delete, Key}, _From, State) ->
    {reply, ok, end_session(Key, State)};
handle_call({attach, Pid, Owner}, _From, #state{sockets = Socks} = State) ->
    Ref = monitor(process, Pid),
    {reply, ok, State#state{sockets = Socks#{Pid => {Ref, Owner}}}};
handle_call(revalidate, _From, State) ->
    {reply, ok, sweep(State)};
handle_call({login_allowed, Addr, Name}, _From, #state{logins = L} = State) ->
    {reply, cell_web_throttle:check(Addr, Name, now_ms(), L), State};
handle_call({login_failed, Addr, Name}, _From, #state{logins = L} = State) ->
    {reply, ok, State#state{logins = cell_web_throttle:failed(Addr, Name, now_ms(), L)}};
handle_call({login_succeeded, Addr, Name}, _From, #state{logins = L} = State) ->
    {reply, ok, State#state{logins = cell_web_throttle:succeeded(Addr, Name, now_ms(), L)}}.

-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({touch, Key, Now}, State) ->
    _ = case ets:lookup(?TAB, Key) of
            [{Key, S}] -> ets:insert(?TAB, {Key, S#{last_seen := max(Now, maps:get(last_seen, S))}});
            [] -> true
        end,
    {noreply, State};
handle_cast({expire, Key}, State) ->
    {noreply, end_session(Key, State)}.

-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info(sweep, #state{logins = L} = State) ->
    _ = erlang:send_after(?SWEEP_MS, self(), sweep),
    {noreply, sweep(State#state{logins = cell_web_throttle:sweep(now_ms(), L)})};
handle_info({'DOWN', _Ref, process, Pid, _}, #state{sockets = Socks} = State) ->
    {noreply, State#state{sockets = maps:remove(Pid, Socks)}}.

%% Ends every session no longer valid, and the anonymous websockets when anonymous
%% viewing is off.
sweep(State0) ->
    Now = now_ms(),
    State = lists:foldl(fun({Key, S}, St) ->
                                case valid(S, Now) of
                                    true -> St;
                                    false -> end_session(Key, St)
                                end
                        end, State0, ets:tab2list(?TAB)),
    case cell_web_settings:get(anonymous_view) of
        true -> State;
        false -> tell(anonymous, State)
    end.

end_session(Key, State) ->
    true = ets:delete(?TAB, Key),
    tell(Key, State).

tell(Owner, #state{sockets = Socks} = State) ->
    Gone = [begin demonitor(Ref, [flush]), Pid ! {cell_web_session, ended}, Pid end
            || {Pid, {Ref, O}} <- maps:to_list(Socks), O =:= Owner],
    State#state{sockets = maps:without(Gone, Socks)}.

%% 32 random bytes as 64 hex digits: safe in a cookie and a header as they are.
token() ->
    string:lowercase(binary:encode_hex(crypto:strong_rand_bytes(32))).
