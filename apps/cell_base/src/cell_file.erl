%% @doc Durable files: a crash or a power cut at any instant leaves the old content or
%% the new, never a torn or empty file.
%%
%% A replacement is written to a temporary file beside the target, flushed to the disk,
%% renamed over the target, and the folder is flushed so the rename itself survives a
%% power cut. A deletion flushes the folder too. Leftover temporary files of an
%% interrupted write are removed by {@link cleanup/1}.
%%
%% Terms are stored with a magic line, a length and a CRC-32, so a damaged file is
%% recognised and reported, never half-read.
-module(cell_file).

-export([write/2, write/3, delete/1, delete/2, fsync_dir/1]).
-export([write_term/2, write_term/3, read_term/1, encode_term/1, decode_term/1]).
-export([cleanup/1]).

-export_type([options/0, error/0]).

-on_load(load_nif/0).

-type options() :: #{sync => boolean()}.
%% `sync => false' skips the flushes: for folders on a RAM disk and for tests.
-type error() :: {error, {file:filename(), term()}}.

-define(MAGIC, "cellrt-term 1\n").
-define(TMP_MARK, ".tmp-").

load_nif() ->
    Dir = case code:priv_dir(cell_base) of
              {error, bad_name} ->
                  filename:join(filename:dirname(filename:dirname(code:which(?MODULE))),
                                "priv");
              D -> D
          end,
    erlang:load_nif(filename:join(Dir, "cell_file_nif"), 0).

%% @doc Replaces the content of `Path' durably and atomically.
-spec write(file:filename(), iodata()) -> ok | error().
write(Path, Data) ->
    write(Path, Data, #{}).

%% @doc As {@link write/2}; `#{sync => false}' skips the flushes.
-spec write(file:filename(), iodata(), options()) -> ok | error().
write(Path, Data, Opts) ->
    Sync = maps:get(sync, Opts, true),
    Tmp = Path ++ ?TMP_MARK ++ integer_to_list(erlang:unique_integer([positive])),
    case write_tmp(Tmp, Data, Sync) of
        ok ->
            case file:rename(Tmp, Path) of
                ok when Sync -> sync_parent(Path);
                ok -> ok;
                {error, Reason} ->
                    _ = file:delete(Tmp),
                    {error, {Path, Reason}}
            end;
        {error, Reason} ->
            _ = file:delete(Tmp),
            {error, {Path, Reason}}
    end.

write_tmp(Tmp, Data, Sync) ->
    case file:open(Tmp, [write, raw, binary]) of
        {ok, Fd} ->
            Result = case file:write(Fd, Data) of
                         ok when Sync -> file:datasync(Fd);
                         Other -> Other
                     end,
            case {Result, file:close(Fd)} of
                {ok, ok} -> ok;
                {ok, CloseError} -> CloseError;
                {Error, _} -> Error
            end;
        Error ->
            Error
    end.

%% @doc Deletes `Path' durably; a missing file is not an error.
-spec delete(file:filename()) -> ok | error().
delete(Path) ->
    delete(Path, #{}).

%% @doc As {@link delete/1}; `#{sync => false}' skips the folder flush.
-spec delete(file:filename(), options()) -> ok | error().
delete(Path, Opts) ->
    case file:delete(Path) of
        ok ->
            case maps:get(sync, Opts, true) of
                true -> sync_parent(Path);
                false -> ok
            end;
        {error, enoent} -> ok;
        {error, Reason} -> {error, {Path, Reason}}
    end.

sync_parent(Path) ->
    Dir = filename:dirname(filename:absname(Path)),
    case fsync_dir(Dir) of
        ok -> ok;
        {error, Reason} -> {error, {Dir, Reason}}
    end.

%% @doc Flushes a folder's entries (renames, creations, deletions) to the disk.
-spec fsync_dir(file:filename()) -> ok | {error, file:posix()}.
fsync_dir(_Dir) ->
    erlang:nif_error(nif_not_loaded).

%% @doc Writes a term durably with a checksum (see {@link read_term/1}).
-spec write_term(file:filename(), term()) -> ok | error().
write_term(Path, Term) ->
    write(Path, encode_term(Term)).

%% @doc As {@link write_term/2} with options.
-spec write_term(file:filename(), term(), options()) -> ok | error().
write_term(Path, Term, Opts) ->
    write(Path, encode_term(Term), Opts).

%% @doc Reads a term written by {@link write_term/2}. A file that is damaged, cut
%% short or not ours is `{error, {corrupt, Why}}', never a partial term.
-spec read_term(file:filename()) ->
          {ok, term()} | {error, enoent} | {error, {corrupt, atom()}} | error().
read_term(Path) ->
    case file:read_file(Path) of
        {ok, Bin} -> decode_term(Bin);
        {error, enoent} -> {error, enoent};
        {error, Reason} -> {error, {Path, Reason}}
    end.

%% @doc The stored form of a term: magic line, length, CRC-32, external term format.
-spec encode_term(term()) -> binary().
encode_term(Term) ->
    Body = term_to_binary(Term),
    <<?MAGIC, (byte_size(Body)):32, (erlang:crc32(Body)):32, Body/binary>>.

%% @doc Decodes {@link encode_term/1}; atoms not already known are refused.
-spec decode_term(binary()) -> {ok, term()} | {error, {corrupt, atom()}}.
decode_term(<<?MAGIC, Len:32, Crc:32, Body:Len/binary>>) ->
    case erlang:crc32(Body) of
        Crc ->
            try binary_to_term(Body, [safe]) of
                Term -> {ok, Term}
            catch
                error:badarg -> {error, {corrupt, bad_term}}
            end;
        _ ->
            {error, {corrupt, bad_checksum}}
    end;
decode_term(<<?MAGIC, Len:32, _Crc:32, Body/binary>>) when byte_size(Body) < Len ->
    {error, {corrupt, truncated}};
decode_term(<<?MAGIC, _/binary>>) ->
    {error, {corrupt, bad_length}};
decode_term(_) ->
    {error, {corrupt, not_a_cellrt_file}}.

%% @doc Removes the temporary files an interrupted write left in `Dir'.
-spec cleanup(file:filename()) -> [file:filename()].
cleanup(Dir) ->
    Leftovers = filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir),
    [begin _ = file:delete(filename:join(Dir, F)), F end || F <- Leftovers].

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% A folder no earlier run has used: the OS pid and a per-VM unique number, emptied.
tmp_dir() ->
    Dir = filename:join(["/tmp", "cell_file_test",
                         os:getpid() ++ "-" ++ integer_to_list(erlang:unique_integer([positive]))]),
    _ = file:del_dir_r(Dir),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Dir.

term_roundtrip_test() ->
    Dir = tmp_dir(),
    P = filename:join(Dir, "a.product"),
    ok = write_term(P, #{serial => <<"S1">>, failed => false}),
    ?assertEqual({ok, #{serial => <<"S1">>, failed => false}}, read_term(P)),
    ok = write_term(P, #{serial => <<"S2">>}, #{sync => false}),
    ?assertEqual({ok, #{serial => <<"S2">>}}, read_term(P)),
    ?assertEqual([], filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir)).

missing_and_delete_test() ->
    Dir = tmp_dir(),
    P = filename:join(Dir, "gone"),
    ?assertEqual({error, enoent}, read_term(P)),
    ?assertEqual(ok, delete(P)),
    ok = write(P, <<"x">>),
    ?assertEqual(ok, delete(P)),
    ?assertEqual({error, enoent}, read_term(P)).

corrupt_test_() ->
    Good = encode_term({a, 1}),
    Size = byte_size(Good),
    <<Head:(Size - 1)/binary, Last>> = Good,
    [?_assertEqual({error, {corrupt, bad_checksum}}, decode_term(<<Head/binary, (Last bxor 1)>>)),
     ?_assertEqual({error, {corrupt, truncated}}, decode_term(Head)),
     ?_assertEqual({error, {corrupt, not_a_cellrt_file}}, decode_term(<<>>)),
     ?_assertEqual({error, {corrupt, not_a_cellrt_file}}, decode_term(<<"hello">>)),
     ?_assertEqual({error, {corrupt, bad_length}}, decode_term(<<?MAGIC, 1, 2>>)),
     ?_assertEqual({ok, {a, 1}}, decode_term(Good))].

unknown_atom_is_corrupt_test() ->
    %% A checksummed body naming an atom this node never saw: refused, not created.
    Body = <<131, 100, 0, 20, "cell_file_never_seen">>,
    Bin = <<?MAGIC, (byte_size(Body)):32, (erlang:crc32(Body)):32, Body/binary>>,
    ?assertEqual({error, {corrupt, bad_term}}, decode_term(Bin)).

cleanup_test() ->
    Dir = tmp_dir(),
    ok = file:write_file(filename:join(Dir, "x.product" ++ ?TMP_MARK ++ "7"), <<"half">>),
    ok = file:write_file(filename:join(Dir, "y.product"), <<"keep">>),
    ?assertEqual(["x.product.tmp-7"], cleanup(Dir)),
    ?assertEqual(["y.product"], filelib:wildcard("*", Dir)).

fsync_dir_test_() ->
    [?_assertEqual(ok, fsync_dir("/tmp")),
     ?_assertEqual({error, enoent}, fsync_dir("/tmp/cell_file_no_such_dir")),
     ?_assertEqual({error, enotdir}, fsync_dir("/etc/hostname")),
     ?_assertError(badarg, fsync_dir(<<>>))].
-endif.
