%% @doc The cell's settings (seed 000 §3, §3.1): the owner of every registered settings
%% object, its file and its revision history.
%%
%% Each object is declared by a {@link cell_settings_schema} module and kept in
%% `Settings/<name>.json', pretty-printed with its fields in declaration order. Reads
%% skip this process: the current objects sit in an ETS table. Changes go through it,
%% one at a time: validated against the schema (an error names the field and nothing
%% changes), written durably with `cell_file', recorded as a new revision with who and
%% when, announced to subscribers as `{cell_settings, changed, Name}'.
%%
%% Tasks never read the current settings while they run: the controller calls {@link
%% snapshot/0} at Start and hands each task its part, so a change saved while the
%% machine runs applies at the next Start (seed 000 §3.1).
%%
%% History: `Settings/.history/<name>/<rev>.json' holds revision `rev' (who, when and
%% the object, in the same layout as the settings file), the last `history' revisions
%% kept. Saving writes the revision first and the settings file second; at load a
%% revision newer than the file whose predecessor matches the file is the trace of a
%% save cut short, and is dropped. A file that differs from the last revision in any
%% other way was edited by hand: it becomes a revision of its own.
%%
%% A file that fails validation at load (a typo by hand, a value out of range) is
%% refused with a log line naming the file and the field; the last good revision, or
%% the defaults, stay in force, and the file is left for someone to fix and
%% {@link reload/1}. Boot never fails on a settings file.
-module(cell_settings).
-behaviour(gen_server).

%% get/1 here reads settings; it is not the process dictionary BIF.
-compile({no_auto_import, [get/1]}).

-export([start_link/0, start_link/1, child_spec/1]).
-export([register/1, names/0, schema/1, name_of/1]).
-export([get/1, get/2, put/3, reload/1, defaults/1]).
-export([snapshot/0, last_snapshot/0, pending/0]).
-export([revisions/1, revision/2, diff/3, restore/3]).
-export([subscribe/0, unsubscribe/0]).
-export([init/1, handle_continue/2, handle_call/3, handle_cast/2, handle_info/2]).

-export_type([name/0, options/0, revision_info/0, error/0]).

-type name() :: atom().
-type options() :: #{dir => file:filename(),   %% default: cell_config:dir(settings)
                     history => pos_integer(), %% revisions kept per object (default 50)
                     schemas => [module()],    %% registered at start
                     sync => boolean()}.       %% flush files to disk (default true)
-type revision_info() :: #{rev := pos_integer(), who := binary(), time := integer()}.
-type error() :: {invalid, cell_settings_schema:path(), term()}
               | not_json
               | {unknown_settings, term()}
               | {no_revision, name(), term()}
               | {bad_who, term()}
               | {file, file:filename(), term()}.

-define(TAB, cell_settings).
-define(SNAPSHOT, '$snapshot').
-define(LOG, settings).
-define(CALL_TIMEOUT, 30000).

-record(rev, {rev :: pos_integer(), who :: binary(), time :: integer()}).

-record(obj, {mod :: module(),
              revs = [] :: [#rev{}],        %% on disk, newest first
              refused = false :: boolean()}). %% the file was refused at its last load

-record(state, {dir :: file:filename(),
                history :: pos_integer(),
                sync :: boolean(),
                objs = #{} :: #{name() => #obj{}},
                subs = #{} :: #{pid() => reference()}}).

%%====================================================================
%% API
%%====================================================================

%% @doc Starts the settings owner with the default options.
-spec start_link() -> {ok, pid()} | {error, term()}.
start_link() ->
    start_link(#{}).

%% @doc Starts the settings owner, registered as `cell_settings'. Options are checked
%% at the door: `{error, {bad_option, Key}}'.
-spec start_link(options()) -> {ok, pid()} | {error, term()}.
start_link(Opts) ->
    case check_options(Opts) of
        {ok, Checked} -> gen_server:start_link({local, ?MODULE}, ?MODULE, Checked, []);
        {error, _} = E -> E
    end.

%% @doc A child spec for the controller's supervisor.
-spec child_spec(options()) -> supervisor:child_spec().
child_spec(Opts) ->
    #{id => ?MODULE, start => {?MODULE, start_link, [Opts]}}.

%% @doc Registers a settings object and loads its file (see the module doc for what
%% happens to a missing or refused file). Registering the same module again is a no-op.
-spec register(module()) -> ok | {error, {bad_schema, module(), term()}
                                  | {name_taken, name(), module()}}.
register(Mod) when is_atom(Mod) ->
    call({register, Mod}, ?CALL_TIMEOUT).

%% @doc The registered object names.
-spec names() -> [name()].
names() ->
    call(names).

%% @doc The schema module of an object.
-spec schema(name()) -> {ok, module()} | {error, {unknown_settings, name()}}.
schema(Name) ->
    call({schema, Name}).

%% @doc The registered name spelled by a binary (from a URL or a form), without making
%% an atom of it.
-spec name_of(binary()) -> {ok, name()} | {error, {unknown_settings, binary()}}.
name_of(Bin) when is_binary(Bin) ->
    case [N || N <- names(), atom_to_binary(N, utf8) =:= Bin] of
        [N] -> {ok, N};
        [] -> {error, {unknown_settings, Bin}}
    end.

%% @doc The current (saved) object. Tasks use the snapshot they were handed at Start
%% instead. Raises `{unknown_settings, Name}' for a name never registered: a bug.
-spec get(name()) -> map().
get(Name) ->
    case ets:lookup(?TAB, Name) of
        [{_, Obj}] ->
            Obj;
        [] ->
            %% Not (yet) in the table: ask the owner, which answers after any
            %% registration still under way.
            case call({get, Name}) of
                {ok, Obj} -> Obj;
                {error, Why} -> erlang:error(Why, [Name])
            end
    end.

