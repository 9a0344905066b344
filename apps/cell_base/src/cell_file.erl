%% @doc Durable files: a crash or a power cut at any instant leaves the old content or
%% the new, never a torn or empty file.
%%
%% A replacement is written to a temporary file beside the target, flushed to the disk,
%% renamed over the target, and the folder is flushed so the rename itself survives a
%% power cut. A deletion flushes the folder too. Leftover temporary files of an
%% interrupted write are removed by {@link cleanup/1}.
%%
%% A replacement or a deletion is one call into C on a dirty I/O scheduler; in a folder
%% held in RAM (tmpfs, ramfs: nothing waits for a device there) it runs on the calling
%% scheduler, which is several times faster, and flushes nothing: a flush there does
%% nothing but cost a system call.
%%
%% A writer killed during its call into C is gone before its write has landed; {@link
%% read_term/1} waits for such a write, so a process restarted after a crash reads what
%% its last incarnation wrote.
%%
%% Terms are stored with a magic line, a length and a CRC-32, so a damaged file is
%% recognised and reported, never half-read.
%%
%% A file rewritten at every change (a task's product) is a record file instead: two
%% slots, each write in place to the slot not holding the record, one write and one
%% flush (see {@link put_record/3}). Its writer may keep it open through a handle
%% ({@link record_file/1}), so a write needs no open, read and close.
-module(cell_file).

-export([write/2, write/3, delete/1, delete/2, fsync_dir/1]).
-export([write_term/2, write_term/3, read_term/1, encode_term/1, decode_term/1]).
-export([put_record/2, put_record/3, get_record/1, record_file/1]).
-export([append_file/1, append/3, close_append/1]).
-export([cleanup/1, in_ram/1]).

-export_type([options/0, error/0, record_file/0, append_file/0]).

-on_load(load_nif/0).

-type options() :: #{sync => boolean()}.
%% `sync => false' skips the flushes: for folders on a RAM disk and for tests.
-type error() :: {error, {file:filename_all(), term()}}.
-opaque record_file() :: {record_file, Path :: binary(), Folder :: binary(), reference()}.
%% A record file kept open by its writer (see {@link record_file/1}).
-opaque append_file() :: {append_file, Path :: binary(), Folder :: binary(), reference()}.
%% A file appended to by its one writer (see {@link append_file/1}).

-define(MAGIC, "cellrt-term 1\n").
-define(TMP_MARK, ".tmp-").
-define(RECORD_MAGIC, "cellrt-record 1\n").
-define(RECORD_HEADER, 32).

load_nif() ->
    Dir = case code:priv_dir(cell_base) of
              {error, bad_name} ->
                  filename:join(filename:dirname(filename:dirname(code:which(?MODULE))),
                                "priv");
              D -> D
          end,
    erlang:load_nif(filename:join(Dir, "cell_file_nif"), 0).

%% @doc Replaces the content of `Path' durably and atomically.
-spec write(file:filename_all(), iodata()) -> ok | error().
write(Path, Data) ->
    write(Path, Data, #{}).

%% @doc As {@link write/2}; `#{sync => false}' skips the flushes.
-spec write(file:filename_all(), iodata(), options()) -> ok | error().
write(Path, Data, Opts) ->
    Target = native(Path),
    Tmp = <<Target/binary, ?TMP_MARK, (integer_to_binary(erlang:unique_integer([positive])))/binary>>,
    in_c(Path, folder(Target), Opts,
         fun(Sync) -> replace_ram_nif(Tmp, Target, Data, Sync) end,
         fun(Sync) -> replace_nif(Tmp, Target, Data, Sync) end).

%% @doc Deletes `Path' durably; a missing file is not an error.
-spec delete(file:filename_all()) -> ok | error().
delete(Path) ->
    delete(Path, #{}).

%% @doc As {@link delete/1}; `#{sync => false}' skips the folder flush.
-spec delete(file:filename_all(), options()) -> ok | error().
delete(Path, Opts) ->
    Target = native(Path),
    in_c(Path, folder(Target), Opts, fun(Sync) -> remove_ram_nif(Target, Sync) end,
         fun(Sync) -> remove_nif(Target, Sync) end).

%% One call into C for a file of Folder, given whether to flush: on the calling
%% scheduler and never flushing in a folder held in RAM (a flush there only costs a
%% system call); on a dirty I/O scheduler, flushing unless `sync => false', elsewhere.
%% An error names the file, or its folder if flushing that failed.
in_c(Path, Folder, Opts, InRam, OnDisk) ->
    Result = case in_ram(Folder) of
                 true -> InRam(false);
                 false -> OnDisk(maps:get(sync, Opts, true))
             end,
    case Result of
        ok -> ok;
        {error, {dir, Reason}} -> {error, {parent(Path), Reason}};
        {error, {_Where, Reason}} -> {error, {Path, Reason}}
    end.

%% @doc A handle on the record file `Path' for its one writer: the file is kept open
%% between writes through it (see {@link put_record/3}), and closed when the handle is
%% no longer referenced. While a handle is used, every write of the file must go
%% through it. A file set aside, replaced or deleted meanwhile is opened anew.
-spec record_file(file:filename_all()) -> record_file().
record_file(Path) ->
    Target = native(Path),
    {record_file, Target, folder(Target), record_open_nif(Target)}.

%% @doc Opens `Path' (created if missing) for its one writer to append to it with
%% {@link append/3}; closed by {@link close_append/1} or when no longer referenced. A
%% crash during an append may leave its data cut short at the end of the file: the
%% reader must recognise a torn tail.
-spec append_file(file:filename_all()) -> {ok, append_file()} | error().
append_file(Path) ->
    Target = native(Path),
    case append_open_nif(Target) of
        {ok, Handle} -> {ok, {append_file, Target, folder(Target), Handle}};
        {error, {_, Reason}} -> {error, {Path, Reason}}
    end.

%% @doc Appends `Data' in one write and flushes it to the disk (not in a folder held in
%% RAM, nor with `sync => false'); returns once it is there.
-spec append(append_file(), iodata(), options()) -> ok | error().
append({append_file, Target, Folder, Handle}, Data, Opts) ->
    in_c(Target, Folder, Opts, fun(Sync) -> append_ram_nif(Handle, Data, Sync) end,
         fun(Sync) -> append_nif(Handle, Data, Sync) end).

%% @doc Closes an append file now.
-spec close_append(append_file()) -> ok.
close_append({append_file, _, _, Handle}) ->
    append_close_nif(Handle).

append_open_nif(_Path) ->
    erlang:nif_error(nif_not_loaded).

append_nif(_Handle, _Data, _Sync) ->
    erlang:nif_error(nif_not_loaded).

append_ram_nif(_Handle, _Data, _Sync) ->
    erlang:nif_error(nif_not_loaded).

append_close_nif(_Handle) ->
    erlang:nif_error(nif_not_loaded).

%% @doc Flushes a folder's entries (renames, creations, deletions) to the disk.
-spec fsync_dir(file:filename_all()) -> ok | {error, file:posix()}.
fsync_dir(_Dir) ->
    erlang:nif_error(nif_not_loaded).

%% Writes Data to Tmp, flushes it, renames it over Path and flushes the folder, all in
%% one call on a dirty I/O scheduler (the flushes only if Sync).
replace_nif(_Tmp, _Path, _Data, _Sync) ->
    erlang:nif_error(nif_not_loaded).

%% Writes Body as the record of Path (see put_record/3), in one call.
record_put_nif(_Path, _Body, _Sync) ->
    erlang:nif_error(nif_not_loaded).

record_put_ram_nif(_Path, _Body, _Sync) ->
    erlang:nif_error(nif_not_loaded).

%% A handle on a record file, and a write through it (on a dirty I/O scheduler, or
%% the calling one in a folder held in RAM).
record_open_nif(_Path) ->
    erlang:nif_error(nif_not_loaded).

record_put_handle_nif(_Handle, _Body, _Sync) ->
    erlang:nif_error(nif_not_loaded).

record_put_handle_ram_nif(_Handle, _Body, _Sync) ->
    erlang:nif_error(nif_not_loaded).

%% Deletes Path and flushes its folder (if Sync), in one call.
remove_nif(_Path, _Sync) ->
    erlang:nif_error(nif_not_loaded).

%% The same two on the calling scheduler, for folders held in RAM.
replace_ram_nif(_Tmp, _Path, _Data, _Sync) ->
    erlang:nif_error(nif_not_loaded).

remove_ram_nif(_Path, _Sync) ->
    erlang:nif_error(nif_not_loaded).

in_ram_nif(_Dir) ->
    erlang:nif_error(nif_not_loaded).

%% Whether a replacement or deletion of Path is under way, asked on the calling
%% scheduler; and a wait, on a dirty one, until none is.
writing_nif(_Path) ->
    erlang:nif_error(nif_not_loaded).

settle_nif(_Path) ->
    erlang:nif_error(nif_not_loaded).

%% A process killed while its write runs in C is gone before the write has landed: a
%% reader waits for it, so a task restarted after a crash reads its last word.
%% A name C cannot take is left for the read to refuse.
settle(Path) ->
    try
        Target = native(Path),
        case writing_nif(Target) of
            false -> ok;
            true -> settle_nif(Target)
        end
    catch
        error:_ -> ok
    end.

%% @doc Whether a folder is held in RAM (tmpfs, ramfs). Asked of the system once per
%% folder; a folder that does not exist yet is asked again next time.
-spec in_ram(file:filename_all()) -> boolean().
in_ram(Dir) ->
    Key = {?MODULE, in_ram, Dir},
    case persistent_term:get(Key, unknown) of
        unknown ->
            case in_ram_nif(native(Dir)) of
                {ok, Ram} ->
                    persistent_term:put(Key, Ram),
                    Ram;
                {error, _} ->
                    false
            end;
        Ram ->
            Ram
    end.

%% The folder of a file name (a binary): what is before its last slash.
folder(Path) ->
    case binary:matches(Path, <<"/">>) of
        [] -> <<".">>;
        [{0, 1}] -> <<"/">>;
        Slashes -> binary_part(Path, 0, element(1, lists:last(Slashes)))
    end.

%% A file name as the system calls take it, encoded as the file module encodes it.
native(Path) when is_binary(Path) ->
    Path;
native(Path) ->
    case unicode:characters_to_binary(Path, unicode, file:native_name_encoding()) of
        Bin when is_binary(Bin) -> Bin;
        _ -> erlang:error({badarg, Path})
    end.

parent(Path) ->
    filename:dirname(filename:absname(Path)).

%% @doc Writes a term durably with a checksum (see {@link read_term/1}).
-spec write_term(file:filename_all(), term()) -> ok | error().
write_term(Path, Term) ->
    write(Path, encode_term(Term)).

%% @doc As {@link write_term/2} with options.
-spec write_term(file:filename_all(), term(), options()) -> ok | error().
write_term(Path, Term, Opts) ->
    write(Path, encode_term(Term), Opts).

%% @doc Reads a term written by {@link write_term/2}. A file that is damaged, cut
%% short or not ours is `{error, {corrupt, Why}}', never a partial term.
-spec read_term(file:filename_all()) ->
          {ok, term()} | {error, enoent} | {error, {corrupt, atom()}} | error().
read_term(Path) ->
    ok = settle(Path),
    case file:read_file(Path) of
        {ok, Bin} -> decode_term(Bin);
        {error, enoent} -> {error, enoent};
        {error, Reason} -> {error, {Path, Reason}}
    end.

%% @doc Makes `Term' the record of `Path', durably and atomically, in place.
%%
%% A record file holds its term in two slots; a write goes to the slot that does not
%% hold the record (one write and one flush, nothing created, renamed or removed), so
%% a crash or a power cut during it leaves the record as it was. That makes it several
%% times cheaper than {@link write_term/2} for a file rewritten at every change, such as
%% a task's product. A missing file, one of another form, or a term too big for the
%% slots is written whole, as by {@link write/2}.
-spec put_record(file:filename_all(), term()) -> ok | error().
put_record(Path, Term) ->
    put_record(Path, Term, #{}).

%% @doc As {@link put_record/2}; `#{sync => false}' skips the flush. Through a handle
%% of {@link record_file/1} the file stays open between writes.
-spec put_record(file:filename_all() | record_file(), term(), options()) -> ok | error().
put_record({record_file, Target, Folder, Handle}, Term, Opts) ->
    Body = term_to_binary(Term),
    in_c(Target, Folder, Opts,
         fun(Sync) -> record_put_handle_ram_nif(Handle, Body, Sync) end,
         fun(Sync) -> record_put_handle_nif(Handle, Body, Sync) end);
put_record(Path, Term, Opts) ->
    Target = native(Path),
    Body = term_to_binary(Term),
    in_c(Path, folder(Target), Opts,
         fun(Sync) -> record_put_ram_nif(Target, Body, Sync) end,
         fun(Sync) -> record_put_nif(Target, Body, Sync) end).

%% @doc The record of a file written by {@link put_record/2}. A file written by {@link
%% write_term/2} is read as such. `{error, {corrupt, Why}}' when neither slot holds a
%% whole record.
-spec get_record(file:filename_all()) ->
          {ok, term()} | {error, enoent} | {error, {corrupt, atom()}} | error().
get_record(Path) ->
    ok = settle(Path),
    case file:read_file(Path) of
        {ok, <<?MAGIC, _/binary>> = Bin} -> decode_term(Bin);
        {ok, Bin} -> decode_record(Bin);
        {error, enoent} -> {error, enoent};
        {error, Reason} -> {error, {Path, Reason}}
    end.

%% The record of a record file's content: of its two slots, the whole one with the
%% higher sequence number.
decode_record(Bin) when byte_size(Bin) rem 2 =:= 0, byte_size(Bin) >= 2 * ?RECORD_HEADER ->
    Size = byte_size(Bin) div 2,
    <<A:Size/binary, B:Size/binary>> = Bin,
    case lists:reverse(lists:sort([slot(A), slot(B)])) of
        [{0, _} | _] -> {error, {corrupt, no_whole_record}};
        [{_Seq, Body} | _] ->
            try {ok, binary_to_term(Body, [safe])}
            catch error:badarg -> {error, {corrupt, bad_term}}
            end
    end;
decode_record(_Bin) ->
    {error, {corrupt, not_a_cellrt_file}}.

%% {Seq, Body} of a whole slot, {0, none} of any other.
slot(<<?RECORD_MAGIC, Seq:64, Len:32, Crc:32, Rest/binary>>) when Len =< byte_size(Rest) ->
    <<Body:Len/binary, _/binary>> = Rest,
    case erlang:crc32(<<Seq:64, Len:32, Body/binary>>) of
        Crc when Seq > 0 -> {Seq, Body};
        _ -> {0, none}
    end;
slot(_) ->
    {0, none}.

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
-spec cleanup(file:filename_all()) -> [file:filename_all()].
cleanup(Dir) ->
    Leftovers = filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir),
    [begin _ = file:delete(filename:join(Dir, F)), F end || F <- Leftovers].

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").
-include_lib("kernel/include/file.hrl").

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

in_ram_test_() ->
    [?_assertEqual(true, in_ram("/dev/shm")),
     ?_assertEqual(false, in_ram("/proc/no/such/folder")),
     ?_assertEqual(<<"/a/b">>, folder(<<"/a/b/c.product">>)),
     ?_assertEqual(<<"/">>, folder(<<"/c.product">>)),
     ?_assertEqual(<<".">>, folder(<<"c.product">>))].

%% The same durable replacement and deletion in a folder held in RAM, which runs on
%% the calling scheduler.
ram_folder_test() ->
    Dir = ram_dir(),
    try
        P = filename:join(Dir, "r.product"),
        ok = write_term(P, {r, 1}),
        ok = write_term(P, {r, 2}, #{sync => false}),
        ?assertEqual({ok, {r, 2}}, read_term(P)),
        ?assertEqual({error, {filename:join(Dir, "none/x"), enoent}},
                     write(filename:join(Dir, "none/x"), <<"x">>)),
        ok = delete(P),
        ?assertEqual({error, enoent}, read_term(P)),
        ?assertEqual([], filelib:wildcard("*", Dir))
    after
        file:del_dir_r(Dir)
    end.

%% A writer killed while its write runs in C: the write lands all the same, and a read
%% right after the kill returns only once it has, so what it returns is what stays. (The
%% delays only vary the moment of the kill; the checks hold at any moment.)
killed_writer_test_() ->
    {timeout, 120,
     fun() ->
             Dir = tmp_dir(),
             P = filename:join(Dir, "k.product"),
             ok = write_term(P, {k, 0}),
             Big = binary:copy(<<"x">>, 32 bsl 20),
             lists:foldl(fun(N, Before) ->
                                 Data = encode_term({k, N, Big}),
                                 Self = self(),
                                 W = spawn(fun() -> Self ! {writing, self()}, write(P, Data) end),
                                 receive {writing, W} -> ok end,
                                 %% Kill it at a different moment each time: before,
                                 %% during and after its call into C.
                                 receive after N * 3 -> ok end,
                                 exit(W, kill),
                                 Read = read_term(P),
                                 ?assertNot(writing_nif(native(P))),
                                 ?assertEqual(Read, read_term(P)),
                                 case Read of
                                     {ok, Before} -> Before;
                                     {ok, {k, N, Big} = New} -> New
                                 end
                         end, {k, 0}, lists:seq(1, 8)),
             ?assertEqual([], filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir))
     end}.

record_roundtrip_test() ->
    Dir = tmp_dir(),
    P = filename:join(Dir, "r.product"),
    ?assertEqual({error, enoent}, get_record(P)),
    [begin
         ok = put_record(P, {r, N}, #{sync => N rem 2 =:= 0}),
         ?assertEqual({ok, {r, N}}, get_record(P))
     end || N <- lists:seq(1, 5)],
    %% Two slots of a page each; the writes went to them in turn, in place.
    ?assertEqual(8192, filelib:file_size(P)),
    ok = put_record(P, undefined),
    ?assertEqual({ok, undefined}, get_record(P)),
    %% A term bigger than the slots: the file is written whole, with bigger slots.
    Big = binary:copy(<<"b">>, 10000),
    ok = put_record(P, Big),
    ?assertEqual({ok, Big}, get_record(P)),
    ?assert(filelib:file_size(P) > 2 * 10000),
    ok = put_record(P, small),
    ?assertEqual({ok, small}, get_record(P)),
    ?assertEqual([], filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir)).

%% The file of write_term/2 is read as a record, and the first put_record/2 turns it
%% into a record file.
record_over_term_file_test() ->
    Dir = tmp_dir(),
    P = filename:join(Dir, "t.product"),
    ok = write_term(P, {old, 1}),
    ?assertEqual({ok, {old, 1}}, get_record(P)),
    ok = put_record(P, {new, 2}),
    ?assertEqual({ok, {new, 2}}, get_record(P)),
    ok = file:write_file(P, <<"not ours at all">>),
    ?assertEqual({error, {corrupt, not_a_cellrt_file}}, get_record(P)),
    ok = put_record(P, {new, 3}),
    ?assertEqual({ok, {new, 3}}, get_record(P)).

%% A write torn anywhere leaves the record before it; a torn slot is the one the next
%% write takes, so two torn writes in a row still leave a whole record.
record_torn_write_test() ->
    Dir = tmp_dir(),
    P = filename:join(Dir, "torn.product"),
    ok = put_record(P, {r, 1}),
    ok = put_record(P, {r, 2}),
    {ok, Whole} = file:read_file(P),
    Size = byte_size(Whole) div 2,
    ok = put_record(P, {r, 3}),
    {ok, After} = file:read_file(P),
    %% The slot {r, 3} went to, and its bytes in the file after the write.
    Slot = hd([S || S <- [0, 1], binary_part(After, S * Size, Size) =/= binary_part(Whole, S * Size, Size)]),
    New = binary_part(After, Slot * Size, Size),
    Written = byte_size(term_to_binary({r, 3})) + ?RECORD_HEADER,
    lists:foreach(
      fun(Cut) ->
              %% The first Cut bytes of the new slot written, the rest as before.
              Torn = <<(binary_part(New, 0, Cut))/binary,
                       (binary_part(Whole, Slot * Size + Cut, Size - Cut))/binary>>,
              File = case Slot of
                         0 -> <<Torn/binary, (binary_part(Whole, Size, Size))/binary>>;
                         1 -> <<(binary_part(Whole, 0, Size))/binary, Torn/binary>>
                     end,
              ok = file:write_file(P, File),
              ?assertEqual({ok, {r, 2}}, get_record(P)),
              ok = put_record(P, {r, 4}),
              ?assertEqual({ok, {r, 4}}, get_record(P)),
              ok = put_record(P, {r, 5}),
              ?assertEqual({ok, {r, 5}}, get_record(P))
      end, lists:seq(1, Written - 1)).

%% Through a handle the file stays open: the writes alternate between its slots in
%% place, and every one is the record at once, for any reader.
record_handle_test_() ->
    on_disk_and_in_ram(fun record_handle/1).

record_handle(Dir) ->
    P = filename:join(Dir, "h.product"),
    H = record_file(P),
    ok = put_record(H, {h, 0}),
    {ok, #file_info{inode = Inode}} = file:read_file_info(P),
    [begin
         ok = put_record(H, {h, N}, #{sync => N rem 2 =:= 0}),
         ?assertEqual({ok, {h, N}}, get_record(P))
     end || N <- lists:seq(1, 6)],
    ?assertMatch({ok, #file_info{inode = Inode, size = 8192}}, file:read_file_info(P)),
    %% Outgrown: written whole, with bigger slots; then in place again.
    Big = binary:copy(<<"b">>, 10000),
    ok = put_record(H, Big),
    ?assertEqual({ok, Big}, get_record(P)),
    ok = put_record(H, small),
    ?assertEqual({ok, small}, get_record(P)),
    ok = put_record(H, undefined),
    ?assertEqual({ok, undefined}, get_record(P)),
    ?assertEqual([], filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir)).

%% The file at the path changed behind the handle: set aside, deleted, replaced. The
%% next write goes to the file now at the path, never to the one the handle had open.
record_handle_file_changed_test_() ->
    on_disk_and_in_ram(fun record_handle_file_changed/1).

record_handle_file_changed(Dir) ->
    P = filename:join(Dir, "c.product"),
    Aside = P ++ ".damaged",
    H = record_file(P),
    ok = put_record(H, {c, 1}),
    ok = file:rename(P, Aside),
    ok = put_record(H, {c, 2}),
    ?assertEqual({ok, {c, 1}}, get_record(Aside)),
    ?assertEqual({ok, {c, 2}}, get_record(P)),
    ok = file:delete(P),
    ok = put_record(H, {c, 3}),
    ?assertEqual({ok, {c, 3}}, get_record(P)),
    ok = write_term(P, {term, 4}),
    ok = put_record(H, {c, 5}),
    ?assertEqual({ok, {c, 5}}, get_record(P)),
    ok = put_record(H, {c, 6}),
    ?assertEqual({ok, {c, 6}}, get_record(P)),
    ?assertEqual({ok, {c, 1}}, get_record(Aside)),
    %% A folder gone: the error names the file, and the handle recovers with it.
    ok = file:del_dir_r(Dir),
    ?assertEqual({error, {native(P), enoent}}, put_record(H, {c, 7})),
    ok = file:make_dir(Dir),
    ok = put_record(H, {c, 8}),
    ?assertEqual({ok, {c, 8}}, get_record(P)).

%% A handle no longer referenced closes its file.
record_handle_closes_test() ->
    Dir = tmp_dir(),
    %% The files of this folder the VM has open, as the system lists them.
    Open = fun() ->
                   Lines = string:split(os:cmd("ls -l /proc/" ++ os:getpid() ++ "/fd"), "\n", all),
                   length([L || L <- Lines, string:find(L, Dir ++ "/") =/= nomatch])
           end,
    Self = self(),
    %% Handles made and written in a process of their own, which ends.
    {Pid, MRef} = spawn_monitor(
                    fun() ->
                            Hs = [record_file(filename:join(Dir, integer_to_list(N)))
                                  || N <- lists:seq(1, 50)],
                            %% The first write creates a file, the second keeps it open.
                            Write = fun(I) -> [ok = put_record(H, {N, I})
                                               || {N, H} <- lists:enumerate(Hs)]
                                    end,
                            _ = [Write(I) || I <- [1, 2]],
                            Self ! {open, Open()},
                            %% Still in use until here: a handle no longer referenced
                            %% may be collected, and its file closed, at any moment.
                            _ = Write(3)
                    end),
    receive {open, During} -> ?assertEqual(50, During) end,
    receive {'DOWN', MRef, process, Pid, normal} -> ok end,
    %% The resources go with the process's heap; the files close with them.
    ?assertEqual(0, Open()).

%% A test run in a fresh folder on the disk and in one held in RAM, each removed after.
on_disk_and_in_ram(Test) ->
    [{Where, fun() ->
                     Dir = Make(),
                     try Test(Dir) after file:del_dir_r(Dir) end
             end} || {Where, Make} <- [{"disk", fun tmp_dir/0}, {"RAM", fun ram_dir/0}]].

%% As tmp_dir/0, in a folder held in RAM.
ram_dir() ->
    Dir = filename:join("/dev/shm", "cell_file_test-" ++ os:getpid() ++ "-"
                        ++ integer_to_list(erlang:unique_integer([positive]))),
    ok = file:make_dir(Dir),
    Dir.

append_test_() ->
    on_disk_and_in_ram(fun append_in/1).

append_in(Dir) ->
    Path = filename:join(Dir, "a.journal"),
    {ok, A} = append_file(Path),
    ok = append(A, <<"one ">>, #{}),
    ok = append(A, [<<"two">>, " "], #{sync => false}),
    %% Opened again: appended after what is there.
    {ok, B} = append_file(Path),
    ok = append(B, <<"three">>, #{}),
    ?assertEqual({ok, <<"one two three">>}, file:read_file(Path)),
    ok = close_append(A),
    ?assertMatch({error, {_, ebadf}}, append(A, <<"x">>, #{})),
    ok = close_append(B),
    Missing = filename:join([Dir, "no_such_folder", "a.journal"]),
    ?assertEqual({error, {Missing, enoent}}, append_file(Missing)).

errors_name_the_file_test() ->
    Dir = tmp_dir(),
    Missing = filename:join([Dir, "no_such_folder", "a.product"]),
    ?assertEqual({error, {Missing, enoent}}, write(Missing, <<"x">>)),
    %% A folder in the way of the rename.
    Busy = filename:join(Dir, "busy"),
    ok = file:make_dir(Busy),
    ok = file:write_file(filename:join(Busy, "inside"), <<"x">>),
    ?assertEqual({error, {Busy, eisdir}}, write(Busy, <<"x">>)),
    ?assertEqual({error, {Busy, eisdir}}, delete(Busy)),
    %% Nothing half-written is left behind.
    ?assertEqual([], filelib:wildcard("*" ++ ?TMP_MARK ++ "*", Dir)).

binary_and_unicode_paths_test() ->
    Dir = tmp_dir(),
    Uni = filename:join(Dir, [16#00e9, "t", 16#00e9, 16#4e2d, ".product"]),
    ok = write_term(Uni, {a, 1}),
    ?assertEqual({ok, {a, 1}}, read_term(Uni)),
    Bin = unicode:characters_to_binary(Uni),
    ok = write_term(Bin, {b, 2}, #{sync => false}),
    ?assertEqual({ok, {b, 2}}, read_term(Uni)),
    ok = delete(Bin),
    ?assertEqual({error, enoent}, read_term(Uni)).
-endif.
