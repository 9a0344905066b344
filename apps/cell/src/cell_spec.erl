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
%% A task's `settings' names the settings object (see {@link cell_settings}) whose
%% snapshot it runs on, taken at each Start; a map gives fixed settings instead. The
%% cell's `settings' lists the schema modules of its own settings objects.
%%
%% A cell application's own module returns it from the settings (seed 000 §2.3.3: one
%% setting switches a cell between simulated and real tasks and IO): the `cell' app's
%% `cell_module' environment key names that module, whose `cell_spec/0' is called at
%% boot. The `cell_spec' key may hold a spec directly (tests do). Every field is checked
%% here; a bad spec stops the boot with an error that names the task and the field.
-module(cell_spec).

-export([load/0, validate/1, empty/0]).

-export_type([spec/0]).

-type spec() :: #{name := binary(), tasks := [cell_task:spec()], settings := [module()]}.

%% @doc A cell without tasks.
-spec empty() -> spec().
empty() ->
    #{name => <<"cell">>, tasks => [], settings => []}.

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
                true -> validate(Mod:cell_spec());
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
    case tasks(Tasks, [], #{}) of
        {ok, _} when not is_binary(Name) ->
            {error, {bad_cell_spec, name, Name}};
        {ok, Checked} ->
            case is_list(Schemas) andalso lists:all(fun is_schema/1, Schemas) of
                true -> {ok, Spec#{name => Name, tasks => Checked, settings => Schemas}};
                false -> {error, {bad_cell_spec, settings, Schemas}}
            end;
        Error ->
            Error
    end;
validate(Other) ->
    {error, {bad_cell_spec, "a cell spec is a map with a list of tasks", Other}}.

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
                {args, #{}, fun is_map/1}],
    case [K || {K, Ok} <- Checks, not (maps:is_key(K, T) andalso Ok(maps:get(K, T)))] of
        [] ->
            case [K || {K, _, Ok} <- Optional, maps:is_key(K, T), not Ok(maps:get(K, T))] of
                [] ->
                    Unknown = maps:keys(T) -- [id | [K || {K, _} <- Checks] ++
                                                   [K || {K, _, _} <- Optional]],
                    case Unknown of
                        [] -> {ok, maps:merge(maps:from_list([{K, D} || {K, D, _} <- Optional]), T)};
                        _ -> {error, {unknown_keys, Unknown}}
                    end;
                Bad ->
                    {error, {bad_option, hd(Bad)}}
            end;
        Bad ->
            {error, {bad_option, hd(Bad)}}
    end.

is_name(B) -> is_binary(B) andalso B =/= <<>>.

is_schema(Mod) when is_atom(Mod) ->
    code:ensure_loaded(Mod) =:= {module, Mod}
        andalso erlang:function_exported(Mod, name, 0)
        andalso erlang:function_exported(Mod, fields, 0);
is_schema(_) ->
    false.

is_task_module(Mod) when is_atom(Mod) ->
    case code:ensure_loaded(Mod) of
        {module, Mod} ->
            lists:all(fun({F, A}) -> erlang:function_exported(Mod, F, A) end,
                      [{init, 1}, {step, 1}, {uninit, 1}]);
        {error, _} ->
            false
    end;
is_task_module(_) ->
    false.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

validate_test_() ->
    Good = #{id => a, module => cell_test_task, zone => <<"Z">>, lane => <<"L">>},
    [?_assertMatch({ok, #{name := <<"cell">>, tasks := [#{io := [], args := #{}}]}},
                   validate(#{tasks => [Good]})),
     ?_assertEqual({error, {bad_task, a, duplicate_id}}, validate(#{tasks => [Good, Good]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, module}}},
                   validate(#{tasks => [Good#{module => lists}]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, zone}}},
                   validate(#{tasks => [Good#{zone => "Z"}]})),
     ?_assertEqual({error, {bad_task, a, {bad_option, io}}},
                   validate(#{tasks => [Good#{io => [<<"x">>]}]})),
     ?_assertEqual({error, {bad_task, a, {unknown_keys, [colour]}}},
                   validate(#{tasks => [Good#{colour => red}]})),
     ?_assertMatch({error, {bad_task, _, _}}, validate(#{tasks => [#{id => "a"}]})),
     ?_assertMatch({error, {bad_cell_spec, _, _}}, validate([])),
     ?_assertMatch({ok, _}, validate(#{tasks => []})),
     ?_assertMatch({ok, #{tasks := [#{settings := loading}]}},
                   validate(#{tasks => [Good#{settings => loading}]})),
     ?_assertMatch({error, {bad_cell_spec, settings, _}},
                   validate(#{tasks => [], settings => [lists]}))].
-endif.