%% @doc One field of the current object: `get(machine, speed_override)' or a path
%% into nested objects and lists, `get(robot, [axes, 2, speed])'.
-spec get(name(), atom() | cell_settings_schema:path()) -> term().
get(Name, Field) when is_atom(Field) ->
    get(Name, [Field]);
get(Name, Path) when is_list(Path) ->
    case cell_settings_schema:get_path(get(Name), Path) of
        {ok, V} -> V;
        error -> erlang:error({unknown_field, Name, Path}, [Name, Path])
    end.

%% @doc Saves changes to an object: the fields `Changes' gives (atom or binary keys,
%% nested objects merged field by field, lists replaced whole); the others keep their
%% value. Refused with the field named, nothing changed, when any value is wrong. A
%% change becomes a new revision by `Who'; saving what is already there is a no-op.
-spec put(name(), map(), binary()) -> ok | {error, error()}.
put(Name, Changes, Who) ->
    call({put, Name, Changes, Who}, ?CALL_TIMEOUT).

%% @doc Reads an object's file again (after someone edited it by hand).
-spec reload(name()) -> ok | {error, error()}.
reload(Name) ->
    call({reload, Name}, ?CALL_TIMEOUT).

%% @doc The object with every field at its default.
-spec defaults(name()) -> {ok, map()} | {error, {unknown_settings, name()}}.
defaults(Name) ->
    case schema(Name) of
        {ok, Mod} -> {ok, cell_settings_schema:defaults(Mod)};
        {error, _} = E -> E
    end.

%% @doc Takes the snapshot the tasks run on (the controller calls it at Start): every
%% object as it is now. Kept as {@link last_snapshot/0}.
-spec snapshot() -> #{name() => map()}.
snapshot() ->
    call(snapshot).

