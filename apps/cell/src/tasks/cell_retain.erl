%% @doc Retained task data (what PLC programmers call RETAIN or PERSISTENT variables):
%% a small key-value store of a task's own (a serial counter, tool wear, the last
%% serial made), durable as its product is.
%%
%% Each task keeps its retained data in `Data/<Zone>@<Lane>.retain', a record file of
%% {@link cell_file} written in place, durably and atomically, at every change: a crash
%% or a power cut at any instant leaves the data before the change or after it, never
%% a mix and never nothing. The engine loads the file when the task starts (again after
%% a crash), so the task goes on from what its predecessor last made durable. A file
%% that cannot be read is reported, never taken for an empty store: a serial counter
%% starting again from zero would make duplicate serials.
%%
%% Keys are atoms or binaries; values are plain data (numbers, atoms, binaries, and
%% lists, tuples and maps of them) of at most {@link max_bytes/0} for the whole store
%% as stored. Pids, ports, references and funs are refused: they mean nothing after a
%% restart. An atom in the data must be one the task's code names, so that it exists
%% again when the file is read (an unknown atom makes the file unreadable, never a new
%% atom). Task modules use the functions of {@link cell_task} (`retained/3',
%% `retain/3', `retain_update/4', `forget_retained/2'); this module is their pure part
%% and the file.
-module(cell_retain).

-export([path/2, file_name/2, max_bytes/0, check/2, put/3, update/4, remove/2,
         load/1, save/3, text/1]).

-export_type([data/0, key/0, refusal/0]).

-type key() :: atom() | binary().
-type data() :: #{key() => term()}.
-type refusal() :: {bad_retained, term(), bad_key | {unsafe, term()}
                                          | {too_big, pos_integer(), pos_integer()}}.

-define(MAX_BYTES, 65536).

%% @doc The retained-data file of a task, as a binary (a binary name goes to the system
%% as it is).
-spec path(binary(), binary()) -> binary().
path(Zone, Lane) ->
    unicode:characters_to_binary(filename:join(cell_config:dir(data), file_name(Zone, Lane)),
                                 unicode, file:native_name_encoding()).

%% @doc `<Zone>@<Lane>.retain', named as the task's product file is.
-spec file_name(binary(), binary()) -> string().
file_name(Zone, Lane) ->
    filename:rootname(cell_product:file_name(Zone, Lane)) ++ ".retain".

%% @doc The most a task's retained data may take as stored (external term format).
-spec max_bytes() -> pos_integer().
max_bytes() ->
    ?MAX_BYTES.

%% @doc Whether `Value' may be retained under `Key'.
-spec check(term(), term()) -> ok | {error, refusal()}.
check(Key, _Value) when not is_atom(Key), not is_binary(Key) ->
    {error, {bad_retained, Key, bad_key}};
check(Key, Value) ->
    case unsafe(Value) of
        none -> ok;
        Part -> {error, {bad_retained, Key, {unsafe, Part}}}
    end.

