%% @doc The operator panel as a message client of the blocks whose settings say
%% `panel_messages': while at least one panel page is open (its websocket joined), the
%% panel counts as a connected client of each such block, receives the PLC's messages
%% and takes the operators' answers (Yes, No, a text).
%%
%% Pages join with {@link join/1} and receive `{cell_inspect_panel, Messages}' with the
%% whole list of messages waiting, every time it changes; a page that closes leaves
%% (monitored). When the last page has left for `panel_linger_ms' (the `cell_inspect'
%% variable, 5 s by default), the panel disconnects from its blocks, so a block whose
%% only client was the panel reports NoAvailableClients; a page that reloads, or
%% connects again after a login, comes back before that and the message stays.
-module(cell_inspect_panel).
-behaviour(gen_server).

-export([start_link/0, join/1, messages/0, answer/4, block/3, client_id/0]).
-export([init/1, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([message/0]).

-type message() :: #{block := binary(), ref := binary(), id := integer(), text := binary(),
                     kind := cell_inspect_status:message_kind(), max_length := pos_integer(),
                     since := integer()}.

-define(ID, <<"panel">>).

-record(state, {pages = #{} :: #{pid() => reference()},
                linger :: reference() | undefined,      %% the last page left: a timer
                blocks = #{} :: #{atom() => {pid(), reference()}},
                messages = #{} :: #{atom() => {cell_inspect_status:ref(), message()}}}).

%% @doc The panel's client id in every block.
-spec client_id() -> binary().
client_id() -> ?ID.

-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    gen_server:start_link({local, ?MODULE}, ?MODULE, [], []).

%% @doc A page joins: it receives the messages waiting now, and every change.
-spec join(pid()) -> {ok, [message()]} | {error, not_running}.
join(Page) ->
    try gen_server:call(?MODULE, {join, Page})
    catch exit:{noproc, _} -> {error, not_running}
    end.

%% @doc The messages waiting for an answer.
-spec messages() -> [message()].
messages() ->
    try gen_server:call(?MODULE, messages)
    catch exit:{noproc, _} -> []
    end.

%% @doc An operator answers a message: `Block' and `Ref' as the page got them
%% (matched against the messages waiting, never made into atoms).
-spec answer(binary(), binary(), cell_inspect_status:answer(), binary()) ->
          ok | {error, term()}.
answer(Block, Ref, Answer, Who) ->
    try gen_server:call(?MODULE, {answer, Block, Ref, Answer, Who}, 10000)
    catch exit:{noproc, _} -> {error, not_running}
    end.

%% @doc A block (re)started or changed its settings: whether the panel serves it.
-spec block(atom(), pid(), boolean()) -> ok.
block(Id, Pid, Enabled) ->
    gen_server:cast(?MODULE, {block, Id, Pid, Enabled}).

%%====================================================================
%% gen_server
%%====================================================================

%% @private
-spec init([]) -> {ok, #state{}}.
init([]) ->
    %% Blocks that run already (this process restarted) announce themselves again.
    _ = [Pid ! {cell_inspect, Id, panel_up, self()} || {Id, Pid} <- cell_inspect_block:running()],
    {ok, #state{}}.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({join, Page}, _From, #state{pages = Pages, linger = L} = S) ->
    S1 = case maps:is_key(Page, Pages) of
             true -> S;
             false when L =/= undefined ->
                 %% Back before the panel let go: nothing changes for the blocks.
                 _ = erlang:cancel_timer(L, [{async, true}, {info, false}]),
                 S#state{pages = Pages#{Page => monitor(process, Page)}, linger = undefined};
             false -> connectivity(S#state{pages = Pages#{Page => monitor(process, Page)}})
         end,
    {reply, {ok, list(S1)}, S1};
handle_call(messages, _From, S) ->
    {reply, list(S), S};
handle_call({answer, BlockBin, RefBin, Answer, Who}, _From, #state{messages = Ms} = S) ->
    case [{B, Ref} || {B, {Ref, #{ref := R}}} <- maps:to_list(Ms),
                      atom_to_binary(B) =:= BlockBin, R =:= RefBin] of
        [{B, Ref}] ->
            {Pid, _} = maps:get(B, S#state.blocks),
            case cell_inspect_block:answer(Pid, ?ID, Ref, Answer) of
                ok ->
                    cell_log:info(inspect, "~ts answered message ~b of ~s on the panel",
                                  [Who, maps:get(id, element(2, maps:get(B, Ms))), B]),
                    {reply, ok, changed(S#state{messages = maps:remove(B, Ms)})};
                {error, _} = E ->
                    {reply, E, S}
            end;
        [] ->
            {reply, {error, no_such_message}, S}
    end.

%% @private
-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({block, Id, Pid, Enabled}, #state{blocks = Bs} = S) ->
    S1 = case maps:find(Id, Bs) of
             {ok, {Old, Mon}} when Old =/= Pid orelse not Enabled ->
                 demonitor(Mon, [flush]),
                 forget(Id, S#state{blocks = maps:remove(Id, Bs)});
             _ -> S
         end,
    S2 = case Enabled andalso not maps:is_key(Id, S1#state.blocks) of
             true ->
                 Blocks = (S1#state.blocks)#{Id => {Pid, monitor(process, Pid)}},
                 tell(Id, Pid, S1),
                 S1#state{blocks = Blocks};
             false ->
                 %% Not served (or no longer): the block hears that the panel is away.
                 _ = Enabled orelse cell_inspect_block:client_state(Pid, ?ID, self(), disconnected),
                 S1
         end,
    {noreply, S2}.

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({cell_inspect, Id, show_message, #{ref := Ref, id := MId, text := T, kind := K,
                                               max_length := Max}}, S) ->
    M = #{block => atom_to_binary(Id), ref => ref_text(Ref), id => MId, text => T, kind => K,
          max_length => Max, since => os:system_time(millisecond)},
    {noreply, changed(S#state{messages = (S#state.messages)#{Id => {Ref, M}}})};
handle_info({cell_inspect, Id, withdraw_message, Ref}, #state{messages = Ms} = S) ->
    case Ms of
        #{Id := {Ref, _}} -> {noreply, changed(S#state{messages = maps:remove(Id, Ms)})};
        _ -> {noreply, S}
    end;
handle_info({cell_inspect, _, What, _}, S) when What =:= request_image; What =:= cancel ->
    {noreply, S};                                 %% the panel takes no images
handle_info({timeout, L, linger}, #state{linger = L} = S) ->
    {noreply, connectivity(S#state{linger = undefined})};
handle_info({timeout, _, linger}, S) ->
    {noreply, S};
handle_info({'DOWN', Mon, process, Pid, _}, #state{pages = Pages, blocks = Bs} = S) ->
    case Pages of
        #{Pid := Mon} when map_size(Pages) =:= 1 ->
            Ms = application:get_env(cell_inspect, panel_linger_ms, 5000),
            {noreply, S#state{pages = #{}, linger = erlang:start_timer(Ms, self(), linger)}};
        #{Pid := Mon} ->
            {noreply, S#state{pages = maps:remove(Pid, Pages)}};
        _ ->
            case [Id || {Id, {_, M}} <- maps:to_list(Bs), M =:= Mon] of
                [Id] -> {noreply, forget(Id, S#state{blocks = maps:remove(Id, Bs)})};
                [] -> {noreply, S}
            end
    end.

%% Connected while a page is open (or the last one left only a moment ago).
connectivity(#state{pages = Pages, blocks = Bs} = S) when map_size(Pages) =< 1 ->
    _ = [tell(Id, Pid, S) || {Id, {Pid, _}} <- maps:to_list(Bs)],
    case map_size(Pages) of
        0 -> changed(S#state{messages = #{}});
        _ -> S
    end;
connectivity(S) ->
    S.

tell(_Id, Pid, #state{pages = Pages, linger = L}) ->
    cell_inspect_block:client_state(Pid, ?ID, self(),
                                    case map_size(Pages) =:= 0 andalso L =:= undefined of
                                        true -> disconnected;
                                        false -> connected
                                    end).

forget(Id, #state{messages = Ms} = S) ->
    case maps:is_key(Id, Ms) of
        true -> changed(S#state{messages = maps:remove(Id, Ms)});
        false -> S
    end.

changed(#state{pages = Pages} = S) ->
    List = list(S),
    _ = [P ! {cell_inspect_panel, List} || P <- maps:keys(Pages)],
    S.

list(#state{messages = Ms}) ->
    lists:sort(fun(#{since := A}, #{since := B}) -> A =< B end, [M || {_, M} <- maps:values(Ms)]).

ref_text({Inc, N}) ->
    iolist_to_binary([integer_to_list(Inc), $., integer_to_list(N)]).
