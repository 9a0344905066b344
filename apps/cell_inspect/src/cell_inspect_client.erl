%% @doc Camera clients (seed 004's mobile devices): the behaviour a client module
%% implements, and the process that runs one client for its block.
%%
%% A client belongs to one block (its settings are under that block). It is connected
%% or not (a phone out of reach is not); while connected the block may ask it:
%% <ul>
%% <li>`request_image(#{ref, point, serial})' — take an image for this inspection; the
%%   client answers later with the event `{image, Ref, Image}';</li>
%% <li>`cancel(Ref)' — the request is over (canceled by the PLC, or another camera was
%%   first);</li>
%% <li>`show_message(#{ref, id, text, kind, max_length})' — show a message of the PLC;
%%   the user's answer is the event `{answer, Ref, yes | no | {text, Binary}}' (a text
%%   of at most `max_length' characters the PLC can hold);</li>
%% <li>`withdraw_message(Ref)' — the message was answered elsewhere or replaced.</li>
%% </ul>
%% A client module reports what happens as events from its callbacks: `connected',
%% `disconnected', `{image, Ref, Image}', `{answer, Ref, Answer}'. The process tells
%% its block; when the block restarts it finds its clients again (the block announces
%% itself to them). Built in: `sim' ({@link cell_inspect_camera_sim}); a cell adds its
%% own types under the `cell_inspect' variable `client_types'.
-module(cell_inspect_client).
-behaviour(gen_server).

-export([start_link/1, child_spec/1, call/2, call/3, module/1]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-export_type([spec/0, event/0]).

-type spec() :: #{id := binary(), block := atom(), module := module(), opts := map()}.
-type event() :: connected | disconnected
               | {image, cell_inspect_status:ref(), cell_inspect_processing:image()}
               | {answer, cell_inspect_status:ref(), cell_inspect_status:answer()}.

-callback init(Id :: binary(), Opts :: map()) -> {ok, Connected :: boolean(), State :: term()}.
-callback request_image(#{ref := cell_inspect_status:ref(), point := binary(),
                          serial := binary()}, State :: term()) ->
    {ok, [event()], term()}.
-callback cancel(cell_inspect_status:ref(), State :: term()) -> {ok, [event()], term()}.
-callback show_message(#{ref := cell_inspect_status:ref(), id := integer(), text := binary(),
                         kind := cell_inspect_status:message_kind(),
                         max_length := pos_integer()}, State :: term()) ->
    {ok, [event()], term()}.
-callback withdraw_message(cell_inspect_status:ref(), State :: term()) -> {ok, [event()], term()}.
-callback handle_call(Request :: term(), State :: term()) -> {reply, term(), [event()], term()}.
-callback handle_info(Info :: term(), State :: term()) -> {ok, [event()], term()}.

-record(state, {id :: binary(),
                block :: atom(),
                module :: module(),
                ms :: term(),
                connected = false :: boolean(),
                block_pid :: pid() | undefined,
                monitor :: reference() | undefined}).

%% @doc The module of a client type named in the settings (matched against the known
%% names, never made into an atom).
-spec module(binary()) -> {ok, module()} | error.
module(Type) ->
    Types = maps:merge(#{<<"sim">> => cell_inspect_camera_sim},
                       maps:fold(fun(K, V, Acc) when is_atom(K) -> Acc#{atom_to_binary(K) => V};
                                    (K, V, Acc) when is_binary(K) -> Acc#{K => V};
                                    (_, _, Acc) -> Acc
                                 end, #{},
                                 application:get_env(cell_inspect, client_types, #{}))),
    maps:find(Type, Types).

-spec start_link(spec()) -> {ok, pid()} | {error, term()}.
start_link(Spec) ->
    gen_server:start_link(?MODULE, Spec, []).

%% @doc A child spec keyed by the client's id.
-spec child_spec(spec()) -> supervisor:child_spec().
child_spec(#{id := Id} = Spec) ->
    #{id => {client, Id}, start => {?MODULE, start_link, [Spec]}, restart => transient}.

%% @doc A request to the client module (a simulation's controls, a device's status).
-spec call(binary(), term()) -> term().
call(Id, Request) ->
    call(Id, Request, 5000).

-spec call(binary(), term(), timeout()) -> term().
call(Id, Request, Timeout) ->
    case cell_inspect_client_sup:whereis(Id) of
        undefined -> {error, no_such_client};
        Pid -> gen_server:call(Pid, {client, Request}, Timeout)
    end.

%%====================================================================
%% gen_server
%%====================================================================

%% @private
-spec init(spec()) -> {ok, #state{}, {continue, find_block}}.
init(#{id := Id, block := Block, module := Mod, opts := Opts}) ->
    {ok, Connected, MS} = Mod:init(Id, Opts),
    {ok, #state{id = Id, block = Block, module = Mod, ms = MS, connected = Connected},
     {continue, find_block}}.

%% @private
-spec handle_continue(find_block, #state{}) -> {noreply, #state{}}.
handle_continue(find_block, #state{block = Block} = S) ->
    case cell_inspect_block:whereis(Block) of
        undefined -> {noreply, S};              %% it announces itself when it starts
        Pid -> {noreply, attach(Pid, S)}
    end.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({client, Request}, _From, #state{module = Mod, ms = MS} = S) ->
    {reply, Reply, Events, MS1} = Mod:handle_call(Request, MS),
    {reply, Reply, events(Events, S#state{ms = MS1})}.

%% @private
-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _S) ->
    erlang:error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_inspect, Block, block_up, Pid}, #state{block = Block} = S) ->
    {noreply, attach(Pid, S)};
handle_info({cell_inspect, Block, What, Arg}, #state{block = Block, module = Mod, ms = MS} = S)
  when What =:= request_image; What =:= cancel; What =:= show_message;
       What =:= withdraw_message ->
    {ok, Events, MS1} = Mod:What(Arg, MS),
    {noreply, events(Events, S#state{ms = MS1})};
handle_info({'DOWN', Ref, process, _, _}, #state{monitor = Ref} = S) ->
    %% The block is gone; it announces itself again when it restarts.
    {noreply, S#state{block_pid = undefined, monitor = undefined}};
handle_info(Info, #state{module = Mod, ms = MS} = S) ->
    {ok, Events, MS1} = Mod:handle_info(Info, MS),
    {noreply, events(Events, S#state{ms = MS1})}.

%% @private
-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, #state{block_pid = Pid, id = Id}) when is_pid(Pid) ->
    cell_inspect_block:client_state(Pid, Id, self(), disconnected);
terminate(_Reason, _S) ->
    ok.

%% Tells the block who we are and whether we are connected.
attach(Pid, #state{monitor = Old, id = Id, connected = C} = S) ->
    _ = Old =/= undefined andalso demonitor(Old, [flush]),
    ok = cell_inspect_block:client_state(Pid, Id, self(), case C of
                                                             true -> connected;
                                                             false -> disconnected
                                                         end),
    S#state{block_pid = Pid, monitor = monitor(process, Pid)}.

events([], S) ->
    S;
events([connected | Rest], #state{connected = true} = S) ->
    events(Rest, S);
events([connected | Rest], #state{block_pid = Pid, id = Id} = S) ->
    _ = is_pid(Pid) andalso cell_inspect_block:client_state(Pid, Id, self(), connected),
    events(Rest, S#state{connected = true});
events([disconnected | Rest], #state{connected = false} = S) ->
    events(Rest, S);
events([disconnected | Rest], #state{block_pid = Pid, id = Id} = S) ->
    _ = is_pid(Pid) andalso cell_inspect_block:client_state(Pid, Id, self(), disconnected),
    events(Rest, S#state{connected = false});
events([{image, Ref, Image} | Rest], #state{block_pid = Pid, id = Id} = S) ->
    _ = is_pid(Pid) andalso cell_inspect_block:image(Pid, Id, Ref, Image),
    events(Rest, S);
events([{answer, Ref, Answer} | Rest], #state{block_pid = Pid, id = Id} = S) ->
    Result = case is_pid(Pid) of
                 true -> cell_inspect_block:answer(Pid, Id, Ref, Answer);
                 false -> {error, no_block}
             end,
    %% A refused answer goes back to the client module, as a device would be told.
    _ = Result =:= ok orelse (self() ! {answer_refused, Ref, element(2, Result)}),
    events(Rest, S).
