%% @doc The router PLC program's side of an inspection block (seed 004): the tags the
%% PLC writes (the block's inputs) as this group's outputs, the tags the block writes as
%% its inputs. The block itself ({@link cell_inspect_io}, S7 layout) keeps its UDT in
%% the PLC's holding registers; the PLC program reaches the same tags here, laid out as
%% every router IO group is ({@link router_io}), and the PLC (in the demo its physics,
%% {@link router_sim}) maps one onto the other: whatever one side writes, the other reads.
%%
%% Only the tags an inspection needs are mapped: point, serial, ClearResults and
%% TriggerInspection one way; their echoes, the status, the error code, PASS, FAIL and
%% the result string the other. Point names are the block's own (an S7 STRING is two
%% points, `<tag>_len' and `<tag>'), so the map is by name.
-module(router_inspect_io).
-behaviour(cell_hal_group).

-export([points/1, block_opts/1, mapped/0, string/3, value/2]).

%% The tags of an inspection, by direction seen from the PLC program.
-define(PLC_WRITES, [trigger_inspection, clear_results, inspection_point_id, part_serial]).
-define(PLC_READS, [trigger_inspection_echo, clear_results_echo, inspection_pass,
                    inspection_fail, inspection_status, error_code, inspection_point_id_echo,
                    part_serial_echo, inspection_string]).

%% @doc The points: `base' as every router group; `block' the block's S7 base.
-spec points(map()) -> [cell_hal_group:point_def()].
points(Opts) ->
    Block = cell_inspect_io:points(block_opts(maps:get(block, Opts, 0))),
    Mapped = mapped(),
    router_io:points(maps:get(base, Opts, 0),
                     [{N, flip(D), T, A, C} || #{name := N, dir := D, type := T, address := A,
                                                caption := C} <- Block,
                                               lists:member(N, Mapped)]).

%% @doc The block's IO options at an S7 base (the seed's string lengths).
-spec block_opts(non_neg_integer()) -> cell_inspect_io:opts().
block_opts(Base) ->
    {ok, Opts} = cell_inspect_io:check_opts(#{layout => s7, base => Base}),
    Opts.

%% @doc The block's points this group maps (strings by both their points).
-spec mapped() -> [atom()].
mapped() ->
    lists:append([case cell_inspect_tags:kind(T) of
                      {string, _} -> [len_point(T), T];
                      _ -> [T]
                  end || T <- ?PLC_WRITES ++ ?PLC_READS]).

%% @doc The writes that put a string into one of the PLC's STRING tags (`part_serial',
%% `inspection_point_id'): the characters, then the length bytes that commit them.
-spec string(atom(), inspection_point_id | part_serial, binary()) ->
          [{atom(), atom(), cell_hal_type:value()}].
string(Group, Tag, Value) ->
    #{lengths := L} = block_opts(0),
    {string, Class} = cell_inspect_tags:kind(Tag),
    N = maps:get(Class, L),
    Bytes = cell_inspect_io:to_plc(Value, N),
    [{Group, Tag, Bytes}, {Group, len_point(Tag), cell_inspect_udt:header(N, byte_size(Bytes))}].

%% @doc A STRING tag the block wrote, as text; `undefined' when it cannot be read.
-spec value(atom(), part_serial_echo | inspection_point_id_echo | inspection_string) ->
          binary() | undefined.
value(Group, Tag) ->
    #{lengths := L} = block_opts(0),
    {string, Class} = cell_inspect_tags:kind(Tag),
    N = maps:get(Class, L),
    case {cell_hal:read(Group, len_point(Tag)), cell_hal:read(Group, Tag)} of
        {{ok, Head}, {ok, Chars}} ->
            cell_inspect_io:from_plc(
              cell_inspect_udt:string_value(N, <<(Head bsr 8), (Head band 255), Chars/binary>>));
        _ ->
            undefined
    end.

flip(in) -> out;
flip(out) -> in.

len_point(inspection_point_id) -> inspection_point_id_len;
len_point(part_serial) -> part_serial_len;
len_point(inspection_point_id_echo) -> inspection_point_id_echo_len;
len_point(part_serial_echo) -> part_serial_echo_len;
len_point(inspection_string) -> inspection_string_len.
