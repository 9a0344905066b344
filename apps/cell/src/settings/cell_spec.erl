%% @doc The cell spec: what the controller builds the cell from.
%%
%% ```
%% #{name => <<"Router">>,
%%   tasks => [#{id => loading_front, module => router_loading_task,
%%               zone => <<"Loading">>, lane => <<"Front">>,
%%               io => [front_loading_io], settings => loading, args => #{...}}],
%%   settings => [router_loading_settings]}
%% '''
%%
%% Each task's zone and lane name its product and retained-data files
%% (`Data/<Zone>@<Lane>.product', `.retain'): two tasks whose names come to one file are
%% refused, naming both and the file.
%%
%% `links' are the handshakes between tasks: `#{id => load_work, from => loading,
%% to => work}'. An end may be a task of another node, `{Task, Node}' (a line of cells),
%% or `undefined' for a master task that connects at run time (the seed's feeders).
%% A link runs on the node of its downstream end (or of its upstream end when the
%% downstream connects at run time), so two nodes naming one link start it once.
%%
%% A task's module is a device task ({@link cell_task}: init, reconcile, step, uninit;
%% one without `reconcile/2' is refused by name, since after a restart nothing else
%% checks its record against the machine) or a unit
%% ({@link cell_unit}: the Zeugwerk lifecycle, told apart by its `unit/1'); a unit's
%% declaration is checked here too. Units take no part in handshakes: a link naming one
%% is refused.
%%
%% A task's `work' (a boolean) says whether it does work on its items (calls
%% `cell_task:work_start/1', or its unit's sequence `cell_sequence:work_start/1'), so
%% that it has cycle times and part counts to report (the SHDR adapter declares them
%% for such tasks only); without it, a unit does, and a device task does when its
%% module calls `cell_task:work_start/1'.
%%
%% A task's `settings' names the settings object (see {@link cell_settings}) whose
%% snapshot it runs on, taken at each Start; a map gives fixed settings instead. The
%% cell's `settings' lists the schema modules of its own settings objects.
%%
%% `hal' is what the monitor connects (connections, IO groups, hardware objects) and
%% `monitor' what it watches and drives (general IO, drives, beacon): both optional,
%% checked by {@link cell_monitor_spec}.
%%
%% A cell application's own module returns it from the settings (seed 000 §2.3.3: one
%% setting switches a cell between simulated and real tasks and IO): the `cell' app's
%% `cell_module' environment key names that module, whose `cell_spec/0' is called at
%% boot. The `cell_spec' key may hold a spec directly (tests do). Every field is checked
%% here; a bad spec stops the boot with an error that names the task and the field.
%% A spec is written with {@link cell_spec_helpers} (the settings as saved, simulated or
%% real IO, the monitor's IO, tasks, units and hardware objects).
-module(cell_spec).

-export([load/0, validate/1, empty/0, hosted_links/1, keep/1, running/0]).

-export_type([spec/0]).

-type spec() :: #{name := binary(), tasks := [cell_task:spec()], settings := [module()],
                  links := [cell_handshake_link:spec()],
                  hal := cell_monitor_spec:hal(), monitor := cell_monitor_spec:monitor()}.

%% @doc A cell without tasks.
-spec empty() -> spec().
empty() ->
    #{name => <<"cell">>, tasks => [], settings => [], links => [],
      hal => cell_monitor_spec:empty_hal(), monitor => cell_monitor_spec:empty_monitor()}.

%% @doc Keeps the spec the controller was built from, for those who show the cell
%% (the panel's picture of the machine): one write a start of the controller.
-spec keep(spec()) -> ok.
keep(Spec) ->
    persistent_term:put({?MODULE, running}, Spec).

%% @doc The spec the controller was last built from; the empty cell before that.
-spec running() -> spec().
running() ->
    persistent_term:get({?MODULE, running}, empty()).

%% @doc The links this node runs.
-spec hosted_links(spec()) -> [cell_handshake_link:spec()].
hosted_links(#{links := Links}) ->
    [L || #{from := From, to := To} = L <- Links, hosted_here(From, To)].

hosted_here(_From, To) when is_atom(To), To =/= undefined -> true;
hosted_here(From, undefined) -> is_atom(From) andalso From =/= undefined;
hosted_here(_From, _To) -> false.

%% @doc The configured spec, validated.
-spec load() -> {ok, spec()} | {error, term()}.
load() ->
    case application:get_env(cell, cell_spec) of
        {ok, Spec} ->
            validate(Spec);
        undefined ->
            case cell_config:get(cell, cell_module, undefined) of
                undefined -> {ok, empty()};
                Name -> from_module(Name)
            end
    end.

from_module(Name) when is_list(Name) ->
    try list_to_existing_atom(Name) of
        Mod -> from_module(Mod)
    catch
        error:badarg -> {error, {unknown_cell_module, Name}}
    end;
from_module(Mod) when is_atom(Mod) ->
    case code:ensure_loaded(Mod) of
        {module, Mod} ->
            case erlang:function_exported(Mod, cell_spec, 0) of
                true ->
                    %% The helpers' refusals, raised from inside the spec's literal, come
                    %% back as the checks' own errors do.
                    try Mod:cell_spec() of
                        Spec -> validate(Spec)
                    catch
                        error:{bad_task, _Id, _Why} = Refused -> {error, Refused}
                    end;
                false -> {error, {not_a_cell_module, Mod, "it exports no cell_spec/0"}}
            end;
        {error, _} ->
            {error, {unknown_cell_module, Mod}}
    end.

%% @doc Checks a spec; fills in the defaults.
-spec validate(term()) -> {ok, spec()} | {error, term()}.
validate(#{tasks := Tasks} = Spec) when is_list(Tasks) ->
    Name = maps:get(name, Spec, <<"cell">>),
    Schemas = maps:get(settings, Spec, []),
    case files_apart(tasks(Tasks, [], #{})) of
        {ok, _} when not is_binary(Name) ->
            {error, {bad_cell_spec, name, Name}};
        {ok, Checked} ->
            case is_list(Schemas) andalso lists:all(fun is_schema/1, Schemas) of
                true ->
                    {Units, Steppers} = lists:partition(fun(#{module := M}) ->
                                                                cell_unit:is_unit_module(M)
                                                        end, Checked),
                    case {links(maps:get(links, Spec, []), [T || #{id := T} <- Steppers],
                                [T || #{id := T} <- Units]),
                          cell_monitor_spec:validate(Spec)} of
                        {{ok, Links}, {ok, HalAndMonitor}} ->
                            {ok, maps:merge(Spec#{name => Name, settings => Schemas,
                                                  links => Links,
                                                  tasks => [with_links(T, Links) || T <- Checked]},
                                            HalAndMonitor)};
                        {{ok, _}, Error} ->
                            Error;
                        {Error, _} ->
                            Error
                    end;
                false ->
                    {error, {bad_cell_spec, settings, Schemas}}
            end;
        Error ->
            Error
    end;
validate(Other) ->
    {error, {bad_cell_spec, "a cell spec is a map with a list of tasks", Other}}.

links(Links, TaskIds, UnitIds) when is_list(Links) ->
    case [{L, U} || #{id := L} = Link <- Links, End <- [from, to],
                    U <- [maps:get(End, Link, undefined)], lists:member(U, UnitIds)] of
        [] -> links(Links, TaskIds, [], #{});
        [{L, U} | _] -> {error, {bad_link, L, {unit, U}}}
    end;
links(Other, _, _) ->
    {error, {bad_cell_spec, links, Other}}.

links([], _TaskIds, Acc, _Seen) ->
    {ok, lists:reverse(Acc)};
links([#{id := Id} = L | Rest], TaskIds, Acc, Seen) when is_atom(Id) ->
    From = maps:get(from, L, undefined),
    To = maps:get(to, L, undefined),
    Unknown = maps:keys(L) -- [id, from, to],
    case {maps:is_key(Id, Seen), Unknown, end_ok(From, TaskIds), end_ok(To, TaskIds)} of
        {true, _, _, _} -> {error, {bad_link, Id, duplicate_id}};
        {_, [_ | _], _, _} -> {error, {bad_link, Id, {unknown_keys, Unknown}}};
        {_, _, false, _} -> {error, {bad_link, Id, {bad_option, from}}};
        {_, _, _, false} -> {error, {bad_link, Id, {bad_option, to}}};
        _ when From =:= undefined, To =:= undefined -> {error, {bad_link, Id, no_ends}};
        _ when From =:= To -> {error, {bad_link, Id, same_task_at_both_ends}};
        _ -> links(Rest, TaskIds, [#{id => Id, from => From, to => To} | Acc], Seen#{Id => true})
    end;
links([Other | _], _TaskIds, _Acc, _Seen) ->
    {error, {bad_link, Other, "a link needs an atom id"}}.

%% A local end names a task of this spec; a remote one is {Task, Node}.
end_ok(undefined, _) -> true;
end_ok({Task, Node}, _) -> is_atom(Task) andalso is_atom(Node);
end_ok(Task, TaskIds) -> is_atom(Task) andalso lists:member(Task, TaskIds).

with_links(#{id := Id} = T, Links) ->
    Mine = maps:from_list([{L, #{role => up}} || #{id := L, from := F} <- Links, F =:= Id]
                          ++ [{L, #{role => down}} || #{id := L, to := To} <- Links, To =:= Id]),
    T#{links => Mine}.

%% Each task keeps its product and its retained data in files named by its zone and
%% lane (see cell_product:file_name/2): two tasks whose names come to the same file
%% would overwrite each other's product, so such a spec is refused, naming both tasks
%% and the file. Names that differ only in characters a file name cannot hold (which
%% become `_'), in where the `@' falls, in upper and lower case, or in how an accented
%% letter is encoded are the same file on some file systems the data folder may live
%% on (FAT, NTFS, APFS): they are refused too. Units are held to it as well: a unit is
%% built as a task (cell_task:new/1 names its files the same way), and the panel and
%% the logs tell the cell's tasks apart by zone and lane.
files_apart({ok, Checked} = Ok) ->
    Named = [{file_key(cell_product:file_name(Zone, Lane)), Id,
              [cell_product:file_name(Zone, Lane), cell_retain:file_name(Zone, Lane)]}
             || #{id := Id, zone := Zone, lane := Lane} <- Checked],
    case first_shared(Named, #{}) of
        none -> Ok;
        {First, Second, Files} ->
            {error, {bad_task, Second,
                     {shares_files_with, First, Files,
                      "each task keeps its product and retained data in files named by "
                      "its zone and lane: give each task its own zone or lane"}}}
    end;
files_apart(Error) ->
    Error.

first_shared([], _Seen) ->
    none;
first_shared([{Key, Id, Files} | Rest], Seen) ->
    case Seen of
        #{Key := {First, FirstFiles}} -> {First, Id, lists:usort(FirstFiles ++ Files)};
        #{} -> first_shared(Rest, Seen#{Key => {Id, Files}})
    end.

file_key(File) ->
    string:casefold(unicode:characters_to_nfc_list(File)).

tasks([], Acc, _Seen) ->
    {ok, lists:reverse(Acc)};
tasks([#{id := Id} = T | Rest], Acc, Seen) when is_atom(Id) ->
    case maps:is_key(Id, Seen) of
        true ->
            {error, {bad_task, Id, duplicate_id}};
        false ->
            case task(T) of
                {ok, Checked} -> tasks(Rest, [Checked | Acc], Seen#{Id => true});
                {error, Why} -> {error, {bad_task, Id, Why}}
            end
    end;
tasks([Other | _], _Acc, _Seen) ->
    {error, {bad_task, Other, "a task needs an atom id"}}.

task(T) ->
    Checks = [{module, fun is_task_module/1},
              {zone, fun is_name/1},
              {lane, fun is_name/1}],
    Optional = [{io, [], fun(L) -> is_list(L) andalso lists:all(fun is_atom/1, L) end},
                {settings, #{}, fun(S) -> is_map(S) orelse is_atom(S) end},
                {args, #{}, fun is_map/1},
                {work, undefined, fun is_boolean/1}],
    case [K || {K, Ok} <- Checks, not (maps:is_key(K, T) andalso Ok(maps:get(K, T)))] of
        [] ->
            case [K || {K, _, Ok} <- Optional, maps:is_key(K, T), not Ok(maps:get(K, T))] of
                [] ->
                    Unknown = maps:keys(T) -- [id, links | [K || {K, _} <- Checks] ++
                                                          [K || {K, _, _} <- Optional]],
                    case Unknown of
                        [] ->
                            Defaults = maps:from_list([{K, D} || {K, D, _} <- Optional]),
                            check_unit(works(maps:merge(Defaults, T)));
                        _ -> {error, {unknown_keys, Unknown}}
                    end;
                Bad ->
                    {error, {bad_option, hd(Bad)}}
            end;
        Bad ->
            {error, {bad_option, hd(Bad)}}
    end.

is_name(B) -> is_binary(B) andalso B =/= <<>>.

%% Whether a task does work (starts and ends work on its items, so it has cycle times
%% and part counts to report): as declared, else a unit does (its sequences, modules
%% of their own, may) and a device task does when its module's code calls
%% cell_task:work_start/1. A module whose code cannot be read is taken to work, so
%% nothing it reports goes unheard.
works(#{work := undefined, module := Mod} = T) ->
    T#{work => cell_unit:is_unit_module(Mod) orelse calls_work_start(Mod)};
works(T) ->
    T.

calls_work_start(Mod) ->
    case code:get_object_code(Mod) of
        {Mod, Beam, _File} -> imports_work_start(Beam);
        error -> true
    end.

imports_work_start(Beam) ->
    case beam_lib:chunks(Beam, [imports]) of
        {ok, {_, [{imports, Imports}]}} -> lists:member({cell_task, work_start, 1}, Imports);
        {error, beam_lib, _} -> true
    end.

is_schema(Mod) when is_atom(Mod) ->
    code:ensure_loaded(Mod) =:= {module, Mod}
        andalso erlang:function_exported(Mod, name, 0)
        andalso erlang:function_exported(Mod, fields, 0);
is_schema(_) ->
    false.

%% A unit's declaration is checked with its args and IO groups; a device task's module
%% must write its restart reconciliation.
check_unit(#{module := Mod} = T) ->
    case cell_unit:is_unit_module(Mod) of
        true ->
            case cell_unit:check(T) of
                {error, _} = Error -> Error;
                _ -> {ok, T}
            end;
        false ->
            case erlang:function_exported(Mod, reconcile, 2) of
                true -> {ok, T};
                false -> {error, {missing_callback, Mod, {reconcile, 2},
                                  "a device task checks what it held against its IO "
                                  "after a restart (see cell_task)"}}
            end
    end.

is_task_module(Mod) when is_atom(Mod) ->
    cell_unit:is_unit_module(Mod) orelse is_step_module(Mod);
is_task_module(_) ->
    false.

is_step_module(Mod) ->
    case code:ensure_loaded(Mod) of
        {module, Mod} ->
            lists:all(fun({F, A}) -> erlang:function_exported(Mod, F, A) end,
                      [{init, 1}, {step, 1}, {uninit, 1}]);
        {error, _} ->
            false
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

validate_test_() ->
    Good = #{id => a, module => cell_test_task, zone => <<"Z">>, lane => <<"L">>},
    B = Good#{id => b, lane => <<"M">>},
    [?_assertMatch({ok, #{name := <<"cell">>, tasks := [#{io := [], args := #{}}]}},
                   validate(#{tasks => [Good]})),
     ?_assertEqual({error, {bad_task, a, duplicate_id}}, validate(#{tasks => [Good, Good]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, module}}},
                   validate(#{tasks => [Good#{module => lists}]})),
     ?_assertMatch({error, {bad_task, a, {missing_callback, cell_unreconciled_task,
                                          {reconcile, 2}, _}}},
                   validate(#{tasks => [Good#{module => cell_unreconciled_task}]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, zone}}},
                   validate(#{tasks => [Good#{zone => "Z"}]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, io}}},
                   validate(#{tasks => [Good#{io => [<<"x">>]}]})),
     %% Whether a task does work: as declared, else as its module's code says (the
     %% test task starts work by a call its commands name, not one of its code).
     ?_assertMatch({ok, #{tasks := [#{work := false}]}}, validate(#{tasks => [Good]})),
     ?_assertMatch({ok, #{tasks := [#{work := true}]}},
                   validate(#{tasks => [Good#{work => true}]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, work}}},
                   validate(#{tasks => [Good#{work => yes}]})),
     ?_assert(calls_work_start(cell_spec_no_such_module)),
     ?_assert(imports_work_start(beam(<<"f(T) -> cell_task:work_start(T).">>))),
     ?_assertNot(imports_work_start(beam(<<"f(T) -> cell_task:work_complete(T).">>))),
     ?_assert(imports_work_start(<<"not a module">>)),
     ?_assertEqual({error, {bad_task, a, {unknown_keys, [colour]}}},
                   validate(#{tasks => [Good#{colour => red}]})),
     ?_assertMatch({error, {bad_task, _, _}}, validate(#{tasks => [#{id => "a"}]})),
     ?_assertMatch({error, {bad_cell_spec, _, _}}, validate([])),
     ?_assertMatch({ok, _}, validate(#{tasks => []})),
     ?_assertMatch({ok, #{tasks := [#{settings := loading}]}},
                   validate(#{tasks => [Good#{settings => loading}]})),
     ?_assertMatch({error, {bad_cell_spec, settings, _}},
                   validate(#{tasks => [], settings => [lists]})),
     ?_assertMatch({ok, #{tasks := [#{links := #{l := #{role := up}}},
                                    #{links := #{l := #{role := down}}}]}},
                   validate(#{tasks => [Good, B],
                              links => [#{id => l, from => a, to => b}]})),
     ?_assertEqual({error, {bad_link, l, {bad_option, to}}},
                   validate(#{tasks => [Good], links => [#{id => l, from => a, to => nobody}]})),
     ?_assertEqual({error, {bad_link, l, same_task_at_both_ends}},
                   validate(#{tasks => [Good], links => [#{id => l, from => a, to => a}]})),
     ?_assertEqual({error, {bad_link, l, duplicate_id}},
                   validate(#{tasks => [Good, B],
                              links => [#{id => l, from => a, to => b},
                                        #{id => l, from => b, to => a}]})),
     ?_assertMatch({ok, _}, validate(#{tasks => [Good],
                                       links => [#{id => l, from => {x, 'n@h'}, to => a}]}))].

%% Two tasks whose zone and lane come to one product file (and one retained-data file)
%% are refused, naming both tasks and the files; every other pair is accepted.
shared_files_test_() ->
    T = fun(Id, Zone, Lane) -> #{id => Id, module => cell_test_task, zone => Zone,
                                  lane => Lane} end,
    Refused = fun(Files, Tasks) ->
                      ?_assertMatch({error, {bad_task, t2, {shares_files_with, t1, Files, _}}},
                                    validate(#{tasks => Tasks}))
              end,
    Same = ["Z@Front.product", "Z@Front.retain"],
    [Refused(Same, [T(t1, <<"Z">>, <<"Front">>), T(t2, <<"Z">>, <<"Front">>)]),
     %% a unit too, and the second of three
     Refused(Same, [T(t1, <<"Z">>, <<"Front">>), T(t0, <<"Y">>, <<"Front">>),
                    #{id => t2, module => cell_test_decl_unit, zone => <<"Z">>,
                      lane => <<"Front">>, args => #{decl => #{}}}]),
     %% characters a file name cannot hold become the same `_'
     Refused(["a_b@L.product", "a_b@L.retain"],
             [T(t1, <<"a/b">>, <<"L">>), T(t2, <<"a:b">>, <<"L">>)]),
     %% the `@' inside a name
     Refused(["a@b@c.product", "a@b@c.retain"],
             [T(t1, <<"a@b">>, <<"c">>), T(t2, <<"a">>, <<"b@c">>)]),
     %% case, and an accent written as one character or as two
     Refused(["Z@Front.product", "Z@Front.retain", "z@FRONT.product", "z@FRONT.retain"],
             [T(t1, <<"Z">>, <<"Front">>), T(t2, <<"z">>, <<"FRONT">>)]),
     Refused([[$S, $a, 16#308, $g, $e, $n, $@, $L | ".product"],
              [$S, $a, 16#308, $g, $e, $n, $@, $L | ".retain"],
              [$S, 16#E4, $g, $e, $n, $@, $L | ".product"],
              [$S, 16#E4, $g, $e, $n, $@, $L | ".retain"]],
             [T(t1, <<"Sägen"/utf8>>, <<"L">>),
              T(t2, <<"Sa", 16#308/utf8, "gen">>, <<"L">>)]),
     ?_assertMatch({ok, _}, validate(#{tasks => [T(t1, <<"Z">>, <<"Front">>),
                                                 T(t2, <<"Z">>, <<"Rear">>),
                                                 T(t3, <<"Y">>, <<"Front">>),
                                                 T(t4, <<"Z_">>, <<"Front">>)]}))].

hosted_links_test() ->
    Links = [#{id => a, from => t1, to => t2}, #{id => b, from => t2, to => {t9, 'n@h'}},
             #{id => c, from => {t0, 'n@h'}, to => t1}, #{id => d, from => t2, to => undefined}],
    ?assertEqual([a, c, d], [I || #{id := I} <- hosted_links(#{links => Links})]).

%% The object code of a module of one exported function `f/1'.
beam(Source) ->
    Forms = [begin
                 {ok, Tokens, _} = erl_scan:string(F),
                 {ok, Form} = erl_parse:parse_form(Tokens),
                 Form
             end || F <- ["-module(cell_spec_work_probe).", "-export([f/1]).",
                          binary_to_list(Source)]],
    {ok, cell_spec_work_probe, Beam} = compile:forms(Forms, [binary]),
    Beam.

-endif.
