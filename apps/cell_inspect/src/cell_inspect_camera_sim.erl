%% @doc A simulated camera client: it takes an image when asked (at once, after
%% `delay_ms', or when told to in `manual' mode), of a scene the simulated processing
%% ({@link cell_inspect_sim_ipm}) reads as PASS or FAIL, and shows messages until it is
%% told an answer. For demo cells without cameras, and for tests.
%%
%% Options from the client's settings: `delay_ms' (0), `manual' (false), `scene'
%% (`<<"PASS">>'; `<<"FAIL">>', `<<"PASS OCR 12">>', anything else is unreadable),
%% `fail_rate' (0.0: the chance that an image shows a bad part, read FAIL whatever the
%% scene; a demo's bad parts now and then). Set
%% with {@link set/2} only: `image_data' (true: the image travels with the answer;
%% false: the camera keeps it and sends a reference).
%%
%% Controls, through {@link cell_inspect_client:call/2} or the functions below:
%% `connect', `disconnect', `shoot' (manual mode), `answer', `set' (options),
%% `fail_next' (the next image shows a bad part, once),
%% `pending', `subscribe' (the caller receives `{cell_inspect_camera_sim, Id, Event}'
%% for every request, cancel, message and withdrawal).
-module(cell_inspect_camera_sim).
-behaviour(cell_inspect_client).

-export([connect/1, disconnect/1, shoot/1, answer/2, set/2, pending/1, subscribe/1,
         fail_next/1]).
-export([init/2, request_image/2, cancel/2, show_message/2, withdraw_message/2,
         handle_call/2, handle_info/2]).

-record(sim, {id :: binary(),
              opts :: map(),
              connected :: boolean(),
              requests = [] :: [map()],
              messages = [] :: [map()],
              subscribers = [] :: [pid()],
              shots = 0 :: non_neg_integer(),
              fail_next = false :: boolean(),
              rand :: rand:state()}).

%%====================================================================
%% Controls
%%====================================================================

-spec connect(binary()) -> ok | {error, term()}.
connect(Id) -> cell_inspect_client:call(Id, connect).

-spec disconnect(binary()) -> ok | {error, term()}.
disconnect(Id) -> cell_inspect_client:call(Id, disconnect).

%% @doc Takes the image for the oldest request (manual mode).
-spec shoot(binary()) -> ok | {error, term()}.
shoot(Id) -> cell_inspect_client:call(Id, shoot).

%% @doc The user answers the message shown (`yes', `no', `{text, T}').
-spec answer(binary(), cell_inspect_status:answer()) -> ok | {error, term()}.
answer(Id, A) -> cell_inspect_client:call(Id, {answer, A}).

%% @doc Changes options (`scene', `delay_ms', `manual', `image_data').
-spec set(binary(), map()) -> ok | {error, term()}.
set(Id, Opts) -> cell_inspect_client:call(Id, {set, Opts}).

%% @doc The next image shows a bad part (its scene read FAIL), once.
-spec fail_next(binary()) -> ok | {error, term()}.
fail_next(Id) -> cell_inspect_client:call(Id, fail_next).

-spec pending(binary()) -> #{requests := [map()], messages := [map()]} | {error, term()}.
pending(Id) -> cell_inspect_client:call(Id, pending).

%% @doc The caller receives `{cell_inspect_camera_sim, Id, Event}' from now on.
-spec subscribe(binary()) -> ok | {error, term()}.
subscribe(Id) -> cell_inspect_client:call(Id, {subscribe, self()}).

%%====================================================================
%% cell_inspect_client
%%====================================================================

-spec init(binary(), map()) -> {ok, boolean(), #sim{}}.
init(Id, Opts) ->
    O = maps:merge(#{delay_ms => 0, manual => false, scene => <<"PASS">>, image_data => true,
                     fail_rate => 0.0}, Opts),
    {ok, true, #sim{id = Id, opts = O, connected = true, rand = rand:seed_s(exsss)}}.

-spec request_image(map(), #sim{}) -> {ok, [cell_inspect_client:event()], #sim{}}.
request_image(Req, #sim{opts = O} = S) ->
    S1 = notify({request, Req}, S#sim{requests = S#sim.requests ++ [Req]}),
    case O of
        #{manual := true} -> {ok, [], S1};
        #{delay_ms := 0} -> take(Req, S1);
        #{delay_ms := Ms} ->
            _ = erlang:send_after(Ms, self(), {shoot, maps:get(ref, Req)}),
            {ok, [], S1}
    end.

-spec cancel(term(), #sim{}) -> {ok, [], #sim{}}.
cancel(Ref, #sim{requests = Rs} = S) ->
    {ok, [], notify({cancel, Ref}, S#sim{requests = [R || #{ref := X} = R <- Rs, X =/= Ref]})}.

-spec show_message(map(), #sim{}) -> {ok, [], #sim{}}.
show_message(Msg, #sim{messages = Ms} = S) ->
    {ok, [], notify({message, Msg}, S#sim{messages = Ms ++ [Msg]})}.

-spec withdraw_message(term(), #sim{}) -> {ok, [], #sim{}}.
withdraw_message(Ref, #sim{messages = Ms} = S) ->
    {ok, [], notify({withdrawn, Ref},
                    S#sim{messages = [M || #{ref := X} = M <- Ms, X =/= Ref]})}.

-spec handle_call(term(), #sim{}) -> {reply, term(), [cell_inspect_client:event()], #sim{}}.
handle_call(connect, S) ->
    {reply, ok, [connected], S#sim{connected = true}};
handle_call(disconnect, S) ->
    %% A device that leaves forgets what it was asked.
    {reply, ok, [disconnected], S#sim{connected = false, requests = [], messages = []}};
handle_call(shoot, #sim{requests = [Req | _]} = S) ->
    {ok, Events, S1} = take(Req, S),
    {reply, ok, Events, S1};
handle_call(shoot, S) ->
    {reply, {error, nothing_requested}, [], S};
handle_call({answer, A}, #sim{messages = [#{ref := Ref} | Rest]} = S) ->
    {reply, ok, [{answer, Ref, A}], S#sim{messages = Rest}};
handle_call({answer, _}, S) ->
    {reply, {error, no_message}, [], S};
handle_call({set, Opts}, #sim{opts = O} = S) when is_map(Opts) ->
    {reply, ok, [], S#sim{opts = maps:merge(O, Opts)}};
handle_call(fail_next, S) ->
    {reply, ok, [], S#sim{fail_next = true}};
handle_call(pending, #sim{requests = Rs, messages = Ms} = S) ->
    {reply, #{requests => Rs, messages => Ms}, [], S};
handle_call({subscribe, Pid}, #sim{subscribers = Subs} = S) ->
    {reply, ok, [], S#sim{subscribers = [Pid | Subs]}}.

-spec handle_info(term(), #sim{}) -> {ok, [cell_inspect_client:event()], #sim{}}.
handle_info({shoot, Ref}, #sim{requests = Rs} = S) ->
    case [R || #{ref := X} = R <- Rs, X =:= Ref] of
        [Req] -> take(Req, S);
        [] -> {ok, [], S}
    end;
handle_info({answer_refused, Ref, Why}, S) ->
    {ok, [], notify({answer_refused, Ref, Why}, S)}.

%% The image of the scene for a request.
take(#{ref := Ref}, #sim{opts = O, requests = Rs, shots = N, id = Id} = S0) ->
    {Bad, Rand} = rand:uniform_s(S0#sim.rand),
    Scene = case S0#sim.fail_next orelse Bad < maps:get(fail_rate, O) of
                true -> <<"FAIL">>;
                false -> maps:get(scene, O)
            end,
    S = S0#sim{fail_next = false, rand = Rand},
    Image = case maps:get(image_data, O) of
                true -> #{data => cell_inspect_sim_ipm:image(Scene, 32, 24),
                          format => <<"pgm">>};
                false -> #{ref => iolist_to_binary([Id, ":/images/", integer_to_list(N + 1),
                                                    ".pgm"])}
            end,
    S1 = S#sim{requests = [R || #{ref := X} = R <- Rs, X =/= Ref], shots = N + 1},
    {ok, [{image, Ref, Image}], notify({image_sent, Ref}, S1)}.

notify(Event, #sim{subscribers = Subs, id = Id} = S) ->
    _ = [P ! {?MODULE, Id, Event} || P <- Subs],
    S.
