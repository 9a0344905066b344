%% @doc One simulated PLC: an image of point values that outlives the connections to
%% it, scripted behaviour (a sensor that follows an output after a delay), and a link
%% that a test or a simulation can break. The HAL talks to it through the driver
%% {@link cell_hal_sim}; people and simulation processes through that module's API.
%%
%% The link has three states: `up' (answers), `down' (every client is dropped and new
%% ones are refused, as when a cable is pulled), `silent' (accepts connections but
%% answers nothing, as a PLC stuck in a long cycle; requests time out). A request on a
%% connection the PLC dropped is never taken, however soon after the drop it comes.
%%
%% The PLC's memory (its image, its rules and its link) is kept in the HAL's table of
%% simulated PLCs, which the HAL's top supervisor owns, as well as in the process: a
%% device that crashes or is killed is started again by its supervisor with the image
%% and the rules it had, as a real PLC comes back from a reboot with its retained
%% memory and its program. What it had scheduled (a sensor due to follow its actuator,
%% an answer delayed by the latency) died with it: at its start again every rule is run
%% once on its point's value as the memory holds it, as if that value had just been
%% written ({@link replay/2}). A rule is therefore a function of the value (a sensor
%% follows its output), not of how often it was written; the simulated router's
%% physics, told an output it already acts on, does nothing more. Meanwhile its
%% clients lost their connection (the HAL reconnects), and {@link
%% cell_hal_sim:stop_device/1} is the only way to make it forget.
-module(cell_hal_sim_device).
-behaviour(gen_server).

-include("cell_hal.hrl").

-export([start_link/2, whereis/1, forget/1]).
-export([recall/2, replay/2]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2,
         terminate/2]).

-export_type([rule/0, memory/0]).

-define(TAB, cell_hal_sim_devices).

-type key() :: {atom(), atom()}.
%% When `Key' changes to a value, the actions the function returns are applied: each
%% sets a point to a value after a delay (0: at once).
-type rule() :: {key(), fun((cell_hal_type:value()) -> [{non_neg_integer(), key(), cell_hal_type:value()}])}.

-record(state, {name :: atom(),
                image = #{} :: #{key() => cell_hal_type:value()},
                rules = #{} :: #{key() => [rule()]},
                link = up :: up | down | silent,
                latency_ms = 0 :: non_neg_integer(),
                clients = #{} :: #{reference() => {pid(), reference()}}, %% conn ref => {client, monitor}
                %% What is due when, in order: by due time, then in the order it was
                %% asked for (two timers of the same millisecond may fire in any order).
                agenda = gb_trees:empty() :: gb_trees:tree({integer(), non_neg_integer()}, task()),
                seq = 0 :: non_neg_integer(),
                timer :: {reference(), integer()} | undefined}).

-type task() :: {set, key(), cell_hal_type:value()} | {answer, reference(), term()}.
%% What a device keeps across its restarts: its image, its rules by point, its link.
-type memory() :: {#{key() => cell_hal_type:value()}, #{key() => [rule()]},
                   up | down | silent}.

%% @doc Starts the simulated PLC `Name'.
-spec start_link(atom(), map()) -> {ok, pid()}.
start_link(Name, Opts) ->
    gen_server:start_link(?MODULE, {Name, Opts}, []).

%% @doc The process of a simulated PLC, if it runs.
-spec whereis(atom()) -> pid() | undefined.
whereis(Name) ->
    case ets:lookup(?TAB, Name) of
        [{_, Pid}] ->
            %% A device killed with its supervisor leaves its row behind.
            case is_process_alive(Pid) of
                true -> Pid;
                false -> undefined
            end;
        [] ->
            undefined
    end.

%% @doc Forgets the memory of the simulated PLC `Name' (once it is stopped: its
%% next start begins from an empty image, with no rules).
-spec forget(atom()) -> ok.
forget(Name) ->
    true = ets:match_delete(?TAB, {{image, Name, '_'}, '_'}),
    true = ets:delete(?TAB, {rules, Name}),
    true = ets:delete(?TAB, {link, Name}),
    ok.

