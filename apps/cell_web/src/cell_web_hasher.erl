%% @doc Computes password hashes one at a time.
%%
%% `crypto:pbkdf2_hmac/5' of OTP 25 runs on a normal scheduler for as long as the
%% hash takes (about 0.2 s at 600,000 iterations) and cannot be preempted. Run from
%% every login request at once it would hold every scheduler and stall the cell's
%% tasks; run from this one process, it holds at most one scheduler, and the cell's
%% processes run on the others. A queue longer than a few logins is refused
%% (`busy') rather than grown.
-module(cell_web_hasher).
-behaviour(gen_server).

-export([start_link/0, hash/1, verify/2]).
-export([init/1, handle_call/3, handle_cast/2]).

-define(MAX_QUEUE, 16).
-define(TIMEOUT, 30000).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc The stored form of a new password.
-spec hash(binary()) -> cell_web_password:hash().
hash(Password) ->
    call({hash, Password}).

%% @doc Whether a password matches a stored hash.
-spec verify(binary(), map()) -> boolean().
verify(Password, Stored) ->
    call({verify, Password, Stored}).

%% Without the panel running (a shell on a node whose panel refused to start), the
%% caller computes the hash itself: no other login can be competing then.
call(Request) ->
    case whereis(?MODULE) of
        undefined ->
            compute(Request);
        Pid ->
            case process_info(Pid, message_queue_len) of
                {message_queue_len, N} when N > ?MAX_QUEUE -> erlang:error(busy);
                _ -> gen_server:call(Pid, Request, ?TIMEOUT)
            end
    end.

-spec init([]) -> {ok, undefined}.
init([]) ->
    {ok, undefined}.

-spec handle_call(term(), gen_server:from(), undefined) -> {reply, term(), undefined}.
handle_call(Request, _From, State) ->
    {reply, compute(Request), State}.

compute({hash, Password}) -> cell_web_password:new(Password);
compute({verify, Password, Stored}) -> cell_web_password:verify(Password, Stored).

-spec handle_cast(term(), undefined) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).
