%% @doc Zip archives from outside, read into memory without trusting them.
%%
%% OTP's `zip' reads the central directory (names, declared sizes, offsets); every
%% limit is checked on that directory before a byte is inflated: archive size, entry
%% count (read from the end record, before the directory is even listed), each
%% entry's declared size, their total, and the compression ratio of large entries
%% (a bomb declares little and inflates to a lot). Names that are absolute, climb
%% with `..', use backslashes or drive letters, or hold control characters are
%% refused, whatever they would have meant.
%%
%% Entries are then inflated here, not by `zip:unzip/2', because that inflates an
%% entry whole, whatever size its header declared. Here inflation runs in steps and
%% stops as soon as an entry grows past its declared size; the size and the CRC-32
%% are checked at the end. Nothing is ever written to disk.
-module(cell_recipe_zip).

-include_lib("kernel/include/file.hrl").
-include_lib("stdlib/include/zip.hrl").

-export([read/2, read/3, write/1, default_limits/0, format_error/1]).

-export_type([limits/0, error/0]).

-type limits() :: #{archive := pos_integer(),   %% bytes of the archive itself
                    entries := pos_integer(),   %% entries, folders included
                    entry := pos_integer(),     %% declared bytes of one entry
                    total := pos_integer(),     %% declared bytes of all entries
                    ratio := pos_integer()}.    %% inflated / compressed, entries > 1 MiB
-type error() :: {too_big, non_neg_integer(), pos_integer()}
               | {too_many_entries, non_neg_integer(), pos_integer()}
               | {entry_too_big, string(), non_neg_integer(), pos_integer()}
               | {total_too_big, non_neg_integer(), pos_integer()}
               | {bomb, string()}
               | {unsafe_entry, string()}
               | {duplicate_entry, string()}
               | {corrupt_entry, string(), term()}
               | {not_a_zip, term()}.