%% @doc The memory of the simulated PLC `Name' from the rows of the table that keeps
%% it (rows of other devices and the devices' processes are skipped): an empty image,
%% no rules and the link up when it has never run.
-spec recall(atom(), [tuple()]) -> memory().
recall(Name, Rows) ->
    lists:foldl(fun({{image, N, Key}, V}, {Img, Rules, Link}) when N =:= Name ->
                        {Img#{Key => V}, Rules, Link};
                   ({{rules, N}, Rules}, {Img, _, Link}) when N =:= Name ->
                        {Img, Rules, Link};
                   ({{link, N}, Link}, {Img, Rules, _}) when N =:= Name ->
                        {Img, Rules, Link};
                   (_, Acc) ->
                        Acc
                end, {#{}, #{}, up}, Rows).

%% @doc What a device started again with its memory runs: each rule whose point holds
%% a value, with that value, points in order and each point's rules in the order they
%% were added. A rule on a point never written (or preset) is not run: nothing was
%% written to it.
-spec replay(#{key() => cell_hal_type:value()}, #{key() => [rule()]}) ->
          [{key(), rule(), cell_hal_type:value()}].
replay(Image, Rules) ->
    [{Key, Rule, V} || {Key, Rs} <- lists:sort(maps:to_list(Rules)),
                       {ok, V} <- [maps:find(Key, Image)], Rule <- Rs].

%% @private
%% The memory it had, if any; its rules run again on it before the first request.
-spec init({atom(), map()}) -> {ok, #state{}} | {ok, #state{}, {continue, replay}}.
init({Name, Opts}) ->
    true = ets:insert(?TAB, {Name, self()}),
    {Image, Rules, Link} = recall(Name, ets:match_object(?TAB, {{'_', Name, '_'}, '_'})
                                        ++ ets:match_object(?TAB, {{'_', Name}, '_'})),
    %% A PLC started anew holds its initial image (none unless given); one started
    %% again, the image it had.
    case map_size(Image) + map_size(Rules) of
        0 ->
            Initial = maps:get(image, Opts, #{}),
            true = ets:insert(?TAB, [{{image, Name, K}, V} || {K, V} <- maps:to_list(Initial)]),
            {ok, #state{name = Name, latency_ms = maps:get(latency_ms, Opts, 0),
                        image = Initial, rules = Rules, link = Link}};
        _ ->
            {ok, #state{name = Name, latency_ms = maps:get(latency_ms, Opts, 0), image = Image,
                        rules = Rules, link = Link},
             {continue, replay}}
    end.

%% @private
-spec handle_continue(replay, #state{}) -> {noreply, #state{}}.
handle_continue(replay, #state{image = Image, rules = Rules} = S)
  when map_size(Image) =:= 0, map_size(Rules) =:= 0 ->
    {noreply, S};
handle_continue(replay, #state{name = Name, image = Image, rules = Rules, link = Link} = S) ->
    Replay = replay(Image, Rules),
    cell_log:notice(Name, "simulated PLC ~s started again with its memory (~b point(s), "
                    "link ~s); its ~b rule(s) act on the values it holds",
                    [Name, map_size(Image), Link, length(Replay)]),
    {noreply, lists:foldl(fun({Key, {_, Fun}, V}, Si) -> schedule(Key, Fun, V, Si) end,
                          S, Replay)}.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({set, Key, V}, _From, S) ->
    {reply, ok, change(Key, V, S)};
handle_call({preset, Image}, _From, #state{name = Name, image = Img} = S) ->
    true = ets:insert(?TAB, [{{image, Name, K}, V} || {K, V} <- maps:to_list(Image)]),
    {reply, ok, S#state{image = maps:merge(Img, Image)}};
handle_call({get, Key}, _From, #state{image = Img} = S) ->
    {reply, maps:find(Key, Img), S};
handle_call({rule, Key, Fun}, _From, #state{rules = Rules} = S) ->
    Rule = {Key, Fun},
    {reply, ok, keep_rules(maps:update_with(Key, fun(Rs) -> Rs ++ [Rule] end, [Rule], Rules), S)};
handle_call(clear_rules, _From, S) ->
    {reply, ok, keep_rules(#{}, S)};
handle_call({link, Link}, _From, #state{name = Name} = S)
  when Link =:= up; Link =:= down; Link =:= silent ->
    S1 = case Link of
             down -> drop_all(S);
             _ -> S
         end,
    true = ets:insert(?TAB, {{link, Name}, Link}),
    {reply, ok, S1#state{link = Link}};
handle_call(drop, _From, S) ->
    {reply, ok, drop_all(S)};
handle_call(clients, _From, #state{clients = Cs} = S) ->
    {reply, maps:size(Cs), S}.

%% @private
%% Requests of the driver: `{connect, Client, Ref}', then `{Op, Ref, Tag, ...}' on that
%% connection; answers go to the client as `{cell_hal_sim, Ref, Answer}'.
-spec handle_cast(term(), #state{}) -> {noreply, #state{}}.
handle_cast({connect, Client, Ref}, #state{link = down} = S) ->
    Client ! {cell_hal_sim, Ref, refused},
    {noreply, S};
handle_cast({connect, Client, Ref}, #state{clients = Cs} = S) ->
    MRef = erlang:monitor(process, Client),
    Client ! {cell_hal_sim, Ref, connected},
    {noreply, S#state{clients = Cs#{Ref => {Client, MRef}}}};
handle_cast({disconnect, Ref}, #state{clients = Cs} = S) ->
    case maps:take(Ref, Cs) of
        {{_, MRef}, Rest} ->
            erlang:demonitor(MRef, [flush]),
            {noreply, S#state{clients = Rest}};
        error ->
            {noreply, S}
    end;
handle_cast(Req, #state{link = silent} = S) when element(1, Req) =:= read;
                                                  element(1, Req) =:= write ->
    {noreply, S};
handle_cast({read, Ref, Tag, Points}, #state{clients = Cs} = S) when is_map_key(Ref, Cs) ->
    Values = [{K, value(K, Type, S)} || {K, Type} <- Points],
    {noreply, answer(Ref, {reply, Tag, {ok, Values}}, S)};
handle_cast({write, Ref, Tag, Key, V}, #state{clients = Cs} = S) when is_map_key(Ref, Cs) ->
    {noreply, answer(Ref, {reply, Tag, ok}, change(Key, V, S))};
handle_cast(Req, S) when element(1, Req) =:= read; element(1, Req) =:= write ->
    %% On a connection this PLC dropped (its cable pulled, a momentary loss, a PLC
    %% started again): sent before the client learnt of the loss, it never arrives, as
    %% nothing reaches a real PLC over a pulled cable or a closed socket.
    {noreply, S}.

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({timeout, TRef, agenda}, #state{timer = {TRef, _}} = S) ->
    {noreply, run_agenda(S#state{timer = undefined})};
handle_info({timeout, _, agenda}, S) ->
    {noreply, S};
handle_info({'DOWN', MRef, process, _, _}, #state{clients = Cs} = S) ->
    {noreply, S#state{clients = maps:filter(fun(_, {_, M}) -> M =/= MRef end, Cs)}}.

%% @private
-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, #state{name = Name}) ->
    true = ets:delete_object(?TAB, {Name, self()}),
    ok.

%% Answers a client, after the configured latency (clients dropped meanwhile get
%% nothing, like a reply lost with its TCP connection).
answer(Ref, Answer, #state{latency_ms = 0} = S) ->
    ok = send(Ref, Answer, S),
    S;
answer(Ref, Answer, #state{latency_ms = Ms} = S) ->
    later(Ms, {answer, Ref, Answer}, S).

%% Puts a task on the agenda, due `Delay' ms from now.
later(Delay, Task, #state{agenda = A, seq = Seq} = S) ->
    Due = erlang:monotonic_time(millisecond) + Delay,
    arm(S#state{agenda = gb_trees:insert({Due, Seq}, Task, A), seq = Seq + 1}).

%% One timer, for the earliest task.
arm(#state{agenda = A, timer = Timer} = S) ->
    case gb_trees:is_empty(A) of
        true ->
            S;
        false ->
            {{Due, _}, _} = gb_trees:smallest(A),
            case Timer of
                {_, At} when At =< Due ->
                    S;
                _ ->
                    _ = case Timer of
                            {TRef, _} -> erlang:cancel_timer(TRef);
                            undefined -> ok
                        end,
                    TRef1 = erlang:start_timer(Due, self(), agenda, [{abs, true}]),
                    S#state{timer = {TRef1, Due}}
            end
    end.

%% Does every task that is due, in order; a task may put more on the agenda.
run_agenda(#state{agenda = A} = S) ->
    Now = erlang:monotonic_time(millisecond),
    case gb_trees:is_empty(A) orelse gb_trees:smallest(A) of
        {{Due, _} = K, Task} when Due =< Now ->
            run_agenda(run(Task, S#state{agenda = gb_trees:delete(K, A)}));
        _ ->
            arm(S)
    end.

run({set, Key, V}, S) -> change(Key, V, S);
run({answer, Ref, Answer}, S) -> ok = send(Ref, Answer, S), S.

send(Ref, Answer, #state{clients = Cs}) ->
    case maps:find(Ref, Cs) of
        {ok, {Client, _}} ->
            Client ! {cell_hal_sim, Ref, Answer},
            ok;
        error ->
            ok
    end.

drop_all(#state{clients = Cs} = S) ->
    maps:foreach(fun(Ref, {Client, MRef}) ->
                         erlang:demonitor(MRef, [flush]),
                         Client ! {cell_hal_sim, Ref, closed}
                 end, Cs),
    S#state{clients = #{}}.

keep_rules(Rules, #state{name = Name} = S) ->
    true = ets:insert(?TAB, {{rules, Name}, Rules}),
    S#state{rules = Rules}.

%% A point changes: store it (in the memory first: a device killed before its rules
%% ran runs them at its start again) and run the rules that watch it.
change(Key, V, #state{name = Name, image = Img, rules = Rules} = S) ->
    true = ets:insert(?TAB, {{image, Name, Key}, V}),
    lists:foldl(fun({_, Fun}, Si) -> schedule(Key, Fun, V, Si) end,
                S#state{image = Img#{Key => V}}, maps:get(Key, Rules, [])).

schedule(Key, Fun, V, #state{name = Name} = S) ->
    %% A rule is the simulation's own code: a fault in it is reported and the device
    %% goes on, as a PLC would keep running with one faulty routine.
    Actions = try Fun(V)
              catch Class:Reason ->
                      cell_log:error(Name, "simulated PLC ~s: the rule on ~p failed: ~p:~tp",
                                     [Name, Key, Class, Reason]),
                      []
              end,
    case is_list(Actions) of
        true ->
            lists:foldl(fun(A, Si) -> schedule_action(Key, A, Si) end, S, Actions);
        false ->
            cell_log:error(Name, "simulated PLC ~s: the rule on ~p returned ~tp, "
                           "not a list of actions", [Name, Key, Actions]),
            S
    end.

schedule_action(Key, {Delay, K, X} = Action, #state{name = Name} = S)
  when is_integer(Delay), Delay >= 0 ->
    case cell_hal_store:point(K) of
        {ok, #hal_point{type = Type}} ->
            case cell_hal_type:check(Type, X) of
                {ok, X1} -> later(Delay, {set, K, X1}, S);
                error -> bad_action(Name, Key, Action), S
            end;
        error ->
            bad_action(Name, Key, Action),
            S
    end;
schedule_action(Key, Action, #state{name = Name} = S) ->
    bad_action(Name, Key, Action),
    S.

bad_action(Name, Key, Action) ->
    cell_log:error(Name, "simulated PLC ~s: the rule on ~p asked for ~tp, which is not "
                   "{Delay, Point, Value} with a known point and a value of its type",
                   [Name, Key, Action]).

%% A point as the image holds it; a preset value that does not fit the point's type
%% reads as zero, reported (the HAL never publishes a value outside its type).
value(Key, Type, #state{image = Img, name = Name}) ->
    %% A forced input answers its forced value (see cell_hal_force).
    case cell_hal_force:input_value(Key) of
        {ok, V} -> V;
        none -> image_value(Key, Type, Img, Name)
    end.

image_value(Key, Type, Img, Name) ->
    case maps:find(Key, Img) of
        {ok, V} ->
            case cell_hal_type:check(Type, V) of
                {ok, V1} -> V1;
                error ->
                    cell_log:error(Name, "simulated PLC ~s holds ~tp for ~p, not a ~s; "
                                   "it reads as zero", [Name, V, Key, cell_hal_type:name(Type)]),
                    zero(Type)
            end;
        error ->
            zero(Type)
    end.

%% What an unwritten point of the image holds: zero of its type.
zero(bool) -> false;
zero(real) -> 0.0;
zero(lreal) -> 0.0;
zero({string, _}) -> <<>>;
zero(date) -> {1970, 1, 1};
zero(decimal) -> <<0:128>>;
zero(_) -> 0.