%% The first part of a term that means nothing after a restart, or `none'.
unsafe(T) when is_number(T); is_atom(T); is_binary(T) -> none;
unsafe([]) -> none;
unsafe([H | Tail]) ->
    case unsafe(H) of
        none -> unsafe_tail(Tail);
        Part -> Part
    end;
unsafe(T) when is_tuple(T) -> first_unsafe(tuple_to_list(T));
unsafe(M) when is_map(M) -> first_unsafe(lists:append([[K, V] || {K, V} <- maps:to_list(M)]));
unsafe(T) -> T.

%% An improper list's tail is data too.
unsafe_tail(L) when is_list(L) -> unsafe(L);
unsafe_tail(T) -> unsafe(T).

first_unsafe([]) -> none;
first_unsafe([T | Rest]) ->
    case unsafe(T) of
        none -> first_unsafe(Rest);
        Part -> Part
    end.

%% @doc `Data' with `Key' set to `Value', checked (the key and value, then the size of
%% the whole).
-spec put(data(), term(), term()) -> {ok, data()} | {error, refusal()}.
put(Data, Key, Value) ->
    case check(Key, Value) of
        ok -> sized(Key, Data#{Key => Value});
        Error -> Error
    end.

%% @doc `Fun' applied to the value of `Key' (to `Default' when it has none), and the
%% data with its result set.
-spec update(data(), term(), fun((term()) -> term()), term()) ->
          {ok, term(), data()} | {error, refusal()}.
update(Data, Key, Fun, Default) ->
    New = Fun(maps:get(Key, Data, Default)),
    case put(Data, Key, New) of
        {ok, Data1} -> {ok, New, Data1};
        Error -> Error
    end.

%% @doc `Data' without `Key'.
-spec remove(data(), term()) -> data().
remove(Data, Key) ->
    maps:remove(Key, Data).

sized(Key, Data) ->
    case erlang:external_size(Data) of
        Bytes when Bytes =< ?MAX_BYTES -> {ok, Data};
        Bytes -> {error, {bad_retained, Key, {too_big, Bytes, ?MAX_BYTES}}}
    end.

%% @doc A task's retained data from its file: empty when it has none yet.
-spec load(file:filename_all()) ->
          {ok, data()} | {error, {corrupt, atom()} | {bad_retained_file, term()}
                                 | {file:filename_all(), term()}}.
load(Path) ->
    case cell_file:get_record(Path) of
        {ok, #{retained := Data}} when is_map(Data) ->
            case valid(Data) of
                true -> {ok, Data};
                false -> {error, {bad_retained_file, Data}}
            end;
        {ok, Other} -> {error, {bad_retained_file, Other}};
        {error, enoent} -> {ok, #{}};
        {error, _} = Error -> Error
    end.

valid(Data) ->
    lists:all(fun({K, V}) -> check(K, V) =:= ok end, maps:to_list(Data)).

%% @doc Makes `Data' the task's retained data, durably: on the disk when this returns
%% (in a folder held in RAM, in the file).
-spec save(file:filename_all() | cell_file:record_file(), data(), cell_file:options()) ->
          ok | cell_file:error().
save(File, Data, Opts) ->
    cell_file:put_record(File, #{retained => Data}, Opts).

%% @doc A refusal or a load error in words.
-spec text(term()) -> iolist().
text({bad_retained, Key, bad_key}) ->
    io_lib:format("the key ~tP is neither an atom nor a binary", [Key, 8]);
text({bad_retained, Key, {unsafe, Part}}) ->
    io_lib:format("the value of ~tP holds ~tP, which means nothing after a restart "
                  "(retain plain data: numbers, atoms, binaries, lists, tuples, maps)",
                  [Key, 8, Part, 8]);
text({bad_retained, Key, {too_big, Bytes, Max}}) ->
    io_lib:format("with ~tP the retained data would take ~b bytes, more than the ~b "
                  "allowed", [Key, 8, Bytes, Max]);
text({corrupt, Why}) ->
    io_lib:format("the file is damaged (~ts)", [Why]);
text({bad_retained_file, _}) ->
    "the file holds something other than retained data";
text({Path, Reason}) ->
    io_lib:format("~ts: ~ts", [Path, file:format_error(Reason)]);
text(Other) ->
    io_lib:format("~tP", [Other, 12]).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

file_name_test_() ->
    [?_assertEqual("Loading@Front.retain", file_name(<<"Loading">>, <<"Front">>)),
     ?_assertEqual("a_b@c_d.retain", file_name(<<"a/b">>, <<"c:d">>)),
     ?_assertEqual("Sägen@Vorn 2.retain", file_name(<<"Sägen"/utf8>>, <<"Vorn 2">>))].

check_test_() ->
    [?_assertEqual(ok, check(serial, 7)),
     ?_assertEqual(ok, check(<<"wear">>, 0.25)),
     ?_assertEqual(ok, check(last, #{serial => <<"P-1">>, at => {2026, [1, 2 | 3]}})),
     ?_assertEqual({error, {bad_retained, "k", bad_key}}, check("k", 1)),
     ?_assertEqual({error, {bad_retained, {a}, bad_key}}, check({a}, 1)),
     ?_assertMatch({error, {bad_retained, k, {unsafe, P}}} when is_pid(P),
                   check(k, [1, {x, self()}])),
     ?_assertMatch({error, {bad_retained, k, {unsafe, F}}} when is_function(F),
                   check(k, #{f => fun() -> ok end})),
     ?_assertMatch({error, {bad_retained, k, {unsafe, R}}} when is_reference(R),
                   check(k, #{make_ref() => 1})),
     ?_assertMatch({error, {bad_retained, k, {unsafe, R}}} when is_reference(R),
                   check(k, [a | make_ref()]))].

%% Both sides of the size limit.
size_limit_test() ->
    Overhead = erlang:external_size(#{k => <<>>}),
    Fits = binary:copy(<<"x">>, ?MAX_BYTES - Overhead),
    ?assertEqual({ok, #{k => Fits}}, put(#{}, k, Fits)),
    ?assertEqual(?MAX_BYTES, erlang:external_size(#{k => Fits})),
    Over = <<Fits/binary, "x">>,
    ?assertEqual({error, {bad_retained, k, {too_big, ?MAX_BYTES + 1, ?MAX_BYTES}}},
                 put(#{}, k, Over)),
    %% The whole counts: a small value is refused when the others fill the store.
    ?assertMatch({error, {bad_retained, j, {too_big, _, _}}}, put(#{k => Fits}, j, 1)).

update_test_() ->
    Inc = fun(N) -> N + 1 end,
    [?_assertEqual({ok, 1, #{n => 1}}, update(#{}, n, Inc, 0)),
     ?_assertEqual({ok, 8, #{n => 8, m => a}}, update(#{n => 7, m => a}, n, Inc, 0)),
     ?_assertMatch({error, {bad_retained, n, {unsafe, _}}},
                   update(#{}, n, fun(_) -> self() end, 0)),
     ?_assertEqual(#{m => a}, remove(#{n => 7, m => a}, n)),
     ?_assertEqual(#{}, remove(#{}, n))].

text_test_() ->
    Flat = fun(T) -> lists:flatten(io_lib:format("~ts", [text(T)])) end,
    [?_assertEqual("the key \"k\" is neither an atom nor a binary",
                   Flat({bad_retained, "k", bad_key})),
     ?_assertMatch("with k the retained data would take 70000 bytes" ++ _,
                   Flat({bad_retained, k, {too_big, 70000, ?MAX_BYTES}})),
     ?_assertEqual("the file is damaged (bad_checksum)", Flat({corrupt, bad_checksum}))].

save_load_test_() ->
    [{Where, fun() ->
                     Dir = Make(),
                     try save_load(Dir) after file:del_dir_r(Dir) end
             end}
     || {Where, Make} <- [{"disk", fun disk_dir/0}, {"RAM", fun ram_dir/0}]].

save_load(Dir) ->
    P = filename:join(Dir, file_name(<<"Z">>, <<"L">>)),
    ?assertEqual({ok, #{}}, load(P)),
    H = cell_file:record_file(P),
    [begin
         ok = save(H, #{serial => N, <<"wear">> => N / 10}, #{}),
         ?assertEqual({ok, #{serial => N, <<"wear">> => N / 10}}, load(P))
     end || N <- lists:seq(1, 5)],
    %% Damaged or foreign: an error, never an empty store.
    {ok, Whole} = file:read_file(P),
    ok = file:write_file(P, binary:copy(<<0>>, byte_size(Whole))),
    ?assertEqual({error, {corrupt, no_whole_record}}, load(P)),
    ok = file:write_file(P, <<"garbage">>),
    ?assertEqual({error, {corrupt, not_a_cellrt_file}}, load(P)),
    ok = cell_file:put_record(P, {something, else}),
    ?assertMatch({error, {bad_retained_file, _}}, load(P)),
    ok = cell_file:put_record(P, #{retained => #{"k" => 1}}),
    ?assertMatch({error, {bad_retained_file, _}}, load(P)),
    ok = save(H, #{serial => 9}, #{}),
    ?assertEqual({ok, #{serial => 9}}, load(P)).

disk_dir() ->
    Dir = filename:join(["/tmp", "cell_retain_test",
                         os:getpid() ++ "-" ++ integer_to_list(erlang:unique_integer([positive]))]),
    _ = file:del_dir_r(Dir),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Dir.

ram_dir() ->
    Dir = filename:join("/dev/shm", "cell_retain_test-" ++ os:getpid() ++ "-"
                        ++ integer_to_list(erlang:unique_integer([positive]))),
    ok = file:make_dir(Dir),
    Dir.
-endif.