%% @doc The snapshot taken at the last Start, or `undefined' before the first.
-spec last_snapshot() -> #{name() => map()} | undefined.
last_snapshot() ->
    case ets:lookup(?TAB, ?SNAPSHOT) of
        [{_, Snap}] -> Snap;
        [] -> undefined
    end.

%% @doc The objects changed since the last snapshot: their changes apply at the next
%% Start.
-spec pending() -> [name()].
pending() ->
    case last_snapshot() of
        undefined -> [];
        Snap -> [N || N <- names(), maps:get(N, Snap, undefined) =/= get(N)]
    end.

%% @doc An object's revisions on disk, newest first.
-spec revisions(name()) -> {ok, [revision_info()]} | {error, {unknown_settings, name()}}.
revisions(Name) ->
    call({revisions, Name}).

%% @doc One revision: who, when, and the object as it was then.
-spec revision(name(), pos_integer()) ->
          {ok, #{rev := pos_integer(), who := binary(), time := integer(), settings := map()}}
              | {error, error()}.
revision(Name, Rev) ->
    call({revision, Name, Rev}, ?CALL_TIMEOUT).

%% @doc The fields that differ from revision `A' to revision `B'.
%% `cell_settings_schema:format_change/1' prints one as `speed_override: 50 -> 80'.
-spec diff(name(), pos_integer(), pos_integer()) ->
          {ok, [cell_settings_schema:change()]} | {error, error()}.
diff(Name, A, B) ->
    call({diff, Name, A, B}, ?CALL_TIMEOUT).

%% @doc Makes revision `Rev' current again, as a new revision by `Who'.
-spec restore(name(), pos_integer(), binary()) -> ok | {error, error()}.
restore(Name, Rev, Who) ->
    call({restore, Name, Rev, Who}, ?CALL_TIMEOUT).