-define(EOCD, 16#06054b50).
-define(LOCAL, 16#04034b50).
-define(DESCRIPTOR, 16#08074b50).
-define(RATIO_FLOOR, 1024 * 1024).

%% @doc The limits a recipe archive is held to.
-spec default_limits() -> limits().
default_limits() ->
    #{archive => 64 * 1024 * 1024, entries => 1000, entry => 128 * 1024 * 1024,
      total => 256 * 1024 * 1024, ratio => 200}.

%% @doc Every entry of the archive as `{Name, Content}', in archive order; folder
%% entries come back as `{Name, folder}'.
-spec read(binary(), limits()) -> {ok, [{string(), binary() | folder}]} | {error, error()}.
read(Bin, Limits) ->
    read(Bin, Limits, all).

%% @doc As {@link read/2}, inflating only the entries named in `Wanted' (all of them
%% are checked); the others come back as `{Name, skipped}'.
-spec read(binary(), limits(), all | [string()]) ->
          {ok, [{string(), binary() | folder | skipped}]} | {error, error()}.
read(Bin, #{archive := MaxArchive} = Limits, Wanted) when is_binary(Bin) ->
    try
        byte_size(Bin) =< MaxArchive orelse throw({too_big, byte_size(Bin), MaxArchive}),
        check_count(Bin, Limits),
        Entries = list(Bin),
        check_entries(Entries, Limits),
        {ok, [{Name, case Wanted =:= all orelse lists:member(Name, Wanted) of
                         true -> extract(Bin, E);
                         false -> skipped
                     end} || #zip_file{name = Name} = E <- Entries]}
    of
        Result -> Result
    catch
        throw:Why -> {error, Why}
    end.

%% The end record says how many entries there are: refuse a flood before listing.
check_count(Bin, #{entries := Max}) ->
    Size = byte_size(Bin),
    From = max(0, Size - (22 + 65535)),
    Tail = binary:part(Bin, From, Size - From),
    case binary:matches(Tail, <<?EOCD:32/little>>) of
        [] ->
            throw({not_a_zip, no_end_record});
        Found ->
            {At, _} = lists:last(Found),
            case Tail of
                <<_:At/binary, ?EOCD:32/little, _Disk:16, _CdDisk:16, _Here:16/little,
                  Total:16/little, _/binary>> when Total =:= 16#FFFF ->
                    throw({not_a_zip, zip64});
                <<_:At/binary, ?EOCD:32/little, _Disk:16, _CdDisk:16, _Here:16/little,
                  Total:16/little, _/binary>> when Total > Max ->
                    throw({too_many_entries, Total, Max});
                <<_:At/binary, ?EOCD:32/little, _:16/binary, _/binary>> ->
                    ok;
                _ ->
                    throw({not_a_zip, truncated_end_record})
            end
    end.

list(Bin) ->
    %% zip raises on some malformed directories instead of returning an error: this
    %% is the boundary where untrusted bytes meet it.
    try zip:list_dir(Bin) of
        {ok, [#zip_comment{} | Entries]} -> Entries;
        {ok, Entries} -> [E || #zip_file{} = E <- Entries];
        {error, Why} -> throw({not_a_zip, simplify(Why)})
    catch
        error:Why -> throw({not_a_zip, simplify(Why)})
    end.

simplify({'EXIT', {Why, _Stack}}) -> Why;
simplify(Why) -> Why.

check_entries(Entries, #{entries := MaxEntries, entry := MaxEntry, total := MaxTotal,
                         ratio := Ratio}) ->
    length(Entries) =< MaxEntries orelse throw({too_many_entries, length(Entries), MaxEntries}),
    _ = lists:foldl(
      fun(#zip_file{name = Name, info = #file_info{size = Size}, comp_size = Comp}, {Seen, Sum}) ->
              safe_name(Name) orelse throw({unsafe_entry, Name}),
              lists:member(Name, Seen) andalso throw({duplicate_entry, Name}),
              Size =< MaxEntry orelse throw({entry_too_big, Name, Size, MaxEntry}),
              Sum + Size =< MaxTotal orelse throw({total_too_big, Sum + Size, MaxTotal}),
              (Size =< ?RATIO_FLOOR orelse Size =< Ratio * Comp) orelse throw({bomb, Name}),
              {[Name | Seen], Sum + Size}
      end, {[], 0}, Entries),
    ok.

%% A relative path of plain parts: no root, no drive, no `..', no backslash, no
%% control characters.
safe_name([]) -> false;
safe_name([$/ | _]) -> false;
safe_name([_, $: | _]) -> false;
safe_name(Name) ->
    lists:all(fun(C) -> C >= 32 andalso C =/= 127 andalso C =/= $\\ end, Name)
        andalso not lists:member("..", string:split(Name, "/", all)).

extract(_Bin, #zip_file{name = Name, info = #file_info{type = directory, size = 0}}) ->
    lists:last(Name) =:= $/ orelse throw({corrupt_entry, Name, folder_without_slash}),
    folder;
extract(Bin, #zip_file{name = Name, info = #file_info{size = Size}, offset = Offset,
                       comp_size = Comp}) ->
    case Bin of
        <<_:Offset/binary, ?LOCAL:32/little, _Version:16, Flags:16/little, Method:16/little,
          _Time:16, _Date:16, Crc0:32/little, _:32, _:32, NameLen:16/little,
          ExtraLen:16/little, _:NameLen/binary, _:ExtraLen/binary, Data:Comp/binary,
          After/binary>> ->
            Flags band 1 =:= 0 orelse throw({corrupt_entry, Name, encrypted}),
            Crc = case Flags band 8 of
                      0 -> Crc0;
                      8 -> descriptor_crc(After, Name)
                  end,
            Out = case Method of
                      0 when byte_size(Data) =:= Size -> Data;
                      0 -> throw({corrupt_entry, Name, size_mismatch});
                      8 -> inflate(Data, Size, Name);
                      _ -> throw({corrupt_entry, Name, {compression_method, Method}})
                  end,
            erlang:crc32(Out) =:= Crc orelse throw({corrupt_entry, Name, bad_crc}),
            Out;
        _ ->
            throw({corrupt_entry, Name, truncated})
    end.

descriptor_crc(<<?DESCRIPTOR:32/little, Crc:32/little, _/binary>>, _Name) -> Crc;
descriptor_crc(<<Crc:32/little, _/binary>>, _Name) -> Crc;
descriptor_crc(_, Name) -> throw({corrupt_entry, Name, truncated}).

%% Raw deflate in steps; more output than declared is a bomb, less a damaged entry.
inflate(Data, Size, Name) ->
    Z = zlib:open(),
    try
        ok = zlib:inflateInit(Z, -15),
        Out = inflate_loop(Z, zlib:safeInflate(Z, Data), Size, Name, [], 0),
        byte_size(Out) =:= Size orelse throw({corrupt_entry, Name, size_mismatch}),
        Out
    catch
        error:data_error -> throw({corrupt_entry, Name, bad_deflate_data});
        error:buf_error -> throw({corrupt_entry, Name, truncated})
    after
        zlib:close(Z)
    end.

inflate_loop(Z, {Status, Chunk}, Size, Name, Acc, Got) ->
    Got1 = Got + iolist_size(Chunk),
    Got1 =< Size orelse throw({bomb, Name}),
    case Status of
        continue -> inflate_loop(Z, zlib:safeInflate(Z, []), Size, Name, [Acc | Chunk], Got1);
        finished -> iolist_to_binary([Acc | Chunk])
    end;
inflate_loop(_Z, {need_dictionary, _, _}, _Size, Name, _Acc, _Got) ->
    throw({corrupt_entry, Name, needs_dictionary}).

%% @doc An archive of `{Name, Content}' entries, compressed.
-spec write([{string(), iodata()}]) -> binary().
write(Entries) ->
    {ok, {_, Bin}} = zip:create("recipe.zprd",
                                [{Name, iolist_to_binary(Data)} || {Name, Data} <- Entries],
                                [memory, {compress, all}]),
    Bin.

%% @doc An archive error in words.
-spec format_error(term()) -> binary().
format_error(Why) ->
    iolist_to_binary(why(Why)).

why({too_big, Size, Max}) ->
    io_lib:format("the archive is ~p bytes, more than the ~p allowed", [Size, Max]);
why({too_many_entries, N, Max}) ->
    io_lib:format("the archive holds ~p entries, more than the ~p allowed", [N, Max]);
why({entry_too_big, Name, Size, Max}) ->
    io_lib:format("~ts would be ~p bytes, more than the ~p allowed", [Name, Size, Max]);
why({total_too_big, Size, Max}) ->
    io_lib:format("the archive would unpack to more than ~p bytes (~p)", [Max, Size]);
why({bomb, Name}) ->
    io_lib:format("~ts inflates far beyond its size: refused as a zip bomb", [Name]);
why({unsafe_entry, Name}) ->
    io_lib:format("the entry ~tp points outside the recipe (absolute path, .. or "
                  "drive): refused", [Name]);
why({duplicate_entry, Name}) ->
    io_lib:format("the entry ~ts appears twice", [Name]);
why({corrupt_entry, Name, What}) ->
    io_lib:format("the entry ~ts is damaged (~p)", [Name, What]);
why({not_a_zip, What}) ->
    io_lib:format("not a zip archive (~0p)", [What]);
why(Other) ->
    io_lib:format("~0tp", [Other]).