%% @doc The caller receives `{cell_settings, changed, Name}' after every change, until
%% it unsubscribes or exits.
-spec subscribe() -> ok.
subscribe() ->
    call({subscribe, self()}).

%% @doc Ends a {@link subscribe/0}.
-spec unsubscribe() -> ok.
unsubscribe() ->
    call({unsubscribe, self()}).

%% A call waits through a restart of this process instead of failing (see
%% cell_service_tables).
call(Request) ->
    call(Request, 5000).

call(Request, Timeout) ->
    cell_service_tables:call(?MODULE, Request, Timeout).

%%====================================================================
%% gen_server
%%====================================================================

%% @private
-spec init(map()) -> {ok, #state{}, {continue, {register, [module()]}}}.
init(#{dir := Dir, history := History, sync := Sync, schemas := Schemas}) ->
    State = #state{dir = Dir, history = History, sync = Sync},
    case cell_service_tables:claim(?TAB, [protected, set, {read_concurrency, true}]) of
        new ->
            {ok, State, {continue, {register, Schemas}}};
        kept ->
            %% Restarted after a fault (see cell_service_tables): the objects stay in
            %% force meanwhile; those registered since the start are registered again
            %% (their files read anew) and the subscribers watched again.
            Registered = [Mod || [Mod] <- ets:match(?TAB, {{registered, '_'}, '$1'})],
            Subs = maps:from_list([{Pid, erlang:monitor(process, Pid)}
                                   || [Pid] <- ets:match(?TAB, {{subscriber, '$1'}})]),
            {ok, State#state{subs = Subs},
             {continue, {register, lists:usort(Schemas ++ Registered)}}}
    end.

%% @private
-spec handle_continue({register, [module()]}, #state{}) -> {noreply, #state{}}.
handle_continue({register, Schemas}, State) ->
    _ = cell_file:cleanup(State#state.dir),
    {noreply, lists:foldl(fun register_at_start/2, State, Schemas)}.

register_at_start(Mod, State) ->
    case do_register(Mod, State) of
        {ok, S1} ->
            S1;
        {error, Why} ->
            cell_log:error(?LOG, "settings schema ~p refused: ~ts",
                           [Mod, cell_settings_schema:format_error(Why)]),
            State
    end.

%% @private
-spec handle_call(term(), gen_server:from(), #state{}) -> {reply, term(), #state{}}.
handle_call({register, Mod}, _From, State) ->
    case do_register(Mod, State) of
        {ok, S1} -> {reply, ok, S1};
        {error, _} = E -> {reply, E, State}
    end;
handle_call(names, _From, #state{objs = Objs} = State) ->
    {reply, lists:sort(maps:keys(Objs)), State};
handle_call({schema, Name}, _From, State) ->
    {reply, with_obj(Name, State, fun(#obj{mod = Mod}) -> {ok, Mod} end), State};
handle_call({get, Name}, _From, State) ->
    {reply, with_obj(Name, State, fun(_) -> {ok, current(Name)} end), State};
handle_call({put, Name, Changes, Who}, _From, State) ->
    case {lookup(Name, State), check_who(Who)} of
        {{ok, #obj{mod = Mod}}, ok} ->
            case cell_settings_schema:validate(Mod, Changes, current(Name)) of
                {ok, New} -> save(Name, New, Who, State);
                {error, _} = E -> {reply, E, State}
            end;
        {{error, _} = E, _} -> {reply, E, State};
        {_, {error, _} = E} -> {reply, E, State}
    end;
handle_call({reload, Name}, _From, State) ->
    case lookup(Name, State) of
        {ok, _} ->
            case load(Name, State) of
                {ok, S1} -> {reply, ok, S1};
                {refused, Why, S1} -> {reply, {error, Why}, S1}
            end;
        {error, _} = E ->
            {reply, E, State}
    end;
handle_call(snapshot, _From, #state{objs = Objs} = State) ->
    Snap = maps:from_list([{N, current(N)} || N <- maps:keys(Objs)]),
    true = ets:insert(?TAB, {?SNAPSHOT, Snap}),
    {reply, Snap, State};
handle_call({revisions, Name}, _From, State) ->
    {reply, with_obj(Name, State,
                     fun(#obj{revs = Revs}) ->
                             {ok, [#{rev => R, who => W, time => T}
                                   || #rev{rev = R, who = W, time = T} <- Revs]}
                     end), State};
handle_call({revision, Name, Rev}, _From, State) ->
    {reply, with_obj(Name, State, fun(Obj) -> read_revision(Name, Rev, Obj, State) end),
     State};
handle_call({diff, Name, A, B}, _From, State) ->
    Reply = with_obj(Name, State,
                     fun(#obj{mod = Mod} = Obj) ->
                             case {read_revision(Name, A, Obj, State),
                                   read_revision(Name, B, Obj, State)} of
                                 {{ok, #{settings := SA}}, {ok, #{settings := SB}}} ->
                                     {ok, cell_settings_schema:diff(Mod, SA, SB)};
                                 {{error, _} = E, _} -> E;
                                 {_, {error, _} = E} -> E
                             end
                     end),
    {reply, Reply, State};
handle_call({restore, Name, Rev, Who}, _From, State) ->
    case {lookup(Name, State), check_who(Who)} of
        {{ok, Obj}, ok} ->
            case read_revision(Name, Rev, Obj, State) of
                {ok, #{settings := Old}} -> save(Name, Old, Who, State);
                {error, _} = E -> {reply, E, State}
            end;
        {{error, _} = E, _} -> {reply, E, State};
        {_, {error, _} = E} -> {reply, E, State}
    end;
handle_call({subscribe, Pid}, _From, #state{subs = Subs} = State) ->
    case Subs of
        #{Pid := _} -> {reply, ok, State};
        _ ->
            true = ets:insert(?TAB, {{subscriber, Pid}}),
            {reply, ok, State#state{subs = Subs#{Pid => erlang:monitor(process, Pid)}}}
    end;
handle_call({unsubscribe, Pid}, _From, #state{subs = Subs} = State) ->
    case maps:take(Pid, Subs) of
        {Ref, Rest} ->
            true = erlang:demonitor(Ref, [flush]),
            true = ets:delete(?TAB, {subscriber, Pid}),
            {reply, ok, State#state{subs = Rest}};
        error ->
            {reply, ok, State}
    end.

%% @private
-spec handle_cast(term(), #state{}) -> no_return().
handle_cast(Msg, _State) ->
    erlang:error({unexpected_cast, Msg}).

%% @private
-spec handle_info(term(), #state{}) -> {noreply, #state{}}.
handle_info({'DOWN', _Ref, process, Pid, _}, #state{subs = Subs} = State) ->
    true = ets:delete(?TAB, {subscriber, Pid}),
    {noreply, State#state{subs = maps:remove(Pid, Subs)}}.

%%====================================================================
%% Registration and loading
%%====================================================================

do_register(Mod, #state{objs = Objs} = State) ->
    case cell_settings_schema:check_schema(Mod) of
        ok ->
            Name = cell_settings_schema:name(Mod),
            case Objs of
                #{Name := #obj{mod = Mod}} ->
                    {ok, State};
                #{Name := #obj{mod = Other}} ->
                    {error, {name_taken, Name, Other}};
                _ ->
                    true = ets:insert(?TAB, {{registered, Name}, Mod}),
                    S1 = State#state{objs = Objs#{Name => #obj{mod = Mod}}},
                    case load(Name, S1) of
                        {ok, S2} -> {ok, S2};
                        {refused, _, S2} -> {ok, S2}
                    end
            end;
        {error, _} = E ->
            E
    end.

%% Reads the object's file and history and puts the object in force; see the module
%% doc for what happens to a missing, hand-edited or refused file. A folder that
%% cannot be written leaves the object in force in memory, and says so.
load(Name, #state{objs = Objs} = State) ->
    try load_file(Name, State)
    catch
        throw:{file, P, R} = Why ->
            cell_log:error(?LOG, "settings ~p: cannot write ~ts (~ts); they are kept in "
                           "memory only", [Name, P, file:format_error(R)]),
            #obj{mod = Mod} = maps:get(Name, Objs),
            _ = ets:insert_new(?TAB, {Name, cell_settings_schema:defaults(Mod)}),
            {refused, Why, State}
    end.

load_file(Name, #state{objs = Objs} = State) ->
    #obj{mod = Mod} = Obj0 = maps:get(Name, Objs),
    ensure_dir(filename:join(history_dir(Name, State), "x")),
    _ = cell_file:cleanup(history_dir(Name, State)),
    Obj = Obj0#obj{revs = scan_history(Name, Mod, State)},
    Path = file_path(Name, State),
    case file:read_file(Path) of
        {ok, Bin} ->
            case cell_settings_schema:from_json(Mod, Bin) of
                {ok, FromFile} ->
                    {ok, reconcile(Name, FromFile, Obj, State)};
                {error, Why} ->
                    {Good, From} = last_good(Name, Obj, State),
                    cell_log:error(?LOG, "settings file ~ts refused: ~ts; ~ts stay in force",
                                   [Path, cell_settings_schema:format_error(Why), From]),
                    {refused, Why, put_obj(Name, Good, Obj#obj{refused = true}, State)}
            end;
        {error, enoent} ->
            {Good, From} = last_good(Name, Obj, State),
            cell_log:info(?LOG, "settings file ~ts missing; written from ~ts", [Path, From]),
            case Obj#obj.revs of
                [] -> {ok, commit(Name, Good, <<"cellrt">>, Obj, State)};
                _ -> {ok, write_main(Name, Good, Obj, State)}
            end;
        {error, Reason} ->
            {Good, From} = last_good(Name, Obj, State),
            cell_log:error(?LOG, "settings file ~ts cannot be read (~ts); ~ts stay in force",
                           [Path, file:format_error(Reason), From]),
            {refused, {file, Path, Reason}, put_obj(Name, Good, Obj#obj{refused = true}, State)}
    end.

%% The file is valid: bring the history in line with it.
reconcile(Name, FromFile, #obj{mod = Mod, revs = Revs} = Obj, State) ->
    case Revs of
        [] ->
            commit(Name, FromFile, <<"cellrt">>, Obj, State);
        [#rev{rev = Last} | Older] ->
            case revision_settings(Name, Last, Mod, State) of
                {ok, FromFile} ->
                    put_obj(Name, FromFile, Obj#obj{refused = false}, State);
                _ ->
                    case Older of
                        [#rev{rev = Prev} | _] ->
                            case revision_settings(Name, Prev, Mod, State) of
                                {ok, FromFile} ->
                                    cell_log:trace(?LOG, "settings ~p: revision ~p was never "
                                                   "saved in full (cut short); dropped",
                                                   [Name, Last]),
                                    _ = cell_file:delete(rev_path(Name, Last, State),
                                                         sync_opts(State)),
                                    put_obj(Name, FromFile,
                                            Obj#obj{revs = Older, refused = false}, State);
                                _ ->
                                    edited_by_hand(Name, FromFile, Obj, State)
                            end;
                        [] ->
                            edited_by_hand(Name, FromFile, Obj, State)
                    end
            end
    end.

edited_by_hand(Name, FromFile, Obj, State) ->
    cell_log:info(?LOG, "settings file ~ts was edited outside cellrt; kept as a new revision",
                  [file_path(Name, State)]),
    commit(Name, FromFile, <<"edited outside cellrt">>, Obj#obj{refused = false}, State).

%% The newest revision that passes the schema, or the defaults.
last_good(Name, #obj{mod = Mod, revs = Revs}, State) ->
    Good = lists:foldl(fun(#rev{rev = R}, none) ->
                               case revision_settings(Name, R, Mod, State) of
                                   {ok, S} -> {R, S};
                                   {error, _} -> none
                               end;
                          (_, Found) -> Found
                       end, none, Revs),
    case Good of
        {R, S} -> {S, io_lib:format("the settings of revision ~p", [R])};
        none -> {cell_settings_schema:defaults(Mod), "the defaults"}
    end.

put_obj(Name, Settings, Obj, #state{objs = Objs} = State) ->
    true = ets:insert(?TAB, {Name, Settings}),
    State#state{objs = Objs#{Name => Obj}}.

current(Name) ->
    [{_, Obj}] = ets:lookup(?TAB, Name),
    Obj.

%%====================================================================
%% Saving
%%====================================================================

save(Name, New, Who, #state{objs = Objs} = State) ->
    case current(Name) of
        New ->
            {reply, ok, State};
        Old ->
            Obj = maps:get(Name, Objs),
            try commit(Name, New, Who, Obj, State) of
                S1 ->
                    #obj{mod = Mod} = Obj,
                    Changes = cell_settings_schema:diff(Mod, Old, New),
                    Lines = [cell_settings_schema:format_change(C) || C <- Changes],
                    cell_log:info(?LOG, "settings ~p changed by ~ts: ~ts",
                                  [Name, Who, lists:join("; ", Lines)]),
                    {reply, ok, S1}
            catch
                throw:{file, _, _} = Why -> {reply, {error, Why}, State}
            end
    end.

%% A new revision on disk first, then the settings file, then the table and the
%% subscribers. A file error throws `{file, Path, Reason}' with nothing changed in
%% memory (a revision written without its settings file is dropped at the next load).
commit(Name, Settings, Who, #obj{mod = Mod, revs = Revs} = Obj, State) ->
    Rev = case Revs of
              [] -> 1;
              [#rev{rev = Last} | _] -> Last + 1
          end,
    Time = os:system_time(millisecond),
    RevPath = rev_path(Name, Rev, State),
    ensure_dir(RevPath),
    ok = write(RevPath, rev_json(Mod, Rev, Who, Time, Settings), State),
    Obj1 = Obj#obj{revs = prune(Name, [#rev{rev = Rev, who = Who, time = Time} | Revs], State)},
    write_main(Name, Settings, Obj1, State).

write_main(Name, Settings, #obj{mod = Mod, refused = Refused} = Obj, State) ->
    Path = file_path(Name, State),
    Refused andalso keep_refused(Path, State),
    ok = write(Path, cell_settings_schema:to_json(Mod, Settings), State),
    S1 = put_obj(Name, Settings, Obj#obj{refused = false}, State),
    notify(Name, S1),
    S1.

%% The refused file is about to be replaced: keep what someone typed beside it.
keep_refused(Path, State) ->
    case file:read_file(Path) of
        {ok, Bin} ->
            Kept = Path ++ ".refused",
            _ = write(Kept, Bin, State),
            cell_log:warning(?LOG, "settings file ~ts had been refused; its text is kept as ~ts",
                             [Path, Kept]);
        {error, _} ->
            ok
    end.

write(Path, Data, #state{} = State) ->
    case cell_file:write(Path, Data, sync_opts(State)) of
        ok -> ok;
        {error, {P, Reason}} -> throw({file, P, Reason})
    end.

sync_opts(#state{sync = Sync}) -> #{sync => Sync}.

ensure_dir(Path) ->
    case filelib:ensure_dir(Path) of
        ok -> ok;
        {error, Reason} -> throw({file, filename:dirname(Path), Reason})
    end.

prune(Name, Revs, #state{history = Keep} = State) when length(Revs) > Keep ->
    {Kept, Dropped} = lists:split(Keep, Revs),
    lists:foreach(fun(#rev{rev = R}) ->
                          _ = cell_file:delete(rev_path(Name, R, State), sync_opts(State))
                  end, Dropped),
    Kept;
prune(_Name, Revs, _State) ->
    Revs.

notify(Name, #state{subs = Subs}) ->
    maps:foreach(fun(Pid, _) -> Pid ! {cell_settings, changed, Name} end, Subs).

check_who(Who) when is_binary(Who), byte_size(Who) > 0, byte_size(Who) =< 256 ->
    case unicode:characters_to_binary(Who) of
        Who -> ok;
        _ -> {error, {bad_who, Who}}
    end;
check_who(Who) ->
    {error, {bad_who, Who}}.

%%====================================================================
%% History files
%%====================================================================

rev_json(Mod, Rev, Who, Time, Settings) ->
    Doc = [{<<"revision">>, Rev},
           {<<"who">>, Who},
           {<<"time">>, iso_time(Time)},
           {<<"settings">>, cell_settings_schema:encode_value({object, Mod}, Settings)}],
    <<(jsx:encode(Doc, [space, {indent, 2}]))/binary, "\n">>.

%% The revisions on disk whose header reads well, newest first.
scan_history(Name, Mod, State) ->
    Dir = history_dir(Name, State),
    Nums = lists:filtermap(fun(F) ->
                                   try {true, list_to_integer(filename:basename(F, ".json"))}
                                   catch error:badarg -> false
                                   end
                           end, filelib:wildcard("*.json", Dir)),
    Revs = lists:filtermap(fun(R) ->
                                   case read_rev_file(Name, R, Mod, State) of
                                       {ok, Info, _} -> {true, Info};
                                       {error, _} -> false
                                   end
                           end, lists:usort(Nums)),
    lists:reverse(Revs).

read_revision(Name, Rev, #obj{mod = Mod, revs = Revs}, State) ->
    case lists:keymember(Rev, #rev.rev, Revs) of
        true ->
            case read_rev_file(Name, Rev, Mod, State) of
                {ok, #rev{who = W, time = T}, Settings} ->
                    {ok, #{rev => Rev, who => W, time => T, settings => Settings}};
                {error, _} = E ->
                    E
            end;
        false ->
            {error, {no_revision, Name, Rev}}
    end.

revision_settings(Name, Rev, Mod, State) ->
    case read_rev_file(Name, Rev, Mod, State) of
        {ok, _, Settings} -> {ok, Settings};
        {error, _} = E -> E
    end.

read_rev_file(Name, Rev, Mod, State) ->
    Path = rev_path(Name, Rev, State),
    case file:read_file(Path) of
        {ok, Bin} ->
            case cell_settings_schema:json_decode(Bin) of
                {ok, #{<<"revision">> := Rev, <<"who">> := Who, <<"time">> := Time,
                       <<"settings">> := S}} when is_binary(Who), is_binary(Time) ->
                    case {parse_time(Time), cell_settings_schema:validate(Mod, S)} of
                        {{ok, Ms}, {ok, Settings}} ->
                            {ok, #rev{rev = Rev, who = Who, time = Ms}, Settings};
                        {error, _} ->
                            {error, {invalid, [time], {not_a_time, Time}}};
                        {_, {error, {invalid, P, Why}}} ->
                            {error, {invalid, [settings | P], Why}}
                    end;
                {ok, _} ->
                    {error, {invalid, [], not_a_revision}};
                {error, _} = E ->
                    E
            end;
        {error, Reason} ->
            {error, {file, Path, Reason}}
    end.

iso_time(Ms) ->
    list_to_binary(calendar:system_time_to_rfc3339(Ms, [{unit, millisecond}, {offset, "Z"}])).

parse_time(Bin) ->
    %% calendar's parser raises on malformed text; this is the boundary for file input.
    try calendar:rfc3339_to_system_time(binary_to_list(Bin), [{unit, millisecond}]) of
        Ms -> {ok, Ms}
    catch
        error:_ -> error
    end.

%%====================================================================
%% Helpers
%%====================================================================

file_path(Name, #state{dir = Dir}) ->
    filename:join(Dir, atom_to_list(Name) ++ ".json").

history_dir(Name, #state{dir = Dir}) ->
    filename:join([Dir, ".history", atom_to_list(Name)]).

rev_path(Name, Rev, State) ->
    filename:join(history_dir(Name, State), integer_to_list(Rev) ++ ".json").

lookup(Name, #state{objs = Objs}) ->
    case Objs of
        #{Name := Obj} -> {ok, Obj};
        _ -> {error, {unknown_settings, Name}}
    end.

with_obj(Name, State, Fun) ->
    case lookup(Name, State) of
        {ok, Obj} -> Fun(Obj);
        {error, _} = E -> E
    end.

check_options(Opts) when is_map(Opts) ->
    Defaults = #{dir => undefined, history => undefined, schemas => [cell_machine_settings],
                 sync => true},
    case [K || K <- maps:keys(Opts), not is_map_key(K, Defaults)] of
        [K | _] ->
            {error, {bad_option, K}};
        [] ->
            O = maps:merge(Defaults, Opts),
            Checks = [{dir, fun(undefined) -> true; (D) -> io_lib:char_list(D) end},
                      {history, fun(undefined) -> true; (H) -> is_integer(H) andalso H >= 1 end},
                      {schemas, fun(L) -> is_list(L) andalso lists:all(fun is_atom/1, L) end},
                      {sync, fun is_boolean/1}],
            case [K || {K, Ok} <- Checks, not Ok(maps:get(K, O))] of
                [K | _] ->
                    {error, {bad_option, K}};
                [] ->
                    {ok, O#{dir := case O of
                                      #{dir := undefined} -> cell_config:dir(settings);
                                      #{dir := D} -> D
                                  end,
                            history := case O of
                                           #{history := undefined} -> default_history();
                                           #{history := H} -> H
                                       end}}
            end
    end;
check_options(_) ->
    {error, {bad_option, options}}.

default_history() ->
    case cell_config:get(cell, settings_history, 50) of
        H when is_integer(H), H >= 1 -> H;
        _ -> 50
    end.
